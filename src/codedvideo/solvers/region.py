"""The per-tile reconstruction kernel (arrays in, arrays out; no I/O, no dask).

For a coded image region and its code, every overlapping 7x7 patch is solved by
OMP (Eq. 3), its space-time estimate ``E_p = D alpha_p`` is added back at its
place, and every pixel is divided by the exact number of patches covering it
(Sec. 5.1: the ``M^2`` estimates of a pixel are averaged).
"""

from __future__ import annotations

import functools
import time
from dataclasses import dataclass

import numpy as np

from codedvideo.model import patches as P
from codedvideo.model.codes import is_binary
from codedvideo.model.units import TOL_FLOOR
from codedvideo.solvers.omp import (PRIOR, GroupedOperator, MaskedOperator, masked_operator, omp, periodic_groups,
                                   pixel_patterns)
from codedvideo.solvers.omp_kernel import (MAX_TABLE_BYTES, TableOMP, WeightsOMP, atom_rows, profile_kernel,
                                           still_kernel, synthesize_rows, table_fits)

#: Names of the per-tile statistics, in the order of the stats vector.
#: Search radius of the non-local method's block matching (:mod:`codedvideo.solvers.nonlocal_sc`), in pixels: a
#: tile's halo reaches this far (:func:`tile_halo`).  Chosen on the benchmark (tasks/bench_nonlocal.py).
WINDOW = 6

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
    static_atoms : int
        Still-scene test: 2D DCT atoms allowed (0: off), see :func:`still_patches`.
    stride : int
        Patch stride (1 to the patch size): ``stride**2`` times fewer patches.
    weighting : {"uniform", "fit"}
        How the overlapping estimates of a pixel are averaged.
    exact : bool
        The measurements are exact (no read noise): the non-local method's result is projected onto them.
    profile_ridge : float or None
        The ridge of the still test's temporal profiles (:func:`still_patches`), in units of one open pixel
        (None: from the tolerance, :attr:`ridge`).
    """

    max_atoms: int = 8
    tol_rms: float = 1.0
    batch: int = 4096
    static_atoms: int = 8
    #: Solve every ``stride``-th patch along each axis (1: every overlapping patch, the paper);
    #: at most the patch size, so that every pixel stays covered.
    stride: int = 1
    #: "uniform": every overlapping estimate counts the same (the paper's average);
    #: "fit": each counts ``1 / (1 + e**2 / tol_rms**2)``, ``e`` the RMS misfit of its
    #: patch to the measurement, so estimates that explain their data poorly weigh less.
    weighting: str = "uniform"
    #: "omp": every patch on its own (the paper); "nonlocal": then groups of similar patches solved
    #: together under their own codes (:mod:`codedvideo.solvers.nonlocal_sc`).
    method: str = "omp"
    #: "nonlocal": stride of its groups' reference patches (0: :data:`codedvideo.solvers.nonlocal_sc.STEP`).
    #: ``--adapt`` surveys with a sparser grid first (:data:`codedvideo.engine.adaptation.ADAPT_SURVEY_STEP`).
    group_step: int = 0
    #: "nonlocal": whether the groups' average is projected onto the measurements, so that it reproduces the
    #: coded image exactly.  False under read noise: the measurements then hold the noise, and projecting onto
    #: them put it back into the estimate (docs/research.md, "The non-local method under read noise").
    exact: bool = True
    #: The still test's temporal profiles: their ridge in units of one open pixel (:attr:`ridge`).  None: from
    #: the tolerance in working units, ``(tol_rms / TOL_FLOOR)**2``: 1 without read noise, growing with it, so
    #: that the profile fits a change of the light and not the noise.
    profile_ridge: float | None = None

    @property
    def ridge(self) -> float:
        """The ridge of the still test's temporal profiles: :attr:`profile_ridge`, or ``(tol_rms / TOL_FLOOR)**2``."""
        return (self.tol_rms / TOL_FLOOR) ** 2 if self.profile_ridge is None else self.profile_ridge


def tile_halo(settings: OmpSettings, patch: int = P.PATCH) -> int:
    """Pixels beyond a tile's core that its answer depends on (what keys a tile's content, and what a
    per-patch tile reads so that its core comes out as in the whole image).

    Per-patch OMP: ``patch - 1`` (every patch over a core pixel).  Non-local: the
    first estimate's ``patch - 1`` plus what a core pixel's groups reach,
    ``patch - 1 + 2 * window`` (:mod:`codedvideo.solvers.nonlocal_sc`; its tiles are
    assembled from stages of their own, :mod:`codedvideo.engine.parallel`).
    """
    if settings.method == "nonlocal":
        return 2 * (patch - 1) + 2 * WINDOW
    return patch - 1


def static_dictionary(frames: int, patch: int = P.PATCH) -> np.ndarray:
    """Atoms of a still scene: the 2D DCT of a patch, constant over the N sub-frames.

    Shape ``(frames * patch**2, patch**2)``, unit-norm columns, ordered from low
    to high spatial frequency (the first atom is the flat patch).
    """
    from codedvideo.solvers.dictionaries import dct_dictionary

    C = dct_dictionary(1, patch=patch)  # (m, m): 2D DCT basis
    fy, fx = np.meshgrid(np.arange(patch), np.arange(patch), indexing="ij")
    C = C[:, np.argsort((fy + fx).ravel(), kind="stable")]
    return (np.tile(C, (frames, 1)) / np.sqrt(frames)).astype(np.float32)


@functools.lru_cache(maxsize=4)
def _still_basis(patch: int) -> np.ndarray:
    """:func:`static_dictionary` for one sub-frame in float64, built once per patch size (read-only).

    Made orthonormal to float64 precision (the nearest orthonormal matrix, which
    keeps the order and signs of the columns): the still test's residuals are
    computed by Parseval's identity, which a float32 basis would break by ~1e-7
    of the patch energy.
    """
    u, _, vt = np.linalg.svd(static_dictionary(1, patch).astype(np.float64))
    C = np.ascontiguousarray(u @ vt)
    C.setflags(write=False)
    return C


def still_answers(y: np.ndarray, n_pix: np.ndarray, frames: int) -> np.ndarray:
    """The still answer of patches ``y`` (P, m): ``coded / open count`` of every pixel in each of the
    ``frames`` sub-frames, as rows of ``frames * m`` (a pixel never open: 0)."""
    q = y / np.maximum(n_pix, 1e-12).astype(np.float32)
    # (the row length spelled out: none of them, 0 x -1, is ambiguous to numpy)
    return np.broadcast_to(q[:, None, :], (q.shape[0], frames, q.shape[1])).reshape(q.shape[0], frames * q.shape[1])


def still_patches(
    y: np.ndarray, n_pix: np.ndarray, tol: np.ndarray, atoms: int, *, frames: int, patch: int = P.PATCH,
    codes: tuple[np.ndarray, np.ndarray] | None = None, ridge: float = 1.0,
) -> tuple[np.ndarray, np.ndarray]:
    """The still-scene test: which patches a still, spatially sparse scene explains.

    A still scene has every sub-frame equal to one image ``s``, so pixel ``i``
    records ``y_i = n_i s_i`` (``n_i`` its open sub-frames) and ``s = y / n``.
    A patch passes when ``s`` keeps the residual ``||n * (s - s_k)||^2`` within
    the tolerance, ``s_k`` holding at most ``atoms`` of the largest coefficients
    of ``s`` in the orthonormal 2D DCT (a flat patch needs one); it then gets
    ``s_k`` in every sub-frame.  Where ``n_i`` is the same over the patch (every
    fixed-bump code) this is exactly OMP over :func:`static_dictionary` seen
    through the code, whose atoms are then orthogonal with equal norms; for
    other codes it is the same greedy choice with the residual measured
    exactly.  No dictionary search is run (compiled:
    :func:`codedvideo.solvers.omp_kernel.still_kernel`, a few per cent of a patch's OMP).
    Patches with a pixel that is never open are left to the full dictionary.

    With ``codes`` each passing patch also gets its temporal profile: one
    value per sub-frame, the same at every pixel, added to ``s_k`` where the
    patch's code sees it (a fade, a flicker of the light, a slow change of a
    flat region, all below the tolerance).  It is the ridge least-squares fit
    of the residual ``y - n s_k`` through the patch's code, with a ridge in
    units of one open pixel (:attr:`OmpSettings.ridge`: 1 without
    read noise, growing with the noise so that a noisy patch keeps its still
    image; docs/research.md, "Flat regions that change below the tolerance").
    The per-patch OMP always asks for it; the non-local method's own still
    test under read noise only (:mod:`codedvideo.solvers.nonlocal_sc`).
    Compiled: :func:`codedvideo.solvers.omp_kernel.profile_kernel`.

    Parameters
    ----------
    y : ndarray of shape (P, m)
    n_pix : ndarray of shape (P, m)
        Open sub-frames of every pixel of every patch (``S.sum(1)``); for a
        calibrated mask the sum of the pixel's weights (a still scene records
        ``y_i = n_i s_i`` all the same).
    tol : ndarray of shape (P,)
        Squared residual tolerance.
    atoms : int
    frames : int
        N, the sub-frames of the estimate.
    codes : (ndarray of shape (h, w, N), ndarray of shape (P, 2)), optional
        The region's code with each pixel's weights in a row (:attr:`RegionPatches.codes`) and every patch's
        corner in it; None: no temporal profile, every sub-frame ``s_k``.
    ridge : float
        The temporal profile's ridge, in units of one open pixel.

    Returns
    -------
    ok : ndarray of shape (P,), bool
    estimate : ndarray of shape (ok.sum(), N * m), float32
    """
    count = y.shape[0]
    ok = np.zeros(count, np.bool_)
    frame = np.zeros((count, patch * patch), np.float64)
    still_kernel(np.ascontiguousarray(y, dtype=np.float32), np.ascontiguousarray(n_pix, dtype=np.float64),
                 _still_basis(patch), np.ascontiguousarray(tol, dtype=np.float64),
                 int(atoms), ok, frame)
    estimate = np.tile(frame[ok].astype(np.float32), (1, frames))
    if codes is not None and ok.any():
        grid, corners = codes
        profile = np.zeros((int(ok.sum()), frames), np.float64)
        profile_kernel(np.ascontiguousarray(y[ok], dtype=np.float32), frame[ok], grid,
                       np.ascontiguousarray(corners[ok], dtype=np.int64), patch, ridge, profile)
        m = patch * patch
        estimate += np.repeat(profile.astype(np.float32), m, axis=1)
    return ok, estimate


def _few_patterns(mask: np.ndarray, D: np.ndarray, m: int) -> bool:
    """Whether a calibrated mask might have few enough distinct pixel patterns for a pattern table.

    A random projection of every pixel's weights counts at most as many
    values as there are patterns (equal patterns project equally), so more
    values than a table holds settles it in about a millisecond, without
    sorting the patterns themselves (a blurred code: every pixel its own).
    """
    limit = MAX_TABLE_BYTES // (m * D.shape[1] * 4)  # the most patterns that table_fits accepts
    probe = np.random.default_rng(0).random(mask.shape[0])
    return np.unique(np.tensordot(probe, mask, axes=(0, 0))).size <= limit


def _still_answer(coded: np.ndarray, mask: np.ndarray, binary: bool) -> np.ndarray:
    """``coded / open count`` (a calibrated mask: over the sum of its weights), 0 where never open; (h, w) float32."""
    k = mask.sum(0, dtype=np.int32) if binary else mask.sum(0, dtype=np.float64)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(k > 0, coded / np.maximum(k, 1e-12).astype(np.float32), 0).astype(np.float32)


@dataclass(frozen=True)
class Placement:
    """A region's place in its image: ``origin``, the region's top-left corner in the image, and
    ``image_shape``, the image's (H, W)."""

    origin: tuple[int, int]
    image_shape: tuple[int, int]


def reconstruct_region(
    coded: np.ndarray, mask: np.ndarray, D: np.ndarray, settings: OmpSettings, *, patch: int = P.PATCH,
    place: Placement | None = None, operator: str = "auto", still: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Reconstruct every pixel of a region from the patches inside it.

    Parameters
    ----------
    coded : ndarray of shape (h, w)
    mask : ndarray of shape (N, h, w)
        A binary code, or a calibrated mask: each pixel's measured response in
        every sub-frame, weights in [0, 1] (the exact forward model
        ``coded = sum_t mask[t] * frame[t]``).  A pixel is measured when its
        weights sum to more than 0.
    D : ndarray of shape (N * patch**2, K)
    settings : OmpSettings
    place : Placement, optional
        The region's top-left corner in the image and the image's (H, W) (default: the region is the
        image); a patch stride counts from the image's corner.
    operator : {"auto", "dense", "patch"}
        "auto": periodic codes use the grouped operator; codes whose distinct
        per-pixel patterns fit a pattern table (every binary single-bump code;
        a calibrated mask with few distinct weight vectors) the compiled table
        kernel; a calibrated mask with more patterns (a blurred, misregistered
        code: every pixel its own weights) the compiled kernel with a table per
        patch (:class:`codedvideo.solvers.omp_kernel.WeightsOMP`); binary codes with too
        many patterns the dense numpy operator ``D^T (Phi_p^T r)``.  "patch":
        the per-patch compiled kernel for every patch (bit for bit the table
        kernel's answers, so the choice between the two never shows);
        "dense": the dense numpy operator for every patch (the same answers
        within float roundoff).  Both for tests and timings.
    still : ndarray of shape (h, w), bool, optional
        Pixels known to be still (their ``coded / open count`` agrees with a
        neighbouring capture, :mod:`codedvideo.model.sequence`).  A patch whose
        every pixel is still takes the still answer, ``coded / open count``
        in every sub-frame, with no dictionary search (counted in
        ``patches_static``); every other patch is solved with all of its
        measurements.

    Patches that a still scene explains (:func:`still_patches`: at most
    ``settings.static_atoms`` atoms of the 2D DCT, constant in time, reach the
    residual tolerance; a flat patch needs one) keep that answer and skip the
    full dictionary.  A moving scene leaves a pixel-random, code-dependent
    residual that few smooth still atoms cannot explain, so this test only
    accepts patches whose motion is below the noise level.

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
    if operator not in ("auto", "dense", "patch"):
        raise ValueError(f"operator {operator!r}: choose auto, dense or patch")
    coded32 = np.asarray(coded, dtype=np.float32)
    binary = is_binary(mask)
    weights = mask if binary else _calibrated(mask)
    hp, wp = P.grid_shape((h, w), patch)
    if still is not None and settings.stride == 1 and np.all(still) and weights.any(0).all():
        # a wholly still region: every patch takes the still answer, so every pixel is coded / open count
        q = _still_answer(coded32, weights, binary)
        stats = np.array([hp * wp, hp * wp, 0, 0, 0, 0.0, time.perf_counter() - t_start], dtype=np.float64)
        return np.repeat(q[None], n, axis=0), stats
    patches = region_patches(coded32, weights, binary, patch)
    # every patch's code, (Pn, N, m): the largest array here, made only where a path reads it
    S_all = functools.cache(lambda: P.extract(weights.astype(np.uint8) if binary else weights, patch))
    solve = _patch_solver(weights, D, binary, operator, patch, S_all, settings.max_atoms)
    # a patch without any measured pixel has nothing to say: it is left out of the
    # average, and pixels no patch with a measurement covers are NaN (filled later)
    valid = patches.n_open > 0
    taken = valid.size  # the patches this region solves or takes the still answer of (its statistics' count)
    origin, image_shape = ((0, 0), (h, w)) if place is None else (place.origin, place.image_shape)
    on_grid = stride_grid(settings.stride, (hp, wp), patch, origin, image_shape)
    if on_grid is not None:
        valid &= on_grid
        taken = int(on_grid.sum())  # (every patch was counted: atoms_mean a quarter, patches/s 4x, at stride 2)
    if settings.weighting not in ("uniform", "fit"):
        raise ValueError(f"weighting {settings.weighting!r}: choose uniform or fit")
    still_rows, skip = stilled = _still_rows(still, valid, patch, (hp, wp))
    summed, weight, counts = _fold_bands(patches, valid, stilled, D, settings, solve, S_all, (n, h, w))
    with np.errstate(invalid="ignore", divide="ignore"):
        volume = np.where(weight > 0, summed / weight, np.nan).astype(np.float32)
    if still_rows is not None:  # pixels only still patches cover: the still answer exactly, as a still tile gives
        others = P.fold((valid & ~still_rows).astype(np.float32), (h, w), patch)[0]
        inner = (others == 0) & (weight > 0)
        volume[:, inner] = _still_answer(coded32, weights, binary)[inner]
    stats = np.array(
        [taken, counts.static, counts.atoms, counts.hit, counts.dep, counts.seconds, time.perf_counter() - t_start],
        dtype=np.float64,
    )
    return volume, stats


def _calibrated(mask: np.ndarray) -> np.ndarray:
    """A calibrated mask's weights in float32, as everywhere else (finite and >= 0, or ValueError)."""
    weights = np.asarray(mask, dtype=np.float32)
    if not np.isfinite(weights).all() or (weights < 0).any():
        raise ValueError("mask weights must be finite and >= 0")
    return weights


@dataclass(frozen=True)
class RegionPatches:
    """Every overlapping patch of a region as the solvers read it (:func:`region_patches`).

    Attributes
    ----------
    y : ndarray of shape (Pn, m), float32
        Coded values (0 where a pixel is never open), C-contiguous.
    n_pix : ndarray of shape (Pn, m)
        Open sub-frames of every patch pixel (a calibrated mask: the sum of its weights).
    n_open : ndarray of shape (Pn,), float32
        Measured pixels of every patch.
    grid : (hp, wp)
        Patch corners along each axis (``Pn = hp * wp``).
    patch : int
        Patch side (``m = patch**2``).
    weights : ndarray of shape (N, h, w)
        The region's code as the solvers read it (binary, or a calibrated mask's float32 weights).
    """

    y: np.ndarray
    n_pix: np.ndarray
    n_open: np.ndarray
    grid: tuple[int, int]
    patch: int
    weights: np.ndarray

    @functools.cached_property
    def codes(self) -> np.ndarray:
        """The code with each pixel's weights in a row, (h, w, N) float32: what the still test's temporal
        profiles read (:func:`still_patches`), made on first use."""
        return np.ascontiguousarray(np.moveaxis(self.weights, 0, -1), dtype=np.float32)

    def corners(self, index: np.ndarray) -> np.ndarray:
        """The (row, column) corners in the region of the patches ``index`` (raveled grid), (len, 2) int64."""
        return np.stack(np.divmod(np.asarray(index, dtype=np.int64), self.grid[1]), axis=1)


def region_patches(coded: np.ndarray, mask: np.ndarray, binary: bool, patch: int) -> RegionPatches:
    """The patches of a region's coded image (h, w) float32 under its mask (N, h, w), both solvers' first step."""
    open_any = mask.any(0)
    y = np.ascontiguousarray(P.extract(np.where(open_any, coded, 0.0).astype(np.float32), patch))
    n_pix = P.extract(mask.sum(0, dtype=np.int32) if binary else mask.sum(0, dtype=np.float64), patch)
    n_open = (n_pix > 0).sum(1).astype(np.float32)
    return RegionPatches(y=y, n_pix=n_pix, n_open=n_open, grid=P.grid_shape(coded.shape, patch),
                          patch=patch, weights=mask)


def stride_grid(stride: int, grid: tuple[int, int], patch: int, origin: tuple[int, int],
                image_shape: tuple[int, int]) -> np.ndarray | None:
    """Which of a region's patches (raveled ``grid``) lie on the ``stride`` grid counted from the image's corner.

    ``origin`` is the region's corner in the image of shape ``image_shape``; None for a stride of 1 or less
    (every patch); a stride beyond the patch size (pixels no patch covers) is a ValueError.
    """
    if stride <= 1:
        return None
    if stride > patch:
        raise ValueError(f"stride {stride}: must be 1 to {patch} (the patch size)")
    ih, iw = image_shape
    rows_on = P.stride_rows(origin[0], grid[0], ih - patch + 1, stride)
    cols_on = P.stride_rows(origin[1], grid[1], iw - patch + 1, stride)
    return (rows_on[:, None] & cols_on[None, :]).ravel()


def _patch_solver(mask: np.ndarray, D: np.ndarray, binary: bool, operator: str, patch: int, S_all,
                  max_atoms: int):
    """The OMP of a region's patches under ``operator`` (:func:`reconstruct_region`): a function of the patches
    ``y`` (rows ``rows`` of the band ``sl`` of the region's patches) and their tolerances, to an :class:`OmpResult`.
    ``S_all()``: every patch's code (P, N, m)."""
    m = patch * patch
    groups = None if operator != "auto" else periodic_groups(mask, patch)
    # periodic codes: the few distinct patch operators are built once for the region, however
    # few its patches, so that small edge tiles solve them with the same arithmetic as large ones
    grouped = None if groups is None else masked_operator(S_all(), D, groups=groups, min_share=0)
    if not isinstance(grouped, GroupedOperator):
        grouped = None
    # any other code whose pixels take few shutter patterns (every single-bump code):
    # the compiled OMP over the region's pixel-pattern table
    if grouped is None and operator == "auto" and (mask.shape[0] <= 64 or not binary) and (
            binary or _few_patterns(mask, D, m)):
        patterns, which = pixel_patterns(mask)
        if table_fits(len(patterns), D, m):
            table, pat_all = TableOMP(patterns, D, m), P.extract(which, patch)
            return lambda y, sl, rows, tol, prior=0.0: table.solve(y, pat_all[sl][rows], max_atoms=max_atoms,
                                                                   tol=tol, prior=prior)
    # calibrated masks beyond a table: the compiled kernel with one table per patch
    if grouped is None and (operator == "patch" or (operator == "auto" and not binary)):
        weights = WeightsOMP(D, m)
        return lambda y, sl, rows, tol, prior=0.0: weights.solve(y, S_all()[sl][rows], max_atoms=max_atoms, tol=tol,
                                                                 prior=prior)

    def dense(y, sl, rows, tol, prior=0.0):
        # periodic codes share few patch operators; any other code has its own per patch (and a guarded solve)
        if grouped is None or prior > 0:
            op = MaskedOperator(S_all()[sl][rows], D, prior=prior)
        else:
            op = grouped.subset(sl.start + rows)
        return omp(y, op, max_atoms=max_atoms, tol=tol)

    return dense


def _still_rows(still: np.ndarray | None, valid: np.ndarray, patch: int, grid: tuple[int, int]):
    """The valid patches wholly inside the ``still`` pixels, and those of them that no other valid patch
    overlaps (their pixels take the still answer, unsummed); (None, None) without still pixels."""
    if still is None or not np.any(still):
        return None, None
    still_rows = P.extract(np.asarray(still, np.uint8), patch).all(1) & valid
    from scipy import ndimage  # lazy: only a job of several captures has still maps

    near = ndimage.maximum_filter((valid & ~still_rows).reshape(grid), size=2 * patch - 1, mode="constant")
    return still_rows, still_rows & ~near.ravel()


@dataclass
class _Counts:
    """What a region's bands did (its statistics)."""

    static: int = 0
    atoms: int = 0
    hit: int = 0
    dep: int = 0
    seconds: float = 0.0


def _fold_bands(patches: RegionPatches, valid: np.ndarray, stilled: tuple, D: np.ndarray, settings: OmpSettings,
                solve, S_all, shape: tuple[int, int, int]) -> tuple[np.ndarray, np.ndarray, _Counts]:
    """Every valid patch's estimate added at its place, whole rows of patches at a time (``settings.batch``):
    the summed estimates (N, h, w), the weight each pixel got (h, w) and the counts.  ``stilled``: the wholly
    still patches and the pixels to skip (:func:`_still_rows`)."""
    n, h, w = shape
    still_rows, skip = stilled
    hp, wp = patches.grid
    m = patches.y.shape[1]
    patch = patches.patch
    summed = np.zeros((n, h, w), np.float32)
    weight = np.zeros((1, h, w), np.float32)
    counts = _Counts()
    band = max(1, settings.batch // wp)  # whole rows of patches, folded as they finish
    atoms = atom_rows(D)  # (once: every band's estimates are synthesised from it)
    for r0 in range(0, hp, band):
        r1 = min(hp, r0 + band)
        sl = slice(r0 * wp, r1 * wp)
        y, tol = patches.y[sl], patches.n_open[sl] * settings.tol_rms**2
        t0 = time.perf_counter()
        calm = None if still_rows is None else still_rows[sl]
        est = _band_estimates(_Band(y, patches.n_pix[sl], tol, np.flatnonzero(valid[sl]), calm, sl, patches), atoms,
                              settings, solve, counts, frames=n, patch=patch)
        counts.seconds += time.perf_counter() - t0
        wp_ = valid[sl].astype(np.float32)
        if settings.weighting == "fit":
            misfit = y - (S_all()[sl] * est.reshape(-1, n, m)).sum(1)
            e2 = np.einsum("pm,pm->p", misfit, misfit) / np.maximum(patches.n_open[sl], 1)
            wp_ = wp_ / (1.0 + e2 / max(settings.tol_rms, 1e-6) ** 2)
            est *= wp_[:, None]
        P.fold_rows(est, summed, r0, patch, skip=None if skip is None else skip[sl])
        P.fold_rows(wp_, weight, r0, patch)
    return summed, weight[0], counts


@dataclass
class _Band:
    """A band of a region's patches: their coded values ``y``, measured pixel counts, tolerances, the rows to
    estimate, which of them are wholly still (None: none known) and where the band lies in the region's rows."""

    y: np.ndarray
    n_pix: np.ndarray
    tol: np.ndarray
    valid_rows: np.ndarray
    calm: np.ndarray | None
    sl: slice
    region: RegionPatches

    def codes(self, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The region's code and the corners of the band's patches ``rows``, for :func:`still_patches`."""
        return self.region.codes, self.region.corners(self.sl.start + rows)


def _band_estimates(band: _Band, atoms: np.ndarray, settings: OmpSettings, solve, counts: _Counts, *, frames: int,
                    patch: int) -> np.ndarray:
    """The estimates (rows of ``frames * m``, zero but for ``valid_rows``) of a band's patches ``y``: the still answer
    of the wholly still ones (``calm``), then the still test's, then OMP (``solve``) for the rest, synthesised from
    the dictionary's :func:`~codedvideo.solvers.omp_kernel.atom_rows` ``atoms``, invented ones guarded
    (:func:`guard_estimates`)."""
    y, n_pix, tol, valid_rows, calm, sl = band.y, band.n_pix, band.tol, band.valid_rows, band.calm, band.sl
    est = np.zeros((y.shape[0], frames * y.shape[1]), np.float32)
    rows = valid_rows  # those still to estimate
    if calm is not None and rows.size:
        calm_rows = calm[rows]
        if calm_rows.any():
            est[rows[calm_rows]] = still_answers(y[rows[calm_rows]], n_pix[rows[calm_rows]], frames)
            counts.static += int(calm_rows.sum())
            rows = rows[~calm_rows]
    if settings.static_atoms > 0 and rows.size:
        ok, still_est = still_patches(y[rows], n_pix[rows], tol[rows], settings.static_atoms, frames=frames,
                                      patch=patch, codes=band.codes(rows), ridge=settings.ridge)
        est[rows[ok]] = still_est
        counts.static += int(ok.sum())
        rows = rows[~ok]
    if rows.size:
        res = solve(y[rows], sl, rows, tol[rows])
        est[rows] = synthesize_rows(res, atoms)
        dark = res.count == 0  # coded values within the tolerance: the still answer, not 0
        if dark.any():
            est[rows[dark]] = still_answers(y[rows[dark]], n_pix[rows[dark]], frames)
        counts.atoms += int(res.count.sum())
        counts.hit += int((res.count >= settings.max_atoms).sum())
        counts.dep += int(res.dependent.sum())
        guard_estimates(est, rows, (y, n_pix, tol), atoms, lambda bad: solve(y[bad], sl, bad, tol[bad], prior=PRIOR),
                        frames=frames, energy=estimate_energy(res, est[rows], n_pix[rows], atoms, frames))
    return est


#: A patch estimate whose energy on its measured pixels exceeds this many times the still answer's (with the
#: noise the tolerance allows) is invented, not measured (:func:`guard_estimates`).  A sub-frame's values summed
#: over a long shutter bump cancel, so the code barely sees how the sub-frames differ, and the fit's least-squares
#: step can amplify whatever atoms lower the residual into values far outside the scene's (docs/research.md,
#: "Long shutter bumps").
BLOWUP = 2.0


def _energy(est: np.ndarray, n_pix: np.ndarray, frames: int) -> np.ndarray:
    """The energy of patch estimates (rows of ``frames * m``) on their measured pixels."""
    measured = n_pix > 0
    return np.einsum("pnm,pm->p", np.square(est.reshape(est.shape[0], frames, n_pix.shape[1]), dtype=np.float64),
                     measured)


def estimate_energy(res, est: np.ndarray, n_pix: np.ndarray, atoms: np.ndarray, frames: int) -> np.ndarray:
    """The energy of the patch estimates ``est`` (rows of ``frames * m``) synthesised from the OMP results ``res``
    with the dictionary's :func:`~codedvideo.solvers.omp_kernel.atom_rows` ``atoms``: ``sum_i alpha_i**2
    ||d_i||**2``, the estimate's own for orthogonal atoms and what an invented estimate's large coefficients show
    whatever their overlap, at a few multiply-adds a patch where summing the estimate takes ``N m``; a patch with a
    pixel never open: its estimate's on the measured pixels; a patch without atoms: 0."""
    used = np.arange(res.index.shape[1])[None, :] < res.count[:, None]
    c = np.where(used, res.coef, 0).astype(np.float64)
    norms2 = np.einsum("km,km->k", atoms, atoms, dtype=np.float64)
    energy = np.einsum("pi,pi->p", c * c, norms2[res.index])
    holes = np.flatnonzero((n_pix == 0).any(1) & (res.count > 0))
    energy[holes] = _energy(est[holes], n_pix[holes], frames)
    return energy


def _blown(e: np.ndarray, y: np.ndarray, n_pix: np.ndarray, tol: np.ndarray, frames: int) -> np.ndarray:
    """Which patch estimates of energy ``e`` on their measured pixels carry more than :data:`BLOWUP` times the
    energy of their still answer there, the still answer's noise allowed for (``tol``: each patch's squared
    residual tolerance, its ``n_open * tol_rms**2``); a pixel never open is left out of both."""
    measured = n_pix > 0
    inv = np.where(measured, 1.0 / np.maximum(n_pix, 1e-12), 0.0)
    still = y * inv
    tol_rms2 = tol / np.maximum(measured.sum(1), 1)
    e_still = frames * (np.einsum("pm,pm->p", still, still) + tol_rms2 * np.einsum("pm,pm->p", inv, inv))
    # the ratio to 10 significant bits, so that roundoff (another scale of the same capture) never flips a near-tie
    ratio = e / np.maximum(e_still, np.finfo(np.float64).tiny)
    mantissa, exponent = np.frexp(ratio)
    return np.ldexp(np.round(mantissa * 1024) / 1024, exponent) > BLOWUP


def guard_estimates(est: np.ndarray, rows: np.ndarray, measured: tuple, atoms: np.ndarray, resolve, *, frames: int,
                    energy: np.ndarray | None = None) -> int:
    """The sparse estimates ``est[rows]`` that :func:`_blown` finds invented, solved again with the coefficient
    prior (:data:`codedvideo.solvers.omp.PRIOR`: ``resolve(bad)`` -> the :class:`OmpResult` of the patches
    ``bad``), and those still invented given their still answer (in place); returns how many were solved again.
    ``measured``: ``(y, n_pix, tol)`` of the patches of ``est``, their coded values, open counts and squared
    residual tolerances.  ``energy``: the energies of ``est[rows]`` when known (:func:`estimate_energy`;
    default: on their measured pixels).  On the paper's codes (N = 8, L = 2 or 3) a patch in a few hundred
    acts, or none."""
    y, n_pix, tol = measured
    if not rows.size:
        return 0
    e = _energy(est[rows], n_pix[rows], frames) if energy is None else energy
    # the still answer's energy is at least frames ||y||^2 / max(n)^2: the patches under that bound by a margin are
    # not invented, found without the per-pixel arrays of the exact test (their allocations cost as much as it)
    low = frames * np.einsum("pm,pm->p", y, y, dtype=np.float64) / np.square(np.maximum(n_pix.max(1), 1e-12),
                                                                              dtype=np.float64)
    maybe = e > 0.99 * BLOWUP * low[rows]
    near = rows[maybe]
    bad = near[_blown(e[maybe], y[near], n_pix[near], tol[near], frames)]
    if not bad.size:
        return 0
    res = resolve(bad)
    est[bad] = synthesize_rows(res, atoms)
    again = estimate_energy(res, est[bad], n_pix[bad], atoms, frames)
    still = bad[(res.count == 0) | _blown(again, y[bad], n_pix[bad], tol[bad], frames)]
    if still.size:
        est[still] = still_answers(y[still], n_pix[still], frames)
    return int(bad.size)
