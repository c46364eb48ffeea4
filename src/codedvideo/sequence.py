"""Captures of a coded video: what did not change from one capture to the next is left out.

For a scene that does not move, the coded value of a pixel divided by its open
count, ``q = coded / open count``, is the frame value itself, the same in every
capture whatever the code.  A single coded image cannot tell still texture from
motion; two captures can.  A pixel is *still* when ``q`` agrees, within the
noise, with the capture before or after it, and so does every pixel of every
7x7 patch that covers it (its 13x13 neighbourhood).  Such a pixel's answer is
``q`` in every sub-frame, with no dictionary search; and since every patch
that contains it lies wholly in the still region, leaving those patches out
takes no measurement away from a patch that moves.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

#: Smallest difference of ``coded / open count`` taken as change, in working units (data range 255).
STILL_FLOOR = 0.5
#: Noise multiple: a still pixel's two normalised values differ by more with probability about 3e-3.
STILL_SIGMAS = 3.0


def normalised(coded: np.ndarray, mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(coded / open count, open count)``; 0 where a pixel is never open."""
    k = np.asarray(mask, np.float32).sum(0)
    return np.where(k > 0, np.asarray(coded, np.float32) / np.maximum(k, 1e-12), 0).astype(np.float32), k


def still_pixels(codeds, masks, i: int, *, sigma: float, patch: int = 7, scale: float = 1.0) -> np.ndarray:
    """Pixels of capture ``i`` whose whole ``2 * patch - 1`` neighbourhood is still (module docstring).

    Parameters
    ----------
    codeds : sequence of (H, W) coded images, in the capture's units
    masks : callable ``masks(j)`` -> the (N, H, W) mask of capture ``j``
    i : the capture
    sigma : read-noise standard deviation, in the capture's units
    scale : factor from the capture's units to working units (:class:`codedvideo.units.DataRange`)

    Returns
    -------
    ndarray of shape (H, W), bool
    """
    sigma = sigma * scale
    q, k = normalised(codeds[i], masks(i))
    q = q * np.float32(scale)
    agree = np.zeros(q.shape, bool)
    for j in (i - 1, i + 1):
        if not 0 <= j < len(codeds):
            continue
        qj, kj = normalised(codeds[j], masks(j))
        qj = qj * np.float32(scale)
        with np.errstate(divide="ignore"):
            spread = sigma * np.sqrt(1 / np.maximum(k, 1e-12) ** 2 + 1 / np.maximum(kj, 1e-12) ** 2)
        tol = np.maximum(STILL_SIGMAS * spread, STILL_FLOOR)
        agree |= (k > 0) & (kj > 0) & (np.abs(q - qj) <= tol)
    # every patch containing the pixel lies inside the still region (patches lie inside the image)
    return ndimage.minimum_filter(agree.view(np.uint8), size=2 * patch - 1, mode="nearest").astype(bool)


class StepErrors:
    """Error of the frame-to-frame step, inside captures and across their boundaries (flicker every N frames).

    ``add(volume, truth)`` capture after capture; the step error of frames
    ``t, t+1`` is the RMS of ``(x[t+1] - x[t]) - (g[t+1] - g[t])``.
    """

    def __init__(self):
        self.inside: list[float] = []
        self.boundary: list[float] = []
        self._last = None

    @staticmethod
    def _rms(a: np.ndarray) -> float:
        return float(np.sqrt(np.mean(np.square(a, dtype=np.float64))))

    def add(self, volume: np.ndarray, truth: np.ndarray) -> None:
        v, g = np.asarray(volume, np.float64), np.asarray(truth, np.float64)
        self.inside += [self._rms((v[t + 1] - v[t]) - (g[t + 1] - g[t])) for t in range(len(v) - 1)]
        if self._last is not None:
            self.boundary.append(self._rms((v[0] - self._last[0]) - (g[0] - self._last[1])))
        self._last = (v[-1], g[-1])

    def summary(self) -> dict:
        inside = float(np.mean(self.inside)) if self.inside else None
        boundary = float(np.mean(self.boundary)) if self.boundary else None
        ratio = boundary / inside if inside and boundary is not None else None
        return dict(step_rms_inside=inside, step_rms_boundary=boundary, boundary_to_inside=ratio,
                    step_rms_per_boundary=self.boundary)
