"""The compiler of the solvers' kernels, in one place: numba's ``njit`` and ``prange``, the fastmath flags the
kernels share, and the small helpers that several kernels call.

Every kernel module of :mod:`codedvideo.solvers` (:mod:`~codedvideo.solvers.omp_kernel`,
:mod:`~codedvideo.solvers.ksvd_kernel`, :mod:`~codedvideo.solvers.nonlocal_kernel`,
:mod:`~codedvideo.solvers.refine_kernel`) takes ``njit`` and ``prange`` from here: numba is imported by this
module only, in this layer.

The helpers are those of the per-patch OMP (:func:`codedvideo.solvers.omp_kernel._omp_kernel`) that the
simultaneous OMP of a group (:func:`codedvideo.solvers.nonlocal_kernel.somp_kernel`) repeats operation for
operation: the table correlation, the interleaved dot product and the column norms; and the small Cholesky
solve that the groups' least squares and the still test's temporal profiles
(:func:`codedvideo.solvers.omp_kernel.profile_kernel`) share.

numba caches a compiled kernel by its own file: a change to a helper here is not seen by a kernel of another
module that is already cached (it calls or inlines the helper) until that kernel's file changes or its
``__pycache__`` is cleared.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

__all__ = ["CONTRACT", "REASSOC", "njit", "prange"]

#: Multiply-adds may be fused (the same machine code, the same bits, on every thread count).
CONTRACT = {"contract"}
#: Fused multiply-adds, and sums that may be reordered into vector lanes.
REASSOC = {"reassoc", "contract"}


@njit(nogil=True, cache=True, inline="always", fastmath=CONTRACT)
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


@njit(nogil=True, cache=True, inline="always", fastmath=CONTRACT)
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
    with its caller's flags, and :func:`codedvideo.solvers.omp_kernel._omp_kernel` allows contraction.
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
