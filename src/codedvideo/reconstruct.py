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
from .omp import MaskedOperator, omp, synthesize

#: Names of the per-tile statistics, in the order of the stats vector.
STAT_NAMES = (
    "patches",
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
    atoms = hit = dep = 0
    t_omp = 0.0
    for s in range(0, y_all.shape[0], settings.batch):
        sl = slice(s, s + settings.batch)
        t0 = time.perf_counter()
        op = MaskedOperator(S_all[sl], D)
        res = omp(y_all[sl], op, max_atoms=settings.max_atoms, tol=n_open[sl] * settings.tol_rms**2)
        est[sl] = synthesize(res, D)
        t_omp += time.perf_counter() - t0
        atoms += int(res.count.sum())
        hit += int((res.count >= settings.max_atoms).sum())
        dep += int(res.dependent.sum())
    summed = P.fold(est, (h, w), patch)
    cover = P.coverage((h, w), patch)
    volume = summed / cover[None].astype(np.float32)
    stats = np.array(
        [y_all.shape[0], atoms, hit, dep, t_omp, time.perf_counter() - t_start],
        dtype=np.float64,
    )
    return volume, stats
