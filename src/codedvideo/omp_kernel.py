"""Compiled OMP for codes whose pixels take few distinct shutter patterns.

A pixel's shutter pattern (which of the N sub-frames it integrates) is one of a
few: a single-bump code of bump length ``L`` has at most ``N - L + 1``.  Pixel
``i`` of a patch with pattern ``u`` sees row ``B[i, u] = sum_t pattern_u[t] D[t*m+i]``
of the masked dictionary, so ``A_p`` is a gather from the table ``B``
(``m x U x K``, under a megabyte for N = 8; :func:`codedvideo.omp.pattern_table`) and a
correlation is::

    A_p^T r = sum_i r_i B[i, u_p(i)]      (m * K multiply-adds)

``N / L`` times fewer operations than the dense ``D^T (Phi_p^T r)`` of
:class:`codedvideo.omp.MaskedOperator`, which spends them on the zeros of a
closed shutter.  A gather-and-add does not run at matrix-multiply speed in
numpy, so this kernel is compiled (numba): one patch at a time, its whole OMP
in cache (table rows, residual, thin QR), and the GIL released, so the tile
tasks of a thread pool run side by side.

It solves the same problem as :func:`codedvideo.omp.omp` with the same rules:
normalised selection rounded to 13 significant bits (:data:`SELECT_BITS`, ties
to the lowest atom), the :data:`MIN_VISIBLE` column floor, classical
Gram-Schmidt applied twice, the residual and linear-dependence stops.  Dot
products of length ``m`` accumulate in float64; correlations are float32.
Every patch is computed alone, so its answer never depends on its batch, tile
or worker.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from .omp import _TINY, DEPENDENCE_TOL, MIN_VISIBLE, SELECT_BITS, OmpResult, pattern_table

#: Largest pattern table (bytes) this path builds; beyond it (codes with many
#: distinct patterns, e.g. Bernoulli at large N) the dense operator is used.
MAX_TABLE_BYTES = 64 << 20


def table_fits(n_patterns: int, D: np.ndarray, patch_pixels: int) -> bool:
    """Whether the pattern table of a code with ``n_patterns`` patterns is small enough."""
    return patch_pixels * n_patterns * D.shape[1] * 4 <= MAX_TABLE_BYTES


@njit(nogil=True, cache=True, inline="always", fastmath={"contract"})
def _correlate(B, pat, r, c):
    """``c = sum_i r_i B[i, pat_i]``, eight table rows per pass over ``c`` (then four, then one)."""
    m = pat.size
    K = c.size
    c[:] = 0.0
    i = 0
    while i + 8 <= m:
        r0, r1, r2, r3 = np.float32(r[i]), np.float32(r[i + 1]), np.float32(r[i + 2]), np.float32(r[i + 3])
        r4, r5, r6, r7 = np.float32(r[i + 4]), np.float32(r[i + 5]), np.float32(r[i + 6]), np.float32(r[i + 7])
        b0, b1, b2, b3 = B[i, pat[i]], B[i + 1, pat[i + 1]], B[i + 2, pat[i + 2]], B[i + 3, pat[i + 3]]
        b4, b5, b6, b7 = B[i + 4, pat[i + 4]], B[i + 5, pat[i + 5]], B[i + 6, pat[i + 6]], B[i + 7, pat[i + 7]]
        for k in range(K):
            c[k] += ((r0 * b0[k] + r1 * b1[k]) + (r2 * b2[k] + r3 * b3[k])) + ((r4 * b4[k] + r5 * b5[k]) + (r6 * b6[k] + r7 * b7[k]))
        i += 8
    while i + 4 <= m:
        r0, r1, r2, r3 = np.float32(r[i]), np.float32(r[i + 1]), np.float32(r[i + 2]), np.float32(r[i + 3])
        b0, b1, b2, b3 = B[i, pat[i]], B[i + 1, pat[i + 1]], B[i + 2, pat[i + 2]], B[i + 3, pat[i + 3]]
        for k in range(K):
            c[k] += (r0 * b0[k] + r1 * b1[k]) + (r2 * b2[k] + r3 * b3[k])
        i += 4
    while i < m:
        ri = np.float32(r[i])
        bi = B[i, pat[i]]
        for k in range(K):
            c[k] += ri * bi[k]
        i += 1


@njit(nogil=True, cache=True, fastmath={"contract"})
def _omp_kernel(y, pat, B, B2, floor, tol, kmax, dep_tol, select_bits, tiny, index, coef, count, res2, dependent):
    P, m = y.shape
    K = B.shape[2]
    c = np.empty(K, np.float32)
    score = np.empty(K, np.float32)
    score_bits = score.view(np.int32)
    inv = np.empty(K, np.float32)
    Q = np.zeros((kmax, m), np.float64)
    R = np.zeros((kmax, kmax), np.float64)
    qy = np.zeros(kmax, np.float64)
    h = np.zeros(kmax, np.float64)
    r = np.empty(m, np.float64)
    q = np.empty(m, np.float64)
    for p in range(P):
        s = 0.0
        for i in range(m):
            r[i] = y[p, i]
            s += r[i] * r[i]
        res2[p] = s
        count[p] = 0
        dependent[p] = False
        if s <= tol[p]:
            continue
        # squared column norms of A_p, then the usable columns' inverse norms
        c[:] = 0.0
        for i in range(m):
            row = B2[i, pat[p, i]]
            for k in range(K):
                c[k] += row[k]
        big = 0.0  # the zero-column floor is relative to the patch's largest column: any atom scale
        for k in range(K):
            inv[k] = np.sqrt(max(c[k], np.float32(0.0)))
            big = max(big, inv[k])
        for k in range(K):
            nk = inv[k]
            inv[k] = np.float32(1.0) / nk if (nk > tiny * big and nk > floor[k]) else np.float32(0.0)
        n_sel = 0
        for it in range(kmax):
            _correlate(B, pat[p], r, c)
            for k in range(K):
                score[k] = c[k] * inv[k]
            best = np.int32(0)
            for k in range(K):  # a max reduction (vectorised), then the first index reaching it
                score_bits[k] &= select_bits
                best = max(best, score_bits[k])
            j = 0
            while score_bits[j] != best:
                j += 1
            # Gram-Schmidt, twice, of the chosen column against the selected ones
            an = 0.0
            for i in range(m):
                q[i] = B[i, pat[p, i], j]
                an += q[i] * q[i]
            for t in range(it):
                h[t] = 0.0
            for _ in range(2):
                for t in range(it):
                    d = 0.0
                    for i in range(m):
                        d += Q[t, i] * q[i]
                    h[t] += d
                    for i in range(m):
                        q[i] -= d * Q[t, i]
            qn = 0.0
            for i in range(m):
                qn += q[i] * q[i]
            qn = np.sqrt(qn)
            if not (qn > dep_tol * np.sqrt(an) and best > 0):
                dependent[p] = True
                break
            proj = 0.0
            for i in range(m):
                q[i] /= qn
                Q[it, i] = q[i]
                proj += q[i] * r[i]
            rr = 0.0
            for i in range(m):
                r[i] -= proj * q[i]
                rr += r[i] * r[i]
            for t in range(it):
                R[t, it] = h[t]
            R[it, it] = qn
            qy[it] = proj
            index[p, it] = j
            n_sel = it + 1
            count[p] = n_sel
            res2[p] = rr
            if rr <= tol[p]:
                break
        for t in range(n_sel - 1, -1, -1):  # back-substitution R x = Q^T y
            v = qy[t]
            for u in range(t + 1, n_sel):
                v -= R[t, u] * coef[p, u]
            coef[p, t] = v / R[t, t]


@njit(nogil=True, cache=True)
def _omp_weights_kernel(y, S, D3, floor, tol, kmax, dep_tol, select_bits, tiny, index, coef, count, res2, dependent):
    """:func:`_omp_kernel` for patches whose pixels each have their own weights (a calibrated mask).

    Every patch gets its own one-pattern table ``B[i, 0] = sum_t S[p, t, i] D[t, i]``,
    built in cache (``N m K`` multiply-adds, about one dense correlation), then the
    table kernel itself solves it, every rule unchanged: later correlations cost
    ``m K``.  The rows are summed exactly as :func:`codedvideo.omp.pattern_table`
    sums them (sub-frame order, each product rounded before it is added: this
    function is compiled without contraction), and the table kernel is called on
    contiguous arrays of the types :class:`TableOMP` passes, so a patch gets the
    same bits here as through a shared pattern table: the choice between the two
    (which depends on how many patterns a region holds) never changes a result.
    """
    P, N, m = S.shape
    K = D3.shape[2]
    B = np.zeros((m, 1, K), np.float32)
    B2 = np.zeros((m, 1, K), np.float32)
    pat = np.zeros((1, m), np.int32)
    y1 = np.empty((1, m), np.float32)
    tol1 = np.empty(1, np.float64)
    index1 = np.zeros((1, index.shape[1]), np.int32)
    coef1 = np.zeros((1, coef.shape[1]), np.float32)
    count1 = np.zeros(1, np.int32)
    res1 = np.zeros(1, np.float32)
    dep1 = np.zeros(1, np.bool_)
    for p in range(P):
        for i in range(m):
            row = B[i, 0]
            row[:] = 0.0
            for t in range(N):
                w = S[p, t, i]
                if w != 0.0:
                    d = D3[t, i]
                    for k in range(K):
                        row[k] += w * d[k]
            row2 = B2[i, 0]
            for k in range(K):
                row2[k] = row[k] * row[k]
        for i in range(m):
            y1[0, i] = y[p, i]
        tol1[0] = tol[p]
        index1[:] = 0
        coef1[:] = 0.0
        _omp_kernel(y1, pat, B, B2, floor, tol1, kmax, dep_tol, select_bits, tiny, index1, coef1, count1, res1, dep1)
        index[p, :] = index1[0]
        coef[p, :] = coef1[0]
        count[p] = count1[0]
        res2[p] = res1[0]
        dependent[p] = dep1[0]


@njit(nogil=True, cache=True)
def still_kernel(y, n_pix, C, tol, atoms, ok, frame):
    """The still-scene test of :func:`codedvideo.reconstruct.still_patches`, one patch at a time.

    ``frame[p]`` (zeros on entry) gets the still image of every passing patch
    ``ok[p]``: the fewest of its largest 2D DCT coefficients (columns of ``C``,
    ties to the lower frequency) whose weighted residual
    ``||n * (y / n - s_k)||^2`` is within ``tol[p]``, at most ``atoms``.
    """
    P, m = y.shape
    k_max = min(atoms, m)
    s = np.empty(m, np.float64)
    c = np.empty(m, np.float64)
    mag = np.empty(m, np.float64)
    top = np.empty(max(k_max, 1), np.int64)
    approx = np.empty(m, np.float64)
    for p in range(P):
        ok[p] = False
        yy = 0.0
        ss = 0.0
        nmin = n_pix[p, 0]
        nmax = nmin
        for i in range(m):
            ni = n_pix[p, i]
            nmin = min(nmin, ni)
            nmax = max(nmax, ni)
            yi = np.float64(y[p, i])
            yy += yi * yi
            s[i] = yi / ni if ni > 0 else 0.0
            ss += s[i] * s[i]
        if nmin <= 0:  # a pixel never open: left to the full dictionary
            continue
        if yy <= tol[p]:
            ok[p] = True  # zero atoms suffice
            continue
        c[:] = 0.0
        for i in range(m):
            si = s[i]
            for k in range(m):
                c[k] += si * C[i, k]
        # the k_max largest |c|, in order (insertion; ties keep the lower frequency first)
        n_top = 0
        for k in range(m):
            v = abs(c[k])
            if n_top == k_max and v <= mag[top[n_top - 1]]:
                continue
            j = min(n_top, k_max - 1)
            while j > 0 and mag[top[j - 1]] < v:
                top[j] = top[j - 1]
                j -= 1
            top[j] = k
            mag[k] = v
            n_top = min(n_top + 1, k_max)
        used = -1
        if nmin == nmax:  # one open count (every fixed-bump code): C orthonormal, residual closed-form
            rest = ss
            for j in range(n_top):
                rest -= c[top[j]] * c[top[j]]
                if nmin * nmin * rest <= tol[p]:
                    used = j + 1
                    break
        else:  # measured exactly, one atom at a time
            approx[:] = 0.0
            for j in range(n_top):
                e = 0.0
                for i in range(m):
                    approx[i] += c[top[j]] * C[i, top[j]]
                    d = n_pix[p, i] * (s[i] - approx[i])
                    e += d * d
                if e <= tol[p]:
                    used = j + 1
                    break
        if used > 0:
            ok[p] = True
            for j in range(used):
                for i in range(m):
                    frame[p, i] += c[top[j]] * C[i, top[j]]


@njit(nogil=True, cache=True, fastmath={"contract"})
def synthesize_into(index, coef, count, Dt, out):
    """``out[p] = sum_t coef[p, t] Dt[index[p, t]]`` over the ``count[p]`` selected atoms."""
    for p in range(index.shape[0]):
        out[p, :] = 0.0
        for t in range(count[p]):
            a = coef[p, t]
            row = Dt[index[p, t]]
            for e in range(out.shape[1]):
                out[p, e] += a * row[e]


def _visibility_floor(D: np.ndarray) -> np.ndarray:
    """Per atom, the smallest coded-column norm that may be selected (``MIN_VISIBLE`` of the atom's norm)."""
    atom_norms = np.sqrt((D.astype(np.float64) ** 2).sum(0)).astype(np.float32)
    return (MIN_VISIBLE * atom_norms).astype(np.float32)


class TableOMP:
    """OMP over the patches of one region through its pixel-pattern table.

    Parameters
    ----------
    patterns : ndarray of shape (U, N)
        From :func:`pixel_patterns`.
    D : ndarray of shape (N*m, K)
    patch_pixels : int
        ``m`` (49 for 7x7 patches).
    """

    def __init__(self, patterns: np.ndarray, D: np.ndarray, patch_pixels: int):
        D = np.asarray(D, dtype=np.float32)
        self.B = pattern_table(patterns, D, patch_pixels)
        self.B2 = self.B * self.B
        self.floor = _visibility_floor(D)

    def solve(self, y: np.ndarray, pat: np.ndarray, *, max_atoms: int, tol) -> OmpResult:
        """OMP of patches ``y`` (P, m) whose pixels have patterns ``pat`` (P, m)."""
        y = np.ascontiguousarray(y, dtype=np.float32)
        pat = np.ascontiguousarray(pat, dtype=np.int32)
        P, m = y.shape
        kmax = int(min(max_atoms, m))
        tol = np.ascontiguousarray(np.broadcast_to(np.asarray(tol, dtype=np.float64), (P,)))
        index = np.zeros((P, kmax), np.int32)
        coef = np.zeros((P, kmax), np.float32)
        count = np.zeros(P, np.int32)
        res2 = np.zeros(P, np.float32)
        dependent = np.zeros(P, np.bool_)
        _omp_kernel(y, pat, self.B, self.B2, self.floor, tol, kmax, DEPENDENCE_TOL, SELECT_BITS,
                    _TINY, index, coef, count, res2, dependent)
        return OmpResult(index=index, coef=coef, count=count, residual=res2, dependent=dependent)



class WeightsOMP:
    """OMP of patches whose pixels take any weights (a calibrated, fractional mask), compiled.

    The same problem and rules as :class:`TableOMP`, with a table of one
    pattern per patch built inside the kernel (:func:`_omp_weights_kernel`):
    about half the multiply-adds of the dense numpy operator, whose column
    norms and ``D^T (Phi_p^T r)`` correlations are recomputed through the zeros
    and fractions of every patch.  Every patch is solved alone, so its answer
    never depends on its batch, tile or worker.

    Parameters
    ----------
    D : ndarray of shape (N*m, K)
    patch_pixels : int
        ``m`` (49 for 7x7 patches).
    """

    def __init__(self, D: np.ndarray, patch_pixels: int):
        D = np.asarray(D, dtype=np.float32)
        self.m = patch_pixels
        self.n = D.shape[0] // patch_pixels
        self.D3 = np.ascontiguousarray(D.reshape(self.n, patch_pixels, D.shape[1]))
        self.floor = _visibility_floor(D)

    def solve(self, y: np.ndarray, S: np.ndarray, *, max_atoms: int, tol) -> OmpResult:
        """OMP of patches ``y`` (P, m) whose pixels have weights ``S`` (P, N, m)."""
        y = np.ascontiguousarray(y, dtype=np.float32)
        S = np.ascontiguousarray(S, dtype=np.float32)
        P, m = y.shape
        if S.shape != (P, self.n, m):
            raise ValueError(f"weights of shape {S.shape}, expected {(P, self.n, m)}")
        kmax = int(min(max_atoms, m))
        tol = np.ascontiguousarray(np.broadcast_to(np.asarray(tol, dtype=np.float64), (P,)))
        index = np.zeros((P, kmax), np.int32)
        coef = np.zeros((P, kmax), np.float32)
        count = np.zeros(P, np.int32)
        res2 = np.zeros(P, np.float32)
        dependent = np.zeros(P, np.bool_)
        _omp_weights_kernel(y, S, self.D3, self.floor, tol, kmax, DEPENDENCE_TOL, SELECT_BITS, _TINY, index, coef,
                            count, res2, dependent)
        return OmpResult(index=index, coef=coef, count=count, residual=res2, dependent=dependent)


def load_kernels() -> float:
    """Compile (first use after install) or load (later) the kernels; returns the seconds spent.

    Happens once per process on first use anyway; benchmarks call it first so
    that the one-off cost is reported on its own instead of inside the first
    timed reconstruction.
    """
    import time

    from .omp import synthesize

    t = time.perf_counter()
    D = np.eye(8, 12, dtype=np.float32)
    table = TableOMP(np.eye(2, dtype=np.float32), D, 4)
    res = table.solve(np.ones((1, 4), np.float32), np.zeros((1, 4), np.int32), max_atoms=2, tol=0.0)
    synthesize(res, D)
    still_kernel(np.ones((1, 4), np.float32), np.ones((1, 4)), np.eye(4), np.zeros(1), 1, np.zeros(1, np.bool_),
                 np.zeros((1, 4)))
    return time.perf_counter() - t
