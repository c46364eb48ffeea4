"""The forward model of a coded-exposure camera and its adjoint.

Sum convention (Hitomi et al. 2011, Eq. 1), used everywhere in codedvideo::

    I(y, x) = sum_t S(t, y, x) * E(t, y, x)

A pixel open for ``k`` sub-frames records the *sum* of ``k`` frame values, in the
units of the frames (no division by the bump length).  The measurement of a
simulated camera is ``sensor(noise(S E))``; here the noise is Gaussian read
noise of standard deviation ``sigma`` in the same units.
"""

from __future__ import annotations

import numpy as np

from .errors import InputError


def check_pair(coded_shape: tuple, mask_shape: tuple, *, where: str = "") -> None:
    """Raise :class:`InputError` unless ``mask (N, H, W)`` matches ``coded (H, W)``."""
    if len(mask_shape) != 3 or tuple(mask_shape[1:]) != tuple(coded_shape):
        pre = f"{where}: " if where else ""
        raise InputError(
            f"{pre}mask shape {tuple(mask_shape)} does not match coded image {tuple(coded_shape)} "
            "(expected (N, H, W) with the coded image's H, W)"
        )


def forward(video: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Coded exposure ``I = sum_t S E``.

    Parameters
    ----------
    video : ndarray of shape (N, H, W)
    mask : ndarray of shape (N, H, W), binary

    Returns
    -------
    coded : ndarray of shape (H, W), float32
    """
    video = np.asarray(video, dtype=np.float32)
    if video.shape != np.shape(mask):
        raise InputError(f"forward: video shape {video.shape} != mask shape {np.shape(mask)}")
    return np.einsum("thw,thw->hw", video, np.asarray(mask, dtype=np.float32), dtype=np.float32)


def adjoint(coded: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Adjoint of :func:`forward`: ``E(t) = S(t) * I``, shape (N, H, W) float32."""
    check_pair(np.shape(coded), np.shape(mask))
    return np.asarray(mask, dtype=np.float32) * np.asarray(coded, dtype=np.float32)[None]


def add_read_noise(coded: np.ndarray, sigma: float, rng: np.random.Generator | int | None) -> np.ndarray:
    """Add Gaussian read noise of standard deviation ``sigma`` (frame units)."""
    if sigma < 0 or not np.isfinite(sigma):
        raise InputError(f"noise: sigma must be finite and >= 0, got {sigma}")
    coded = np.asarray(coded, dtype=np.float32)
    if sigma == 0:
        return coded.copy()
    rng = np.random.default_rng(rng)
    return (coded + rng.normal(0.0, sigma, size=coded.shape)).astype(np.float32)


def simulate(
    video: np.ndarray, mask: np.ndarray, *, sigma: float = 0.0, rng: np.random.Generator | int | None = 0
) -> np.ndarray:
    """``noise(S E)``: the coded image a camera with this code would record."""
    return add_read_noise(forward(video, mask), sigma, rng)


def static_estimate(coded: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """The trivial estimate: every sub-frame = coded / open count of its pixel.

    Pixels that are never open get 0 here; reconstruction fills them from
    their neighbours.  Shape (N, H, W) float32.
    """
    check_pair(np.shape(coded), np.shape(mask))
    n_open = np.asarray(mask, dtype=np.float32).sum(0)
    frame = np.divide(coded, n_open, out=np.zeros(np.shape(coded), np.float32), where=n_open > 0)
    return np.broadcast_to(frame, np.shape(mask)).astype(np.float32)
