"""The per-tile reconstruction kernel (arrays in, arrays out; no I/O, no dask).

For a coded image region and its code, every overlapping 7x7 patch is solved by
OMP (Eq. 3), its space-time estimate ``E_p = D alpha_p`` is added back at its
place, and every pixel is divided by the exact number of patches covering it
(Sec. 5.1: the ``M^2`` estimates of a pixel are averaged).
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from . import patches as P
from .omp import masked_operator, omp, synthesize

#: Names of the per-tile statistics, in the order of the stats vector.
STAT_NAMES = (
    "patches",
    "patches_static",
    "atoms_total",
    "atoms_max_hit",
    "dependent_stops",
    "seconds_omp",
    "seconds_total",
)


@dataclass(frozen=True)
class OmpSettings:
    """Settings of the sparse-coding step.

    Attributes
    ----------
    max_atoms : int
        Maximum sparsity of a patch (Eq. 3).
    tol_rms : float
        Residual tolerance of Eq. 3 as an RMS per measured pixel (frame units):
        OMP stops once ``||A alpha - y||^2 <= n_open * tol_rms**2``.
    batch : int
        Patches solved together (bounds memory: about ``batch * K * 8`` bytes).
    """

    max_atoms: int = 8
    tol_rms: float = 1.0
    batch: int = 4096
    static_atoms: int = 4


def static_dictionary(frames: int, patch: int = P.PATCH) -> np.ndarray:
    """Atoms of a still scene: the 2D DCT of a patch, constant over the N sub-frames.

    Shape ``(frames * patch**2, patch**2)``, unit-norm columns, ordered from low
    to high spatial frequency (the first atom is the flat patch).
    """
    from .dictionaries import dct_dictionary

    C = dct_dictionary(1, patch=patch)  # (m, m): 2D DCT basis
    fy, fx = np.meshgrid(np.arange(patch), np.arange(patch), indexing="ij")
    C = C[:, np.argsort((fy + fx).ravel(), kind="stable")]
    return (np.tile(C, (frames, 1)) / np.sqrt(frames)).astype(np.float32)


def reconstruct_region(
    coded: np.ndarray, mask: np.ndarray, D: np.ndarray, settings: OmpSettings, *, patch: int = P.PATCH
) -> tuple[np.ndarray, np.ndarray]:
    """Reconstruct every pixel of a region from the patches inside it.

    Parameters
    ----------
    coded : ndarray of shape (h, w)
    mask : ndarray of shape (N, h, w)
    D : ndarray of shape (N * patch**2, K)
    settings : OmpSettings

    Patches that a still scene explains -- OMP over :func:`static_dictionary`
    reaches the residual tolerance with at most ``settings.static_atoms`` atoms
    (a flat patch needs one) -- keep that answer and skip the full dictionary.
    A moving scene leaves a pixel-random, code-dependent residual that few
    smooth still atoms cannot explain, so this test only accepts patches
    whose motion is below the noise level.

    Returns
    -------
    volume : ndarray of shape (N, h, w), float32
        Average of the estimates of all patches inside the region covering each
        pixel.  Pixels near the region's border see fewer patches than in the
        whole image, so callers keep only pixels at least ``patch - 1`` away
        from a border that is not the image's own border.
    stats : ndarray of shape (len(STAT_NAMES),), float64
    """
    t_start = time.perf_counter()
    n, h, w = mask.shape
    if h < patch or w < patch:
        raise ValueError(f"region {h}x{w} is smaller than one {patch}x{patch} patch")
    coded = np.asarray(coded, dtype=np.float32)
    open_any = mask.any(0)
    y_all = P.extract(np.where(open_any, coded, 0.0).astype(np.float32), patch)  # (Pn, m)
    S_all = P.extract(mask.astype(np.uint8), patch)  # (Pn, N, m)
    n_open = (S_all.any(1)).sum(1).astype(np.float32)
    est = np.empty((y_all.shape[0], n * patch * patch), np.float32)
    atoms = hit = dep = n_static = 0
    t_omp = 0.0
    D_still = static_dictionary(n, patch) if settings.static_atoms > 0 else None
    for s in range(0, y_all.shape[0], settings.batch):
        sl = slice(s, s + settings.batch)
        y, S, tol = y_all[sl], S_all[sl], n_open[sl] * settings.tol_rms**2
        t0 = time.perf_counter()
        rows = np.arange(y.shape[0])
        if D_still is not None:
            still = omp(y, masked_operator(S, D_still), max_atoms=settings.static_atoms, tol=tol)
            ok = still.residual <= tol
            est[s + rows[ok]] = synthesize(still.select(ok), D_still)
            n_static += int(ok.sum())
            rows = rows[~ok]
        if rows.size:
            res = omp(y[rows], masked_operator(S[rows], D), max_atoms=settings.max_atoms, tol=tol[rows])
            est[s + rows] = synthesize(res, D)
            atoms += int(res.count.sum())
            hit += int((res.count >= settings.max_atoms).sum())
            dep += int(res.dependent.sum())
        t_omp += time.perf_counter() - t0
    summed = P.fold(est, (h, w), patch)
    cover = P.coverage((h, w), patch)
    volume = summed / cover[None].astype(np.float32)
    stats = np.array(
        [y_all.shape[0], n_static, atoms, hit, dep, t_omp, time.perf_counter() - t_start],
        dtype=np.float64,
    )
    return volume, stats
