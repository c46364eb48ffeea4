"""Compiled kernels of K-SVD (:mod:`codedvideo.solvers.ksvd`): the residual of every sample's code
(:func:`subtract_codes`), row energies (:func:`row_energy`) and the atom-by-atom dictionary update
(:func:`update_atoms`).  Its coding step is :func:`codedvideo.solvers.omp_kernel.batch_omp`.
"""

from __future__ import annotations

import numpy as np

from codedvideo.solvers._jit import REASSOC, njit, prange


@njit(parallel=True, nogil=True, cache=True, fastmath=REASSOC)
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


@njit(parallel=True, nogil=True, cache=True, fastmath=REASSOC)
def row_energy(E):
    """``sum_e E[p, e]**2`` of every row, float64, shape (P,)."""
    out = np.empty(E.shape[0], np.float64)
    for p in prange(E.shape[0]):
        s = 0.0
        for e in range(E.shape[1]):
            s += np.float64(E[p, e]) ** 2
        out[p] = s
    return out


@njit(nogil=True, cache=True, fastmath=REASSOC)
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
