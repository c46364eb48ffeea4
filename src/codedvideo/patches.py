"""Overlapping patches at stride 1: extraction, its adjoint (overlap-add), coverage.

A patch vector has ``N * M * M`` entries ordered ``(t, dy, dx)``; patches are
ordered by their top-left corner in raster order.  Only windows that lie fully
inside the array exist (no padding: a reflected border would invent patches),
so a border pixel is covered by fewer than ``M * M`` patches and the average
divides by the exact count from :func:`coverage`.
"""

from __future__ import annotations

import numpy as np

PATCH = 7


def grid_shape(shape: tuple[int, int], patch: int = PATCH) -> tuple[int, int]:
    """Number of patch positions ``(H - M + 1, W - M + 1)`` in an image."""
    return max(shape[0] - patch + 1, 0), max(shape[1] - patch + 1, 0)


def extract(volume: np.ndarray, patch: int = PATCH) -> np.ndarray:
    """All overlapping ``patch x patch`` patches of a volume or image.

    Parameters
    ----------
    volume : ndarray of shape (N, H, W) or (H, W)

    Returns
    -------
    patches : ndarray of shape (P, N, M*M) or (P, M*M)
        ``P = (H - M + 1) * (W - M + 1)``, a copy.
    """
    vol = np.asarray(volume)
    two_d = vol.ndim == 2
    if two_d:
        vol = vol[None]
    n = vol.shape[0]
    win = np.lib.stride_tricks.sliding_window_view(vol, (patch, patch), axis=(1, 2))
    # win: (N, Hp, Wp, M, M) -> (Hp, Wp, N, M, M)
    hp, wp = win.shape[1:3]
    out = np.ascontiguousarray(win.transpose(1, 2, 0, 3, 4)).reshape(hp * wp, n, patch * patch)
    return out[:, 0, :] if two_d else out


def fold(patches: np.ndarray, shape: tuple[int, int], patch: int = PATCH) -> np.ndarray:
    """Adjoint of :func:`extract`: add every patch back at its place (sums overlaps).

    Parameters
    ----------
    patches : ndarray of shape (P, N, M*M) or (P, N*M*M)
    shape : (H, W)

    Returns
    -------
    volume : ndarray of shape (N, H, W), float32
    """
    hp, wp = grid_shape(shape, patch)
    p = patches.shape[0]
    if p != hp * wp:
        raise ValueError(f"fold: {p} patches do not tile an image of shape {shape}")
    pt = patches.reshape(hp, wp, -1, patch, patch)
    n = pt.shape[2]
    out = np.zeros((n, *shape), dtype=np.float32)
    for dy in range(patch):
        for dx in range(patch):
            out[:, dy : dy + hp, dx : dx + wp] += np.moveaxis(pt[:, :, :, dy, dx], 2, 0)
    return out


def coverage(shape: tuple[int, int], patch: int = PATCH) -> np.ndarray:
    """Exact number of patches covering every pixel, shape (H, W) int32.

    Computed separably: along each axis a pixel at ``i`` is covered by the
    windows starting in ``max(0, i - M + 1) .. min(i, n - M)``.
    """

    def axis_count(n: int) -> np.ndarray:
        i = np.arange(n)
        lo = np.maximum(0, i - patch + 1)
        hi = np.minimum(i, n - patch)
        return np.maximum(hi - lo + 1, 0)

    return (axis_count(shape[0])[:, None] * axis_count(shape[1])[None, :]).astype(np.int32)
