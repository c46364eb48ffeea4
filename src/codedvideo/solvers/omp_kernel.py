"""Compiled OMP for codes whose pixels take few distinct shutter patterns.

A pixel's shutter pattern (which of the N sub-frames it integrates) is one of a
few: a single-bump code of bump length ``L`` has at most ``N - L + 1``.  Pixel
``i`` of a patch with pattern ``u`` sees row ``B[i, u] = sum_t pattern_u[t] D[t*m+i]``
of the masked dictionary, so ``A_p`` is a gather from the table ``B``
(``m x U x K``, under a megabyte for N = 8; :func:`codedvideo.solvers.omp.pattern_table`) and a
correlation is::

    A_p^T r = sum_i r_i B[i, u_p(i)]      (m * K multiply-adds)

``N / L`` times fewer operations than the dense ``D^T (Phi_p^T r)`` of
:class:`codedvideo.solvers.omp.MaskedOperator`, which spends them on the zeros of a
closed shutter.  A gather-and-add does not run at matrix-multiply speed in
numpy, so this kernel is compiled (numba): one patch at a time, its whole OMP
in cache (table rows, residual, thin QR), and the GIL released, so the tile
tasks of a thread pool run side by side.  A code with many patterns (Bernoulli
at N = 8: 256 patterns, a 25 MB table that no cache holds) pays for bringing
its 49 rows into cache once per patch: the column norms are computed from those
rows (no second table of squares), and the table is built compiled and kept
for the next tiles (:func:`shared_table`) instead of once per tile.

It solves the same problem as :func:`codedvideo.solvers.omp.omp` with the same rules:
normalised selection rounded to 13 significant bits (:data:`SELECT_BITS`, ties
to the lowest atom), the :data:`MIN_VISIBLE` column floor, classical
Gram-Schmidt applied twice, the residual and linear-dependence stops.  Dot
products of length ``m`` accumulate in float64; correlations are float32.
Every patch is computed alone, so its answer never depends on its batch, tile
or worker.

K-SVD's coding step, where every signal shares one unmasked dictionary, has
its own kernel here (numba is imported by this module only):
:func:`batch_omp`, Batch-OMP from the Gram matrix ``D^T D`` and one matrix
product ``X D``, with the same selection and stopping rules.  So do the
residual and the atom-by-atom dictionary update of :mod:`codedvideo.solvers.ksvd`
(:func:`subtract_codes`, :func:`update_atoms`).
"""

from __future__ import annotations

import hashlib
import threading
from collections import OrderedDict

import numpy as np
from numba import njit, prange

from codedvideo.solvers.omp import _TINY, DEPENDENCE_TOL, MIN_VISIBLE, SELECT_BITS, OmpResult, _safe_inverse

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


@njit(nogil=True, cache=True, inline="always", fastmath={"contract"})
def _dot(a, b, m):
    """``sum_i a_i b_i`` over the first ``m`` in four interleaved partial sums added ``(s0 + s1) + (s2 + s3)``,
    then the tail in order: a fixed order (the same bits on every machine and thread count) whose four
    dependency chains run side by side instead of one multiply-add waiting for the last (the Gram-Schmidt
    steps of OMP were bound by that latency)."""
    s0 = s1 = s2 = s3 = 0.0
    i = 0
    while i + 4 <= m:
        s0 += a[i] * b[i]
        s1 += a[i + 1] * b[i + 1]
        s2 += a[i + 2] * b[i + 2]
        s3 += a[i + 3] * b[i + 3]
        i += 4
    s = (s0 + s1) + (s2 + s3)
    while i < m:
        s += a[i] * b[i]
        i += 1
    return s


@njit(nogil=True, cache=True, fastmath=False)
def _column_norms2(B, pat, c):
    """``c[k] = sum_i B[i, pat_i, k]**2`` in float32, every square rounded before it is added.

    Compiled without contraction (a fused multiply-add would skip that rounding),
    so the norms are the sums of the float32 squares ``B * B``, in pixel order.
    ``fastmath=False`` is explicit: numba compiles a callee that does not set it
    with its caller's flags, and :func:`_omp_kernel` allows contraction.
    Read from the table rows themselves: a table of squares beside ``B`` would
    double the bytes a patch brings into cache (the table of a code with many
    patterns does not fit in it).
    """
    K = c.size
    c[:] = 0.0
    for i in range(pat.size):
        row = B[i, pat[i]]
        for k in range(K):
            c[k] += row[k] * row[k]


@njit(nogil=True, cache=True, fastmath={"contract"})
def _column_norms2_as_in_kernel(B, pat, c):
    _column_norms2(B, pat, c)


def column_norms2(B: np.ndarray, pat: np.ndarray) -> np.ndarray:
    """The squared column norms of one patch's ``A_p`` as :func:`_omp_kernel` computes them (for tests).

    Called from a function compiled with the kernel's flags, so a test sees
    whether contraction leaks into the norms (it would change selected atoms).
    """
    c = np.empty(B.shape[2], np.float32)
    _column_norms2_as_in_kernel(B, np.ascontiguousarray(pat, dtype=np.int32), c)
    return c


@njit(nogil=True, cache=True, fastmath=False)
def _fill_table(patterns, D3, B):
    """``B[i, u] = sum_t patterns[u, t] D3[t, i]``: each row summed in sub-frame order from zero.

    Compiled without contraction: each product is rounded before it is added,
    exactly as :func:`codedvideo.solvers.omp.pattern_table` (numpy) sums them.
    """
    U, N = patterns.shape
    m, K = D3.shape[1], D3.shape[2]
    for i in range(m):
        for u in range(U):
            row = B[i, u]
            row[:] = 0.0
            for t in range(N):
                w = patterns[u, t]
                if w != 0.0:
                    d = D3[t, i]
                    for k in range(K):
                        row[k] += w * d[k]


def build_table(patterns: np.ndarray, D: np.ndarray, patch_pixels: int) -> np.ndarray:
    """:func:`codedvideo.solvers.omp.pattern_table`, compiled (the same bits; GIL released).

    The numpy version makes a pass over the whole table per sub-frame; a code
    with many patterns (Bernoulli at N = 8: 256 patterns, 25 MB) spent a tenth
    of a tile's time there.
    """
    patterns = np.ascontiguousarray(patterns, dtype=np.float32)
    n = patterns.shape[1]
    D3 = np.ascontiguousarray(np.asarray(D, dtype=np.float32).reshape(n, patch_pixels, -1))
    B = np.empty((patch_pixels, patterns.shape[0], D3.shape[2]), np.float32)
    _fill_table(patterns, D3, B)
    return B


@njit(nogil=True, cache=True, fastmath={"contract"})
def _omp_kernel(y, pat, B, floor, tol, kmax, dep_tol, select_bits, tiny, index, coef, count, res2, dependent):
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
        _column_norms2(B, pat[p], c)  # squared column norms of A_p, then the usable columns' inverse norms
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
            for i in range(m):
                q[i] = B[i, pat[p, i], j]
            an = _dot(q, q, m)
            for t in range(it):
                h[t] = 0.0
            for _ in range(2):
                for t in range(it):
                    d = _dot(Q[t], q, m)
                    h[t] += d
                    for i in range(m):
                        q[i] -= d * Q[t, i]
            qn = np.sqrt(_dot(q, q, m))
            if not (qn > dep_tol * np.sqrt(an) and best > 0):
                dependent[p] = True
                break
            for i in range(m):
                q[i] /= qn
                Q[it, i] = q[i]
            proj = _dot(q, r, m)
            for i in range(m):
                r[i] -= proj * q[i]
            rr = _dot(r, r, m)
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
    ``m K``.  The rows are summed exactly as :func:`codedvideo.solvers.omp.pattern_table`
    sums them (sub-frame order, each product rounded before it is added: this
    function is compiled without contraction), and the table kernel is called on
    contiguous arrays of the types :class:`TableOMP` passes, so a patch gets the
    same bits here as through a shared pattern table: the choice between the two
    (which depends on how many patterns a region holds) never changes a result.
    """
    P, N, m = S.shape
    K = D3.shape[2]
    B = np.zeros((m, 1, K), np.float32)
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
        for i in range(m):
            y1[0, i] = y[p, i]
        tol1[0] = tol[p]
        index1[:] = 0
        coef1[:] = 0.0
        _omp_kernel(y1, pat, B, floor, tol1, kmax, dep_tol, select_bits, tiny, index1, coef1, count1, res1, dep1)
        index[p, :] = index1[0]
        coef[p, :] = coef1[0]
        count[p] = count1[0]
        res2[p] = res1[0]
        dependent[p] = dep1[0]


@njit(nogil=True, cache=True)
def still_kernel(y, n_pix, C, tol, atoms, ok, frame):
    """The still-scene test of :func:`codedvideo.solvers.region.still_patches`, one patch at a time.

    ``frame[p]`` (zeros on entry) gets the still image of every passing patch
    ``ok[p]``: the fewest of its largest 2D DCT coefficients (columns of ``C``,
    ties to the lower frequency) whose weighted residual
    ``||n * (y / n - s_k)||^2`` is within ``tol[p]``, at most ``atoms``; a patch
    whose coded values are themselves within ``tol[p]`` gets ``y / n``.
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
        if yy <= tol[p]:  # a patch as dark as the tolerance: its still answer (zero atoms would give 0)
            ok[p] = True
            for i in range(m):
                frame[p, i] = s[i]
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


#: Pattern tables kept for the next regions: the tiles of one image share their code's patterns
#: and the dictionary, and a table with many patterns (25 MB for Bernoulli at N = 8) is worth keeping.
TABLES_KEPT = 2
_tables: OrderedDict = OrderedDict()
_tables_lock = threading.Lock()


def shared_table(patterns: np.ndarray, D: np.ndarray, patch_pixels: int) -> np.ndarray:
    """:func:`build_table`, reused while the same patterns and dictionary come back (read only).

    Keyed by the contents of both (a hash), so a table is never reused for
    another dictionary or code; the last :data:`TABLES_KEPT` are kept.  One
    builder at a time: a tile that asks while another builds the same table waits for it.
    """
    patterns = np.ascontiguousarray(patterns, dtype=np.float32)
    D = np.ascontiguousarray(D, dtype=np.float32)
    h = hashlib.blake2b(digest_size=16)
    h.update(np.array([patch_pixels, *patterns.shape, *D.shape], np.int64).tobytes())
    h.update(patterns.data)
    h.update(D.data)
    key = h.digest()
    with _tables_lock:
        B = _tables.get(key)
        if B is None:
            B = build_table(patterns, D, patch_pixels)
            _tables[key] = B
            while len(_tables) > TABLES_KEPT:
                _tables.popitem(last=False)
        _tables.move_to_end(key)
    return B


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
        self.B = shared_table(patterns, D, patch_pixels)
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
        _omp_kernel(y, pat, self.B, self.floor, tol, kmax, DEPENDENCE_TOL, SELECT_BITS,
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


#: Signals per block of :func:`_batch_omp_kernel`: a thread allocates its work arrays once per block.
_BATCH_BLOCK = 256


@njit(parallel=True, nogil=True, cache=True, fastmath={"reassoc", "contract"})
def _batch_omp_kernel(X, Dt, alpha0, G, inv, tol, kmax, dep_tol, select_bits, index, coef, count, res2, dependent):
    """Batch-OMP (Rubinstein, Zibulevsky and Elad 2008) of the signals ``X`` given ``alpha0 = X D``.

    Only the Gram matrix ``G = D^T D`` and the initial correlations are used:
    with the selected atoms ``I``, the Cholesky factor ``L L^T = G[I, I]`` and
    ``z = L^{-1} D[:, I]^T x`` (so ``gamma = L^{-T} z``), the correlations of
    the residual are ``alpha0 - G[:, I] gamma`` and its squared norm is
    ``||x||^2 - ||z||^2``.  ``L`` is the transpose of the ``R`` of the thin QR
    that :func:`codedvideo.solvers.omp.omp` keeps, and ``z`` its ``Q^T y``: the same
    pursuit, without a residual vector.

    ``alpha0`` (float32 or float64) only ranks the atoms.  The correlations of
    the selected atoms, from which ``z``, the coefficients and the residual
    follow, are recomputed in float64 from ``X`` and ``Dt`` (``m`` multiply-adds
    an atom): the residual is a difference of two nearly equal energies, and
    float32 correlations (relative error ~1e-7 of ``||x||^2``) would decide a
    small tolerance by roundoff.
    """
    P, K = alpha0.shape
    m = X.shape[1]
    n_blocks = (P + _BATCH_BLOCK - 1) // _BATCH_BLOCK
    for b in prange(n_blocks):
        alpha = np.empty(K, np.float64)
        score = np.empty(K, np.float32)
        score_bits = score.view(np.int32)
        L = np.zeros((kmax, kmax), np.float64)
        z = np.zeros(kmax, np.float64)
        w = np.zeros(kmax, np.float64)
        gamma = np.zeros(kmax, np.float64)
        sel = np.zeros(kmax, np.int64)
        for p in range(b * _BATCH_BLOCK, min(P, (b + 1) * _BATCH_BLOCK)):
            rr = 0.0
            for e in range(m):
                rr += np.float64(X[p, e]) ** 2
            res2[p] = rr
            count[p] = 0
            dependent[p] = False
            if rr <= tol[p]:
                continue
            for k in range(K):
                alpha[k] = alpha0[p, k]
            n_sel = 0
            for it in range(kmax):
                # selection exactly as omp._select: |score| rounded to 13 bits, ties to the lowest atom
                best = np.int32(0)
                for k in range(K):
                    score[k] = np.float32(alpha[k]) * inv[k]
                    score_bits[k] &= select_bits
                    best = max(best, score_bits[k])
                j = 0
                while score_bits[j] != best:
                    j += 1
                # new row of the Cholesky factor: L[:it, :it] w = G[I, j]
                for t in range(it):
                    v = G[sel[t], j]
                    for s in range(t):
                        v -= L[t, s] * w[s]
                    w[t] = v / L[t, t]
                gjj = G[j, j]
                piv = gjj
                for t in range(it):
                    piv -= w[t] * w[t]
                # sqrt(piv) is the norm of the atom's component outside the span of the selected ones
                # (R[it, it] of the QR path), so the dependence stop is the same test
                qn = np.sqrt(piv) if piv > 0.0 else 0.0
                if not (qn > dep_tol * np.sqrt(max(gjj, 0.0)) and best > 0):
                    dependent[p] = True
                    break
                for t in range(it):
                    L[it, t] = w[t]
                L[it, it] = qn
                sel[it] = j
                v = 0.0
                for e in range(m):
                    v += np.float64(X[p, e]) * np.float64(Dt[j, e])
                for t in range(it):
                    v -= L[it, t] * z[t]
                z[it] = v / qn
                rr -= z[it] * z[it]  # the new orthonormal direction removes z[it]**2 of the energy
                n_sel = it + 1
                if rr < 0.0:
                    rr = 0.0
                # gamma = L^-T z: the coefficients on the selected atoms
                for t in range(n_sel - 1, -1, -1):
                    v = z[t]
                    for s in range(t + 1, n_sel):
                        v -= L[s, t] * gamma[s]
                    gamma[t] = v / L[t, t]
                if rr <= tol[p] or n_sel == kmax:
                    break
                # correlations of the new residual: alpha0 - G[:, I] gamma (G symmetric: rows of G)
                for k in range(K):
                    alpha[k] = alpha0[p, k]
                for t in range(n_sel):
                    g = G[sel[t]]
                    c = gamma[t]
                    for k in range(K):
                        alpha[k] -= c * g[k]
            count[p] = n_sel
            res2[p] = rr
            for t in range(n_sel):
                index[p, t] = sel[t]
                coef[p, t] = gamma[t]


def batch_omp(X: np.ndarray, D: np.ndarray, *, max_atoms: int, tol=0.0, chunk: int = 8192,
              precision=np.float32) -> OmpResult:
    """OMP of many signals over one dictionary (Batch-OMP), compiled and parallel over signals.

    The same problem and rules as :func:`codedvideo.solvers.omp.omp` with
    :class:`codedvideo.solvers.omp.PlainOperator` (normalised selection rounded to
    :data:`SELECT_BITS`, ties to the lowest atom, the residual, sparsity and
    linear-dependence stops), computed from ``G = D^T D`` (once) and
    ``X D`` (one matrix product per chunk of signals) instead of explicit
    residuals, as suits K-SVD's coding step where every signal shares ``D``.

    Parameters
    ----------
    X : ndarray of shape (P, m)
        Signals (rows).
    D : ndarray of shape (m, K)
        Dictionary; atoms of any norm (selection is by normalised correlation,
        zero atoms are never selected).
    max_atoms : int
        Maximum atoms per signal (``<= m``).
    tol : float or ndarray of shape (P,)
        Stop when the squared residual ``||D alpha - x||^2 <= tol``.
    chunk : int
        Signals per matrix product ``X D`` (bounds the memory to ``chunk * K`` values).
    precision : dtype
        Of the product ``X D`` that ranks the atoms: float32 (the precision of
        the numpy path's correlations, and twice as fast) or float64.  The
        pursuit itself (Cholesky factor, coefficients, residual) is float64.

    Returns
    -------
    OmpResult
        ``index``, ``coef`` (coefficients of the atoms of ``D`` as given) of shape
        (P, min(max_atoms, m)); ``count``; ``residual`` (squared, float32); ``dependent``.
    """
    X = np.ascontiguousarray(X, dtype=np.float32)
    D = np.ascontiguousarray(D, dtype=np.float32)
    P, m = X.shape
    if D.shape[0] != m:
        raise ValueError(f"dictionary has {D.shape[0]} rows, signals have {m} entries")
    kmax = int(min(max_atoms, m))
    D64 = D.astype(np.float64)
    G = D64.T @ D64
    # the same inverse norms as PlainOperator, so that the rounded scores are the same numbers
    inv = _safe_inverse(np.sqrt((D64**2).sum(0)).astype(np.float32))
    tol = np.ascontiguousarray(np.broadcast_to(np.asarray(tol, dtype=np.float64), (P,)))
    index = np.zeros((P, kmax), np.int32)
    coef64 = np.zeros((P, kmax), np.float64)
    count = np.zeros(P, np.int32)
    res2 = np.zeros(P, np.float64)
    dependent = np.zeros(P, np.bool_)
    Dp = D64 if np.dtype(precision) == np.float64 else D
    Dt = np.ascontiguousarray(D.T)
    for a in range(0, P, chunk):
        b = min(P, a + chunk)
        alpha0 = X[a:b].astype(Dp.dtype, copy=False) @ Dp
        _batch_omp_kernel(X[a:b], Dt, alpha0, G, inv, tol[a:b], kmax, DEPENDENCE_TOL, SELECT_BITS, index[a:b],
                          coef64[a:b], count[a:b], res2[a:b], dependent[a:b])
    return OmpResult(index=index, coef=coef64.astype(np.float32), count=count, residual=res2.astype(np.float32),
                     dependent=dependent)


@njit(parallel=True, nogil=True, cache=True, fastmath={"reassoc", "contract"})
def subtract_codes(X, index, coef, count, Dt, E, err):
    """K-SVD's residual ``E[p] = X[p] - sum_t coef[p, t] Dt[index[p, t]]`` (``count[p]`` atoms) and ``err[p] = ||E[p]||^2``.

    Parameters
    ----------
    X : ndarray of shape (P, f), float32
    index, coef, count : ndarray
        An :class:`codedvideo.solvers.omp.OmpResult`'s fields.
    Dt : ndarray of shape (K, f), float32
        Atoms as rows.
    E : ndarray of shape (P, f), float32
        Output.
    err : ndarray of shape (P,), float64
        Output.
    """
    for p in prange(X.shape[0]):
        for e in range(X.shape[1]):
            E[p, e] = X[p, e]
        for t in range(count[p]):
            a = coef[p, t]
            row = Dt[index[p, t]]
            for e in range(X.shape[1]):
                E[p, e] -= a * row[e]
        s = 0.0
        for e in range(X.shape[1]):
            s += np.float64(E[p, e]) ** 2
        err[p] = s


@njit(parallel=True, nogil=True, cache=True, fastmath={"reassoc", "contract"})
def row_energy(E):
    """``sum_e E[p, e]**2`` of every row, float64, shape (P,)."""
    out = np.empty(E.shape[0], np.float64)
    for p in prange(E.shape[0]):
        s = 0.0
        for e in range(E.shape[1]):
            s += np.float64(E[p, e]) ** 2
        out[p] = s
    return out


@njit(nogil=True, cache=True, fastmath={"reassoc", "contract"})
def update_atoms(E, err, Dt, coef, atoms, order, bounds, power_steps):
    """K-SVD's dictionary update of ``atoms``, one after the other (each sees the previous ones' residual).

    For atom ``k`` with users ``r`` (the samples whose code uses it, at slot ``s``):
    ``E_k = E[r] + coef[r, s] d_k^T``; its leading singular pair by
    ``power_steps`` power-iteration steps warm-started from ``d_k``
    (``x = E_k d``, ``d = E_k^T x / ||E_k^T x||``) gives the new unit atom ``d``
    and coefficients ``x = E_k d``; then ``E[r] = E_k - x d^T``.

    Each step is one pass over the rows of ``E_k``: ``x_i = E_k[i] d`` and its
    share of ``E_k^T x`` while the row is in cache (the sums may be reordered
    into vector lanes: the same machine code gives the same bits).  Single-threaded on
    purpose: an atom's update is a few hundred microseconds, and parallel
    regions that short (two per step) stall whenever another process holds a
    core, which made the update ten times slower on a shared machine.  Dot
    products accumulate in float64; ``E``, ``Dt`` and ``coef`` stay float32.

    Parameters
    ----------
    E : ndarray of shape (P, f), float32
        Residual of every sample (updated).
    err : ndarray of shape (P,), float64
        ``||E[p]||^2`` (updated with ``E``).
    Dt : ndarray of shape (K, f), float32
        Atoms as rows (updated).
    coef : ndarray of shape (P, S), float32
        Coefficients of every sample's code (updated).
    atoms : ndarray of shape (n,), int
        Atoms to update, in this order; every one has at least one user.
    order, bounds : ndarray
        Users of atom ``k``: the flat positions ``order[bounds[k]:bounds[k + 1]]``
        into ``coef`` (position ``r * S + s``).
    power_steps : int
    """
    f = E.shape[1]
    S = coef.shape[1]
    most = 0
    for k in atoms:
        most = max(most, bounds[k + 1] - bounds[k])
    Ek = np.empty((most, f), np.float32)
    d = np.empty(f, np.float64)
    dn = np.empty(f, np.float64)
    d32 = np.empty(f, np.float32)
    for k in atoms:
        b0 = bounds[k]
        nu = bounds[k + 1] - b0
        for e in range(f):
            d[e] = Dt[k, e]
            d32[e] = Dt[k, e]
        for i in range(nu):  # E_k: the users' residuals with the atom's own contribution added back
            r = order[b0 + i] // S
            a = coef[r, order[b0 + i] % S]
            for e in range(f):
                Ek[i, e] = E[r, e] + a * d32[e]
        for step in range(power_steps):
            dn[:] = 0.0
            for i in range(nu):
                row = Ek[i]
                v = 0.0
                for e in range(f):
                    v += row[e] * d[e]
                for e in range(f):
                    dn[e] += v * row[e]
            nd = 0.0
            for e in range(f):
                nd += dn[e] * dn[e]
            if nd == 0.0:
                break  # x = E_k d = 0: keep the atom (its users' coefficients become 0)
            nd = np.sqrt(nd)
            for e in range(f):
                d[e] = dn[e] / nd
                d32[e] = np.float32(d[e])
        for i in range(nu):  # the final x = E_k d: new coefficients and residual rows
            row = Ek[i]
            v = 0.0
            for e in range(f):
                v += row[e] * d[e]
            xi = np.float32(v)
            r = order[b0 + i] // S
            coef[r, order[b0 + i] % S] = xi
            sq = 0.0
            for e in range(f):
                E[r, e] = row[e] - xi * d32[e]
                sq += np.float64(E[r, e]) ** 2
            err[r] = sq
        for e in range(f):
            Dt[k, e] = d32[e]


def load_kernels() -> float:
    """Compile (first use after install) or load (later) the kernels; returns the seconds spent.

    Happens once per process on first use anyway; benchmarks call it first so
    that the one-off cost is reported on its own instead of inside the first
    timed reconstruction.
    """
    import time

    t = time.perf_counter()
    D = np.eye(8, 12, dtype=np.float32)
    table = TableOMP(np.eye(2, dtype=np.float32), D, 4)
    res = table.solve(np.ones((1, 4), np.float32), np.zeros((1, 4), np.int32), max_atoms=2, tol=0.0)
    synthesize(res, D)
    still_kernel(np.ones((1, 4), np.float32), np.ones((1, 4)), np.eye(4), np.zeros(1), 1, np.zeros(1, np.bool_),
                 np.zeros((1, 4)))
    return time.perf_counter() - t


# --------------------------------------------------------------------------------------------
# Non-local sparse coding (codedvideo.solvers.nonlocal_sc): block matching, simultaneous OMP of a group
# of similar patches each seen through its own code, scatter-add of the members' estimates.


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


@njit(nogil=True, cache=True, fastmath={"contract"})
def somp_kernel(y, pat, members, size, B, floor, tol, kmax, dep_tol, select_bits, tiny,
                index, coef, count, res2, dependent, consensus):
    """Simultaneous OMP of groups of patches, each member through its own code (shared support).

    Group ``g`` holds the patches ``members[g, :size[g]]`` (rows of ``y`` and ``pat``).
    Each iteration picks one atom for the whole group: the largest sum over the
    members still above their tolerance of ``|A_p^T r_p|`` normalised by the
    column norms of their own ``A_p`` (rounded to :data:`SELECT_BITS`, ties to the
    lowest atom).  Every member then adds that atom to its own least-squares fit of
    its own measurement (Gram-Schmidt, twice, as :func:`_omp_kernel`), skipping an
    atom its code hides (below the visibility floor); a member stops when its
    residual is within ``tol`` or the atom is linearly dependent on its selection,
    the group when no member is left.  With one member this is :func:`_omp_kernel`
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
def _chol_solve(M, b, n, L, x):
    """Solve ``M x = b`` for the symmetric positive definite ``M[:n, :n]`` (lower triangle read)."""
    for i in range(n):
        for j in range(i + 1):
            s = M[i, j]
            for t in range(j):
                s -= L[i, t] * L[j, t]
            if i == j:
                L[i, i] = np.sqrt(s) if s > 0.0 else 1e-150
            else:
                L[i, j] = s / L[j, j]
    for i in range(n):
        s = b[i]
        for t in range(i):
            s -= L[i, t] * x[t]
        x[i] = s / L[i, i]
    for i in range(n - 1, -1, -1):
        s = x[i]
        for t in range(i + 1, n):
            s -= L[t, i] * x[t]
        x[i] = s / L[i, i]


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


def synthesize(result: OmpResult, D: np.ndarray) -> np.ndarray:
    """Patch estimates ``E_p = D alpha_p``, shape (P, D.shape[0]) float32."""
    # only the selected atoms are added: count * N*m multiply-adds a patch, not a dense product
    Dt = np.ascontiguousarray(np.asarray(D, dtype=np.float32).T)
    out = np.empty((result.count.size, Dt.shape[1]), np.float32)
    synthesize_into(np.ascontiguousarray(result.index), np.ascontiguousarray(result.coef, dtype=np.float32),
                    np.ascontiguousarray(result.count), Dt, out)
    return out


# --------------------------------------------------------------------------------------------
# GAP refinement with a low-rank prior on groups (codedvideo.solvers.refine): 2D patches of single frames, the
# matching of the reference patches across neighbouring frames, each group shrunk in the eigenbasis of its Gram
# matrix, and the members' estimates added frame by frame.  A patch is the flat index t * H * W + r * W + c of
# its top-left corner.


@njit(parallel=True, nogil=True, cache=True, fastmath={"reassoc", "contract"})
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


@njit(parallel=True, nogil=True, cache=True, fastmath={"reassoc", "contract"})
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
