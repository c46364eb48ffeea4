"""Refinement under the measurement: GAP iterations with a low-rank prior on groups of similar patches (issue 31).

A sparse method's result ``x0`` reproduces the coded image, but each of its patches was solved from the
measurements of one patch (or of one group, once).  The refinement alternates, from ``x0``:

1. accelerated GAP (generalised alternating projection, as in GAP-TV and the plug-and-play methods): for
   coded exposure ``Phi Phi^T`` is diagonal (each pixel's summed squared shutter weights), so the step to
   the measurements is per pixel, with the residual accumulated over the iterations;
2. a denoiser at a noise level annealed from :data:`SIGMA_START` to :data:`SIGMA_END` grey levels
   (geometrically) on 2D patches of single sub-frames, as DeSCI (Liu et al., TPAMI 2019) groups them: for
   every :data:`STEP`-th :data:`SIDE` x :data:`SIDE` patch of every sub-frame (each sub-frame's grid shifted, so
   their references fall on different places), the :data:`GROUP` patches of the current estimate closest to
   it in the sub-frames up to :data:`FRAMES` away, corners within :data:`WINDOW` pixels
   (:func:`codedvideo.solvers.refine_kernel.match_frame_patches`), matched again every :data:`REGROUP`
   iterations on a grid shifted each time (:func:`grid_shift`), so that over the iterations every place of
   a sub-frame is a reference's in turn.  A group follows the motion from sub-frame to sub-frame, and its
   members were seen under different shutter codes.  Each group less its mean is shrunk by weighted nuclear
   norm (the singular values of the members' matrix, from the eigendecomposition of their ``k x k`` Gram
   matrix, lowered by ``SHRINK sqrt(k) sigma^2 / s``, the rule of Gu et al., "Weighted nuclear norm
   minimization", CVPR 2014, that DeSCI iterates under the measurement); every member's estimate averaged at
   its place.

The last estimate is projected onto the measurements and averaged with ``x0`` (:data:`BLEND`): both
reproduce the coded image (``x0`` to its method's tolerance).  The noise levels are fixed; a capture's read
noise (``noise_sigma``) makes the steps plain GAP, relaxed (:func:`relaxed`), rather than exact.  The recipe
was chosen on two clips and held out on two others (docs/quality.md, "Refinement under the measurement");
whole ``7 x 7 x N`` blocks as the groups' members, the recipe before it, gained a quarter as much held out.

In working units (the grey levels of an 8-bit capture: the noise levels are in them).  Arrays in, arrays
out, on the whole image: the groups of a chunk of references are solved, then added frame by frame in a
fixed order, so the result does not depend on the threads.  Memory: four volumes (the estimate, the sum of
the estimates and their count, the start), the groups' table (its members' corners and their order: about 3
bytes a voxel, so most of a fifth volume), one chunk's estimates (:data:`CHUNK`), and a band of rows of the mask
in float32 at a time (:data:`BAND`).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np

from codedvideo.model import physics
from codedvideo.solvers.refine_kernel import match_frame_patches, scatter_frame_patches, shrink_frame_groups

#: Side of a group's patches, pixels (one sub-frame each).
SIDE = 8
#: Patches a group holds, the reference first (at most ``SIDE**2``).
GROUP = 20
#: Stride of the reference patches in each direction of every sub-frame (the last row and column included).
STEP = 11
#: Sub-frames searched on each side of a reference's.
FRAMES = 2
#: Search radius of a group's members around its reference's corner, pixels.
WINDOW = 6
#: Iterations between two matchings of the groups on the current estimate (each on a shifted grid).
REGROUP = 4
#: The weighted-nuclear-norm constant ``c`` of the threshold ``c sqrt(k) sigma^2 / s``.
SHRINK = 2.8
#: The denoiser's noise level in the first and the last iteration, grey levels of an 8-bit capture.
SIGMA_START = 6.0
SIGMA_END = 1.0
#: The result's share of the start: ``(1 - BLEND) refined + BLEND x0``.
BLEND = 0.5
#: References whose groups are solved at once (their estimates: CHUNK * GROUP * SIDE**2 floats).
CHUNK = 4096
#: A noisy capture's relaxation of the steps to the measurements, ``RELAX noise_sigma^2 / sigma^2`` (:func:`relaxed`).
RELAX = 0.25
#: From this read noise on (grey levels of an 8-bit capture) the steps are relaxed by :data:`RELAX_HEAVY` instead of
#: :data:`RELAX`: under such noise the steps relaxed by ``RELAX`` drew the estimate toward the noise and the refined
#: result fell below its start on some held-out clips, while below it ``RELAX`` gained more (docs/research.md,
#: "Under read noise").
HEAVY_NOISE = 25.0
RELAX_HEAVY = 1.0
#: Elements of a band of rows in a step to the measurements (its float32 copy of the mask's band: 16 MB).
BAND = 1 << 22


def recipe() -> dict:
    """The refinement's settings but the iterations (what a record of its result is keyed by)."""
    return dict(prior="frame-patches", side=SIDE, group=GROUP, step=STEP, frames=FRAMES, window=WINDOW,
                regroup=REGROUP, grids="shifted", shrink=SHRINK, sigma_start=SIGMA_START, sigma_end=SIGMA_END,
                blend=BLEND, relax=RELAX, heavy_noise=HEAVY_NOISE, relax_heavy=RELAX_HEAVY)


def grid_shift(matching: int, step: int = STEP) -> tuple[int, int]:
    """The shift (rows, columns) of the reference grids at the ``matching``-th matching of a refinement (0: none):
    the points of the plastic-number sequence (Roberts' R2, a low-discrepancy sequence on the unit square) scaled
    to ``step``, so that successive matchings put their references on places spread over the ``step x step``
    cell, whatever the number of matchings."""
    g = 1.324717957244746  # (the plastic number: x^3 = x + 1)
    return int(step * ((matching / g) % 1.0)), int(step * ((matching / (g * g)) % 1.0))


def reference_grid(n: int, h: int, w: int, step: int = STEP, side: int = SIDE, *, blocks: int = 1,
                   matching: int = 0) -> np.ndarray:
    """Flat corners (t * h * w + row * w + col) of every ``step``-th patch in each direction of every sub-frame,
    the first and last row and column of patches included; sub-frame ``t``'s grid starts ``t * step // n``
    pixels in (both directions), so the sub-frames' references fall on different places, and the
    ``matching``-th matching's grids further by :func:`grid_shift`.  ``blocks``: the ``n`` sub-frames are that
    many videos of ``n / blocks`` each (a colour video's channels, stacked), each block's grids laid as one
    video's are (its ``t`` counted from its own first sub-frame)."""
    def axis(m: int, offset: int) -> np.ndarray:
        s = np.arange(offset, m, step)
        if s.size == 0 or s[0] != 0:
            s = np.concatenate([[0], s])
        return s if s[-1] == m - 1 else np.append(s, m - 1)

    per_block = _block_frames(n, blocks)
    down, across = grid_shift(matching, step)
    grids = []
    for t in range(n):
        offset = (t % per_block) * step // per_block
        rows, cols = axis(h - side + 1, (offset + down) % step), axis(w - side + 1, (offset + across) % step)
        grids.append((t * h * w + rows[:, None] * w + cols[None, :]).ravel())
    return np.concatenate(grids).astype(np.int64)


def moving_references(refs: np.ndarray, known: np.ndarray | None, shape: tuple) -> np.ndarray:
    """The references of ``refs`` (flat corners in a volume of ``shape``) whose patch holds at least one pixel
    not in ``known`` (H, W) bool, the pixels whose values are kept whatever the refinement does (a stream's still
    answers); None: all of them."""
    if known is None or not known.any():
        return refs
    n, h, w = shape
    # how many known pixels each SIDE x SIDE patch holds, at its corner (a box sum of the map)
    box = np.pad(np.asarray(known, np.int32), ((1, 0), (1, 0))).cumsum(0).cumsum(1)
    full = box[SIDE:, SIDE:] - box[:-SIDE, SIDE:] - box[SIDE:, :-SIDE] + box[:-SIDE, :-SIDE] == SIDE * SIDE
    corner = refs % (h * w)
    return refs[~full[corner // w, corner % w]]


def _block_frames(n: int, blocks: int) -> int:
    """The sub-frames of each of ``blocks`` equal blocks of ``n`` (ValueError unless they divide it)."""
    if blocks < 1 or n % blocks:
        raise ValueError(f"{n} sub-frames are not {blocks} equal blocks")
    return n // blocks


def shrinkage(gram: np.ndarray, d: int, sigma: float, c: float = SHRINK) -> np.ndarray:
    """Each group's weighted-nuclear-norm shrinkage in its members' space, ``(G, k, k)`` from the Gram
    matrices ``(G, k, k)`` of its centred members (``d`` entries each): ``U diag(f) U^T`` with
    ``gram = U diag(s^2) U^T`` and ``f = max(s - c sqrt(k) sigma^2 / s_hat, 0) / s``, where
    ``s_hat^2 = max(s^2 - d sigma^2, 0)`` estimates the clean singular value."""
    k = gram.shape[-1]
    lam, U = np.linalg.eigh(gram)
    lam = np.maximum(lam, 0.0)
    s = np.sqrt(lam)
    clean = np.sqrt(np.maximum(lam - d * sigma * sigma, 0.0))
    threshold = c * np.sqrt(k) * sigma * sigma / (clean + 1e-8)
    f = np.divide(np.maximum(s - threshold, 0.0), s, out=np.zeros_like(s), where=s > 0)
    return np.einsum("giq,gq,gjq->gij", U, f, U)


def match(x: np.ndarray, refs: np.ndarray, *, chunk: int | None = None, blocks: int = 1) -> list[tuple]:
    """The groups of the references ``refs`` on the estimate ``x`` (N, H, W) float32, in chunks of ``chunk``
    references (None: :data:`CHUNK`): each ``(groups, where, order, bounds)``, its members' corners flat and
    their order frame by frame for :func:`denoise`.  ``blocks``: the sub-frames are that many videos stacked
    (:func:`reference_grid`); a reference's members are sought in its own block's sub-frames only."""
    per_chunk = CHUNK if chunk is None else chunk
    n, h, w = x.shape
    per_block = _block_frames(n, blocks)
    groups = np.empty((refs.size, GROUP), np.int64)
    volume = per_block * h * w  # (each block matched as a video of its own, its corners shifted back)
    for b in range(blocks):
        mine = np.flatnonzero(refs // volume == b)
        found = np.empty((mine.size, GROUP), np.int64)
        match_frame_patches(x[b * per_block:(b + 1) * per_block], refs[mine] - b * volume, SIDE, WINDOW,
                            min(FRAMES, per_block - 1), GROUP, found)
        groups[mine] = found + b * volume
    chunks = []
    for start in range(0, refs.size, per_chunk):
        part = np.ascontiguousarray(groups[start:start + per_chunk])
        where = part.ravel()
        frames = where // (h * w)
        order = np.argsort(frames, kind="stable")
        bounds = np.searchsorted(frames[order], np.arange(n + 1))
        chunks.append((part, where, order.astype(np.int64), bounds.astype(np.int64)))
    return chunks


def denoise(x: np.ndarray, chunks: list[tuple], sigma: float, weight: np.ndarray | None = None) -> np.ndarray:
    """The estimate ``x`` (N, H, W) float32 with every group of ``chunks`` (:func:`match`) shrunk
    (:func:`shrinkage`) and the members' estimates averaged at their places; pixels no member covers keep
    their value.  ``weight``: :func:`coverage` of ``chunks`` if counted already (the same for every estimate of
    the same groups); None: counted here."""
    summed = np.zeros_like(x)
    for part, where, order, bounds in chunks:
        est = np.empty((where.size, SIDE * SIDE), np.float32)
        shrink_frame_groups(x, part, SIDE, float(sigma) ** 2, SHRINK, est)
        scatter_frame_patches(est, where, order, bounds, SIDE, summed, False)
    return _averaged(x, summed, coverage(x.shape, chunks) if weight is None else weight)


def coverage(shape: tuple, chunks: list[tuple]) -> np.ndarray:
    """How many members of the groups of ``chunks`` (:func:`match`) cover each voxel of a volume of ``shape``."""
    covers = np.zeros(shape, np.float32)
    nothing = np.empty((0, SIDE * SIDE), np.float32)
    for _, where, order, bounds in chunks:
        scatter_frame_patches(nothing, where, order, bounds, SIDE, covers, True)
    return covers


def _averaged(x: np.ndarray, summed: np.ndarray, weight: np.ndarray) -> np.ndarray:
    """(In place in ``summed``) the sums divided by their count, ``x`` where nothing covers a voxel."""
    covered = weight > 0
    np.divide(summed, weight, out=summed, where=covered)
    summed[~covered] = x[~covered]
    return summed


def sigmas(iterations: int, start: float = SIGMA_START, end: float = SIGMA_END) -> np.ndarray:
    """The annealed noise levels, geometric from ``start`` to ``end`` (one iteration: ``end``)."""
    return np.geomspace(start, end, iterations) if iterations > 1 else np.array([end], np.float64)


def relaxed(open2: np.ndarray, noise_sigma: float, sigma: float) -> np.ndarray:
    """The reciprocal of each pixel's summed squared shutter weights ``open2`` plus ``RELAX noise_sigma^2 /
    sigma^2`` (0 where a pixel is never open; ``RELAX_HEAVY`` from read noise :data:`HEAVY_NOISE` on): a noisy
    capture's step to its measurements, shorter the lower the denoiser's level ``sigma`` (the measurements' noise
    then weighs more against the prior's)."""
    relax = RELAX_HEAVY if noise_sigma >= HEAVY_NOISE else RELAX
    lam = np.float32(relax * noise_sigma * noise_sigma / (sigma * sigma))
    return np.divide(1.0, open2 + lam, out=np.zeros_like(open2), where=open2 > 0)


def to_measurements(x: np.ndarray, mask: np.ndarray, coded: np.ndarray, inv: np.ndarray,
                    accumulated: np.ndarray | None = None) -> None:
    """In place, a band of rows at a time: ``x += S^T ((target - S x) / (S S^T))`` per pixel (``inv``: the
    reciprocal of each pixel's summed squared shutter weights, 0 where it is never open).  ``target`` is
    ``coded``, or with ``accumulated`` (accelerated GAP) that sum of the residuals, ``coded - S x`` added
    to it first."""
    n, h, w = x.shape
    rows = max(1, BAND // max(n * w, 1))
    for r in range(0, h, rows):
        band = slice(r, r + rows)
        s = np.asarray(mask[:, band], np.float32)
        predicted = np.einsum("thw,thw->hw", x[:, band], s, dtype=np.float32)
        if accumulated is None:
            target = coded[band]
        else:
            accumulated[band] += coded[band] - predicted
            target = accumulated[band]
        x[:, band] += s * ((target - predicted) * inv[band])[None]


#: Iterations between two estimates shown to a ``watch`` of :func:`refine` (and after the last).
WATCH_EVERY = 8


#: Voxels of a volume refined whole; a larger one is refined a band of rows at a time (each band's volumes
#: about this size: 64 MB in float32), so that the memory of the refinement is bounded at any image size.
BAND_VOXELS = 1 << 24
#: Rows a band reads beyond its own on either side (its results there are left to the neighbouring band): the
#: groups of a band's edge see this many rows of the image beyond it.  Wider halos gave the same result for more
#: time (docs/quality.md, "Refinement under the measurement").
HALO = 16


def bands(shape: tuple) -> list[tuple[int, int]]:
    """The bands of rows ``(first, end)`` a volume of ``shape`` (N, H, W) is refined in: the whole image when it
    holds at most :data:`BAND_VOXELS` voxels, else bands of about that many with their halos."""
    n, h, w = shape
    if n * h * w <= BAND_VOXELS:
        return [(0, h)]
    rows = max(4 * HALO, BAND_VOXELS // max(n * w, 1) - 2 * HALO)
    return [(r, min(r + rows, h)) for r in range(0, h, rows)]


@dataclass(frozen=True)
class RefineRun:
    """How :func:`refine` runs, none of which changes the values of its result: its progress hooks and where
    the result is written.

    Attributes
    ----------
    tick : callable, optional
        Called once per iteration of each band (a progress bar of ``iterations * len(bands(shape))``).
    watch : callable, optional
        Called as ``watch(i, estimate, seconds, rows)`` after every :data:`WATCH_EVERY` iterations and after
        the last, with the rows ``rows`` (a slice; every row unless banded) of the result the run would give
        if it ended there (projected and blended as the last is; after the last, the result itself) and the
        band's seconds so far, its own calls left out.
    overwrite : bool
        A float32 ``start`` takes the result (the memory of one band beside it).
    """

    tick: Callable[[], object] | None = None
    watch: Callable[[int, np.ndarray, float, slice], object] | None = None
    overwrite: bool = False


def refine(coded: np.ndarray, mask: np.ndarray, start: np.ndarray, *, iterations: int, noise_sigma: float = 0.0,
           known: np.ndarray | None = None, blocks: int = 1, run: RefineRun = RefineRun()) -> tuple[np.ndarray, dict]:
    """``iterations`` of GAP with the group prior from ``start`` (N, H, W), in working units.

    ``coded`` (H, W) and ``mask`` (N, H, W) are the measurements the result keeps (a pixel never open is not
    held to any).  ``noise_sigma``: the capture's read noise; above 0 the measurements are not held exactly:
    plain GAP (no accumulated residual), each step (and the last projection) relaxed by ``RELAX noise_sigma^2 /
    sigma^2`` (``RELAX_HEAVY`` from :data:`HEAVY_NOISE` on) at the iteration's noise level ``sigma``
    (:func:`relaxed`, :func:`to_measurements`).  0: accelerated GAP, exact
    steps.  ``known`` (H, W) bool: pixels whose values are known (a stream's still answers): they keep their
    values of ``start`` in every estimate, and no group is referenced where a patch holds only those (a still
    scene costs the steps to the measurements only).  ``blocks``: the N frames are that many videos of
    N / blocks sub-frames stacked (a colour video's channels under its colour mask,
    :func:`codedvideo.engine.bayer.color_mask`): the steps to the measurements take the whole stack, but a group's
    members and the references' grids stay within one block (:func:`reference_grid`, :func:`match`); 1: one
    video.

    A volume of more than :data:`BAND_VOXELS` voxels is refined a band of rows at a time (:func:`bands`), each
    with :data:`HALO` rows of the image on either side, and its own rows kept: the memory is that of one band's
    volumes beside the start and the result (with ``run.overwrite``, a float32 ``start`` takes the result: the
    memory of one band beside it).  ``run``: the progress hooks ``tick`` and ``watch`` and ``overwrite``
    (:class:`RefineRun`).  The noise levels (:data:`SIGMA_START` to :data:`SIGMA_END`) and the share of the
    start (:data:`BLEND`) are the module's.  Returns the video (N, H, W) float32 and what was done: iterations,
    the noise levels, the groups shrunk an iteration (the mean over its matchings; summed over the bands),
    seconds.
    """
    t0 = time.perf_counter()
    shape = np.shape(mask)
    parts = bands(shape)
    if len(parts) == 1 or shape[2] < SIDE:
        return _refine_whole(coded, mask, start, iterations=iterations, noise_sigma=noise_sigma, known=known,
                             blocks=blocks, run=run)
    in_place = run.overwrite and isinstance(start, np.ndarray) and start.dtype == np.float32 and start.flags.writeable
    out = start if in_place else np.empty(shape, np.float32)
    groups = 0
    above = None  # in place: the start's rows above a band (its upper halo), before the band above wrote them
    for first, end in parts:
        lo, hi = max(0, first - HALO), min(shape[1], end + HALO)
        band_watch = None if run.watch is None else \
            (lambda i, v, seconds, rows, cut=slice(first - lo, end - lo), kept=slice(first, end):
             run.watch(i, v[:, cut], seconds, kept))
        band = start[:, lo:hi] if above is None else np.concatenate([above, start[:, first:hi]], axis=1)
        if in_place:
            above = start[:, max(first, end - HALO):end].copy()
        v, info = _refine_whole(coded[lo:hi], mask[:, lo:hi], band, iterations=iterations, noise_sigma=noise_sigma,
                                known=None if known is None else known[lo:hi], blocks=blocks,
                                run=replace(run, watch=band_watch))
        out[:, first:end] = v[:, first - lo:end - lo]
        groups += info.get("groups", 0)
        del v
    return out, dict(info, groups=groups, bands=len(parts), halo=HALO, seconds=time.perf_counter() - t0)


def _refine_whole(coded: np.ndarray, mask: np.ndarray, start: np.ndarray, *, iterations: int, noise_sigma: float,
                  known: np.ndarray | None, blocks: int, run: RefineRun) -> tuple[np.ndarray, dict]:
    """:func:`refine` of one image (or band), ``run.overwrite`` aside: the estimates shown to ``run.watch`` are
    said to be every row of ``coded`` (``slice(0, H)``; :func:`refine` maps a band's to the image's)."""
    t0 = time.perf_counter()
    y = np.asarray(coded, np.float32)
    mask_arr = np.asarray(mask)
    n, h, w = mask_arr.shape
    if h < SIDE or w < SIDE or iterations < 1:
        return np.asarray(start, np.float32).copy(), dict(iterations=0, seconds=time.perf_counter() - t0)
    open2 = physics.forward(mask_arr, mask_arr)
    inv = relaxed(open2, 0.0, 1.0)  # (exact: 1 / open2)
    x0 = np.ascontiguousarray(start, np.float32)
    x = x0.copy()
    noisy = noise_sigma > 0
    accumulated = None if noisy else y.copy()
    levels = sigmas(iterations, SIGMA_START, SIGMA_END)
    tick, watch, rows = run.tick, run.watch, slice(0, h)

    still = None if known is None or not known.any() else np.asarray(known, bool)

    def settle(v: np.ndarray, sigma: float) -> np.ndarray:  # (in place) the result a run ending here gives
        to_measurements(v, mask_arr, y, relaxed(open2, noise_sigma, sigma) if noisy else inv)
        np.multiply(v, np.float32(1.0 - BLEND), out=v)
        np.add(v, np.float32(BLEND) * x0, out=v)
        if still is not None:  # the known pixels keep their values
            v[:, still] = x0[:, still]
        return v

    watched = 0.0  # seconds in the watch's calls, left out of the refinement's
    shrunk = 0  # groups shrunk, over the iterations
    for i, sigma in enumerate(levels):
        to_measurements(x, mask_arr, y, relaxed(open2, noise_sigma, sigma) if noisy else inv, accumulated)
        if i % REGROUP == 0:  # matched again, on the next shifted grid (the last matching's tables freed first)
            chunks = weight = None
            refs = moving_references(reference_grid(n, h, w, blocks=blocks, matching=i // REGROUP), known, (n, h, w))
            chunks = match(x, refs, blocks=blocks)
            weight = coverage(x.shape, chunks)
        shrunk += refs.size
        x = denoise(x, chunks, float(sigma), weight)
        if tick is not None:
            tick()
        if watch is not None and (i + 1) % WATCH_EVERY == 0 and i + 1 < len(levels):
            t_watch = time.perf_counter()
            watch(i + 1, settle(x.copy(), float(sigma)), t_watch - t0 - watched, rows)
            watched += time.perf_counter() - t_watch
    x = settle(x, levels[-1])
    seconds = time.perf_counter() - t0 - watched
    if watch is not None:
        watch(len(levels), x, seconds, rows)
    info = dict(recipe(), iterations=int(iterations), sigma_start=float(SIGMA_START), sigma_end=float(SIGMA_END),
                blend=float(BLEND), noise_sigma=float(noise_sigma),
                groups=int(round(shrunk / len(levels))),
                **(dict(blocks=int(blocks)) if blocks != 1 else {}), seconds=seconds)
    return x, info
