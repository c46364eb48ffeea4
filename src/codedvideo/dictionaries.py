"""Dictionaries of 7x7xN video patches: 3D DCT and learned (K-SVD).

A dictionary is a float32 array of shape ``(N * M * M, K)`` whose rows are
ordered ``(t, dy, dx)`` (as :mod:`codedvideo.patches`) and whose columns
(atoms) have unit norm.  Storage is in :mod:`codedvideo.store`.
"""

from __future__ import annotations

import math
import time

import numpy as np
from scipy.fft import dct

from .errors import InputError
from .ksvd import ksvd

PATCH = 7


def _dct_1d(n: int, atoms: int) -> np.ndarray:
    """Orthonormal DCT-II basis (atoms == n) or an overcomplete cosine frame."""
    if atoms == n:
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
    rng = np.random.default_rng(rng)
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
        t0 = rng.integers(0, f - frames + 1, cand)
        y0 = rng.integers(0, h - patch + 1, cand)
        x0 = rng.integers(0, w - patch + 1, cand)
        tt = t0[:, None, None, None] + np.arange(frames)[None, :, None, None]
        yy = y0[:, None, None, None] + np.arange(patch)[None, None, :, None]
        xx = x0[:, None, None, None] + np.arange(patch)[None, None, None, :]
        blocks = v[tt, yy, xx].astype(np.float32)  # (cand, frames, M, M)
        contrast = blocks.reshape(cand, -1).std(1) + 1.0
        half = count // 2
        pick_u = rng.choice(cand, count - half, replace=False)
        pick_c = rng.choice(cand, half, replace=False, p=contrast / contrast.sum())
        blocks = blocks[np.concatenate([pick_u, pick_c])]
        if augment:
            orient = rng.integers(0, DIHEDRAL, blocks.shape[0])
            backward = rng.random(blocks.shape[0]) < 0.5
            for k in range(DIHEDRAL):
                sel = orient == k
                blocks[sel] = _dihedral(blocks[sel], k)
            blocks[backward] = blocks[backward][:, ::-1]
        out.append(blocks.reshape(blocks.shape[0], -1))
    X = np.concatenate(out)
    return X[rng.permutation(X.shape[0])]


def learn_dictionary(
    videos: list[np.ndarray],
    *,
    frames: int,
    atoms: int = 512,
    samples: int = 20000,
    iterations: int = 15,
    sparsity: int = 6,
    tol_rms: float = 0.5,
    seed: int = 0,
    patch: int = PATCH,
    progress=None,
) -> tuple[np.ndarray, dict]:
    """Learn a dictionary with K-SVD, initialised from the 3D DCT.

    The initial dictionary is the complete 3D DCT basis, topped up with random
    training patches up to ``atoms`` columns.  ``tol_rms`` stops the coding of
    a sample once its RMS residual (grey levels per entry) is below it.

    Returns
    -------
    D : ndarray of shape (frames * patch**2, atoms)
    meta : dict
        Patch size, frames, seed, iterations, final error, timings.
    """
    rng = np.random.default_rng(seed)
    n_feat = frames * patch * patch
    t0 = time.perf_counter()
    X = training_patches(videos, frames=frames, samples=samples, rng=rng, patch=patch)
    D0 = dct_dictionary(frames, patch=patch)
    if atoms > D0.shape[1]:
        extra = X[rng.choice(X.shape[0], atoms - D0.shape[1], replace=False)].T
        D0 = np.concatenate([D0, extra], axis=1)
    else:
        # keep the lowest-frequency DCT atoms (ordered by total frequency)
        ft, fy, fx = np.meshgrid(np.arange(frames), np.arange(patch), np.arange(patch), indexing="ij")
        order = np.argsort((ft + fy + fx).ravel(), kind="stable")
        D0 = D0[:, order[:atoms]]
    D, hist = ksvd(
        X, D0, sparsity=sparsity, iterations=iterations, tol=n_feat * tol_rms**2, rng=rng, progress=progress
    )
    meta = dict(
        patch=patch,
        frames=frames,
        method="ksvd",
        seed=seed,
        iterations=iterations,
        samples=int(X.shape[0]),
        sparsity=sparsity,
        tol_rms=tol_rms,
        init="dct3d+samples",
        final_rmse=hist.rmse[-1] if hist.rmse else None,
        rmse_history=hist.rmse,
        replaced_history=hist.replaced,
        seconds=time.perf_counter() - t0,
    )
    return D, meta
