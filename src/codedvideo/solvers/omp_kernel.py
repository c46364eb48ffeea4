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
its own kernel here: :func:`batch_omp`, Batch-OMP from the Gram matrix
``D^T D`` and one matrix product ``X D``, with the same selection and stopping
rules.  The other solvers' kernels have modules of their own:
:mod:`codedvideo.solvers.ksvd_kernel` (K-SVD's residual and dictionary update),
:mod:`codedvideo.solvers.nonlocal_kernel` (block matching, simultaneous OMP) and
:mod:`codedvideo.solvers.refine_kernel` (the refinement's groups); numba itself
is imported by :mod:`codedvideo.solvers._jit` only.
"""

from __future__ import annotations

import hashlib
import threading
from collections import OrderedDict

import numpy as np

from codedvideo.solvers._jit import CONTRACT, REASSOC, _chol_solve, _column_norms2, _correlate, _dot, njit, prange
from codedvideo.solvers.omp import _TINY, DEPENDENCE_TOL, MIN_VISIBLE, SELECT_BITS, OmpResult, _safe_inverse

#: Largest pattern table (bytes) this path builds; beyond it (codes with many
#: distinct patterns, e.g. Bernoulli at large N) the dense operator is used.
MAX_TABLE_BYTES = 64 << 20


def table_fits(n_patterns: int, D: np.ndarray, patch_pixels: int) -> bool:
    """Whether the pattern table of a code with ``n_patterns`` patterns is small enough."""
    return patch_pixels * n_patterns * D.shape[1] * 4 <= MAX_TABLE_BYTES


@njit(nogil=True, cache=True, fastmath=CONTRACT)
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
    pats = np.ascontiguousarray(patterns, dtype=np.float32)
    n = pats.shape[1]
    D3 = np.ascontiguousarray(np.asarray(D, dtype=np.float32).reshape(n, patch_pixels, -1))
    B = np.empty((patch_pixels, pats.shape[0], D3.shape[2]), np.float32)
    _fill_table(pats, D3, B)
    return B


@njit(nogil=True, cache=True, fastmath=CONTRACT)
def _omp_kernel(y, pat, B, floor, tol, kmax, dep_tol, select_bits, tiny, prior, index, coef, count, res2, dependent):
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
        if prior > 0.0:  # the coefficient prior (a loop of its own: plain OMP's stays vectorised)
            eps2 = np.float32(prior * big) * np.float32(prior * big)
            for k in range(K):
                nk = inv[k]
                inv[k] = np.float32(1.0) / np.sqrt(nk * nk + eps2) if (nk > tiny * big and nk > floor[k]) \
                    else np.float32(0.0)
        else:
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
def _omp_weights_kernel(y, S, D3, floor, tol, kmax, dep_tol, select_bits, tiny, prior, index, coef, count, res2,
                        dependent):
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
        _omp_kernel(y1, pat, B, floor, tol1, kmax, dep_tol, select_bits, tiny, prior, index1, coef1, count1, res1,
                    dep1)
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


@njit(nogil=True, cache=True, fastmath=CONTRACT)
def profile_kernel(y, frame, codes, corners, patch, ridge, out):
    """The temporal profiles of :func:`codedvideo.solvers.region.still_patches`, one patch at a time.

    Patch ``p`` (corner ``corners[p]`` in the region, coded values ``y[p]``,
    still image ``frame[p]``) gets in ``out[p]`` the profile ``f`` (one value
    per sub-frame, the same at every pixel of the patch) that minimises
    ``||y - W (s + f)||^2 + ridge ||f||^2``: ``(W W^T + ridge I) f = W r``
    with ``r = y - n s`` the still image's residual, solved by Cholesky (:func:`codedvideo.solvers._jit._chol_solve`).
    ``codes`` is the region's code as (h, w, N) (each pixel's weights in a
    row); only the sub-frames a pixel is open in are visited.
    """
    N = codes.shape[2]
    M = np.empty((N, N), np.float64)
    L = np.empty((N, N), np.float64)
    b = np.empty(N, np.float64)
    f = np.empty(N, np.float64)
    open_t = np.empty(N, np.int64)
    open_w = np.empty(N, np.float64)
    for p in range(y.shape[0]):
        M[:, :] = 0.0
        b[:] = 0.0
        for dy in range(patch):
            for dx in range(patch):
                r0 = corners[p, 0] + dy
                c0 = corners[p, 1] + dx
                k = 0
                n_i = 0.0
                for t in range(N):
                    v = codes[r0, c0, t]
                    if v != 0.0:
                        open_t[k] = t
                        open_w[k] = v
                        n_i += v
                        k += 1
                r = np.float64(y[p, dy * patch + dx]) - n_i * frame[p, dy * patch + dx]
                for a in range(k):
                    b[open_t[a]] += open_w[a] * r
                    for c in range(k):
                        M[open_t[a], open_t[c]] += open_w[a] * open_w[c]
        for t in range(N):
            M[t, t] += ridge
        _chol_solve(M, b, N, L, f)
        for t in range(N):
            out[p, t] = f[t]


@njit(nogil=True, cache=True, fastmath=CONTRACT)
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
    pats = np.ascontiguousarray(patterns, dtype=np.float32)
    D32 = np.ascontiguousarray(D, dtype=np.float32)
    h = hashlib.blake2b(digest_size=16)
    h.update(np.array([patch_pixels, *pats.shape, *D32.shape], np.int64).tobytes())
    h.update(pats.data)
    h.update(D32.data)
    key = h.digest()
    with _tables_lock:
        B = _tables.get(key)
        if B is None:
            B = build_table(pats, D32, patch_pixels)
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
        D32 = np.asarray(D, dtype=np.float32)
        self.B = shared_table(patterns, D32, patch_pixels)
        self.floor = _visibility_floor(D32)

    def solve(self, y: np.ndarray, pat: np.ndarray, *, max_atoms: int, tol, prior: float = 0.0) -> OmpResult:
        """OMP of patches ``y`` (P, m) whose pixels have patterns ``pat`` (P, m); ``prior``: the coefficient
        prior of the selection (:data:`codedvideo.solvers.omp.PRIOR`; 0: plain OMP)."""
        y32 = np.ascontiguousarray(y, dtype=np.float32)
        pat32 = np.ascontiguousarray(pat, dtype=np.int32)
        P, m = y32.shape
        kmax = int(min(max_atoms, m))
        tols = np.ascontiguousarray(np.broadcast_to(np.asarray(tol, dtype=np.float64), (P,)))
        index = np.zeros((P, kmax), np.int32)
        coef = np.zeros((P, kmax), np.float32)
        count = np.zeros(P, np.int32)
        res2 = np.zeros(P, np.float32)
        dependent = np.zeros(P, np.bool_)
        _omp_kernel(y32, pat32, self.B, self.floor, tols, kmax, DEPENDENCE_TOL, SELECT_BITS,
                    _TINY, np.float32(prior), index, coef, count, res2, dependent)
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
        D32 = np.asarray(D, dtype=np.float32)
        self.m = patch_pixels
        self.n = D32.shape[0] // patch_pixels
        self.D3 = np.ascontiguousarray(D32.reshape(self.n, patch_pixels, D32.shape[1]))
        self.floor = _visibility_floor(D32)

    def solve(self, y: np.ndarray, S: np.ndarray, *, max_atoms: int, tol, prior: float = 0.0) -> OmpResult:
        """OMP of patches ``y`` (P, m) whose pixels have weights ``S`` (P, N, m); ``prior`` as :meth:`TableOMP.solve`."""
        y32 = np.ascontiguousarray(y, dtype=np.float32)
        S32 = np.ascontiguousarray(S, dtype=np.float32)
        P, m = y32.shape
        if S32.shape != (P, self.n, m):
            raise ValueError(f"weights of shape {S32.shape}, expected {(P, self.n, m)}")
        kmax = int(min(max_atoms, m))
        tols = np.ascontiguousarray(np.broadcast_to(np.asarray(tol, dtype=np.float64), (P,)))
        index = np.zeros((P, kmax), np.int32)
        coef = np.zeros((P, kmax), np.float32)
        count = np.zeros(P, np.int32)
        res2 = np.zeros(P, np.float32)
        dependent = np.zeros(P, np.bool_)
        _omp_weights_kernel(y32, S32, self.D3, self.floor, tols, kmax, DEPENDENCE_TOL, SELECT_BITS, _TINY,
                            np.float32(prior), index, coef, count, res2, dependent)
        return OmpResult(index=index, coef=coef, count=count, residual=res2, dependent=dependent)


#: Signals per block of :func:`_batch_omp_kernel`: a thread allocates its work arrays once per block.
_BATCH_BLOCK = 256


@njit(parallel=True, nogil=True, cache=True, fastmath=REASSOC)
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
    X32 = np.ascontiguousarray(X, dtype=np.float32)
    D32 = np.ascontiguousarray(D, dtype=np.float32)
    P, m = X32.shape
    if D32.shape[0] != m:
        raise ValueError(f"dictionary has {D32.shape[0]} rows, signals have {m} entries")
    kmax = int(min(max_atoms, m))
    D64 = D32.astype(np.float64)
    G = D64.T @ D64
    # the same inverse norms as PlainOperator, so that the rounded scores are the same numbers
    inv = _safe_inverse(np.sqrt((D64**2).sum(0)).astype(np.float32))
    tols = np.ascontiguousarray(np.broadcast_to(np.asarray(tol, dtype=np.float64), (P,)))
    index = np.zeros((P, kmax), np.int32)
    coef64 = np.zeros((P, kmax), np.float64)
    count = np.zeros(P, np.int32)
    res2 = np.zeros(P, np.float64)
    dependent = np.zeros(P, np.bool_)
    Dp = D64 if np.dtype(precision) == np.float64 else D32
    Dt = np.ascontiguousarray(D32.T)
    for a in range(0, P, chunk):
        b = min(P, a + chunk)
        alpha0 = X32[a:b].astype(Dp.dtype, copy=False) @ Dp
        _batch_omp_kernel(X32[a:b], Dt, alpha0, G, inv, tols[a:b], kmax, DEPENDENCE_TOL, SELECT_BITS, index[a:b],
                          coef64[a:b], count[a:b], res2[a:b], dependent[a:b])
    return OmpResult(index=index, coef=coef64.astype(np.float32), count=count, residual=res2.astype(np.float32),
                     dependent=dependent)


def atom_rows(D: np.ndarray) -> np.ndarray:
    """The atoms of ``D`` (rows, K) as the rows of a contiguous float32 (K, rows) array: the form
    :func:`synthesize_rows` reads, made once where many batches of results share one dictionary."""
    return np.ascontiguousarray(np.asarray(D, dtype=np.float32).T)


def synthesize(result: OmpResult, D: np.ndarray) -> np.ndarray:
    """Patch estimates ``E_p = D alpha_p``, shape (P, D.shape[0]) float32."""
    return synthesize_rows(result, atom_rows(D))


def synthesize_rows(result: OmpResult, Dt: np.ndarray) -> np.ndarray:
    """:func:`synthesize` from the dictionary's :func:`atom_rows` ``Dt``."""
    # only the selected atoms are added: count * N*m multiply-adds a patch, not a dense product
    out = np.empty((result.count.size, Dt.shape[1]), np.float32)
    synthesize_into(np.ascontiguousarray(result.index), np.ascontiguousarray(result.coef, dtype=np.float32),
                    np.ascontiguousarray(result.count), Dt, out)
    return out


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
    profile_kernel(np.ones((1, 1), np.float32), np.ones((1, 1)), np.ones((1, 1, 2), np.float32),
                   np.zeros((1, 2), np.int64), 1, 1.0, np.zeros((1, 2)))
    return time.perf_counter() - t
