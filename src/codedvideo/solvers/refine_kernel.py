"""Compiled kernels of the GAP refinement with a low-rank prior on groups (:mod:`codedvideo.solvers.refine`):
2D patches of single frames, the matching of the reference patches across neighbouring frames
(:func:`match_frame_patches`), each group shrunk in the eigenbasis of its Gram matrix
(:func:`shrink_frame_groups`), and the members' estimates added frame by frame
(:func:`scatter_frame_patches`).  A patch is the flat index ``t * H * W + r * W + c`` of its top-left corner.
"""

from __future__ import annotations

import numpy as np

from codedvideo.solvers._jit import CONTRACT, REASSOC, njit, prange


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


#: A group whose Gram matrix has more eigenvalues than this above the shrinkage's cut is decomposed whole
#: (LAPACK); below it, only the eigenpairs the shrinkage keeps are computed (:func:`kept_eigenpairs`).
SELECT_MAX = 10


@njit(nogil=True, cache=True, fastmath=CONTRACT)
def _tridiagonalize(A, V, a, b, p):
    """Householder reduction of the symmetric ``A`` (n x n float64, overwritten) to the tridiagonal ``(a, b)``:
    ``A = Q T Q^T`` with ``Q = H_0 ... H_{n-3}``, ``H_j = I - 2 v v^T``, ``v = V[j]`` (a zero row: no reflection);
    ``p``: n floats of scratch."""
    n = A.shape[0]
    for j in range(n - 2):
        alpha2 = 0.0
        for i in range(j + 1, n):
            alpha2 += A[i, j] * A[i, j]
        x0 = A[j + 1, j]
        tail = alpha2 - x0 * x0
        V[j, :] = 0.0
        if not tail > 1e-300 * alpha2:  # (the column is tridiagonal already)
            b[j] = x0
            continue
        alpha = -np.sqrt(alpha2) if x0 >= 0 else np.sqrt(alpha2)
        v0 = x0 - alpha
        vn = np.sqrt(tail + v0 * v0)
        V[j, j + 1] = v0 / vn
        for i in range(j + 2, n):
            V[j, i] = A[i, j] / vn
        b[j] = alpha
        # the trailing block S <- H S H: p = S v, w = p - (v.p) v, S -= 2 (v w^T + w v^T)
        vp = 0.0
        for i in range(j + 1, n):
            s = 0.0
            for col in range(j + 1, n):
                s += A[i, col] * V[j, col]
            p[i] = s
            vp += V[j, i] * s
        for i in range(j + 1, n):
            p[i] -= vp * V[j, i]
        for i in range(j + 1, n):
            vi = 2.0 * V[j, i]
            pi = 2.0 * p[i]
            for col in range(j + 1, n):
                A[i, col] -= vi * p[col] + pi * V[j, col]
    for i in range(n):
        a[i] = A[i, i]
    if n >= 2:
        b[n - 2] = A[n - 1, n - 2]


@njit(nogil=True, cache=True, inline="always")
def _below(a, b2, x):
    """How many eigenvalues of the tridiagonal with diagonal ``a`` and squared off-diagonal ``b2`` (both scaled to
    about 1) lie below ``x``: the sign changes of the Sturm sequence ``p_i = (a_i - x) p_{i-1} - b2_{i-1} p_{i-2}``,
    rescaled when it grows small (a zero taken as a change)."""
    prev = 1.0
    p = a[0] - x
    if p == 0.0:
        p = -1e-280
    count = 1 if p < 0 else 0
    for i in range(1, a.size):
        nxt = (a[i] - x) * p - b2[i - 1] * prev
        if nxt == 0.0:
            nxt = -1e-280 if p > 0 else 1e-280
        count += (nxt < 0) ^ (p < 0)
        prev = p
        p = nxt
        if abs(p) < 1e-150:
            p *= 1e150
            prev *= 1e150
    return count


@njit(nogil=True, cache=True)
def _inverse_iteration(a, b, mu, U, j, z, lu):
    """``z``: the eigenvector of the tridiagonal ``(a, b)`` at the eigenvalue ``mu`` (to 1e-7 of the spectrum's
    scale), by two solves with ``T - mu I`` (factored once, partial pivoting, into the rows of ``lu`` (5, n)),
    each made orthogonal to the ``j`` vectors in ``U[:, :j]`` found before it (so a cluster's vectors stay
    apart), and normalised."""
    n = a.size
    dd, dl, du, du2, piv = lu[0], lu[1], lu[2], lu[3], lu[4]
    for i in range(n):
        dd[i] = a[i] - mu
        du2[i] = 0.0
        piv[i] = 0.0
    dl[:n - 1] = b[:n - 1]
    du[:n - 1] = b[:n - 1]
    tiny = 1e-300 + 1e-300 * (abs(mu) + 1.0)
    for i in range(n - 1):
        if abs(dd[i]) >= abs(dl[i]):
            if dd[i] == 0.0:
                dd[i] = tiny
            f = dl[i] / dd[i]
            dd[i + 1] -= f * du[i]
        else:
            piv[i] = 1.0
            f = dd[i] / dl[i]
            dd[i] = dl[i]
            t = dd[i + 1]
            dd[i + 1] = du[i] - f * t
            if i < n - 2:
                du2[i] = du[i + 1]
                du[i + 1] = -f * du2[i]
            du[i] = t
        dl[i] = f
    if dd[n - 1] == 0.0:
        dd[n - 1] = tiny
    for i in range(n):
        dd[i] = 1.0 / dd[i]
        z[i] = 1.0 + 0.001 * ((7 * i + 13 * j) % 11)  # (a fixed start, not orthogonal to any eigenvector)
    for _ in range(2):
        for i in range(n - 1):
            if piv[i] != 0.0:
                zi = z[i]
                z[i] = z[i + 1]
                z[i + 1] = zi - dl[i] * z[i + 1]
            else:
                z[i + 1] -= dl[i] * z[i]
        z[n - 1] *= dd[n - 1]
        if n >= 2:
            z[n - 2] = (z[n - 2] - du[n - 2] * z[n - 1]) * dd[n - 2]
        for i in range(n - 3, -1, -1):
            z[i] = (z[i] - du[i] * z[i + 1] - du2[i] * z[i + 2]) * dd[i]
        for q in range(j):
            s = 0.0
            for i in range(n):
                s += z[i] * U[i, q]
            for i in range(n):
                z[i] -= s * U[i, q]
        norm = 0.0
        for i in range(n):
            norm += z[i] * z[i]
        norm = 1.0 / np.sqrt(norm)
        for i in range(n):
            z[i] *= norm


@njit(nogil=True, cache=True)
def kept_eigenpairs(C, floor, lam, U, work):
    """The eigenpairs of the symmetric ``C`` (n x n float64) whose eigenvalues exceed ``floor``, the largest first:
    ``lam[:m]`` and the columns ``U[:, :m]``; returns ``m``, or -1 (nothing computed) when ``m`` exceeds
    :data:`SELECT_MAX`.  ``work``: ``(2 n + 11, n)`` float64 of scratch.

    Householder tridiagonalisation; the count above ``floor`` and each eigenvalue by bisection of the Sturm
    sequence (to 1e-7 of the spectrum's scale), its vector by inverse iteration, the eigenvalue then the
    vector's Rayleigh quotient; the vectors taken back through the reflections.  The few eigenpairs a group's
    shrinkage keeps cost a fraction of the whole decomposition."""
    n = C.shape[0]
    A, V = work[:n], work[n:2 * n]
    q = 2 * n  # (the rows after A's and V's)
    a, b, an, b2, z, p = work[q], work[q + 1], work[q + 2], work[q + 3], work[q + 4], work[q + 5]
    lu = work[q + 6:q + 11]
    A[:, :] = C
    b[:] = 0.0
    _tridiagonalize(A, V, a, b, p)
    lo, hi = np.inf, -np.inf
    for i in range(n):  # Gershgorin bounds of the spectrum
        r = (abs(b[i - 1]) if i > 0 else 0.0) + (abs(b[i]) if i < n - 1 else 0.0)
        lo = min(lo, a[i] - r)
        hi = max(hi, a[i] + r)
    scale = max(abs(lo), abs(hi), 1e-300)
    for i in range(n):
        an[i] = a[i] / scale
        b2[i] = (b[i] / scale) * (b[i] / scale)
    bottom = max(floor, lo)
    if not bottom < hi:
        return 0
    m = n - _below(an, b2, bottom / scale)
    if m > SELECT_MAX:
        return -1
    top = hi
    for j in range(m):
        index = n - 1 - j  # the ascending index of the j-th largest
        low, high = bottom, top
        for _ in range(80):
            mid = 0.5 * (low + high)
            if _below(an, b2, mid / scale) > index:
                high = mid
            else:
                low = mid
            if high - low <= 1e-7 * scale:
                break
        top = high
        _inverse_iteration(a, b, 0.5 * (low + high), U, j, z, lu)
        rq = 0.0
        for i in range(n):
            t = a[i] * z[i]
            if i > 0:
                t += b[i - 1] * z[i - 1]
            if i < n - 1:
                t += b[i] * z[i + 1]
            rq += z[i] * t
        lam[j] = rq
        U[:, j] = z
    for j in range(m):  # U <- Q U
        for r in range(n - 3, -1, -1):
            s = 0.0
            for i in range(r + 1, n):
                s += V[r, i] * U[i, j]
            s *= 2.0
            for i in range(r + 1, n):
                U[i, j] -= s * V[r, i]
    return m


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
    # below this eigenvalue s^2 a direction is shrunk to nothing: s * s_hat = c sqrt(k) sigma2 solved for s^2 (the
    # threshold's 1e-8 left out, so the cut lies just below the rule's own; the rule itself decides each pair)
    cut = 0.5 * (d * sigma2 + np.sqrt((d * sigma2) ** 2 + 4.0 * c * c * k * sigma2 * sigma2)) * (1.0 - 1e-9)
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
        # the eigenpairs above the cut only (most are shrunk to nothing), or all where many are kept
        lam = np.empty(k)
        U = np.empty((k, k))
        count = kept_eigenpairs(C, cut, lam, U, np.empty((2 * k + 11, k))) if sigma2 > 0.0 else -1
        if count < 0:
            lam_all, U_all = np.linalg.eigh(C)
            lam[:] = lam_all
            U[:, :] = U_all
            count = k
        # the kept directions: V = diag(f) U_kept^T M, then U_kept V
        V = np.zeros((k, d), np.float32)
        kept = 0
        for q in range(count):
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
def scatter_frame_patches(est, where, order, bounds, side, summed, ones):
    """Add the rows ``est[e]`` at their patches ``where[e]`` (flat corners) into ``summed`` (N, H, W), the frames
    in parallel: frame ``t``'s entries are ``order[bounds[t]:bounds[t + 1]]``, added in that order (so nothing
    depends on the threads).  With ``ones``, 1 for every row instead (``est`` unread): the count of estimates."""
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
                    summed[t, r0 + yy, c0 + xx] += 1.0 if ones else est[e, yy * side + xx]
