"""Batched orthogonal matching pursuit (OMP) for many small problems at once.

Every patch ``p`` is its own sparse-coding problem (Hitomi et al. 2011, Eq. 3)::

    min ||alpha||_0  subject to  ||A_p alpha - y_p||^2 <= tol,  ||alpha||_0 <= max_atoms

with ``A_p = Phi_p D``: the dictionary ``D`` (``N*M*M x K``, unit-norm atoms)
seen through the patch's shutter code ``Phi_p``.  The columns of ``A_p`` are not
unit-norm, so atoms are selected by the normalised correlation
``|a_k^T r| / ||a_k||`` (as scikit-learn's OMP assumes unit atoms, we normalise
explicitly).

All patches of a batch advance together, one atom per iteration:

* correlations of all active patches are one matrix product,
  ``A_p^T r = D^T (Phi_p^T r)``;
* the selected columns are orthogonalised against the patch's earlier ones by
  classical Gram-Schmidt applied twice (numerically as good as Householder QR
  for these sizes), which keeps a thin QR ``A_sel = Q R`` per patch;
* the residual is updated by one projection, ``r -= (q^T r) q``, so the exact
  OMP residual is available without solving any system inside the loop;
* a patch leaves the active set when its residual is within ``tol``, when it
  reaches ``max_atoms``, or when its best new column is (numerically) in the
  span of the selected ones -- a linear dependence that is counted and
  reported, never a NaN;
* the coefficients come from one batched back-substitution ``R alpha = Q^T y``
  at the end.

Operators
---------
An operator builds a *view* of the active patches, compacted as patches finish,
with ``scores(r)`` -> ``(P_active, K)`` normalised correlations
``a_k^T r / ||a_k||`` (zero for a zero column), ``column(j)`` -> ``(P_active, m)``
and ``keep(mask)``; its ``order`` (or None) is the order in which it prefers the
patches.  :class:`PlainOperator` (``A_p = D``, used by K-SVD),
:class:`MaskedOperator` (any coded patches) and :class:`GroupedOperator`
(few distinct patch codes: tiled and global codes) implement it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from codedvideo.model.codes import is_binary

#: Relative size of a new column's component outside the span of the selected
#: columns below which it counts as linearly dependent.
DEPENDENCE_TOL = 1e-4
_TINY = 1e-12
#: Selection compares correlations with their sign bit and the 10 lowest mantissa
#: bits cleared (one integer AND on the float32 bits: absolute value and rounding
#: down to 13 significant bits, a relative step of 2**-13 ~ 1.2e-4).  Near-ties
#: then become exact ties, which go to the lowest atom index, so the choice does
#: not depend on roundoff (batch size, chunking, BLAS blocking).
SELECT_BITS = np.int32(0x7FFFFC00)


def _select(score: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Best atom of every row of float32 ``score`` (overwritten) and its rounded |score|."""
    bits = score.view(np.int32)
    np.bitwise_and(bits, SELECT_BITS, out=bits)
    j = score.argmax(1)
    return j.astype(np.int32), score[np.arange(score.shape[0]), j]


#: A coded column ``Phi_p d_k`` whose norm is below this fraction of the atom's own
#: norm ``||d_k||`` is never selected: the code barely sees that atom, so its
#: coefficient would be fitted to roundoff or noise and blown up by the inverse
#: (e.g. temporal DCT atoms summed over a bump that is open all the time).
MIN_VISIBLE = 0.05

#: The coefficient prior of a guarded solve (:func:`codedvideo.solvers.region.reconstruct_region`): atoms are
#: selected by ``|a_k^T r| / sqrt(||a_k||^2 + eps^2)`` with ``eps`` this fraction of the patch's largest coded
#: column norm, instead of ``|a_k^T r| / ||a_k||``.  Under a Gaussian prior of one scale on every coefficient
#: this is the atom's evidence: an atom the code barely sees must explain the residual with a coefficient of
#: plausible size, or it is not chosen (docs/research.md, "Long shutter bumps").
PRIOR = 0.25


def _safe_inverse(norms: np.ndarray, atom_norms: np.ndarray | None = None, prior: float = 0.0) -> np.ndarray:
    """1 / norm for usable columns, 0 for the others, which are never chosen.

    A column is unusable when it is (numerically) zero, below :data:`_TINY`
    times the largest of ``norms`` (relative, so that a dictionary scaled by any
    factor selects the same columns), or, given the norms of the atoms
    themselves (broadcast against ``norms``), when it keeps less than
    :data:`MIN_VISIBLE` of its atom's norm.  ``prior`` > 0: ``1 / sqrt(norm**2 + eps**2)`` instead, ``eps``
    that fraction of each row's largest norm (:data:`PRIOR`).
    """
    col_norms = np.asarray(norms, dtype=np.float32)
    good = col_norms > _TINY * float(col_norms.max(initial=0.0))
    if atom_norms is not None:
        good &= col_norms > MIN_VISIBLE * np.asarray(atom_norms, dtype=np.float32)
    if prior > 0:
        eps = np.float32(prior) * col_norms.max(axis=-1, keepdims=True, initial=0.0)
        return np.where(good, 1.0 / np.sqrt(col_norms * col_norms + eps * eps), 0.0).astype(np.float32)
    return np.where(good, 1.0 / np.where(good, col_norms, 1.0), 0.0).astype(np.float32)


@dataclass
class OmpResult:
    """Sparse codes of a batch of patches.

    Attributes
    ----------
    index : ndarray of shape (P, max_atoms), int32
        Selected atoms; entries at and beyond ``count[p]`` are meaningless.
    coef : ndarray of shape (P, max_atoms), float32
        Coefficients (0 beyond ``count[p]``).
    count : ndarray of shape (P,), int32
        Number of atoms used by each patch.
    residual : ndarray of shape (P,), float32
        Final squared residual ``||A_p alpha - y_p||^2``.
    dependent : ndarray of shape (P,), bool
        Patches that stopped early because the next column was dependent.
    """

    index: np.ndarray
    coef: np.ndarray
    count: np.ndarray
    residual: np.ndarray
    dependent: np.ndarray

    def select(self, rows: np.ndarray) -> "OmpResult":
        """The results of a subset of patches (boolean mask or indices)."""
        return OmpResult(self.index[rows], self.coef[rows], self.count[rows], self.residual[rows], self.dependent[rows])

    def dense(self, n_atoms: int) -> np.ndarray:
        """Coefficients as a dense array of shape (P, K)."""
        out = np.zeros((self.count.size, n_atoms), dtype=np.float32)
        used = np.arange(self.index.shape[1])[None, :] < self.count[:, None]
        rows = np.broadcast_to(np.arange(self.count.size)[:, None], used.shape)[used]
        out[rows, self.index[used]] = self.coef[used]  # atoms of a patch are distinct
        return out


def pixel_patterns(mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Distinct per-pixel shutter patterns of a code.

    Parameters
    ----------
    mask : ndarray of shape (N, ...)
        A code (N, h, w), or patch codes arranged (N, P, m).  Binary codes need
        N <= 64 (patterns packed in 64-bit integers); a calibrated mask (values
        other than 0 and 1) gives its distinct weight vectors, any N.

    Returns
    -------
    patterns : ndarray of shape (U, N), float32
        The distinct patterns (0/1 for a binary code, the weights otherwise).
    which : ndarray of shape mask.shape[1:], int32
        Index of every pixel's pattern.
    """
    n = mask.shape[0]
    if not is_binary(mask):
        # a new array (never a view of the mask); + 0.0 turns -0.0 into 0.0: one pattern per value
        rows = np.ascontiguousarray(np.moveaxis(np.asarray(mask, np.float32), 0, -1).reshape(-1, n)) + np.float32(0.0)
        patterns, which = np.unique(rows, axis=0, return_inverse=True)
        return np.ascontiguousarray(patterns, np.float32), which.reshape(mask.shape[1:]).astype(np.int32)
    if n > 64:
        raise ValueError(f"{n} sub-frames: pattern tables need N <= 64")
    weights = np.left_shift(np.uint64(1), np.arange(n, dtype=np.uint64))
    codes = np.tensordot(weights, (np.asarray(mask) > 0).astype(np.uint64), axes=(0, 0))
    uniq, which = np.unique(codes, return_inverse=True)
    patterns = ((uniq[:, None] >> np.arange(n, dtype=np.uint64)) & np.uint64(1)).astype(np.float32)
    return patterns, which.reshape(codes.shape).astype(np.int32)


def pattern_table(patterns: np.ndarray, D: np.ndarray, patch_pixels: int) -> np.ndarray:
    """``B[i, u, k] = sum_t patterns[u, t] D[t*m + i, k]``, shape (m, U, K), float32.

    Summed in sub-frame order, one element at a time (no BLAS): an entry depends
    only on its own pattern, not on which other patterns a region holds or on
    the BLAS threads, so tiles of any size get the same table rows.
    """
    n = patterns.shape[1]
    D3 = np.asarray(D, dtype=np.float32).reshape(n, patch_pixels, -1)
    pat = np.asarray(patterns, dtype=np.float32)
    B = np.zeros((patch_pixels, pat.shape[0], D3.shape[2]), np.float32)
    for t in range(n):
        on = np.flatnonzero(pat[:, t])
        if on.size == 0:
            continue
        if (pat[on, t] == 1).all():
            B[:, on, :] += D3[t][:, None, :]
        else:
            B[:, on, :] += pat[on, t][None, :, None] * D3[t][:, None, :]
    return B


class PlainOperator:
    """``A_p = D`` for every patch (unmasked sparse coding, used by K-SVD).

    Parameters
    ----------
    D : ndarray of shape (m, K)
    """

    order = None

    def __init__(self, D: np.ndarray):
        self.D = np.ascontiguousarray(D, dtype=np.float32)
        self.Dt = np.ascontiguousarray(self.D.T)
        self.K = self.D.shape[1]
        self._norms = np.sqrt((self.D.astype(np.float64) ** 2).sum(0)).astype(np.float32)
        self._Dn = self.D * _safe_inverse(self._norms)[None, :]  # unit columns; zero atoms stay 0

    def norms(self, rows: np.ndarray) -> np.ndarray:
        return np.broadcast_to(self._norms, (len(rows), self._norms.size))

    def view(self, rows: np.ndarray) -> "_PlainView":
        return _PlainView(self)


class _PlainView:
    def __init__(self, op: PlainOperator):
        self.op = op

    def scores(self, r: np.ndarray) -> np.ndarray:
        return r @ self.op._Dn

    def column(self, j: np.ndarray) -> np.ndarray:
        return self.op.Dt[j]

    def keep(self, keep: np.ndarray) -> None:
        pass


class MaskedOperator:
    """``A_p = Phi_p D`` for coded patches.

    ``(A_p)[i, k] = sum_t S_p[t, i] D[t*m + i, k]`` for pixel ``i`` of the patch.

    The column norms are computed exactly through a table of the distinct
    per-pixel shutter patterns: with ``B[i, u, k] = sum_t pattern_u[t] D[t*m+i, k]``,
    ``||a_k||^2 = sum_i B[i, u_p(i), k]^2``, one matrix product of a one-hot
    pattern indicator with ``B**2``.  Single-bump codes have at most ``N - L + 1``
    patterns, so the product is about as cheap as one correlation.  Masks with
    many distinct patterns (e.g. Bernoulli with large N) fall back to one small
    product per pixel position.

    A calibrated mask (fractional weights in [0, 1], :func:`codedvideo.model.codes.is_binary` false)
    is the same exact operator with ``S_p`` holding the weights; its column
    norms are then computed per pixel position.

    Parameters
    ----------
    S : ndarray of shape (P, N, m)
        Shutter code of every patch: binary, or the weights of a calibrated mask.
    D : ndarray of shape (N*m, K)
        Dictionary, rows ordered ``(t, i)``.
    prior : float
        The coefficient prior of the selection (:data:`PRIOR`; 0: plain OMP).
    """

    #: Above this many (pixel, pattern) pairs the one-hot product is not used.
    MAX_ONEHOT = 2048
    order = None

    def __init__(self, S: np.ndarray, D: np.ndarray, prior: float = 0.0):
        P, N, m = S.shape
        self.N, self.m = N, m
        self.prior = float(prior)
        self.S = np.ascontiguousarray(S, dtype=np.float32)
        self.D = np.ascontiguousarray(D, dtype=np.float32)
        self.K = self.D.shape[1]
        if self.D.shape[0] != N * m:
            raise ValueError(f"dictionary has {self.D.shape[0]} rows, patches need N*m = {N * m}")
        self.Dt = np.ascontiguousarray(self.D.T)
        self.atom_norms = np.sqrt((self.D.astype(np.float64) ** 2).sum(0)).astype(np.float32)
        self._norms = self._column_norms()

    def _column_norms(self) -> np.ndarray:
        P, N, m = self.S.shape
        D3 = self.D.reshape(N, m, self.K)
        if P == 0:
            return np.zeros((0, self.K), np.float32)
        binary = is_binary(self.S)  # calibrated (fractional) masks: pixels rarely share a pattern
        if N <= 64 and binary:  # patterns as 64-bit integers
            patterns, inv = pixel_patterns(self.S.transpose(1, 0, 2))  # (U, N), (P, m)
        if N <= 64 and binary and m * len(patterns) <= self.MAX_ONEHOT:
            U = len(patterns)
            B = pattern_table(patterns, self.D, m)  # (m, U, K)
            onehot = np.zeros((P, m * U), dtype=np.float32)
            onehot[np.arange(P)[:, None], np.arange(m)[None, :] * U + inv] = 1.0
            sq = onehot @ (B * B).reshape(m * U, self.K)
        else:
            sq = np.zeros((P, self.K), dtype=np.float32)
            for i in range(m):
                a = self.S[:, :, i] @ D3[:, i, :]
                sq += a * a
        return np.sqrt(np.maximum(sq, 0.0))

    def norms(self, rows: np.ndarray) -> np.ndarray:
        return self._norms[rows]

    def view(self, rows: np.ndarray) -> "_MaskedView":
        return _MaskedView(self, rows)


class _MaskedView:
    """The active patches of a :class:`MaskedOperator`, compacted as patches finish."""

    def __init__(self, op: MaskedOperator, rows: np.ndarray):
        self.op = op
        self.S = op.S[rows]
        self.inv = _safe_inverse(op._norms[rows], op.atom_norms[None, :], op.prior)

    def scores(self, r: np.ndarray) -> np.ndarray:
        # A_p^T r = D^T (Phi_p^T r): one matrix product for all active patches
        z = (self.S * r[:, None, :]).reshape(r.shape[0], -1)
        out = z @ self.op.D
        out *= self.inv
        return out

    def column(self, j: np.ndarray) -> np.ndarray:
        atoms = self.op.Dt[j].reshape(len(j), self.op.N, self.op.m)
        return np.einsum("pnm,pnm->pm", atoms, self.S)

    def keep(self, keep: np.ndarray) -> None:
        self.S = self.S[keep]
        self.inv = self.inv[keep]


class GroupedOperator:
    """``A_p = Phi_p D`` when few distinct patch codes exist (tiled or global codes).

    A periodic code with a 7x7 period gives at most 49 distinct patch codes
    (one per phase), so every ``A_u`` (``m x K``) is built once and the
    correlations of a group are one product ``r @ A_u``: ``N`` times fewer
    operations than ``D^T (Phi^T r)``.  OMP visits the patches in group order
    (:attr:`order`), so every group is a contiguous block of the active set and
    its correlations are one matrix product on a slice, without gathers.

    Parameters
    ----------
    S : ndarray of shape (P, N, m)
    D : ndarray of shape (N*m, K)
    groups : tuple (codes, inverse), optional
        Precomputed ``numpy.unique(..., return_inverse=True)`` of the patch codes.
    """

    def __init__(self, S: np.ndarray, D: np.ndarray, groups=None):
        P, N, m = S.shape
        D3 = np.asarray(D, dtype=np.float32).reshape(N, m, -1)
        first, self.inv = groups if groups is not None else patch_code_groups(S)
        # contiguous: einsum may return a strided layout, and BLAS needs unit strides
        self.A = np.ascontiguousarray(np.einsum("unm,nmk->umk", S[first].astype(np.float32), D3, optimize=True))  # (U, m, K)
        self.At = np.ascontiguousarray(self.A.transpose(0, 2, 1))  # (U, K, m)
        self._norms = np.sqrt(np.einsum("umk,umk->uk", self.A, self.A))
        atom_norms = np.sqrt((D3.astype(np.float64) ** 2).sum((0, 1))).astype(np.float32)
        self._An = np.ascontiguousarray(self.A * _safe_inverse(self._norms, atom_norms[None, :])[:, None, :])  # unit columns
        self.K = D3.shape[2]
        #: Patches in group order (stable): OMP solves them in this order.
        self.order = np.argsort(self.inv, kind="stable")

    def norms(self, rows: np.ndarray) -> np.ndarray:
        return self._norms[self.inv[rows]]

    def subset(self, rows: np.ndarray) -> "GroupedOperator":
        """The operator of some of the patches, sharing the per-group tables (no rebuild)."""
        sub = object.__new__(GroupedOperator)
        sub.__dict__.update(self.__dict__)
        sub.inv = self.inv[rows]
        sub.order = np.argsort(sub.inv, kind="stable")
        return sub

    def view(self, rows: np.ndarray) -> "_GroupedView":
        """``rows`` index the patches in :attr:`order`."""
        return _GroupedView(self, self.inv[self.order][rows])


class _GroupedView:
    def __init__(self, op: GroupedOperator, groups: np.ndarray):
        self.op = op
        self.g = groups  # non-decreasing

    def scores(self, r: np.ndarray) -> np.ndarray:
        out = np.empty((r.shape[0], self.op.K), np.float32)
        bounds = np.searchsorted(self.g, np.arange(self.op.A.shape[0] + 1))
        for u in np.flatnonzero(np.diff(bounds)):
            b0, b1 = bounds[u], bounds[u + 1]
            np.matmul(r[b0:b1], self.op._An[u], out=out[b0:b1])
        return out

    def column(self, j: np.ndarray) -> np.ndarray:
        return self.op.At[self.g, j]

    def keep(self, keep: np.ndarray) -> None:
        self.g = self.g[keep]


def patch_code_groups(S: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Distinct patch codes: (index of each code's first patch, group of every patch).

    Binary codes are compared packed; calibrated (fractional) masks by their float32 weights.
    """
    if not is_binary(S):
        flat = np.ascontiguousarray(np.asarray(S, np.float32).reshape(S.shape[0], -1)) + np.float32(0.0)
        _, first, inv = np.unique(flat, axis=0, return_index=True, return_inverse=True)
        return first, inv.ravel()
    packed = np.packbits(S.reshape(S.shape[0], -1) > 0, axis=1)
    _, first, inv = np.unique(packed, axis=0, return_index=True, return_inverse=True)
    return first, inv.ravel()


def periodic_groups(mask: np.ndarray, patch: int) -> np.ndarray | None:
    """Group of every patch when the code repeats with period 1 or ``patch``, else None.

    A code that repeats every ``patch`` pixels along both axes (``hitomi-tiled``)
    gives identical codes to patches whose corners agree modulo ``patch``; a code
    that is the same at every pixel (``global``, ``flutter``) gives one code to
    all.  Checked in O(image) on the mask, unlike a comparison of all patch codes.

    Parameters
    ----------
    mask : ndarray of shape (N, h, w)

    Returns
    -------
    groups : ndarray of shape (P,), int, or None
        In the raster order of :func:`codedvideo.model.patches.extract`.
    """
    n, h, w = mask.shape
    hp, wp = h - patch + 1, w - patch + 1
    if hp < 1 or wp < 1:
        return None
    for period in (1, patch):
        if (mask[:, period:, :] == mask[:, :-period, :]).all() and (mask[:, :, period:] == mask[:, :, :-period]).all():
            yy, xx = np.mgrid[0:hp, 0:wp]
            return ((yy % period) * period + xx % period).ravel()
    return None


def masked_operator(S: np.ndarray, D: np.ndarray, *, groups: np.ndarray | None = None, max_groups: int = 64,
                    min_share: int = 4):
    """The cheaper exact operator for a batch: grouped when few distinct codes exist.

    ``groups`` (one id per patch, patches with equal ids have equal codes), when
    known, saves the comparison of all patch codes.  Grouped needs at most
    ``max_groups`` codes and at least ``min_share`` patches per code on average
    (0: whenever the codes are few, whatever the batch size).
    """
    if groups is not None:
        _, first, inv = np.unique(groups, return_index=True, return_inverse=True)
        found = (first, inv.ravel())
    else:
        found = patch_code_groups(S)
    if len(found[0]) <= max_groups and S.shape[0] >= min_share * len(found[0]):
        return GroupedOperator(S, D, found)
    return MaskedOperator(S, D)


def omp(
    y: np.ndarray,
    op,
    *,
    max_atoms: int,
    tol: float | np.ndarray = 0.0,
    dependence_tol: float = DEPENDENCE_TOL,
) -> OmpResult:
    """Batched OMP with both stopping rules of Eq. 3.

    Parameters
    ----------
    y : ndarray of shape (P, m)
        Measurements of every patch.
    op : PlainOperator, MaskedOperator or GroupedOperator
        The per-patch matrices ``A_p``.
    max_atoms : int
        Maximum number of atoms per patch (``<= m``).
    tol : float or ndarray of shape (P,)
        Stop when the squared residual ``||A_p alpha - y_p||^2 <= tol``.
    dependence_tol : float
        A new column whose component orthogonal to the selected ones is below
        this fraction of its norm ends the patch (counted in ``dependent``).

    Returns
    -------
    OmpResult
    """
    y32 = np.ascontiguousarray(y, dtype=np.float32)
    P, m = y32.shape
    kmax = int(min(max_atoms, m))
    tols = np.broadcast_to(np.asarray(tol, dtype=np.float32), (P,))
    order = op.order
    if order is not None:  # the operator's preferred order; undone at the end
        y32, tols = y32[order], tols[order]
    index = np.zeros((P, kmax), np.int32)
    count = np.zeros(P, np.int32)
    R = np.zeros((P, kmax, kmax), np.float32)
    qy = np.zeros((P, kmax), np.float32)
    dependent = np.zeros(P, bool)
    res2 = np.einsum("pm,pm->p", y32, y32)
    # working arrays hold the active patches only, compacted as patches finish
    rows = np.flatnonzero(res2 > tols)
    view = op.view(rows)
    r = y32[rows]
    Q = np.zeros((rows.size, kmax, m), np.float32)
    for k in range(kmax):
        if rows.size == 0:
            break
        j, best = _select(view.scores(r))  # normalised correlations |a_k^T r| / ||a_k||
        a = view.column(j).astype(np.float32, copy=False)
        Qk = Q[:, :k]
        h = np.einsum("pkm,pm->pk", Qk, a)
        q = a - np.einsum("pk,pkm->pm", h, Qk)
        h2 = np.einsum("pkm,pm->pk", Qk, q)
        q -= np.einsum("pk,pkm->pm", h2, Qk)
        h += h2
        qn = np.sqrt(np.einsum("pm,pm->p", q, q))
        an = np.sqrt(np.einsum("pm,pm->p", a, a))
        ok = (qn > dependence_tol * an) & (best > 0)  # relative: any atom scale
        q /= np.where(ok, qn, 1.0)[:, None]
        c = np.einsum("pm,pm->p", q, r)
        r_new = r - c[:, None] * q
        rr = np.einsum("pm,pm->p", r_new, r_new)
        done = rows[ok]
        dependent[rows[~ok]] = True
        Q[:, k] = q
        R[done, :k, k] = h[ok]
        R[done, k, k] = qn[ok]
        qy[done, k] = c[ok]
        index[done, k] = j[ok]
        count[done] = k + 1
        res2[done] = rr[ok]
        keep = ok & (rr > tols[rows])
        if keep.all():
            r = r_new
        else:
            rows, r, Q = rows[keep], r_new[keep], Q[keep]
            view.keep(keep)
    coef = _back_substitute(R, qy, count)
    result = OmpResult(index=index, coef=coef, count=count, residual=res2.astype(np.float32), dependent=dependent)
    if order is not None:
        result = result.select(np.argsort(order))
    return result


def _back_substitute(R: np.ndarray, qy: np.ndarray, count: np.ndarray) -> np.ndarray:
    """Solve ``R[:n, :n] x = qy[:n]`` for every patch (upper triangular)."""
    P, kmax = qy.shape
    x = np.zeros((P, kmax), np.float32)
    for k in range(kmax - 1, -1, -1):
        valid = count > k
        if not valid.any():
            continue
        rhs = qy[:, k] - np.einsum("pj,pj->p", R[:, k, k + 1 :], x[:, k + 1 :])
        x[:, k] = np.where(valid, rhs / np.where(valid, R[:, k, k], 1.0), 0.0)
    return x


def omp_reference(A: np.ndarray, y: np.ndarray, *, max_atoms: int, tol: float = 0.0) -> np.ndarray:
    """Textbook OMP for one problem ``A alpha ~ y`` (for tests).

    Normalised selection, least squares by ``numpy.linalg.lstsq`` each step.
    Returns the dense coefficient vector of shape (K,), float64.
    """
    A64 = np.asarray(A, dtype=np.float64)
    y64 = np.asarray(y, dtype=np.float64)
    norms = np.linalg.norm(A64, axis=0)
    usable = norms > _TINY * norms.max(initial=0.0)
    sel: list[int] = []
    coef = np.zeros(0)
    r = y64.copy()
    while len(sel) < min(max_atoms, A64.shape[0]) and r @ r > tol:
        score = np.where(usable, (A64.T @ r) / np.where(usable, norms, 1.0), 0.0).astype(np.float32)
        score[sel] = 0.0
        jj, best = _select(score[None])
        j = int(jj[0])
        if best[0] <= 0:
            break
        sel.append(j)
        coef, *_ = np.linalg.lstsq(A64[:, sel], y64, rcond=None)
        r = y64 - A64[:, sel] @ coef
    out = np.zeros(A64.shape[1])
    out[sel] = coef
    return out
