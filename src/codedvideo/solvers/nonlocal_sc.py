"""Non-local sparse coding: similar patches under different codes solved together (issue 16).

The same structure recurs in many patches of a scene, and every copy was seen
through a different shutter pattern: a group of ``k`` similar patches holds
``k x 49`` measurements of nearly the same unknowns.  From a first estimate (the
default per-patch OMP of :func:`codedvideo.solvers.region.reconstruct_region`):

1. block matching: for every reference patch, the ``group`` patches of the
   current estimate closest to it as whole ``7 x 7 x N`` blocks (sum of squared
   differences over every sub-frame, so similar in space and in motion) whose
   corners lie within ``window`` pixels (:func:`codedvideo.solvers.nonlocal_kernel.block_match`:
   deterministic, the reference itself first, ties to the earlier offset);
2. joint solve: simultaneous OMP of the group (:func:`codedvideo.solvers.nonlocal_kernel.somp_kernel`),
   one support for the whole group, every member's coefficients fit to its own
   measurement ``y_p = S_p D alpha_p`` under its own code;
3. aggregation: every member's estimate is added at its own place ("all") or
   only the reference's ("reference"), each pixel divided by the weight it got;
4. iterations: the next pass regroups on the new estimate.

Arrays in, arrays out: no I/O, no dask.  Like ``reconstruct_region``, a region
sees only its own patches, so tiled callers keep a halo of at least
``iterations * (patch - 1 + 2 * window)`` pixels (a kept pixel's estimates come
from members whose references lie ``window`` away, whose candidates lie another
``window`` further; tested), and pass the first estimate over the whole region
(itself valid there: the default's own halo around it).  The tile graph instead
splits one pass by its reference patches (``refs=``, ``sums=True``: blocks whose
sums add up to the whole pass, then :func:`finish`), so that no group is solved
twice (:mod:`codedvideo.engine.parallel`).  With ``group=1`` it is the default
reconstruction (the same still test, the same OMP operation for operation, the same fold).

Measured (tasks/bench_nonlocal.py, 256x256, N = 8, the 3 codes x sigma 0 and 4 of
case_quality; seconds include the default's): on the four held-out real clips
33.71 dB against the default's 32.40 and GAP-TV's 30.68 (GAP-TV + 3.03 dB, the
default GAP-TV + 1.72), 4.4x the default's time on the tile graph (4.1x after
the interleaved dot products of the Gram-Schmidt steps, 2026-11-26), never
below it (+0.64 to +2.45 dB a case); synthetic scenes +0.90 dB.  Chosen on a 5-case mix: groups of
16 at reference stride 3 (8 at stride 2: +1.08 dB, 12: +1.25 but 1.4x slower,
24 at stride 3: +1.29 but 1.75x), a support of 16 atoms (8: +0.75, 24 helps
noiseless Bernoulli and hurts noisy hitomi L=3), projection onto the
measurements (+0.1).  Measured and left off: a second pass regrouping on the new
estimate (+0.01), similarity weights (0), a distance cap on members (groups
shrink, worse), a pull of the members' coefficients towards the group's shared
fit (worse at every strength tried: the members are shifted copies, not the same
coefficients), misfit weights (+0.1, slower), BM3D's 1/atoms weights (+0.01),
a tolerance 0.6x or 1.5x the default's (0 / -0.04).
"""

from __future__ import annotations

import time

import numpy as np

from codedvideo.model import patches as P
from codedvideo.solvers.omp import _TINY, DEPENDENCE_TOL, SELECT_BITS, OmpResult, is_binary, pixel_patterns
from codedvideo.solvers.nonlocal_kernel import block_match, scatter_patches, somp_kernel
from codedvideo.solvers.omp_kernel import TableOMP, synthesize, table_fits
from codedvideo.solvers.region import WINDOW, OmpSettings, still_answers, still_patches

#: Names of the statistics, in the order of the stats vector.
STAT_NAMES = ("patches", "groups", "members_mean", "atoms_total", "patches_static", "seconds_match",
              "seconds_solve", "seconds_total", "fallback")

#: Defaults chosen on the benchmark (tasks/bench_nonlocal.py).
GROUP = 16
ITERATIONS = 1
STEP = 3
#: A group's atom budget is this times ``settings.max_atoms`` (k x 49 measurements afford more atoms) ...
ATOMS_FACTOR = 2
#: ... up to this many (unless ``max_atoms`` itself is more) ...
GROUP_ATOMS_CAP = 24


def group_atoms(max_atoms: int, m: int = P.PATCH * P.PATCH) -> int:
    """The atoms of a group's shared support for the per-patch budget ``max_atoms``, and never more than
    4/5 of a patch's ``m`` measurements: every member still fits its coefficients to its own measurements,
    and a support as large as them fits the noise and the code (measured, 64x64 synthetic scene, hitomi
    L = 2, tolerance 0: a support of 64 or 49 atoms gave values from -220 to 496 for 0..255 and 21 dB
    against the default's 30.6; 32 to 40 atoms 31.3 to 30.7 dB)."""
    return min(max(max_atoms, min(ATOMS_FACTOR * max_atoms, GROUP_ATOMS_CAP)), (4 * m) // 5)


def nonlocal_region(
    coded: np.ndarray, mask: np.ndarray, D: np.ndarray, first: np.ndarray, settings: OmpSettings, *,
    group: int = GROUP, window: int = WINDOW, iterations: int = ITERATIONS, step: int | None = None,
    atoms: int | None = None, consensus: float = 0.0, similarity: float | None = None,
    aggregate: str = "all", max_distance: float | None = None, project: bool | None = None,
    patch: int = P.PATCH, origin: tuple[int, int] = (0, 0), image_shape: tuple[int, int] | None = None,
    refs: tuple[int, int, int, int] | None = None, sums: bool = False, still: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Reconstruct a region by simultaneous sparse coding of groups of similar patches.

    Parameters
    ----------
    coded : ndarray of shape (h, w)
    mask : ndarray of shape (N, h, w)
        A binary code or a calibrated mask whose distinct pixel patterns fit a
        pattern table (any other mask: ``first`` is returned, ``stats[fallback] = 1``).
    D : ndarray of shape (N * patch**2, K)
    first : ndarray of shape (N, h, w)
        First estimate of the region (the default reconstruction); NaN reads as 0.
    settings : OmpSettings
        ``max_atoms``, ``tol_rms`` (per member), ``static_atoms`` (still test of
        the reference patches), ``stride`` (reference patches, as the default's),
        ``weighting`` ("fit": an estimate counts ``1 / (1 + e**2 / tol_rms**2)``).
    group : int
        Patches per group, the reference included (1: the default reconstruction).
    window : int
        Search radius in pixels around the reference's corner.
    iterations : int
        Passes; each regroups on the previous pass's estimate.
    step : int
        Stride of the reference patches (combined with ``settings.stride``; None:
        1 for a group of one, ``settings.group_step`` or ``STEP`` otherwise); with
        ``aggregate="all"`` every pixel still gets about ``group * 49 / step**2`` estimates.
    atoms : int, optional
        Atoms of a group's shared support (None: ``settings.max_atoms`` for a group
        of one, ``ATOMS_FACTOR`` times it otherwise).
    consensus : float
        Pull of every member's coefficients towards the group's shared fit
        (:func:`codedvideo.solvers.nonlocal_kernel.somp_kernel`; 0: none).
    similarity : float, optional
        With ``aggregate="all"``, a member's estimate counts ``exp(-d**2 / similarity**2)``,
        ``d`` its RMS block difference to the reference (grey levels); None: all count 1.
    aggregate : {"all", "reference"}
        Add every member's estimate at its place, or only the reference's.
    max_distance : float, optional
        Keep only members whose RMS block difference to the reference is at
        most this (grey levels per voxel); None: the ``group`` closest.
    project : bool
        After each pass, add the per-pixel minimum-norm correction that makes
        the estimate reproduce the coded image exactly (None: for groups of more
        than one; measured +0.1 dB on average).
    origin, image_shape : the region's corner in the image and the image's (H, W)
        (reference strides count from the image's corner, as in the default).
    refs : (y0, y1, x0, x1), optional
        Only reference patches whose corners lie in these rows and columns of
        the region (None: all).  Boxes that partition the corners split the
        work of one pass into parts whose ``sums`` add up to the whole
        (the tile graph, :mod:`codedvideo.engine.parallel`).
    sums : bool
        Return ``(summed, weight, stats)`` of the (single) pass: every
        estimate added at its place and the weight each pixel got, not yet
        divided or projected (:func:`finish`); the fallback returns None.
    still : ndarray of shape (h, w) bool, optional
        Pixels known to be still across captures (:mod:`codedvideo.model.sequence`).
        A patch wholly inside them takes the still answer (``coded / open
        count`` in every sub-frame) and is neither solved nor a member of any
        group, and pixels that only such patches cover keep the still answer
        exactly (:func:`keep_still`), as the default's tiles do.

    Returns
    -------
    volume : ndarray of shape (N, h, w), float32
    stats : ndarray of shape (len(STAT_NAMES),), float64
    """
    t_start = time.perf_counter()
    n, h, w = mask.shape
    if h < patch or w < patch:
        raise ValueError(f"region {h}x{w} is smaller than one {patch}x{patch} patch")
    if step is None:
        step = 1 if group == 1 else settings.group_step or STEP
    if project is None:
        project = group > 1
    if group < 1 or window < 0 or iterations < 0 or step < 1:
        raise ValueError("group >= 1, window >= 0, iterations >= 0, step >= 1")
    if sums and iterations != 1:
        raise ValueError("sums: one pass only (iterations=1)")
    if aggregate not in ("all", "reference"):
        raise ValueError(f"aggregate {aggregate!r}: choose all or reference")
    if settings.weighting not in ("uniform", "fit"):
        raise ValueError(f"weighting {settings.weighting!r}: choose uniform or fit")
    m = patch * patch
    F = n * m
    if D.shape[0] != F:
        raise ValueError(f"dictionary has {D.shape[0]} rows, patches have {F}")
    coded = np.asarray(coded, dtype=np.float32)
    first = np.asarray(first, dtype=np.float32)
    binary = is_binary(mask)
    if not binary:
        mask = np.asarray(mask, dtype=np.float32)
    stats = np.zeros(len(STAT_NAMES))
    hp, wp = P.grid_shape((h, w), patch)
    stats[0] = hp * wp
    patterns, which = pixel_patterns(mask)
    if not table_fits(len(patterns), D, m):
        stats[8] = 1.0
        stats[7] = time.perf_counter() - t_start
        return None if sums else (first.copy(), stats)
    table = TableOMP(patterns, D, m)
    open_any = mask.any(0)
    y_all = np.ascontiguousarray(P.extract(np.where(open_any, coded, 0.0).astype(np.float32), patch))
    pat_all = np.ascontiguousarray(P.extract(which, patch), dtype=np.int32)
    n_pix = P.extract(mask.sum(0, dtype=np.int32) if binary else mask.sum(0, dtype=np.float64), patch)
    n_open = (n_pix > 0).sum(1).astype(np.float32)
    tol_all = np.ascontiguousarray(n_open * settings.tol_rms**2, dtype=np.float64)
    measured = n_open > 0
    calm = np.zeros(hp * wp, np.bool_)  # wholly still across captures: the still answer, in no group
    if still is not None and np.any(still):
        calm = P.extract(np.asarray(still, np.uint8), patch).all(1) & measured
    # reference patches: the default's stride grid combined with ``step``
    stride = max(settings.stride, step)
    ref = measured.copy()
    if stride > 1:
        if stride > patch:
            raise ValueError(f"stride {stride}: must be 1 to {patch} (the patch size)")
        ih, iw = image_shape or (h, w)
        rows_on = P.stride_rows(origin[0], hp, ih - patch + 1, stride)
        cols_on = P.stride_rows(origin[1], wp, iw - patch + 1, stride)
        ref &= (rows_on[:, None] & cols_on[None, :]).ravel()
    if refs is not None:
        ry0, ry1, rx0, rx1 = refs
        rows, cols = np.arange(hp), np.arange(wp)
        ref &= (((rows >= ry0) & (rows < ry1))[:, None] & ((cols >= rx0) & (cols < rx1))[None, :]).ravel()
    # the still test of the reference patches (it does not depend on the estimate)
    still_est = np.zeros((0, F), np.float32)
    still_ok = np.zeros(hp * wp, np.bool_)
    if settings.static_atoms > 0:
        rows = np.flatnonzero(ref & ~calm)
        if rows.size:
            ok, still_est = still_patches(y_all[rows], n_pix[rows], tol_all[rows], settings.static_atoms,
                                          frames=n, patch=patch)
            still_ok[rows[ok]] = True
            stats[4] = ok.sum()
    if calm.any():  # their still answer, each pixel's value in every sub-frame, after the still test's rows
        rows = np.flatnonzero(ref & calm)
        still_est = np.concatenate([still_est, still_answers(y_all[rows], n_pix[rows], n)])
        order = np.concatenate([np.flatnonzero(still_ok), rows])
        still_ok[rows] = True
        stats[4] += rows.size
    else:
        order = np.flatnonzero(still_ok)
    still_slot = np.full(hp * wp, -1, np.int64)
    still_slot[order] = np.arange(order.size)
    if atoms is None:
        atoms = settings.max_atoms if group == 1 else group_atoms(settings.max_atoms, m)
    kmax = int(min(atoms, m))
    current = np.nan_to_num(first, nan=0.0).astype(np.float32)
    volume = first.copy()
    for _ in range(iterations):
        t0 = time.perf_counter()
        k = min(group, (2 * window + 1) ** 2, hp * wp)
        if (ref & ~still_ok).any():
            idx, dist = match_groups(current, k, window, patch=patch)
        else:  # every reference still: no group to match (a still block of a sequence)
            idx, dist = np.full((hp * wp, k), -1, np.int64), np.full((hp * wp, k), np.inf)
        if max_distance is not None:
            far = dist > (max_distance**2) * F
            far[:, 0] = False
            idx[far] = -1
        idx[~measured[np.maximum(idx, 0)] | calm[np.maximum(idx, 0)]] = -1  # nothing to add: unmeasured or still
        idx[:, 0] = np.arange(hp * wp)
        stats[5] += time.perf_counter() - t0
        t0 = time.perf_counter()
        summed = np.zeros((n, h, w), np.float32)
        weight = np.zeros((h, w), np.float32)
        solved = ref & ~still_ok  # references whose group is solved jointly
        n_groups = n_members = atoms = 0
        band = max(1, settings.batch // max(1, wp * (k if aggregate == "all" else 1)))
        for r0 in range(0, hp, band):
            r1 = min(hp, r0 + band)
            sl = slice(r0 * wp, r1 * wp)
            refs = np.flatnonzero(solved[sl]) + r0 * wp
            mem = idx[refs]
            # compact each group's members to the front (refs first, matches in order)
            order = np.argsort(mem < 0, axis=1, kind="stable")
            mem = np.ascontiguousarray(np.take_along_axis(mem, order, 1))
            dmem = np.take_along_axis(dist[refs], order, 1)
            size = (mem >= 0).sum(1).astype(np.int64)
            G = refs.size
            index = np.zeros((G, k, kmax), np.int32)
            coef = np.zeros((G, k, kmax), np.float32)
            count = np.zeros((G, k), np.int32)
            res2 = np.zeros((G, k), np.float32)
            dep = np.zeros((G, k), np.bool_)
            if G:
                somp_kernel(y_all, pat_all, np.maximum(mem, 0), size, table.B, table.floor, tol_all, kmax,
                            DEPENDENCE_TOL, SELECT_BITS, _TINY, index, coef, count, res2, dep, float(consensus))
            n_groups += G
            n_members += int(size.sum())
            atoms += int(count.sum())
            if aggregate == "reference" or k == 1:  # one estimate per patch: the default's fold
                est = np.zeros(((r1 - r0) * wp, F), np.float32)
                wgt = ref[sl].astype(np.float32)
                res = OmpResult(index=index[:, 0], coef=coef[:, 0], count=count[:, 0], residual=res2[:, 0],
                                dependent=dep[:, 0])
                est[refs - r0 * wp] = synthesize(res, D)
                st = np.flatnonzero(still_ok[sl])
                est[st] = still_est[still_slot[st + r0 * wp]]
                if settings.weighting == "fit":
                    e2 = _misfit(est, y_all[sl], pat_all[sl], patterns, n, m) / np.maximum(n_open[sl], 1)
                    wgt = wgt / (1.0 + e2 / max(settings.tol_rms, 1e-6) ** 2)
                    est *= wgt[:, None]
                P.fold_rows(est, summed, r0, patch)
                P.fold_rows(wgt, weight[None], r0, patch)
            else:
                live = np.arange(k)[None, :] < size[:, None]
                where = mem[live]
                res = OmpResult(index=index[live], coef=coef[live], count=count[live], residual=res2[live],
                                dependent=dep[live])
                est = synthesize(res, D)
                wgt = np.ones(where.size, np.float32)
                if similarity is not None:
                    wgt = np.exp(-dmem[live] / F / max(similarity, 1e-6) ** 2).astype(np.float32)
                if settings.weighting == "fit":
                    e2 = _misfit(est, y_all[where], pat_all[where], patterns, n, m) / np.maximum(n_open[where], 1)
                    wgt = wgt / (1.0 + e2 / max(settings.tol_rms, 1e-6) ** 2)
                scatter_patches(est, where, wgt, wp, patch, summed, weight)
                st = np.flatnonzero(still_ok[sl]) + r0 * wp
                if st.size:
                    scatter_patches(still_est[still_slot[st]], st, np.ones(st.size, np.float32), wp, patch,
                                    summed, weight)
        stats[6] += time.perf_counter() - t0
        stats[1] += n_groups
        stats[2] = n_members / max(n_groups, 1)
        stats[3] += atoms
        if sums:
            stats[7] = time.perf_counter() - t_start
            return summed, weight, stats
        volume = finish(summed, weight, coded, mask, project=project)
        if calm.any():
            keep_still(volume, coded, mask, still, patch)
        current = np.nan_to_num(volume, nan=0.0).astype(np.float32)
    stats[7] = time.perf_counter() - t_start
    return volume, stats


def keep_still(volume: np.ndarray, coded: np.ndarray, mask: np.ndarray, still: np.ndarray | None, patch: int,
               rows: slice = slice(None), cols: slice = slice(None)) -> None:
    """Give the pixels that only wholly still patches cover (``still``: pixels still across captures) the
    still answer exactly, in place: what a still tile gives, whatever groups reached them.

    ``coded``, ``mask``, ``still`` cover a region; ``volume`` is its ``[rows, cols]`` part, which must lie
    ``patch - 1`` pixels inside the region wherever the region is not cut by the image's border.
    """
    from codedvideo.solvers.region import _still_answer

    if still is None or not np.any(still):
        return
    h, w = coded.shape
    if h < patch or w < patch:
        return
    open_any = mask.any(0) if is_binary(mask) else mask.sum(0) > 0
    measured = P.extract(open_any.astype(np.uint8), patch).any(1)
    calm = P.extract(np.asarray(still, np.uint8), patch).all(1) & measured
    others = P.fold((measured & ~calm).astype(np.float32), (h, w), patch)[0]
    covered = P.fold(calm.astype(np.float32), (h, w), patch)[0]
    inner = ((others == 0) & (covered > 0))[rows, cols]
    if inner.any():
        volume[:, inner] = _still_answer(coded, mask, is_binary(mask))[rows, cols][inner]


def finish(summed: np.ndarray, weight: np.ndarray, coded: np.ndarray, mask: np.ndarray, *, project: bool = True
           ) -> np.ndarray:
    """A pass's estimate from its sums: each pixel's summed estimates divided by its weight (NaN where
    it got none), then, with ``project``, made to reproduce the coded image (:func:`project_measurements`)."""
    with np.errstate(invalid="ignore", divide="ignore"):
        volume = np.where(weight > 0, summed / weight, np.nan).astype(np.float32)
    return project_measurements(volume, coded, mask) if project else volume


def match_groups(volume: np.ndarray, group: int, window: int, *, patch: int = P.PATCH
                 ) -> tuple[np.ndarray, np.ndarray]:
    """The ``group`` patches of ``volume`` (N, h, w) closest to every patch, corners within ``window`` pixels.

    Distance: the sum of squared differences of the whole ``patch x patch x N``
    blocks.  Deterministic: the patch itself first, then increasing distance,
    ties to the earlier offset (``(0, 0)``, then raster order of ``(dy, dx)``).

    Returns
    -------
    idx : ndarray of shape (P, group), int64
        Raster indices of the members (``-1`` where fewer candidates exist).
    dist : ndarray of shape (P, group), float64
        Their squared distances (``inf`` for ``-1``).
    """
    vol = np.ascontiguousarray(np.nan_to_num(np.asarray(volume, np.float32), nan=0.0))
    hp, wp = P.grid_shape(vol.shape[1:], patch)
    idx = np.zeros((hp * wp, group), np.int64)
    dist = np.zeros((hp * wp, group), np.float64)
    block_match(vol, patch, window, group, idx, dist)
    return idx, dist


def joint_omp(y: np.ndarray, S: np.ndarray, D: np.ndarray, *, max_atoms: int, tol, consensus: float = 0.0
              ) -> np.ndarray:
    """Simultaneous OMP of one group: patches ``y`` (k, m) seen through codes ``S`` (k, N, m).

    One support for the group, each member's coefficients fit to its own
    measurement (:func:`codedvideo.solvers.nonlocal_kernel.somp_kernel`); a group of one is
    the default OMP.  Returns the members' estimates ``D alpha_p``, shape (k, N*m).
    """
    y = np.ascontiguousarray(y, np.float32)
    k, n, m = S.shape
    patterns, which = pixel_patterns(np.moveaxis(np.asarray(S), 1, 0))  # (N, k, m) -> which (k, m)
    table = TableOMP(patterns, D, m)
    kmax = int(min(max_atoms, m))
    tol = np.ascontiguousarray(np.broadcast_to(np.asarray(tol, np.float64), (k,)))
    index = np.zeros((1, k, kmax), np.int32)
    coef = np.zeros((1, k, kmax), np.float32)
    count = np.zeros((1, k), np.int32)
    res2 = np.zeros((1, k), np.float32)
    dep = np.zeros((1, k), np.bool_)
    somp_kernel(y, np.ascontiguousarray(which, np.int32), np.arange(k, dtype=np.int64)[None], np.array([k], np.int64),
                table.B, table.floor, tol, kmax, DEPENDENCE_TOL, SELECT_BITS, _TINY, index, coef, count,
                res2, dep, float(consensus))
    return synthesize(OmpResult(index=index[0], coef=coef[0], count=count[0], residual=res2[0], dependent=dep[0]), D)


def _misfit(est: np.ndarray, y: np.ndarray, pat: np.ndarray, patterns: np.ndarray, n: int, m: int) -> np.ndarray:
    """``||y_p - S_p E_p||^2`` of every patch estimate (rows of ``est``)."""
    S = patterns[pat].transpose(0, 2, 1)  # (P, N, m)
    r = y - (S * est.reshape(-1, n, m)).sum(1)
    return np.einsum("pm,pm->p", r, r)


def project_measurements(volume: np.ndarray, coded: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """The nearest volume (per pixel, least squares) that reproduces the coded image exactly.

    ``v + s (y - s.v) / (s.s)`` at every measured pixel (``s`` its shutter weights);
    unmeasured and NaN pixels are left as they are.
    """
    s = np.asarray(mask, np.float32)
    v = np.asarray(volume, np.float32)
    ss = (s * s).sum(0)
    r = np.asarray(coded, np.float32) - (s * np.nan_to_num(v)).sum(0)
    with np.errstate(invalid="ignore", divide="ignore"):
        corr = np.where(ss > 0, r / ss, 0.0).astype(np.float32)
    return (v + s * corr[None]).astype(np.float32)
