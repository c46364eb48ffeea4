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

Its quality and time are in docs/quality.md; how the group size, stride, support and projection were
chosen, and the variants left off, are in docs/research.md, "The non-local method".
"""

from __future__ import annotations

import time
from dataclasses import dataclass, replace

import numpy as np

from codedvideo.model import patches as P
from codedvideo.model.codes import is_binary
from codedvideo.solvers.omp import _TINY, DEPENDENCE_TOL, PRIOR, SELECT_BITS, OmpResult, pixel_patterns
from codedvideo.solvers.nonlocal_kernel import block_match, scatter_patches, somp_kernel
from codedvideo.solvers.omp_kernel import TableOMP, atom_rows, synthesize, synthesize_rows, table_fits
from codedvideo.solvers.region import (WINDOW, OmpSettings, RegionPatches, estimate_energy, guard_estimates,
                                       region_patches, still_answers, still_patches, stride_grid)

#: Names of the statistics, in the order of the stats vector (:meth:`NonlocalStats.as_array`).
STAT_NAMES = ("patches", "groups", "members_mean", "atoms_total", "patches_static", "seconds_match",
              "seconds_solve", "seconds_total", "fallback")


@dataclass
class NonlocalStats:
    """What a region's non-local pass did: its patches, groups and their mean size, atoms, still patches, the
    seconds matching, solving and in all, and whether it fell back to the first estimate (1) because the mask's
    patterns do not fit a table."""

    patches: float = 0.0
    groups: float = 0.0
    members_mean: float = 0.0
    atoms_total: float = 0.0
    patches_static: float = 0.0
    seconds_match: float = 0.0
    seconds_solve: float = 0.0
    seconds_total: float = 0.0
    fallback: float = 0.0

    def as_array(self) -> np.ndarray:
        """The statistics as a vector in the order of :data:`STAT_NAMES` (a working store's row)."""
        return np.array([float(getattr(self, name)) for name in STAT_NAMES], np.float64)

#: Defaults chosen on the benchmark (tasks/bench_nonlocal.py).
GROUP = 16
ITERATIONS = 1
STEP = 3
#: A group's atom budget is this times ``settings.max_atoms`` (k x 49 measurements afford more atoms) ...
ATOMS_FACTOR = 2
#: ... up to this many (unless ``max_atoms`` itself is more) ...
GROUP_ATOMS_CAP = 24


#: A patch with fewer pixels than this within a pixel of one ever open is neither a reference nor a member of any
#: group: beside a block of missing pixels (saturated or defective), a group's shared atoms fitted to the few
#: measured pixels of a corner give values far outside the data range.  Its pixels take the estimates of the
#: patches that see enough of them, or the first estimate's where none does (:func:`finish`).  Two thirds of the
#: patch, counted within a pixel of a measurement, so that a code's own scattered never-open pixels leave every
#: patch in (docs/research.md, "The non-local method").
MIN_OPEN = P.PATCH * P.PATCH * 2 // 3 + 1


def _near_measured(mask: np.ndarray) -> np.ndarray:
    """(h, w) uint8: the pixels ever open under ``mask`` (N, h, w) and their eight neighbours."""
    open_any = np.pad(np.asarray(mask).any(0), 1)
    h, w = open_any.shape[0] - 2, open_any.shape[1] - 2
    near = np.zeros((h, w), bool)
    for dy in range(3):
        for dx in range(3):
            near |= open_any[dy:dy + h, dx:dx + w]
    return near.astype(np.uint8)


def group_atoms(max_atoms: int, m: int = P.PATCH * P.PATCH) -> int:
    """The atoms of a group's shared support for the per-patch budget ``max_atoms``, and never more than
    4/5 of a patch's ``m`` measurements: every member still fits its coefficients to its own measurements,
    and a support as large as them fits the noise and the code (docs/research.md, "The non-local method")."""
    return min(max(max_atoms, min(ATOMS_FACTOR * max_atoms, GROUP_ATOMS_CAP)), (4 * m) // 5)


def nonlocal_region(
    coded: np.ndarray, mask: np.ndarray, D: np.ndarray, first: np.ndarray, settings: OmpSettings,
    options: NonlocalOptions | None = None, *, still: np.ndarray | None = None, **choices,
) -> tuple[np.ndarray, np.ndarray]:
    """Reconstruct a region by simultaneous sparse coding of groups of similar patches.

    Parameters
    ----------
    coded : ndarray of shape (h, w)
    mask : ndarray of shape (N, h, w)
        A binary code or a calibrated mask whose distinct pixel patterns fit a
        pattern table (any other mask: ``first`` is returned, its ``fallback`` statistic 1).
    D : ndarray of shape (N * patch**2, K)
    first : ndarray of shape (N, h, w)
        First estimate of the region (the default reconstruction); NaN reads as 0.
    settings : OmpSettings
        ``max_atoms``, ``tol_rms`` (per member), ``static_atoms`` (still test of
        the reference patches), ``stride`` (reference patches, as the default's),
        ``weighting`` ("fit": an estimate counts ``1 / (1 + e**2 / tol_rms**2)``).
    options : NonlocalOptions, optional
        The groups, the passes and the region's place (None: the defaults); checked and resolved
        (:func:`_options`) before any work.
    choices
        Fields of :class:`NonlocalOptions` given one by one (``group=8, window=3``), over ``options``.
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
    opts = _options(replace(options or NonlocalOptions(), **choices), settings, mask.shape, D)
    patch, group, window, sums = opts.patch, opts.group, opts.window, opts.sums
    first32 = np.asarray(first, dtype=np.float32)
    binary = is_binary(mask)
    weights = mask if binary else np.asarray(mask, dtype=np.float32)
    hp, wp = P.grid_shape(mask.shape[1:], patch)
    stats = NonlocalStats(patches=hp * wp)
    patterns, which = pixel_patterns(weights)
    if not table_fits(len(patterns), D, patch * patch):
        stats.fallback = 1.0
        stats.seconds_total = time.perf_counter() - t_start
        return None if sums else (first32.copy(), stats.as_array())
    coded32 = np.asarray(coded, dtype=np.float32)
    region = _region(coded32, weights, binary, D, (patterns, which), settings.tol_rms, still, patch)
    chosen = _references(region, settings, opts, stats)
    k = min(group, (2 * window + 1) ** 2, hp * wp)
    current = np.nan_to_num(first32, nan=0.0).astype(np.float32)
    volume = first32.copy()
    for _ in range(opts.iterations):
        t0 = time.perf_counter()
        idx, dist = _match(region, chosen, current, k, opts)
        stats.seconds_match += time.perf_counter() - t0
        t0 = time.perf_counter()
        summed, weight, (n_groups, n_members, n_atoms) = _solve_pass(region, chosen, idx, dist, D, settings, opts)
        stats.seconds_solve += time.perf_counter() - t0
        stats.groups += n_groups
        stats.members_mean = n_members / max(n_groups, 1)
        stats.atoms_total += n_atoms
        if sums:
            stats.seconds_total = time.perf_counter() - t_start
            return summed, weight, stats.as_array()
        volume = finish(summed, weight, coded32, weights, project=opts.project, first=first32)
        if region.calm.any():
            keep_still(volume, coded32, weights, still, patch)
        current = np.nan_to_num(volume, nan=0.0).astype(np.float32)
    stats.seconds_total = time.perf_counter() - t_start
    return volume, stats.as_array()


@dataclass(frozen=True)
class NonlocalOptions:
    """The choices of :func:`nonlocal_region`, with ``step``, ``atoms`` and ``project`` resolved from None by
    :func:`_options`.

    Parameters
    ----------
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
        than one when ``settings.exact``, the capture free of read noise; docs/research.md, "The non-local
        method").
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
    """

    group: int = GROUP
    window: int = WINDOW
    iterations: int = ITERATIONS
    step: int | None = None
    atoms: int | None = None
    consensus: float = 0.0
    similarity: float | None = None
    aggregate: str = "all"
    max_distance: float | None = None
    project: bool | None = None
    patch: int = P.PATCH
    origin: tuple[int, int] = (0, 0)
    image_shape: tuple[int, int] | None = None
    refs: tuple[int, int, int, int] | None = None
    sums: bool = False


def _options(opts: NonlocalOptions, settings: OmpSettings, shape: tuple[int, int, int], D: np.ndarray
             ) -> NonlocalOptions:
    """``opts`` checked against the settings, the region's mask shape (N, h, w) and the dictionary (a ValueError
    otherwise), with the defaults of ``step``, ``project`` and ``atoms`` filled in."""
    n, h, w = shape
    patch, group = opts.patch, opts.group
    if h < patch or w < patch:
        raise ValueError(f"region {h}x{w} is smaller than one {patch}x{patch} patch")
    step = opts.step
    if step is None:
        step = 1 if group == 1 else settings.group_step or STEP
    project = group > 1 and settings.exact if opts.project is None else opts.project
    if group < 1 or opts.window < 0 or opts.iterations < 0 or step < 1:
        raise ValueError("group >= 1, window >= 0, iterations >= 0, step >= 1")
    if opts.sums and opts.iterations != 1:
        raise ValueError("sums: one pass only (iterations=1)")
    if opts.aggregate not in ("all", "reference"):
        raise ValueError(f"aggregate {opts.aggregate!r}: choose all or reference")
    if settings.weighting not in ("uniform", "fit"):
        raise ValueError(f"weighting {settings.weighting!r}: choose uniform or fit")
    m = patch * patch
    if D.shape[0] != n * m:
        raise ValueError(f"dictionary has {D.shape[0]} rows, patches have {n * m}")
    atoms = opts.atoms
    if atoms is None:
        atoms = settings.max_atoms if group == 1 else group_atoms(settings.max_atoms, m)
    return replace(opts, step=step, project=project, atoms=atoms)


@dataclass(frozen=True)
class _Region:
    """A region's patches as every pass reads them (:func:`_region`): ``patches`` (:class:`RegionPatches`),
    their pattern indices ``pat`` (Pn, m) into ``patterns`` and its ``table``, squared tolerances ``tol``, the
    ``measured`` ones (a pixel ever open, and at least :data:`MIN_OPEN` within a pixel of one) and the ``calm`` ones (wholly still across captures: the still
    answer, in no group)."""

    shape: tuple[int, int, int]
    patches: RegionPatches
    patterns: np.ndarray
    table: TableOMP
    pat: np.ndarray
    tol: np.ndarray
    measured: np.ndarray
    calm: np.ndarray


def _region(coded: np.ndarray, mask: np.ndarray, binary: bool, D: np.ndarray, patterned: tuple[np.ndarray, np.ndarray],
            tol_rms: float, still: np.ndarray | None, patch: int) -> _Region:
    """The :class:`_Region` of a coded image (h, w) float32 under ``mask`` with its pixel patterns and each
    pixel's pattern, ``patterned`` (:func:`pixel_patterns`)."""
    patterns, which = patterned
    table = TableOMP(patterns, D, patch * patch)
    patches = region_patches(coded, mask, binary, patch)
    tol = np.ascontiguousarray(patches.n_open * tol_rms**2, dtype=np.float64)
    measured = (patches.n_open > 0) & (P.extract(_near_measured(mask), patch).sum(1) >= MIN_OPEN)
    calm = np.zeros(measured.size, np.bool_)
    if still is not None and np.any(still):
        calm = P.extract(np.asarray(still, np.uint8), patch).all(1) & measured
    return _Region(shape=mask.shape, patches=patches, patterns=patterns, table=table,
                   pat=np.ascontiguousarray(P.extract(which, patch), dtype=np.int32), tol=tol, measured=measured,
                   calm=calm)


@dataclass(frozen=True)
class _References:
    """The reference patches of a region (``ref``, raveled grid), which of them take a still answer
    (``still_ok``), and those answers (rows of ``still_est``; ``still_slot``: a patch's row, or -1)."""

    ref: np.ndarray
    still_ok: np.ndarray
    still_est: np.ndarray
    still_slot: np.ndarray


def _references(region: _Region, settings: OmpSettings, opts: NonlocalOptions, stats: NonlocalStats) -> _References:
    """The reference patches: the measured ones on the default's stride grid combined with ``opts.step``, inside
    ``opts.refs``; then the still test of them (it does not depend on the estimate; counted in ``stats``)."""
    n, h, w = region.shape
    patches = region.patches
    hp, wp = patches.grid
    ref = region.measured.copy()
    on_grid = stride_grid(max(settings.stride, opts.step), patches.grid, opts.patch, opts.origin,
                          opts.image_shape or (h, w))
    if on_grid is not None:
        ref &= on_grid
    if opts.refs is not None:
        ry0, ry1, rx0, rx1 = opts.refs
        rows, cols = np.arange(hp), np.arange(wp)
        ref &= (((rows >= ry0) & (rows < ry1))[:, None] & ((cols >= rx0) & (cols < rx1))[None, :]).ravel()
    still_est = np.zeros((0, n * opts.patch**2), np.float32)
    still_ok = np.zeros(hp * wp, np.bool_)
    if settings.static_atoms > 0:
        rows = np.flatnonzero(ref & ~region.calm)
        if rows.size:
            # the still images get their temporal profiles under read noise only: without noise the profiles here
            # cost best up to 1.5 dB on a flat corner (docs/research.md, "Flat regions that change below the tolerance")
            ok, still_est = still_patches(patches.y[rows], patches.n_pix[rows], region.tol[rows],
                                          settings.static_atoms, frames=n, patch=opts.patch,
                                          codes=None if settings.exact else (patches.codes, patches.corners(rows)),
                                          ridge=settings.ridge)
            still_ok[rows[ok]] = True
            stats.patches_static = int(ok.sum())
    if region.calm.any():  # their still answer, each pixel's value in every sub-frame, after the still test's rows
        rows = np.flatnonzero(ref & region.calm)
        still_est = np.concatenate([still_est, still_answers(patches.y[rows], patches.n_pix[rows], n)])
        order = np.concatenate([np.flatnonzero(still_ok), rows])
        still_ok[rows] = True
        stats.patches_static += rows.size
    else:
        order = np.flatnonzero(still_ok)
    still_slot = np.full(hp * wp, -1, np.int64)
    still_slot[order] = np.arange(order.size)
    return _References(ref=ref, still_ok=still_ok, still_est=still_est, still_slot=still_slot)


def _match(region: _Region, chosen: _References, current: np.ndarray, k: int, opts: NonlocalOptions
           ) -> tuple[np.ndarray, np.ndarray]:
    """Every patch's group of ``k`` on the estimate ``current`` (:func:`match_groups`): members farther than
    ``opts.max_distance``, unmeasured or still are dropped (-1), the patch itself always first."""
    n_patches = region.measured.size
    if (chosen.ref & ~chosen.still_ok).any():
        idx, dist = match_groups(current, k, opts.window, patch=opts.patch)
    else:  # every reference still: no group to match (a still block of a sequence)
        idx, dist = np.full((n_patches, k), -1, np.int64), np.full((n_patches, k), np.inf)
    if opts.max_distance is not None:
        far = dist > (opts.max_distance**2) * (region.shape[0] * opts.patch**2)
        far[:, 0] = False
        idx[far] = -1
    # nothing to add: unmeasured or still
    idx[~region.measured[np.maximum(idx, 0)] | region.calm[np.maximum(idx, 0)]] = -1
    idx[:, 0] = np.arange(n_patches)
    return idx, dist


def _solve_pass(region: _Region, chosen: _References, idx: np.ndarray, dist: np.ndarray, D: np.ndarray,
                settings: OmpSettings, opts: NonlocalOptions) -> tuple[np.ndarray, np.ndarray, tuple[int, int, int]]:
    """One pass: the groups ``idx`` (distances ``dist``) of the references solved jointly, whole rows of
    references at a time, and their estimates added up: the sums (N, h, w), the weights (h, w) and the
    groups, members and atoms solved."""
    n, h, w = region.shape
    hp, wp = region.patches.grid
    k = idx.shape[1]
    summed = np.zeros((n, h, w), np.float32)
    weight = np.zeros((h, w), np.float32)
    solved = chosen.ref & ~chosen.still_ok  # references whose group is solved jointly
    n_groups = n_members = n_atoms = 0
    band = max(1, settings.batch // max(1, wp * (k if opts.aggregate == "all" else 1)))
    atoms = atom_rows(D)  # (once: every band's estimates are synthesised from it)
    for r0 in range(0, hp, band):
        r1 = min(hp, r0 + band)
        band_refs = np.flatnonzero(solved[r0 * wp:r1 * wp]) + r0 * wp
        groups = _solve_groups(region, band_refs, idx[band_refs], dist[band_refs], opts)
        n_groups += band_refs.size
        n_members += int(groups.size.sum())
        n_atoms += int(groups.count.sum())
        if opts.aggregate == "reference" or k == 1:  # one estimate per patch: the default's fold
            _fold_references(region, chosen, groups, atoms, settings, (r0, r1), summed, weight)
        else:
            _scatter_members(region, chosen, groups, atoms, settings, opts.similarity, (r0, r1), (summed, weight))
    return summed, weight, (n_groups, n_members, n_atoms)


@dataclass(frozen=True)
class _Groups:
    """Solved groups: the references ``refs``, their members ``mem`` (G, k; -1 past ``size``) at distances
    ``dmem``, and per (group, member) the :class:`OmpResult` fields ``index``, ``coef`` (G, k, kmax), ``count``,
    ``res2``, ``dep`` (G, k)."""

    refs: np.ndarray
    mem: np.ndarray
    dmem: np.ndarray
    size: np.ndarray
    index: np.ndarray
    coef: np.ndarray
    count: np.ndarray
    res2: np.ndarray
    dep: np.ndarray


def _solve_groups(region: _Region, refs: np.ndarray, members: np.ndarray, dist: np.ndarray,
                  opts: NonlocalOptions) -> _Groups:
    """The groups of references ``refs`` (their rows ``members``, ``dist`` of the matched groups) solved by
    simultaneous OMP (:func:`codedvideo.solvers.nonlocal_kernel.somp_kernel`)."""
    k = members.shape[1]
    kmax = int(min(opts.atoms, opts.patch**2))
    # compact each group's members to the front (refs first, matches in order)
    order = np.argsort(members < 0, axis=1, kind="stable")
    mem = np.ascontiguousarray(np.take_along_axis(members, order, 1))
    dmem = np.take_along_axis(dist, order, 1)
    size = (mem >= 0).sum(1).astype(np.int64)
    G = refs.size
    index = np.zeros((G, k, kmax), np.int32)
    coef = np.zeros((G, k, kmax), np.float32)
    count = np.zeros((G, k), np.int32)
    res2 = np.zeros((G, k), np.float32)
    dep = np.zeros((G, k), np.bool_)
    if G:
        somp_kernel(region.patches.y, region.pat, np.maximum(mem, 0), size, region.table.B, region.table.floor,
                    region.tol, kmax, DEPENDENCE_TOL, SELECT_BITS, _TINY, index, coef, count, res2, dep,
                    float(opts.consensus))
    return _Groups(refs=refs, mem=mem, dmem=dmem, size=size, index=index, coef=coef, count=count, res2=res2, dep=dep)


def _fold_references(region: _Region, chosen: _References, groups: _Groups, atoms: np.ndarray,
                     settings: OmpSettings, band: tuple[int, int], summed: np.ndarray, weight: np.ndarray) -> None:
    """``aggregate="reference"`` (or groups of one): each reference's own estimate (or its still answer) added
    at its place, the rows ``band`` of patches (the default's fold); ``atoms``: the dictionary's
    :func:`~codedvideo.solvers.omp_kernel.atom_rows`."""
    n = region.shape[0]
    patches = region.patches
    m = patches.y.shape[1]
    r0, r1 = band
    wp = patches.grid[1]
    sl = slice(r0 * wp, r1 * wp)
    est = np.zeros(((r1 - r0) * wp, n * m), np.float32)
    wgt = chosen.ref[sl].astype(np.float32)
    res = OmpResult(index=groups.index[:, 0], coef=groups.coef[:, 0], count=groups.count[:, 0],
                    residual=groups.res2[:, 0], dependent=groups.dep[:, 0])
    rows = groups.refs - r0 * wp
    est[rows] = synthesize_rows(res, atoms)
    _guarded(region, est, rows, rows + r0 * wp, res, atoms, settings)
    st = np.flatnonzero(chosen.still_ok[sl])
    est[st] = chosen.still_est[chosen.still_slot[st + r0 * wp]]
    if settings.weighting == "fit":
        e2 = _misfit(est, patches.y[sl], region.pat[sl], region.patterns, n, m) / np.maximum(patches.n_open[sl], 1)
        wgt = wgt / (1.0 + e2 / max(settings.tol_rms, 1e-6) ** 2)
        est *= wgt[:, None]
    P.fold_rows(est, summed, r0, patches.patch)
    P.fold_rows(wgt, weight[None], r0, patches.patch)


def _scatter_members(region: _Region, chosen: _References, groups: _Groups, atoms: np.ndarray,
                     settings: OmpSettings, similarity: float | None, band: tuple[int, int],
                     sums: tuple[np.ndarray, np.ndarray]) -> None:
    """``aggregate="all"``: every member's estimate added at its own place (weighted by ``similarity`` and the
    ``fit`` weighting), then the still answers of the still references of the rows ``band``; ``atoms``: the
    dictionary's :func:`~codedvideo.solvers.omp_kernel.atom_rows`; ``sums``: the summed estimates and weights they
    are added to."""
    summed, weight = sums
    n = region.shape[0]
    patches = region.patches
    m = patches.y.shape[1]
    r0, r1 = band
    wp = patches.grid[1]
    live = np.arange(groups.mem.shape[1])[None, :] < groups.size[:, None]
    where = groups.mem[live]
    res = OmpResult(index=groups.index[live], coef=groups.coef[live], count=groups.count[live],
                    residual=groups.res2[live], dependent=groups.dep[live])
    est = synthesize_rows(res, atoms)
    _guarded(region, est, np.arange(where.size), where, res, atoms, settings)
    wgt = np.ones(where.size, np.float32)
    if similarity is not None:
        wgt = np.exp(-groups.dmem[live] / (n * m) / max(similarity, 1e-6) ** 2).astype(np.float32)
    if settings.weighting == "fit":
        e2 = _misfit(est, patches.y[where], region.pat[where], region.patterns, n, m) / np.maximum(
            patches.n_open[where], 1)
        wgt = wgt / (1.0 + e2 / max(settings.tol_rms, 1e-6) ** 2)
    scatter_patches(est, where, wgt, wp, patches.patch, summed, weight)
    st = np.flatnonzero(chosen.still_ok[r0 * wp:r1 * wp]) + r0 * wp
    if st.size:
        scatter_patches(chosen.still_est[chosen.still_slot[st]], st, np.ones(st.size, np.float32), wp,
                        patches.patch, summed, weight)


def _guarded(region: _Region, est: np.ndarray, rows: np.ndarray, patches: np.ndarray, res: OmpResult,
             atoms: np.ndarray, settings: OmpSettings) -> None:
    """The default's guard (:func:`codedvideo.solvers.region.guard_estimates`) on the estimates ``est[rows]`` of the
    region's patches ``patches`` (one each, from the results ``res``): an invented one is solved alone again with
    the coefficient prior."""
    p = region.patches
    y, n_pix, tol = p.y[patches], p.n_pix[patches], region.tol[patches]
    frames = region.shape[0]
    own = est[rows]  # (one row a patch of ``patches``)
    if guard_estimates(own, np.arange(rows.size), (y, n_pix, tol), atoms, lambda bad: region.table.solve(
            y[bad], region.pat[patches[bad]], max_atoms=settings.max_atoms, tol=tol[bad], prior=PRIOR),
            frames=frames, energy=estimate_energy(res, own, n_pix, atoms, frames)):
        est[rows] = own


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


def finish(summed: np.ndarray, weight: np.ndarray, coded: np.ndarray, mask: np.ndarray, *, project: bool = True,
           first: np.ndarray | None = None) -> np.ndarray:
    """A pass's estimate from its sums: each pixel's summed estimates divided by its weight (where it got none,
    the ``first`` estimate's value, or NaN), then, with ``project``, made to reproduce the coded image
    (:func:`project_measurements`).  Only pixels whose patches all see few measurements (:data:`MIN_OPEN`) get no
    estimate from a group and are not filled as uncovered.  A pixel with no open pixel within half a patch of it
    (inside a block of bad pixels) keeps the ``first`` estimate's value where given: no measurement near it holds
    the groups' atoms, and there they reached values far beyond the scene's (tests/test_nonlocal.py)."""
    from scipy.ndimage import maximum_filter

    with np.errstate(invalid="ignore", divide="ignore"):
        volume = np.where(weight > 0, summed / weight, np.nan if first is None else first).astype(np.float32)
    if first is not None:
        unseen = ~maximum_filter(np.asarray(mask).any(0), size=P.PATCH, mode="constant", cval=False)
        if unseen.any():
            volume[:, unseen] = first[:, unseen]
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
    y32 = np.ascontiguousarray(y, np.float32)
    k, n, m = S.shape
    patterns, which = pixel_patterns(np.moveaxis(np.asarray(S), 1, 0))  # (N, k, m) -> which (k, m)
    table = TableOMP(patterns, D, m)
    kmax = int(min(max_atoms, m))
    tols = np.ascontiguousarray(np.broadcast_to(np.asarray(tol, np.float64), (k,)))
    index = np.zeros((1, k, kmax), np.int32)
    coef = np.zeros((1, k, kmax), np.float32)
    count = np.zeros((1, k), np.int32)
    res2 = np.zeros((1, k), np.float32)
    dep = np.zeros((1, k), np.bool_)
    somp_kernel(y32, np.ascontiguousarray(which, np.int32), np.arange(k, dtype=np.int64)[None], np.array([k], np.int64),
                table.B, table.floor, tols, kmax, DEPENDENCE_TOL, SELECT_BITS, _TINY, index, coef, count,
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
