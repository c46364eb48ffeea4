"""Compiled kernels of the GAP refinement with a low-rank prior on groups (:mod:`codedvideo.solvers.refine`):
2D patches of single frames, the matching of the reference patches across neighbouring frames
(:func:`match_frame_patches`), each group shrunk in the eigenbasis of its Gram matrix
(:func:`shrink_frame_groups`), and the members' estimates added frame by frame
(:func:`scatter_frame_patches`).  A patch is the flat index ``t * H * W + r * W + c`` of its top-left corner.
"""

from __future__ import annotations

import numpy as np

from codedvideo.solvers._jit import REASSOC, njit, prange


@njit(parallel=True, nogil=True, cache=True, fastmath=REASSOC)
def match_frame_patches(vol, refs, side, window, frames, k, idx):
    """``idx[g]``: the ``k`` ``side x side`` patches of ``vol`` (N, H, W) closest to the patch ``refs[g]`` (sum of
    squared differences), among the patches of frames ``t - frames .. t + frames`` whose corners are within
    ``window`` pixels of the reference's.

    The reference itself first; then candidates in order of sub-frame (the reference's own, then 1, 2, ...
    away, the earlier first), row and column, one entering only when strictly closer than the current ``k``-th
    (ties to the earlier candidate: on equal patches, as in flat or smooth regions, a group stays in and near its
    own sub-frame, so every sub-frame's patches are covered alike); a sum stops once past it.  Fewer than ``k``
    candidates: the reference fills the rest.  Every reference alone, so the groups never depend on the
    threads."""
    n, h, w = vol.shape
    hw = h * w
    for g in prange(refs.shape[0]):
        p = refs[g]
        t0 = p // hw
        r0 = (p % hw) // w
        c0 = p % w
        best = np.full(k, np.inf)
        bidx = np.full(k, -1, np.int64)
        best[0] = -1.0
        bidx[0] = p
        for order in range(2 * frames + 1):
            away = (order + 1) // 2
            t = t0 - away if order % 2 == 1 else t0 + away
            if t < 0 or t >= n:
                continue
            for r in range(max(0, r0 - window), min(h - side, r0 + window) + 1):
                for cc in range(max(0, c0 - window), min(w - side, c0 + window) + 1):
                    if t == t0 and r == r0 and cc == c0:
                        continue
                    lim = best[k - 1]
                    s = 0.0
                    for yy in range(side):
                        row = np.float32(0.0)
                        for xx in range(side):
                            d = vol[t0, r0 + yy, c0 + xx] - vol[t, r + yy, cc + xx]
                            row += d * d
                        s += np.float64(row)
                        if s >= lim:
                            break
                    if s >= lim:
                        continue
                    j = k - 1
                    while j > 0 and best[j - 1] > s:
                        best[j] = best[j - 1]
                        bidx[j] = bidx[j - 1]
                        j -= 1
                    best[j] = s
                    bidx[j] = t * hw + r * w + cc
        for j in range(k):
            idx[g, j] = bidx[j] if bidx[j] >= 0 else p


@njit(parallel=True, nogil=True, cache=True, fastmath=REASSOC)
def shrink_frame_groups(vol, groups, side, sigma2, c, est):
    """``est[g * k + i]`` (``side**2`` values): member ``i`` of group ``g`` with the group shrunk by weighted nuclear
    norm.

    The members less their mean ``M`` (k, d), ``k <= d``; the eigendecomposition ``M M^T = U diag(s^2) U^T`` of
    their Gram matrix (float64); each singular value ``s`` lowered by ``c sqrt(k) sigma2 / s_hat`` (``s_hat^2 =
    max(s^2 - d sigma2, 0)``, the clean value's estimate) and kept as ``f = max(s - threshold, 0) / s``; the
    estimate the mean plus ``U diag(f) U^T M``.  :func:`codedvideo.solvers.refine.shrinkage` is the same rule in
    numpy.  Every group alone, so nothing depends on the threads."""
    n, h, w = vol.shape
    hw = h * w
    G, k = groups.shape
    d = side * side
    for g in prange(G):
        M = np.empty((k, d), np.float32)
        mu = np.zeros(d, np.float32)
        for i in range(k):
            p = groups[g, i]
            t = p // hw
            r0 = (p % hw) // w
            c0 = p % w
            for yy in range(side):
                for xx in range(side):
                    v = vol[t, r0 + yy, c0 + xx]
                    M[i, yy * side + xx] = v
                    mu[yy * side + xx] += v
        for e in range(d):
            mu[e] /= k
        for i in range(k):
            for e in range(d):
                M[i, e] -= mu[e]
        C = np.empty((k, k), np.float64)
        for i in range(k):
            for j in range(i, k):
                acc = 0.0
                for e in range(d):
                    acc += np.float64(M[i, e]) * np.float64(M[j, e])
                C[i, j] = acc
                C[j, i] = acc
        lam, U = np.linalg.eigh(C)
        # the kept directions only (most are shrunk to nothing): V = diag(f) U_kept^T M, then U_kept V
        V = np.zeros((k, d), np.float32)
        kept = 0
        for q in range(k):
            if lam[q] > 0.0:
                sq = np.sqrt(lam[q])
                threshold = c * np.sqrt(k) * sigma2 / (np.sqrt(max(lam[q] - d * sigma2, 0.0)) + 1e-8)
                f = max(sq - threshold, 0.0) / sq
                if f > 0.0:
                    for j in range(k):
                        U[j, kept] = U[j, q]
                        uj = np.float32(U[j, q] * f)
                        for e in range(d):
                            V[kept, e] += uj * M[j, e]
                    kept += 1
        for i in range(k):
            row = est[g * k + i]
            for e in range(d):
                row[e] = mu[e]
            for q in range(kept):
                u = np.float32(U[i, q])
                for e in range(d):
                    row[e] += u * V[q, e]


@njit(parallel=True, nogil=True, cache=True)
def scatter_frame_patches(est, where, order, bounds, side, summed, weight):
    """Add the rows ``est[e]`` at their patches ``where[e]`` (flat corners), the frames in parallel: frame ``t``'s
    entries are ``order[bounds[t]:bounds[t + 1]]``, added in that order (so nothing depends on the threads).
    ``summed`` and ``weight`` (N, H, W) accumulate the estimates and their count."""
    n, h, w = summed.shape
    hw = h * w
    for t in prange(n):
        for o in range(bounds[t], bounds[t + 1]):
            e = order[o]
            p = where[e]
            r0 = (p % hw) // w
            c0 = p % w
            for yy in range(side):
                for xx in range(side):
                    summed[t, r0 + yy, c0 + xx] += est[e, yy * side + xx]
                    weight[t, r0 + yy, c0 + xx] += 1.0
