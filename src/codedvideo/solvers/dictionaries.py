"""Dictionaries of 7x7xN video patches: 3D DCT and learned (K-SVD).

A dictionary is a float32 array of shape ``(N * M * M, K)`` whose rows are
ordered ``(t, dy, dx)`` (as :mod:`codedvideo.model.patches`) and whose columns
(atoms) have unit norm.  Storage is in :mod:`codedvideo.formats.store`.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np

from codedvideo.model import doors
from codedvideo.model.errors import InputError
from codedvideo.model.patches import PATCH
from codedvideo.solvers.ksvd import ksvd

#: K-SVD's defaults (:func:`learn_dictionary`, ``dictionary:`` in pipeline.yaml): atoms, training patches drawn,
#: iterations and atoms per patch while training.
KSVD_ATOMS, KSVD_SAMPLES, KSVD_ITERATIONS, KSVD_SPARSITY = 512, 80000, 20, 6


@dataclass(frozen=True)
class KsvdSettings:
    """How :func:`learn_dictionary` trains: the K-SVD knobs, with its defaults.

    Parameters
    ----------
    atoms : int
        Columns of the dictionary: the complete 3D DCT basis topped up with random training patches (an
        ``init`` given keeps its own K atoms instead).
    samples : int
        Training patches drawn.
    iterations : int
        K-SVD iterations.
    sparsity : int
        Atoms per patch while training.
    tol_rms : float
        The coding of a sample stops once its RMS residual (grey levels per entry) is below it.
    augment : bool
        Rotations, flips and time reversal of the patches (off to fit a scene).
    replace_unused : bool
        An atom no patch's code uses becomes one of the worst represented patches (False: it is kept,
        :func:`codedvideo.solvers.ksvd.ksvd`).
    """

    atoms: int = KSVD_ATOMS
    samples: int = KSVD_SAMPLES
    iterations: int = KSVD_ITERATIONS
    sparsity: int = KSVD_SPARSITY
    tol_rms: float = 0.5
    augment: bool = True
    replace_unused: bool = True


#: Atoms are rescaled to unit norm when some nonzero atom's norm differs from 1
#: by more than this; a dictionary within it (every learned or DCT dictionary,
#: float32 roundoff is ~1e-7) is used bit for bit as given.
UNIT_NORM_TOL = 1e-4


def _column_norms(D: np.ndarray) -> np.ndarray:
    """Euclidean norms of the columns in float64, without overflow or underflow for any finite entries."""
    A = np.abs(np.asarray(D, dtype=np.float64))
    with np.errstate(invalid="ignore", over="ignore"):
        peak = A.max(axis=0, initial=0.0)  # NaN where a column holds NaN, Inf where it holds Inf
        scale = np.where((peak > 0) & np.isfinite(peak), peak, 1.0)
        return scale * np.sqrt(((A / scale) ** 2).sum(axis=0))  # NaN or Inf stays non-finite


def prepare_dictionary(D: np.ndarray, where: str) -> np.ndarray:
    """The dictionary as the reconstruction uses it: float32, nonzero atoms of unit norm.

    Reconstruction is invariant to the scale of each atom (OMP selects by
    normalised correlation and ``D alpha`` does not change when an atom and its
    coefficient trade a factor), but its numerics are not: float32 squares of
    atoms near 1e30 overflow, and atoms near 1e-12 fall under the zero-column
    floors.  So atoms are made unit-norm here, once, before any tile is solved.

    * Column norms are computed in float64 (scaled by each column's largest
      entry, so no finite atom overflows or underflows).
    * Atoms that are all zero, or whose norm is not finite (NaN or Inf entries),
      are dropped with a warning that says how many.
    * Every atom is divided by its norm only when some norm differs from 1 by
      more than :data:`UNIT_NORM_TOL`; otherwise the kept atoms are returned bit
      for bit (a float32 dictionary with nothing to drop: the array itself), so
      unit-norm dictionaries give the same results and cache keys.

    Parameters
    ----------
    D : ndarray of shape (features, K)
    where : str
        Names the dictionary in messages (a path, or how it was given).

    Returns
    -------
    ndarray of shape (features, K'), float32, K' <= K the nonzero finite atoms.

    Raises
    ------
    InputError
        When ``D`` is not a 2D array, has no atoms, or every atom is zero or not finite.
    """
    atoms = np.asarray(D)
    if atoms.ndim != 2:
        raise InputError(f"dictionary {where}: expected a 2D array (features, atoms), got shape {atoms.shape}")
    if atoms.shape[1] == 0 or atoms.shape[0] == 0:
        raise InputError(f"dictionary {where}: has no atoms (shape {atoms.shape})")
    if not np.issubdtype(atoms.dtype, np.number) or np.iscomplexobj(atoms):
        raise InputError(f"dictionary {where}: atoms must be real numbers, got dtype {atoms.dtype}")
    norms = _column_norms(atoms)
    finite = np.isfinite(norms)
    zero = finite & (norms == 0)
    keep = finite & ~zero
    n_zero, n_bad, k = int(zero.sum()), int((~finite).sum()), atoms.shape[1]
    if not keep.any():
        if n_bad == 0:
            raise InputError(f"dictionary {where}: every atom is zero ({k} atoms); it cannot represent any patch")
        raise InputError(f"dictionary {where}: every atom is zero or not finite ({n_zero} zero, {n_bad} with NaN or Inf)")
    if n_zero or n_bad:
        what = " and ".join(part for part in (f"{n_zero} all-zero" if n_zero else "",
                                               f"{n_bad} non-finite (NaN or Inf)" if n_bad else "") if part)
        doors.warn(f"dictionary {where}: dropped {what} of its {k} atoms; reconstructing with the other "
                      f"{int(keep.sum())}", UserWarning)
        atoms, norms = atoms[:, keep], norms[keep]
    if np.abs(norms - 1.0).max() > UNIT_NORM_TOL:
        return np.ascontiguousarray(atoms.astype(np.float64) / norms[None, :], dtype=np.float32)
    return atoms if atoms.dtype == np.float32 else atoms.astype(np.float32)


def _dct_1d(n: int, atoms: int) -> np.ndarray:
    """Orthonormal DCT-II basis (atoms == n) or an overcomplete cosine frame."""
    if atoms == n:
        from scipy.fft import dct  # lazy: only the DCT needs it, and it costs every command 0.03 to 0.08 s

        return dct(np.eye(n), norm="ortho", axis=0).T  # columns are basis vectors
    i = np.arange(n)[:, None]
    k = np.arange(atoms)[None, :]
    B = np.cos(np.pi * (2 * i + 1) * k / (2 * atoms))
    return B / np.linalg.norm(B, axis=0)


def dct_dictionary(frames: int, *, patch: int = PATCH, redundancy: float = 1.0) -> np.ndarray:
    """Separable 3D DCT dictionary of shape ``(frames * patch**2, K)``.

    ``redundancy = 1`` gives the complete orthonormal 3D DCT-II basis
    (``K = frames * patch**2``); larger values oversample each axis by
    ``redundancy ** (1/3)`` (an overcomplete cosine frame).
    """
    if redundancy < 1:
        raise InputError(f"dct dictionary: redundancy must be >= 1, got {redundancy}")
    r = redundancy ** (1 / 3)
    nt, ns = frames, patch
    Bt = _dct_1d(nt, max(nt, math.ceil(nt * r - 1e-9)))
    Bs = _dct_1d(ns, max(ns, math.ceil(ns * r - 1e-9)))
    D = np.kron(Bt, np.kron(Bs, Bs))
    return (D / np.linalg.norm(D, axis=0)).astype(np.float32)


DIHEDRAL = 8


def _dihedral(block: np.ndarray, k: int) -> np.ndarray:
    """One of the 8 rotations/flips of the two spatial axes of ``(..., M, M)``."""
    out = np.rot90(block, k % 4, axes=(-2, -1))
    return out[..., ::-1] if k >= 4 else out


def training_patches(
    videos: list[np.ndarray],
    *,
    frames: int,
    samples: int,
    rng: np.random.Generator | int | None = 0,
    patch: int = PATCH,
    augment: bool = True,
) -> np.ndarray:
    """Sample ``patch x patch x frames`` training patches from videos.

    Augmentation as in the paper: each patch is rotated/flipped into one of 8
    orientations and played forward or backward, chosen at random.  Patches
    are drawn with probability growing with their temporal-spatial contrast,
    so that flat patches do not crowd out edges and motion (half the draws are
    uniform, half contrast-weighted).

    Parameters
    ----------
    videos : list of ndarray of shape (F, H, W), F >= frames

    Returns
    -------
    X : ndarray of shape (samples, frames * patch**2), float32
    """
    gen = np.random.default_rng(rng)
    usable = [v for v in videos if v.shape[0] >= frames and min(v.shape[1:]) >= patch]
    if not usable:
        raise InputError(f"training: no video has >= {frames} frames and {patch}x{patch} pixels")
    per = np.full(len(usable), samples // len(usable))
    per[: samples - per.sum()] += 1
    out = []
    for v, count in zip(usable, per):
        if count == 0:
            continue
        f, h, w = v.shape
        cand = 3 * count
        t0 = gen.integers(0, f - frames + 1, cand)
        y0 = gen.integers(0, h - patch + 1, cand)
        x0 = gen.integers(0, w - patch + 1, cand)
        tt = t0[:, None, None, None] + np.arange(frames)[None, :, None, None]
        yy = y0[:, None, None, None] + np.arange(patch)[None, None, :, None]
        xx = x0[:, None, None, None] + np.arange(patch)[None, None, None, :]
        blocks = v[tt, yy, xx].astype(np.float32)  # (cand, frames, M, M)
        contrast = blocks.reshape(cand, -1).std(1) + 1.0
        half = count // 2
        pick_u = gen.choice(cand, count - half, replace=False)
        pick_c = gen.choice(cand, half, replace=False, p=contrast / contrast.sum())
        blocks = blocks[np.concatenate([pick_u, pick_c])]
        if augment:
            orient = gen.integers(0, DIHEDRAL, blocks.shape[0])
            backward = gen.random(blocks.shape[0]) < 0.5
            for k in range(DIHEDRAL):
                sel = orient == k
                blocks[sel] = _dihedral(blocks[sel], k)
            blocks[backward] = blocks[backward][:, ::-1]
        out.append(blocks.reshape(blocks.shape[0], -1))
    X = np.concatenate(out)
    return X[gen.permutation(X.shape[0])]


def _initial_dictionary(X: np.ndarray, frames: int, atoms: int, patch: int, rng: np.random.Generator) -> np.ndarray:
    """The complete 3D DCT basis topped up with random training patches up to ``atoms`` columns (or its
    lowest-frequency ``atoms`` atoms)."""
    D0 = dct_dictionary(frames, patch=patch)
    if atoms - D0.shape[1] > X.shape[0]:  # (a config checks samples; short videos can give fewer patches)
        raise InputError(f"dictionary of {atoms} atoms: K-SVD starts from the {D0.shape[1]} DCT atoms and draws the "
                         f"other {atoms - D0.shape[1]} among the training patches, but only {X.shape[0]} were drawn; "
                         "give more training samples or video, or fewer atoms")
    if atoms > D0.shape[1]:
        extra = X[rng.choice(X.shape[0], atoms - D0.shape[1], replace=False)].T
        return np.concatenate([D0, extra], axis=1)
    # keep the lowest-frequency DCT atoms (ordered by total frequency)
    ft, fy, fx = np.meshgrid(np.arange(frames), np.arange(patch), np.arange(patch), indexing="ij")
    order = np.argsort((ft + fy + fx).ravel(), kind="stable")
    return D0[:, order[:atoms]]


def learn_dictionary(
    videos: list[np.ndarray],
    *,
    frames: int,
    settings: KsvdSettings = KsvdSettings(),
    seed: int = 0,
    patch: int = PATCH,
    progress=None,
    init: np.ndarray | None = None,
) -> tuple[np.ndarray, dict]:
    """Learn a dictionary with K-SVD, initialised from the 3D DCT (or from ``init``).

    The initial dictionary is the complete 3D DCT basis, topped up with random
    training patches up to ``settings.atoms`` columns; or ``init`` (N * patch**2, K), whose
    K atoms it keeps (``settings.atoms`` does not apply): a dictionary adapted to the
    training videos, such as one scene's reconstruction.  ``settings``: the training
    patches drawn, the iterations, the atoms per patch, the coding's tolerance, the
    augmentation and the unused atoms' replacement (:class:`KsvdSettings`).

    Returns
    -------
    D : ndarray of shape (frames * patch**2, atoms)
    meta : dict
        Patch size, frames, seed, iterations, final error, timings.
    """
    rng = np.random.default_rng(seed)
    n_feat = frames * patch * patch
    t0 = time.perf_counter()
    X = training_patches(videos, frames=frames, samples=settings.samples, rng=rng, patch=patch,
                         augment=settings.augment)
    spread = np.ptp(X, axis=1) if X.size else np.zeros(0)
    if not (spread > 1e-3 * max(1.0, float(np.abs(X).max(initial=0.0)))).any():
        raise InputError(f"training videos: every one of the {X.shape[0]} training patches drawn is flat (no change "
                         "in space or time), so K-SVD has nothing to learn (a dictionary of one flat atom); train on "
                         "videos with texture and motion")
    if init is not None:
        if init.shape[0] != n_feat:
            raise InputError(f"initial dictionary: {init.shape[0]} rows, patches of N = {frames} have {n_feat}")
        D0 = np.asarray(init, np.float32)
    else:
        D0 = _initial_dictionary(X, frames, settings.atoms, patch, rng)
    D, hist = ksvd(
        X, D0, sparsity=settings.sparsity, iterations=settings.iterations, tol=n_feat * settings.tol_rms**2, rng=rng,
        progress=progress, replace_unused=settings.replace_unused,
    )
    meta = dict(
        patch=patch,
        frames=frames,
        method="ksvd",
        seed=seed,
        iterations=settings.iterations,
        samples=int(X.shape[0]),
        sparsity=settings.sparsity,
        tol_rms=settings.tol_rms,
        init="dct3d+samples" if init is None else "given",
        augment=settings.augment,
        final_rmse=hist.rmse[-1] if hist.rmse else None,
        rmse_history=hist.rmse,
        replaced_history=hist.replaced,
        seconds=time.perf_counter() - t0,
    )
    return D, meta
