"""K-SVD dictionary learning (Aharon, Elad and Bruckstein, 2006).

Each iteration is a sparse-coding step (Batch-OMP, :func:`codedvideo.solvers.omp_kernel.batch_omp`)
composed with a dictionary-update step: every atom in turn is replaced by the
leading left singular vector of the residual restricted to the samples that
use it, and those samples' coefficients by the matching right singular vector
times the singular value (a rank-1 SVD, computed by power iteration warm-started
from the current atom and coefficients, which converges to the exact leading
pair; compiled, :func:`codedvideo.solvers.ksvd_kernel.update_atoms`).  Atoms that no sample uses, and atoms that nearly duplicate another,
are replaced by the training sample that the dictionary represents worst.
Per-iteration statistics are returned as data.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from codedvideo.solvers.ksvd_kernel import row_energy, subtract_codes, update_atoms
from codedvideo.solvers.omp_kernel import batch_omp

DUPLICATE_COS = 0.99
# power-iteration steps of each rank-1 atom update (warm-started, so a few suffice)
POWER_STEPS = 3


@dataclass
class KsvdHistory:
    """Per-iteration statistics of a K-SVD run."""

    rmse: list[float] = field(default_factory=list)
    mean_atoms: list[float] = field(default_factory=list)
    replaced: list[int] = field(default_factory=list)


def ksvd(
    X: np.ndarray,
    D0: np.ndarray,
    *,
    sparsity: int,
    iterations: int,
    tol: float = 0.0,
    rng: np.random.Generator | int | None = 0,
    progress=None,
    replace_unused: bool = True,
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
    progress : callable, optional
        Called as ``progress(iteration, rmse)`` after each iteration.
    replace_unused : bool
        An atom no sample's code uses is replaced by one of the worst represented samples (True), or kept as it
        is (False: a basis adapted to few samples, whose unused atoms are directions its span needs).

    Returns
    -------
    D : ndarray of shape (n_features, K), float32, unit-norm columns
    history : KsvdHistory
    """
    gen = np.random.default_rng(rng)
    X32 = np.ascontiguousarray(X, dtype=np.float32)
    D = np.array(D0, dtype=np.float32)
    D = _normalise_or_replace(D, X32, gen)
    K = D.shape[1]
    # atoms as rows: the compiled update reads and writes an atom contiguously; D is a view of it
    Dt = np.ascontiguousarray(D.T)
    D = Dt.T
    hist = KsvdHistory()
    E = np.empty_like(X32)
    err = np.empty(X32.shape[0])  # ||E[p]||^2, kept up to date with E (it picks the replacements)
    for it in range(iterations):
        codes = batch_omp(X32, D, max_atoms=sparsity, tol=tol)
        coef = codes.coef  # updated with the atoms
        subtract_codes(X32, codes.index, coef, codes.count, Dt, E, err)  # E = X - codes D^T
        S = codes.index.shape[1]
        valid = np.arange(S)[None, :] < codes.count[:, None]
        flat_atom = np.where(valid, codes.index, -1).ravel()
        order = np.argsort(flat_atom, kind="stable")  # flat positions p * S + s, grouped by atom
        bounds = np.searchsorted(flat_atom[order], np.arange(K + 1))
        replaced = 0
        perm = gen.permutation(K)
        # the atoms in turn: runs of used atoms compiled, an unused one replaced where its turn comes (or kept,
        # the used ones then updated in one run, in the same order)
        unused = np.flatnonzero(bounds[perm + 1] == bounds[perm])
        if not replace_unused:
            perm = np.delete(perm, unused)
            unused = unused[:0]
        start = 0
        for i in unused:
            if i > start:
                update_atoms(E, err, Dt, coef, perm[start:i], order, bounds, POWER_STEPS)
            replaced += _replace_atom(D, perm[i], E, err, gen)
            start = i + 1
        if start < perm.size:
            update_atoms(E, err, Dt, coef, perm[start:], order, bounds, POWER_STEPS)
        replaced += _replace_duplicates(D, E, err, gen)
        rmse = float(np.sqrt(err.sum() / E.size))
        hist.rmse.append(rmse)
        hist.mean_atoms.append(float(codes.count.mean()))
        hist.replaced.append(replaced)
        if progress is not None:
            progress(it, rmse)
    return np.ascontiguousarray(D), hist


def _worst_sample(err: np.ndarray, rng: np.random.Generator) -> int:
    """One of the 1% of samples with the largest squared residual ``err``, at random."""
    # at random so that several replacements differ; the top 1% in increasing order, as a full argsort
    # would list them, without sorting all the samples at every replacement
    n = max(1, err.size // 100)
    top = np.argpartition(err, err.size - n)[-n:]
    top = top[np.argsort(err[top])]
    return int(rng.choice(top))


def _replace_atom(D: np.ndarray, k: int, E: np.ndarray, err: np.ndarray, rng: np.random.Generator) -> int:
    """Atom ``k`` becomes one of the worst represented samples (``err[p] = ||E[p]||^2``), normalised."""
    s = _worst_sample(err, rng)
    v = E[s].astype(np.float32)
    nv = np.linalg.norm(v)
    if nv == 0:
        v = rng.normal(size=D.shape[0]).astype(np.float32)
        nv = np.linalg.norm(v)
    D[:, k] = v / nv
    E[s] = 0.0  # do not hand the same sample to the next replacement
    err[s] = 0.0
    return 1


def _replace_duplicates(D: np.ndarray, E: np.ndarray, err: np.ndarray, rng: np.random.Generator) -> int:
    G = np.abs(D.T @ D)
    np.fill_diagonal(G, 0.0)
    count = 0
    for k in np.flatnonzero((np.triu(G) > DUPLICATE_COS).any(0)):
        count += _replace_atom(D, k, E, err, rng)
    return count


def _normalise_or_replace(D: np.ndarray, X: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    norms = np.linalg.norm(D, axis=0)
    bad = ~(np.isfinite(norms) & (norms > 1e-8))
    D[:, ~bad] /= norms[~bad]
    for k in np.flatnonzero(bad):
        D[:, k] = 0.0
        few = X[rng.integers(X.shape[0], size=64)]  # a copy: _replace_atom zeroes the row it takes
        _replace_atom(D, k, few, row_energy(few), rng)
    return D
