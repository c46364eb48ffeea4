"""Compiled kernels of non-local sparse coding (:mod:`codedvideo.solvers.nonlocal_sc`): block matching
(:func:`block_match`), simultaneous OMP of a group of similar patches each seen through its own code
(:func:`somp_kernel`, operation for operation :func:`codedvideo.solvers.omp_kernel._omp_kernel` for a group of
one), and the scatter-add of the members' estimates (:func:`scatter_patches`).
"""

from __future__ import annotations

import numpy as np

from codedvideo.solvers._jit import CONTRACT, _chol_solve, _column_norms2, _correlate, _dot, njit


@njit(nogil=True, cache=True)
def block_match(vol, patch, window, k, idx, dist):
    """The ``k`` patches of ``vol`` most similar to every patch, within ``window`` pixels.

    Patches are compared as whole ``patch x patch x N`` blocks (sum of squared
    differences over every sub-frame: similar in space and in motion).  Offsets are
    visited in a fixed order, ``(0, 0)`` first, then raster order of ``(dy, dx)``;
    a candidate enters the list only when strictly closer than the one it would
    displace, so ties go to the earlier offset and the patch itself is always first.

    Parameters
    ----------
    vol : ndarray of shape (N, h, w), float32
    idx : ndarray of shape (hp * wp, k), int64
        Output: raster indices of the matched patches (``-1`` past the candidates).
    dist : ndarray of shape (hp * wp, k), float64
        Output: their squared distances (``inf`` past the candidates), increasing.
    """
    n, h, w = vol.shape
    wp = w - patch + 1
    idx[:] = -1
    dist[:] = np.inf
    e = np.zeros((h, w), np.float64)
    I = np.zeros((h + 1, w + 1), np.float64)
    offs = [(0, 0)]
    for dy in range(-window, window + 1):
        for dx in range(-window, window + 1):
            if dy != 0 or dx != 0:
                offs.append((dy, dx))
    for oy, ox in offs:
        # pixels (y, x) with (y + oy, x + ox) inside: squared difference summed over sub-frames
        y0 = max(0, -oy)
        y1 = min(h, h - oy)
        x0 = max(0, -ox)
        x1 = min(w, w - ox)
        if y1 - y0 < patch or x1 - x0 < patch:
            continue
        for y in range(y0, y1):
            for x in range(x0, x1):
                s = 0.0
                for t in range(n):
                    d = np.float64(vol[t, y, x]) - np.float64(vol[t, y + oy, x + ox])
                    s += d * d
                e[y, x] = s
        for y in range(y0, y1):  # integral image over the valid rectangle
            run = 0.0
            for x in range(x0, x1):
                run += e[y, x]
                I[y + 1, x + 1] = I[y, x + 1] + run
        for x in range(x0, x1 + 1):
            I[y0, x] = 0.0
        for y in range(y0, y1 + 1):
            I[y, x0] = 0.0
        for r in range(y0, y1 - patch + 1):
            for c in range(x0, x1 - patch + 1):
                d = I[r + patch, c + patch] - I[r, c + patch] - I[r + patch, c] + I[r, c]
                if d < 0.0:
                    d = 0.0
                p = r * wp + c
                if d >= dist[p, k - 1]:
                    continue
                j = k - 1
                while j > 0 and dist[p, j - 1] > d:
                    dist[p, j] = dist[p, j - 1]
                    idx[p, j] = idx[p, j - 1]
                    j -= 1
                dist[p, j] = d
                idx[p, j] = (r + oy) * wp + (c + ox)
        # the integral image rows/cols used are rewritten for every offset
        for y in range(y0, y1 + 1):
            for x in range(x0, x1 + 1):
                I[y, x] = 0.0


@njit(nogil=True, cache=True, fastmath=CONTRACT)
def somp_kernel(y, pat, members, size, B, floor, tol, kmax, dep_tol, select_bits, tiny,
                index, coef, count, res2, dependent, consensus):
    """Simultaneous OMP of groups of patches, each member through its own code (shared support).

    Group ``g`` holds the patches ``members[g, :size[g]]`` (rows of ``y`` and ``pat``).
    Each iteration picks one atom for the whole group: the largest sum over the
    members still above their tolerance of ``|A_p^T r_p|`` normalised by the
    column norms of their own ``A_p`` (rounded to :data:`SELECT_BITS`, ties to the
    lowest atom).  Every member then adds that atom to its own least-squares fit of
    its own measurement (Gram-Schmidt, twice, as :func:`codedvideo.solvers.omp_kernel._omp_kernel`), skipping an
    atom its code hides (below the visibility floor); a member stops when its
    residual is within ``tol`` or the atom is linearly dependent on its selection,
    the group when no member is left.  With one member this is :func:`~codedvideo.solvers.omp_kernel._omp_kernel`
    operation for operation (the same bits).

    ``consensus > 0`` then refits every member on its own atoms with a pull
    towards the group's shared coefficients ``a_bar`` (the least-squares fit of all
    the members' measurements at once on the group's atoms)::

        alpha_p = argmin ||y_p - A_p a||^2 + lam_p ||a - a_bar||^2,
        lam_p = consensus * mean diag(A_p^T A_p)

    (0: every member alone, the plain SOMP; ``res2`` is then the refit's residual).

    Outputs are per (group, member): ``index``, ``coef`` (G, k, kmax), ``count``,
    ``res2``, ``dependent`` (G, k).
    """
    G, kg = members.shape
    m = y.shape[1]
    K = B.shape[2]
    c = np.empty(K, np.float32)
    score = np.empty(K, np.float32)
    score_bits = score.view(np.int32)
    inv = np.empty((kg, K), np.float32)
    Q = np.zeros((kg, kmax, m), np.float64)
    R = np.zeros((kg, kmax, kmax), np.float64)
    qy = np.zeros((kg, kmax), np.float64)
    h = np.zeros(kmax, np.float64)
    r = np.empty((kg, m), np.float64)
    q = np.empty(m, np.float64)
    active = np.zeros(kg, np.bool_)
    nsel = np.zeros(kg, np.int64)
    gsel = np.zeros(kmax, np.int64)
    M = np.zeros((kmax, kmax), np.float64)
    bvec = np.zeros(kmax, np.float64)
    abar = np.zeros(kmax, np.float64)
    L = np.zeros((kmax, kmax), np.float64)
    A = np.zeros((m, kmax), np.float64)
    for g in range(G):
        ng = size[g]
        n_active = 0
        for a in range(ng):
            p = members[g, a]
            s = 0.0
            for i in range(m):
                r[a, i] = y[p, i]
                s += r[a, i] * r[a, i]
            res2[g, a] = s
            count[g, a] = 0
            dependent[g, a] = False
            nsel[a] = 0
            active[a] = s > tol[p]
            if active[a]:
                n_active += 1
                _column_norms2(B, pat[p], c)  # as the table kernel computes them (a group of one is the default)
                big = 0.0
                for k in range(K):
                    inv[a, k] = np.sqrt(max(c[k], np.float32(0.0)))
                    big = max(big, inv[a, k])
                for k in range(K):
                    nk = inv[a, k]
                    inv[a, k] = np.float32(1.0) / nk if (nk > tiny * big and nk > floor[k]) else np.float32(0.0)
        it = 0
        while n_active > 0 and it < kmax:
            it += 1
            score[:] = 0.0
            for a in range(ng):
                if not active[a]:
                    continue
                _correlate(B, pat[members[g, a]], r[a], c)
                for k in range(K):
                    score[k] += abs(c[k] * inv[a, k])
            best = np.int32(0)
            for k in range(K):
                score_bits[k] &= select_bits
                best = max(best, score_bits[k])
            if best <= 0:
                for a in range(ng):
                    if active[a]:
                        dependent[g, a] = True
                break
            j = 0
            while score_bits[j] != best:
                j += 1
            gsel[it - 1] = j
            for a in range(ng):
                if not active[a] or inv[a, j] == 0.0:
                    continue
                p = members[g, a]
                na = nsel[a]
                for i in range(m):
                    q[i] = B[i, pat[p, i], j]
                an = _dot(q, q, m)
                for t in range(na):
                    h[t] = 0.0
                for _ in range(2):
                    for t in range(na):
                        d = _dot(Q[a, t], q, m)
                        h[t] += d
                        for i in range(m):
                            q[i] -= d * Q[a, t, i]
                qn = np.sqrt(_dot(q, q, m))
                if not (qn > dep_tol * np.sqrt(an)):
                    dependent[g, a] = True
                    active[a] = False
                    n_active -= 1
                    continue
                for i in range(m):
                    q[i] /= qn
                    Q[a, na, i] = q[i]
                proj = _dot(q, r[a], m)
                for i in range(m):
                    r[a, i] -= proj * q[i]
                rr = _dot(r[a], r[a], m)
                for t in range(na):
                    R[a, t, na] = h[t]
                R[a, na, na] = qn
                qy[a, na] = proj
                index[g, a, na] = j
                nsel[a] = na + 1
                count[g, a] = na + 1
                res2[g, a] = rr
                if rr <= tol[p]:
                    active[a] = False
                    n_active -= 1
        for a in range(ng):
            n_sel = nsel[a]
            for t in range(n_sel - 1, -1, -1):
                v = qy[a, t]
                for u in range(t + 1, n_sel):
                    v -= R[a, t, u] * coef[g, a, u]
                coef[g, a, t] = v / R[a, t, t]
        if consensus > 0.0 and ng > 1 and it > 0:
            nj = it
            # the group's shared coefficients on its atoms: sum_p A_p^T A_p a = sum_p A_p^T y_p
            M[:nj, :nj] = 0.0
            bvec[:nj] = 0.0
            for a in range(ng):
                p = members[g, a]
                for u in range(nj):
                    for i in range(m):
                        A[i, u] = B[i, pat[p, i], gsel[u]]
                for u in range(nj):
                    s = 0.0
                    for i in range(m):
                        s += A[i, u] * y[p, i]
                    bvec[u] += s
                    for v2 in range(u + 1):
                        s = 0.0
                        for i in range(m):
                            s += A[i, u] * A[i, v2]
                        M[u, v2] += s
            tr = 0.0
            for u in range(nj):
                tr += M[u, u]
            for u in range(nj):
                M[u, u] += 1e-6 * tr / nj + 1e-30
            _chol_solve(M, bvec, nj, L, abar)
            for a in range(ng):
                n_sel = nsel[a]
                if n_sel == 0:
                    continue
                p = members[g, a]
                for u in range(n_sel):
                    for i in range(m):
                        A[i, u] = B[i, pat[p, i], index[g, a, u]]
                d = 0.0
                for u in range(n_sel):
                    s = 0.0
                    for i in range(m):
                        s += A[i, u] * A[i, u]
                    d += s
                lam = consensus * d / n_sel
                for u in range(n_sel):
                    jj = index[g, a, u]
                    prior = 0.0
                    for v2 in range(nj):
                        if gsel[v2] == jj:
                            prior = abar[v2]
                            break
                    s = 0.0
                    for i in range(m):
                        s += A[i, u] * y[p, i]
                    bvec[u] = s + lam * prior
                    for v2 in range(u + 1):
                        s = 0.0
                        for i in range(m):
                            s += A[i, u] * A[i, v2]
                        M[u, v2] = s
                    M[u, u] += lam + 1e-30
                _chol_solve(M, bvec, n_sel, L, h)
                rr = 0.0
                for i in range(m):
                    e = np.float64(y[p, i])
                    for u in range(n_sel):
                        e -= A[i, u] * h[u]
                    rr += e * e
                for u in range(n_sel):
                    coef[g, a, u] = h[u]
                res2[g, a] = rr


@njit(nogil=True, cache=True)
def scatter_patches(est, where, wgt, wp, patch, summed, weight):
    """Add patch estimates ``wgt[e] * est[e]`` (rows of ``N * patch**2``) at raster positions ``where[e]``.

    ``summed`` (N, h, w) and ``weight`` (h, w) accumulate in the order of ``e``.
    """
    n = summed.shape[0]
    m = patch * patch
    for e in range(est.shape[0]):
        p = where[e]
        if p < 0:
            continue
        r0 = p // wp
        c0 = p % wp
        wv = wgt[e]
        if wv == 0.0:
            continue
        for t in range(n):
            for dy in range(patch):
                for dx in range(patch):
                    summed[t, r0 + dy, c0 + dx] += wv * est[e, t * m + dy * patch + dx]
        for dy in range(patch):
            for dx in range(patch):
                weight[r0 + dy, c0 + dx] += wv
