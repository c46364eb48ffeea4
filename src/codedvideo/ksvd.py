"""K-SVD dictionary learning (Aharon, Elad and Bruckstein, 2006).

Each iteration is a sparse-coding step (Batch-OMP, :func:`codedvideo.omp_kernel.batch_omp`)
composed with a dictionary-update step: every atom in turn is replaced by the
leading left singular vector of the residual restricted to the samples that
use it, and those samples' coefficients by the matching right singular vector
times the singular value (a rank-1 SVD, computed by power iteration warm-started
from the current atom and coefficients, which converges to the exact leading
pair).  Atoms that no sample uses, and atoms that nearly duplicate another,
are replaced by the training sample that the dictionary represents worst.
Per-iteration statistics are returned as data.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .omp_kernel import batch_omp

DUPLICATE_COS = 0.99


@dataclass
class KsvdHistory:
    """Per-iteration statistics of a K-SVD run."""

    rmse: list[float] = field(default_factory=list)
    mean_atoms: list[float] = field(default_factory=list)
    replaced: list[int] = field(default_factory=list)


def _rank1(E: np.ndarray, d: np.ndarray, steps: int) -> tuple[np.ndarray, np.ndarray]:
    """Leading singular pair of ``E`` (rows = samples) as ``(d, x)``, ``E ~ x d^T``."""
    x = E @ d
    for _ in range(steps):
        d = E.T @ x
        nd = np.linalg.norm(d)
        if nd == 0:
            break
        d = d / nd
        x = E @ d
    return d.astype(np.float32), x.astype(np.float32)


def ksvd(
    X: np.ndarray,
    D0: np.ndarray,
    *,
    sparsity: int,
    iterations: int,
    tol: float = 0.0,
    rng: np.random.Generator | int | None = 0,
    power_steps: int = 3,
    progress=None,
) -> tuple[np.ndarray, KsvdHistory]:
    """Learn a dictionary.

    Parameters
    ----------
    X : ndarray of shape (n_samples, n_features)
        Training vectors (rows).
    D0 : ndarray of shape (n_features, K)
        Initial dictionary; columns are normalised here.
    sparsity : int
        Maximum atoms per sample in the coding step.
    iterations : int
    tol : float
        Squared-residual tolerance of the coding step (0: use ``sparsity`` atoms).
    rng : Generator or int
        Order of the atom updates.
    power_steps : int
        Power-iteration steps of each rank-1 update.
    progress : callable, optional
        Called as ``progress(iteration, rmse)`` after each iteration.

    Returns
    -------
    D : ndarray of shape (n_features, K), float32, unit-norm columns
    history : KsvdHistory
    """
    rng = np.random.default_rng(rng)
    X = np.ascontiguousarray(X, dtype=np.float32)
    D = np.array(D0, dtype=np.float32)
    D = _normalise_or_replace(D, X, rng)
    n, f = X.shape
    K = D.shape[1]
    hist = KsvdHistory()
    for it in range(iterations):
        codes = batch_omp(X, D, max_atoms=sparsity, tol=tol)
        coef = codes.coef.copy()
        # residual E = X - codes D^T
        E = X.copy()
        for k in range(codes.index.shape[1]):
            rows = np.flatnonzero(codes.count > k)
            E[rows] -= coef[rows, k, None] * D.T[codes.index[rows, k]]
        valid = np.arange(codes.index.shape[1])[None, :] < codes.count[:, None]
        flat_atom = np.where(valid, codes.index, -1).ravel()
        order = np.argsort(flat_atom, kind="stable")
        bounds = np.searchsorted(flat_atom[order], np.arange(K + 1))
        replaced = 0
        for k in rng.permutation(K):
            pos = order[bounds[k] : bounds[k + 1]]
            if pos.size == 0:
                replaced += _replace_atom(D, k, E, rng)
                continue
            users, slot = np.divmod(pos, codes.index.shape[1])
            Ek = E[users] + coef[users, slot, None] * D[:, k][None, :]
            d, x = _rank1(Ek, D[:, k], power_steps)
            D[:, k] = d
            coef[users, slot] = x
            E[users] = Ek - x[:, None] * d[None, :]
        replaced += _replace_duplicates(D, E, rng)
        rmse = float(np.sqrt(np.mean(E.astype(np.float64) ** 2)))
        hist.rmse.append(rmse)
        hist.mean_atoms.append(float(codes.count.mean()))
        hist.replaced.append(replaced)
        if progress is not None:
            progress(it, rmse)
    return D, hist


def _worst_sample(E: np.ndarray, rng: np.random.Generator) -> int:
    err = np.einsum("nf,nf->n", E, E)
    # pick among the 1% worst at random so that several replacements differ
    top = np.argsort(err)[-max(1, err.size // 100) :]
    return int(rng.choice(top))


def _replace_atom(D: np.ndarray, k: int, E: np.ndarray, rng: np.random.Generator) -> int:
    s = _worst_sample(E, rng)
    v = E[s].astype(np.float32)
    nv = np.linalg.norm(v)
    if nv == 0:
        v = rng.normal(size=D.shape[0]).astype(np.float32)
        nv = np.linalg.norm(v)
    D[:, k] = v / nv
    E[s] = 0.0  # do not hand the same sample to the next replacement
    return 1


def _replace_duplicates(D: np.ndarray, E: np.ndarray, rng: np.random.Generator) -> int:
    G = np.abs(D.T @ D)
    np.fill_diagonal(G, 0.0)
    count = 0
    for k in np.flatnonzero((np.triu(G) > DUPLICATE_COS).any(0)):
        count += _replace_atom(D, k, E, rng)
    return count


def _normalise_or_replace(D: np.ndarray, X: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    norms = np.linalg.norm(D, axis=0)
    bad = ~(np.isfinite(norms) & (norms > 1e-8))
    D[:, ~bad] /= norms[~bad]
    for k in np.flatnonzero(bad):
        D[:, k] = 0.0
        _replace_atom(D, k, X[rng.integers(X.shape[0], size=64)].copy(), rng)
    return D
