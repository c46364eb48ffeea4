"""Classical baselines on the same forward model.

GAP-TV: generalized alternating projection with total-variation denoising
(Yuan, ICIP 2016), accelerated variant.  For a binary code ``Phi Phi^T`` is
diagonal (the open count of each pixel), so the projection onto
``{x : Phi x = y}`` is a per-pixel update.  The TV step is scikit-image's
Chambolle denoiser applied to each sub-frame.

It starts from the static estimate (coded / open count in every sub-frame),
not from the mask-weighted one: on single-bump codes the latter stalls far
below the static estimate, while on Bernoulli masks both starts agree
(measured; see shared/field.md).
"""

from __future__ import annotations

import numpy as np
from skimage.restoration import denoise_tv_chambolle

from .physics import adjoint, check_pair, forward, static_estimate


def gap_tv(
    coded: np.ndarray,
    mask: np.ndarray,
    *,
    iterations: int = 40,
    tv_weight: float = 0.06,
    tv_iterations: int = 5,
    data_range: float = 255.0,
    accelerate: bool = True,
    x0: np.ndarray | None = None,
) -> np.ndarray:
    """Reconstruct a video by GAP-TV.

    Parameters
    ----------
    coded : ndarray of shape (H, W)
    mask : ndarray of shape (N, H, W)
    iterations : int
        GAP iterations.
    tv_weight : float
        Chambolle weight on frames scaled to [0, 1].
    tv_iterations : int
        Inner iterations of each TV denoising.
    data_range : float
        Peak frame value (frames are scaled by it for the TV step).
    accelerate : bool
        Accumulate the measurement residual (accelerated GAP).
    x0 : ndarray of shape (N, H, W), optional
        Start; default the static estimate.

    Returns
    -------
    video : ndarray of shape (N, H, W), float32
    """
    check_pair(coded.shape, mask.shape)
    y = np.asarray(coded, dtype=np.float32) / data_range
    m = np.asarray(mask, dtype=np.float32)
    n_open = m.sum(0)
    inv = np.divide(1.0, n_open, out=np.zeros_like(n_open), where=n_open > 0)
    x = (static_estimate(coded, mask) / data_range) if x0 is None else np.asarray(x0, np.float32) / data_range
    y1 = y.copy()
    for _ in range(iterations):
        yb = forward(x, m)
        if accelerate:
            y1 = y1 + (y - yb)
            x = x + adjoint((y1 - yb) * inv, m)
        else:
            x = x + adjoint((y - yb) * inv, m)
        x = np.stack([denoise_tv_chambolle(f, weight=tv_weight, max_num_iter=tv_iterations) for f in x]).astype(np.float32)
    return x * data_range
