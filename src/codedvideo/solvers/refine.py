"""Refinement under the measurement: GAP iterations with a low-rank prior on groups of similar blocks (issue 31).

A sparse method's result ``x0`` reproduces the coded image, but each of its patches was solved from the
measurements of one patch (or of one group, once).  The refinement alternates, from ``x0``:

1. accelerated GAP (generalised alternating projection, as in GAP-TV and the plug-and-play methods): for
   coded exposure ``Phi Phi^T`` is diagonal (each pixel's summed squared shutter weights), so the step to
   the measurements is per pixel, with the residual accumulated over the iterations;
2. a denoiser at a noise level annealed from :data:`SIGMA_START` to :data:`SIGMA_END` grey levels
   (geometrically): for every :data:`STEP`-th block (in each direction) the :data:`GROUP` blocks of the
   current estimate closest to it as whole ``7 x 7 x N`` blocks within :data:`WINDOW` pixels, matched again
   every :data:`REGROUP` iterations (:func:`codedvideo.solvers.omp_kernel.match_references`); each group less
   its mean shrunk by weighted nuclear norm (the singular values of the members' matrix, from the eigen-
   decomposition of their ``k x k`` Gram matrix, lowered by ``SHRINK sqrt(k) sigma^2 / s``, the rule of
   Gu et al., "Weighted nuclear norm minimization", CVPR 2014, that DeSCI (Liu et al., TPAMI 2019) iterates
   under the measurement); every member's estimate averaged at its place.

The last estimate is projected onto the measurements and averaged with ``x0`` (:data:`BLEND`): both
reproduce the coded image (``x0`` to its method's tolerance), and the mean held every case of the research
above ``x0`` (docs/quality.md).  The noise levels are fixed: a capture's read noise does not change them.

In working units (the grey levels of an 8-bit capture: the noise levels are in them).  Arrays in, arrays
out, on the whole image: the groups of a chunk of references are solved and added in order, so the result
does not depend on the threads.  Memory: three volumes (the estimate, the sum of the estimates, the start),
one chunk of groups (:data:`CHUNK`), and a band of rows of the mask in float32 at a time (:data:`BAND`).
"""

from __future__ import annotations

import time

import numpy as np

from codedvideo.model import physics
from codedvideo.model.patches import PATCH
from codedvideo.solvers.omp_kernel import match_references, scatter_patches, shrink_groups

#: Blocks a group holds, the reference first.
GROUP = 16
#: Search radius of a group's members around its reference's corner, pixels.
WINDOW = 6
#: Stride of the reference blocks, in each direction (the last row and column of blocks always included).
STEP = 4
#: Iterations between two matchings of the groups on the current estimate.
REGROUP = 4
#: The weighted-nuclear-norm constant ``c`` of the threshold ``c sqrt(k) sigma^2 / s``.
SHRINK = 2.8
#: The denoiser's noise level in the first and the last iteration, grey levels of an 8-bit capture.
SIGMA_START = 4.0
SIGMA_END = 1.0
#: The result's share of the start: ``(1 - BLEND) refined + BLEND x0``.
BLEND = 0.5
#: References whose groups are solved at once (their estimates: CHUNK * GROUP * N * 49 floats).
CHUNK = 2048
#: Elements of a band of rows in a step to the measurements (its float32 copy of the mask's band: 16 MB).
BAND = 1 << 22


def recipe() -> dict:
    """The refinement's settings but the iterations (what a record of its result is keyed by)."""
    return dict(group=GROUP, window=WINDOW, step=STEP, regroup=REGROUP, shrink=SHRINK, sigma_start=SIGMA_START,
                sigma_end=SIGMA_END, blend=BLEND)


def reference_grid(h: int, w: int, step: int = STEP, patch: int = PATCH) -> np.ndarray:
    """Raster corners (row * (w - patch + 1) + col) of every ``step``-th block in each direction, the last
    row and column of blocks included."""
    def axis(n: int) -> np.ndarray:
        s = np.arange(0, n, step)
        return s if s[-1] == n - 1 else np.append(s, n - 1)

    wp = w - patch + 1
    rows, cols = axis(h - patch + 1), axis(wp)
    return (rows[:, None] * wp + cols[None, :]).ravel().astype(np.int64)


def shrinkage(gram: np.ndarray, d: int, sigma: float, c: float = SHRINK) -> np.ndarray:
    """Each group's weighted-nuclear-norm shrinkage in its members' space, ``(G, k, k)`` from the Gram
    matrices ``(G, k, k)`` of its centred members (``d`` entries each): ``U diag(f) U^T`` with
    ``gram = U diag(s^2) U^T`` and ``f = max(s - c sqrt(k) sigma^2 / s_hat, 0) / s``, where
    ``s_hat^2 = max(s^2 - d sigma^2, 0)`` estimates the clean singular value."""
    k = gram.shape[-1]
    lam, U = np.linalg.eigh(gram)
    lam = np.maximum(lam, 0.0)
    s = np.sqrt(lam)
    clean = np.sqrt(np.maximum(lam - d * sigma * sigma, 0.0))
    threshold = c * np.sqrt(k) * sigma * sigma / (clean + 1e-8)
    f = np.divide(np.maximum(s - threshold, 0.0), s, out=np.zeros_like(s), where=s > 0)
    return np.einsum("giq,gq,gjq->gij", U, f, U)


def denoise(x: np.ndarray, groups: np.ndarray, sigma: float, *, chunk: int | None = None) -> np.ndarray:
    """The estimate ``x`` (N, H, W) float32 with every group shrunk (:func:`shrinkage`) and the members'
    estimates averaged at their places; pixels no member covers keep their value.  ``chunk``: groups solved
    at once (None: :data:`CHUNK`)."""
    chunk = CHUNK if chunk is None else chunk
    n, h, w = x.shape
    wp = w - PATCH + 1
    k = groups.shape[1]
    d = n * PATCH * PATCH
    summed = np.zeros_like(x)
    weight = np.zeros((h, w), np.float32)
    for start in range(0, groups.shape[0], chunk):
        part = np.ascontiguousarray(groups[start:start + chunk])
        est = np.empty((part.shape[0] * k, d), np.float32)
        shrink_groups(x, part, wp, PATCH, float(sigma) ** 2, SHRINK, est)
        scatter_patches(est, part.ravel(), np.ones(est.shape[0], np.float32), wp, PATCH, summed, weight)
    covered = weight > 0
    np.divide(summed, weight, out=summed, where=covered)
    summed[:, ~covered] = x[:, ~covered]
    return summed


def sigmas(iterations: int, start: float = SIGMA_START, end: float = SIGMA_END) -> np.ndarray:
    """The annealed noise levels, geometric from ``start`` to ``end`` (one iteration: ``end``)."""
    return np.geomspace(start, end, iterations) if iterations > 1 else np.array([end], np.float64)


def to_measurements(x: np.ndarray, mask: np.ndarray, coded: np.ndarray, inv: np.ndarray,
                    accumulated: np.ndarray | None = None) -> None:
    """In place, a band of rows at a time: ``x += S^T ((target - S x) / (S S^T))`` per pixel (``inv``: the
    reciprocal of each pixel's summed squared shutter weights, 0 where it is never open).  ``target`` is
    ``coded``, or with ``accumulated`` (accelerated GAP) that sum of the residuals, ``coded - S x`` added
    to it first."""
    n, h, w = x.shape
    rows = max(1, BAND // max(n * w, 1))
    for r in range(0, h, rows):
        band = slice(r, r + rows)
        s = np.asarray(mask[:, band], np.float32)
        predicted = np.einsum("thw,thw->hw", x[:, band], s, dtype=np.float32)
        if accumulated is None:
            target = coded[band]
        else:
            accumulated[band] += coded[band] - predicted
            target = accumulated[band]
        x[:, band] += s * ((target - predicted) * inv[band])[None]


def refine(coded: np.ndarray, mask: np.ndarray, start: np.ndarray, *, iterations: int,
           sigma_start: float = SIGMA_START, sigma_end: float = SIGMA_END, blend: float = BLEND,
           tick=None) -> tuple[np.ndarray, dict]:
    """``iterations`` of GAP with the group prior from ``start`` (N, H, W), in working units.

    ``coded`` (H, W) and ``mask`` (N, H, W) are the measurements the result keeps (a pixel never open is not
    held to any).  ``tick``: called once per iteration (a progress bar).  Returns the video (N, H, W) float32
    and what was done: iterations, the noise levels, the groups, seconds.
    """
    t0 = time.perf_counter()
    y = np.asarray(coded, np.float32)
    mask = np.asarray(mask)
    n, h, w = mask.shape
    if h < PATCH or w < PATCH or iterations < 1:
        return np.asarray(start, np.float32).copy(), dict(iterations=0, seconds=time.perf_counter() - t0)
    open2 = physics.forward(mask, mask)
    inv = np.divide(1.0, open2, out=np.zeros_like(open2), where=open2 > 0)
    x0 = np.ascontiguousarray(start, np.float32)
    x = x0.copy()
    refs = reference_grid(h, w)
    groups = np.empty((refs.size, GROUP), np.int64)
    accumulated = y.copy()
    levels = sigmas(iterations, sigma_start, sigma_end)
    for i, sigma in enumerate(levels):
        to_measurements(x, mask, y, inv, accumulated)
        if i % REGROUP == 0:
            match_references(x, refs, w - PATCH + 1, h - PATCH + 1, PATCH, WINDOW, GROUP, groups)
        x = denoise(x, groups, float(sigma))
        if tick is not None:
            tick()
    to_measurements(x, mask, y, inv)
    x *= np.float32(1.0 - blend)
    x += np.float32(blend) * x0
    info = dict(recipe(), iterations=int(iterations), sigma_start=float(sigma_start), sigma_end=float(sigma_end),
                blend=float(blend), groups=int(refs.size), seconds=time.perf_counter() - t0)
    return x, info
