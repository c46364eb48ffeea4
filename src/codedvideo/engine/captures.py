"""Reconstructing captures by any method: a capture, a job of captures, a stream; the methods' dispatch.

:class:`CaptureSettings` holds how captures are reconstructed (the method and its options);
:func:`reconstruct_captures` runs a job of captures with it, in three steps: prepared (:func:`_prepare`: the
method's settings and dictionary, the passes), adapted (:func:`_adapt`, ``--adapt`` only: each capture's
dictionary) and finished capture by capture (:func:`_finish`: static estimates, the baselines, refinement,
units).  :func:`reconstruct_capture` is a job of one, :func:`reconstruct_stream` a coded camera's stream with
its captures joined, :func:`reconstruct_method` one capture by any method without units.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from codedvideo.model import doors
from codedvideo.engine import methods
from codedvideo.engine.adaptation import ADAPT_LAST_STEP, ADAPT_REFINE_STEP, ADAPT_SURVEY_STEP, adapt_capture
from codedvideo.engine.cache import CacheBudget, content_key
from codedvideo.engine.config import DEFAULT_CACHE, ReconstructConfig
from codedvideo.engine.parallel import progress_bar
from codedvideo.engine.windows import Execution, reconstruct_volume, sparse_volumes, static_volume
from codedvideo.model import physics
from codedvideo.model.errors import ConfigError, InputError, OutputError
from codedvideo.model.patches import PATCH
from codedvideo.model.sequence import erode_to_patches, normalised
from codedvideo.model.units import EIGHT_BIT, DataRange
from codedvideo.solvers import guard
from codedvideo.solvers import refine as refinement
from codedvideo.solvers import stillness
from codedvideo.solvers import temporal
from codedvideo.solvers.region import OmpSettings


@dataclasses.dataclass(frozen=True, eq=False)
class CaptureSettings:
    """How captures are reconstructed: the method and every option of :func:`reconstruct_captures`.

    Attributes
    ----------
    method : str
        One of :data:`codedvideo.engine.methods.METHOD_NAMES`.
    data_range : :class:`codedvideo.model.units.DataRange`
        The captures are scaled to working units (``settings`` already in
        them), reconstructed and scaled back, so the same captures in other
        units give the same videos times the scale.
    settings : :class:`codedvideo.solvers.region.OmpSettings`
        The sparse methods' settings, in working units.
    dictionary, dictionary_key, dictionary_name
        The dictionary of ``omp`` and ``nonlocal`` (:func:`sparse_method`), its cache key (empty: keyed by
        its contents) and its name in messages.
    white_level : float, optional
        Pixels at or above it (capture units) recorded at least it: kept as measurements at their clipped value,
        and each result's frame sums there raised to it.
    where : str
        Names the captures in messages.
    config : :class:`codedvideo.engine.config.ReconstructConfig`
        The validated ``reconstruct:`` settings the job reads as they are: its tiles, scheduler and workers
        (:func:`codedvideo.engine.windows.sparse_volumes`), its cache budget, and its steps beyond the method:
        ``adapt`` (reconstruct each capture, adapt the dictionary to its result,
        :func:`codedvideo.engine.adaptation.adapt_dictionary`, reconstruct every capture again with its own;
        ``nonlocal``: a survey first, :data:`~codedvideo.engine.adaptation.ADAPT_SURVEY_STEP`), ``adapt_rounds``
        (2: adapt again to the second pass's result and reconstruct a third time,
        :data:`~codedvideo.engine.adaptation.ADAPT_LAST_STEP`) and ``refine`` (iterations of GAP with a low-rank
        prior on groups after each capture's result, :func:`codedvideo.solvers.refine.refine`, in the process,
        not cached; pixels that only still patches cover keep their still answer).  Its OMP fields are read
        through ``settings``, in working units.
    cache, progress
        The sparse methods' cache folder and progress bars (:attr:`execution`).
    blocks : int
        With ``refine``: the frames of a capture are that many videos stacked, each of its own sub-frames (a
        Bayer capture's colour channels, :func:`codedvideo.engine.bayer.reconstruct_bayer`); the refinement's
        groups stay within one (:func:`codedvideo.solvers.refine.refine`).  1: one video.
    noise_sigma : float
        The captures' read noise (capture units, ``--noise-sigma``): with ``refine``, a noisy capture's steps to
        its measurements are relaxed by it (:func:`codedvideo.solvers.refine.refine`); a stream's still
        answers follow it (:func:`reconstruct_stream`).
    still_regions : bool
        Move a sparse method's result toward the still estimate where the capture's code shows the scene holding
        still (:mod:`codedvideo.solvers.stillness`); the temporal windows' own captures, a Bayer capture's
        stacked colours (``blocks`` above 1) and a stream's captures with still answers from other captures are
        not.
    trace : callable, optional
        With ``refine``: ``trace(i, iterations, volume, seconds, rows)`` with the rows ``rows`` of capture ``i``'s
        estimate (working units) before the refinement (``iterations`` 0) and every few of its iterations
        (:data:`codedvideo.solvers.refine.WATCH_EVERY`), and the capture's seconds so far (error against time);
        with ``adapt`` also after each pass before the last, ``iterations`` then the pass's label (``"pass 1"``).
    """

    method: str
    data_range: DataRange
    settings: OmpSettings
    dictionary: np.ndarray | None = None
    dictionary_key: str = ""
    dictionary_name: str = ""
    white_level: float | None = None
    where: str = "coded image"
    config: ReconstructConfig = dataclasses.field(default_factory=ReconstructConfig)
    cache: str | Path = DEFAULT_CACHE
    progress: bool = True
    blocks: int = 1
    noise_sigma: float = 0.0
    still_regions: bool = True
    trace: object = None

    @property
    def execution(self) -> Execution:
        """Where the sparse methods' tiles run (a view of ``config``, ``cache`` and ``progress``)."""
        c = self.config
        return Execution(tile=c.tile, cache=self.cache, scheduler=c.scheduler, workers=c.workers,
                         progress=self.progress)


class _Inputs:
    """The captures of a job as reconstructed (:meth:`used`), the last one asked kept (the finishing step asks
    twice in a row; one capture's inputs held at most)."""

    def __init__(self, options: CaptureSettings, codeds, mask_of, still_of):
        self.options, self.codeds, self.mask_of, self.still_of = options, codeds, mask_of, still_of
        self.count = len(codeds)
        self.scale = np.float32(options.data_range.scale)
        self.blown: set[int] = set()  # captures saturated everywhere (warned once each)
        self.used = functools.lru_cache(maxsize=1)(self._used)

    def forget(self) -> None:
        """Ask every capture afresh, and say its warnings again (the first jobs of ``--adapt`` swallowed them)."""
        self.blown.clear()
        self.used.cache_clear()

    def _used(self, i: int):
        """Capture i as reconstructed: working units, saturated pixels left out, the pixels only still patches
        cover measuring their still answer; its agreeing pixels (None: none), whether anything moves, its
        saturated count, and its own measurement where still answers changed it (else None)."""
        coded_used, mask_used, saturated = self._unsaturated(i)
        coded_used = (np.asarray(coded_used, np.float32) * self.scale if self.scale != 1
                      else np.asarray(coded_used, np.float32))
        still = measured = None
        if self.still_of is not None:  # asked again when the capture is finished (not kept: T maps of H x W)
            values = self.still_of(i)
            found = np.isfinite(values) & np.asarray(mask_used).any(0)
            if found.any():
                # a pixel that only still patches cover measures its still answer (the captures it agrees with
                # averaged in): coded = open count x value.  Pixels that a patch which moves covers keep their
                # own measurement, so the per-patch search of that patch is the one it was (tested); the
                # methods that couple patches (nonlocal groups, gap-tv, --adapt's learning) see the averages
                still, inner = found, erode_to_patches(found, PATCH)
                averaged = np.where(inner, np.asarray(mask_used).sum(0, dtype=np.float32) * values,
                                    coded_used).astype(np.float32)
                if not np.array_equal(averaged, coded_used):
                    measured, coded_used = coded_used, averaged
        moving = still is None or int(still.sum()) < int(np.asarray(mask_used).any(0).sum())
        return coded_used, mask_used, still, moving, saturated, measured

    def _unsaturated(self, i: int):
        """Capture i (capture units), its mask, and its saturated pixels' count: a pixel at or above the white
        level recorded at least it, so it stays a measurement at its clipped value and the result's frame sums
        there are raised to the white level after the solve (:func:`codedvideo.model.physics.raise_to_white`);
        leaving it out threw away what it says and let blocks of clipped highlights be guessed from their
        neighbours (docs/research.md, "Clipped captures").  A capture of a stream saturated everywhere is taken
        with its clipped values (said once)."""
        white_level, where, count = self.options.white_level, self.options.where, self.count
        coded, mask = self.codeds[i], self.mask_of(i)
        if white_level is None:
            return coded, mask, 0
        opened = np.asarray(mask).any(0)
        saturated = int(np.count_nonzero((np.asarray(coded) >= np.float32(white_level)) & opened))
        if saturated and saturated == int(np.count_nonzero(opened)):
            if count == 1:
                raise InputError(f"{where}: every measured pixel is at or above {doors.name('white_level')} "
                                 f"{white_level}; nothing is left to reconstruct ({doors.name('trust_saturated')} uses "
                                 "them anyway)")
            # one blown-out capture of a stream (a flash, the sun): its clipped values, said, and the rest go on
            if i not in self.blown:
                self.blown.add(i)
                doors.warn(f"{where}, capture {i + 1} of {count}: every measured pixel is at or above "
                           f"{doors.name('white_level')} {white_level}; it is reconstructed from its clipped values")
            return coded, mask, 0
        return coded, mask, saturated


@dataclasses.dataclass(eq=False)
class _Job:
    """A job of captures, prepared (:func:`_prepare`): its options with the method's settings (the last pass's),
    dictionary and key resolved, its captures, and what its passes and adaptations leave for the last job."""

    options: CaptureSettings
    inputs: _Inputs
    sparse: bool
    #: ``nonlocal --adapt``: the passes before the last survey on sparser grids of groups, each matched on by the next.
    survey: bool
    pass_settings: list
    budget: CacheBudget | None
    nonlocal_checked: dict = dataclasses.field(default_factory=dict)
    adapted: dict = dataclasses.field(default_factory=dict)  # capture -> its adapted dictionary (until planned)
    records: dict = dataclasses.field(default_factory=dict)  # capture -> its adaptation, the earlier jobs' seconds
    first_stores: dict = dataclasses.field(default_factory=dict)  # capture -> the store its last pass is matched on
    warned_nonlocal: bool = False

    def for_sparse(self, i: int):
        """Capture ``i``'s inputs for :func:`sparse_volumes`, or None where it is not sparse-coded."""
        coded_used, mask_used, still, moving, _, _ = self.inputs.used(i)
        return (coded_used, mask_used, still) if self.sparse and moving else None

    def nonlocal_problem(self, mask) -> str | None:
        """Why the non-local method cannot solve a capture with this mask, or None (a code's patterns are
        counted once: 3 s for a 4K mask, N = 18)."""
        code = content_key(np.asarray(mask))
        if code not in self.nonlocal_checked:
            self.nonlocal_checked[code] = _nonlocal_unavailable(mask, self.options.dictionary)
        return self.nonlocal_checked[code]


def _prepare(options: CaptureSettings, codeds, mask_of, still_of) -> _Job:
    """A job of captures with ``options``: the method checked, its settings and dictionary resolved
    (:func:`sparse_method`), the passes' settings (``--adapt``), the cache budget."""
    entry = methods.method(options.method)
    inputs = _Inputs(options, codeds, mask_of, still_of)
    resolved = options
    if entry.sparse:
        settings, dictionary, key = sparse_method(options.method, options.settings, options.dictionary,
                                                  options.dictionary_key, options.dictionary_name,
                                                  frames=mask_of(0).shape[0])
        resolved = dataclasses.replace(options, settings=settings, dictionary=dictionary, dictionary_key=key)
    if options.config.adapt and not entry.adapts:
        raise ConfigError(f"{doors.name('adapt')}: method {options.method} has no dictionary to adapt "
                          f"({', '.join(methods.ADAPTIVE[:-1])} and {methods.ADAPTIVE[-1]} have)")
    # --adapt with the non-local method: a first pass on a sparser grid of groups (a survey: what K-SVD learns
    # from and the groups of the second pass are matched on), then the groups solved from it (no default tiles);
    # with adapt_rounds 2 the second pass is learnt from and matched on in turn, and a third pass gives the result
    rounds = options.config.adapt_rounds
    survey = resolved.settings.method == "nonlocal" and options.config.adapt
    steps = (ADAPT_SURVEY_STEP, ADAPT_REFINE_STEP, ADAPT_LAST_STEP)[:rounds + 1] if survey else ()
    pass_settings = [dataclasses.replace(resolved.settings, group_step=step) for step in steps] if survey \
        else [resolved.settings] * (rounds + 1)
    limit = options.config.cache_budget
    budget = None if limit is None or not entry.sparse else CacheBudget(options.cache, limit)
    return _Job(dataclasses.replace(resolved, settings=pass_settings[-1]), inputs, entry.sparse, survey,
                pass_settings, budget)


def _adapt(job: _Job) -> None:
    """``--adapt``: each capture's passes before the last, and its dictionary adapted to them
    (:func:`codedvideo.engine.adaptation.adapt_capture`), into ``job``."""
    o = job.options
    for i in range(job.inputs.count):
        stage = None if o.trace is None else functools.partial(_stage, o.trace, i)
        D_i, store, record = adapt_capture(job, i, stage=stage)
        if D_i is not o.dictionary:
            job.adapted[i] = D_i
        if store is not None:
            job.first_stores[i] = store
        if record is not None:
            job.records[i] = record
    job.inputs.forget()  # the warnings the first jobs swallowed are said by the second


def _stage(trace, i: int, label: str, volume: np.ndarray, seconds: float) -> None:
    """Capture ``i``'s result after the pass ``label`` of its adaptation, shown to the job's ``trace``."""
    trace(i, label, volume, seconds, slice(0, volume.shape[1]))


def _solved(job: _Job):
    """The job's sparse-coded volumes, in order (``(i, None, None)`` for every capture of a baseline)."""
    o, count = job.options, job.inputs.count
    if not job.sparse:
        return ((i, None, None) for i in range(count))
    solve = functools.partial(sparse_volumes, count, job.for_sparse, settings=o.settings, budget=job.budget)
    if not job.adapted:
        return solve(o.dictionary, run=o.execution, dictionary_key=o.dictionary_key)
    # a capture not adapted (flat) keeps the dictionary and its key: its second job is the first's, from the cache
    # (with the survey, the method's own job at the second pass's stride)
    adapted = job.adapted
    return solve(lambda i: (adapted.pop(i), "") if i in adapted else (o.dictionary, o.dictionary_key),
                 run=dataclasses.replace(o.execution, desc="adapted"),
                 first_of=job.first_stores.get if job.survey else None)


def reconstruct_captures(options: CaptureSettings, codeds, mask_of, *,
                         still_of=None) -> Iterator[tuple[int, np.ndarray, dict]]:
    """Captures in their own units -> their videos in the same units, by any method, in order, as one job.

    Parameters
    ----------
    options : CaptureSettings
        The method and its options.
    codeds : sequence of T coded images (H, W), in the capture's units
    mask_of : callable ``mask_of(i)`` -> the (N, H, W) mask of capture ``i``
    still_of : callable, optional
        ``still_of(i)`` -> (H, W) float32 (:func:`codedvideo.model.sequence.still_values`):
        the still answer, in working units, of the pixels whose ``coded / open
        count`` agrees with a neighbouring capture, NaN elsewhere.  Patches wholly inside them take the still
        answer in every sub-frame without a dictionary search (that value where only still patches cover
        a pixel; elsewhere the capture's own, which the patches that move see); a capture in which every
        measured pixel agrees is the still estimate itself.  (Methods without
        patches: the pixels whose 13x13 neighbourhood agrees take it.)

    Yields
    ------
    ``(i, volume (N, H, W) float32, info)`` for i = 0 .. T-1, each as soon as
    it is done; the sparse methods run every capture's tiles in one graph.
    """
    job = _prepare(options, codeds, mask_of, still_of)
    if job.sparse and options.config.adapt:
        _adapt(job)
    results = _solved(job)
    with contextlib.closing(results) if job.sparse else contextlib.nullcontext():
        for i, volume, info in results:
            # (as sparse_volumes: not held while the consumer works on it)
            handed = [_finish(job, i, volume, info)]
            del volume, info
            yield handed.pop()
    if job.budget is not None and job.budget.keep:  # the job is over: the first passes' stores may go too
        job.budget.keep.clear()
        job.budget.finished([])


def _finish(job: _Job, i: int, solved: np.ndarray | None, solved_info: dict | None) -> tuple[int, np.ndarray, dict]:
    """Capture ``i``'s result: its sparse-coded volume, or the static estimate where nothing moves, or its
    baseline's; refined, saturated pixels raised to the white level, still answers kept, in capture units."""
    o, inputs = job.options, job.inputs
    coded_used, mask_used, still, moving, saturated, measured = inputs.used(i)
    taken = None if solved_info is None else solved_info.pop("misfit_taken", None)  # (a map: not for the record)
    if not moving:  # nothing moves: no sparse coding at all
        volume, info = static_volume(coded_used, mask_used)
        if guard.shared_by_all(mask_used):  # (where every capture looks still: the floor holds there too)
            volume, info = _guarded(volume, info, coded_used, mask_used, None)
    elif solved is None:
        volume, info = reconstruct_method(o.method, coded_used, mask_used)
    else:
        volume, info = _guarded(solved, solved_info, coded_used, mask_used, still)
    used = (coded_used, mask_used, still)
    excluded = _clipped(job, i) if saturated else None  # (the still regions leave them; raised at the end)
    if taken is not None:  # (the sparse estimate's share of a result blended with GAP-TV)
        taken = taken * np.float32(info.get("guard", {}).get("sparse_weight", 1.0))
    judged = None
    if o.config.refine and moving and info.get("method") != "static":
        if solved is not None:  # (judged before the refinement: it brings the result to the measurement)
            judged = _still_weight(job, used, volume, excluded, taken)
        volume, info = _refined(job, i, used, volume, info)
    if solved is not None:
        volume, info = _windowed(job, i, used, volume, info)
        volume, info = _still_regions(job, used, volume, info, judged if judged is not None
                                      else _still_weight(job, used, volume, excluded, taken))
    if measured is not None:  # still answers averaged over captures: the residual of this capture's own
        residual = physics.forward(volume, mask_used) - measured
        info["measurement_residual_rms"] = float(np.sqrt(np.mean(residual.astype(np.float64) ** 2)))
    if job.sparse and info.get("method") != "static":  # (the static estimate says so)
        info = _sparse_info(job, i, info, mask_used)
    if saturated:  # a saturated pixel recorded at least the white level: no frame sum below it
        info["saturated_raised"] = physics.raise_to_white(volume, excluded, inputs.mask_of(i),
                                                          float(o.white_level) * float(inputs.scale))
    if still is not None and not job.sparse:  # no patches: the pixels whose every patch would be still
        inner = erode_to_patches(still, PATCH)
        volume[:, inner] = normalised(coded_used, mask_used)[0][inner]
    info["still_pixels"] = 0 if still is None else int(still.sum())
    if inputs.scale != 1:
        volume /= inputs.scale
        if info.get("measurement_residual_rms") is not None:
            info["measurement_residual_rms"] = float(info["measurement_residual_rms"]) / float(inputs.scale)
    info["saturated_pixels"] = saturated
    return i, volume, info


def _keeping_still(volume: np.ndarray, still: np.ndarray | None, blend) -> np.ndarray:
    """``blend(volume)`` (which may overwrite ``volume``), the pixels that only still patches cover (of the still
    pixels ``still``; None: none) keeping their values in ``volume``: their still answer."""
    kept = None if still is None else erode_to_patches(still, PATCH)
    values = None if kept is None else volume[:, kept]
    result = blend(volume)
    if values is not None:
        result[:, kept] = values
    return result


def _guarded(volume: np.ndarray, info: dict, coded: np.ndarray, mask: np.ndarray,
             still: np.ndarray | None) -> tuple[np.ndarray, dict]:
    """A sparse-coded capture's result under the floor of :mod:`codedvideo.solvers.guard`: on a code whose
    patches are blind to what they fit, blended with GAP-TV (working units; the pixels only still patches
    cover keep their still answer), its weight and reason in the record (``guard``).  A still answer is kept
    as it is, but under a code that every pixel shares (where any scene looks still)."""
    weight, reason = guard.sparse_weight(mask)
    if weight >= 1.0 or info.get("method") == "static" and not guard.shared_by_all(mask):
        return volume, info
    t0 = time.perf_counter()
    result = _keeping_still(volume, still, lambda v: guard.blended(v, coded, mask, weight, data_range=EIGHT_BIT))
    seconds = dict(info.get("seconds", {}), guard=time.perf_counter() - t0)
    return result, dict(info, guard=dict(sparse_weight=round(weight, 4), reason=reason), seconds=seconds)


@functools.lru_cache(maxsize=1)
def _window_dictionary() -> tuple[np.ndarray, str] | None:
    """The shipped dictionary of :data:`codedvideo.solvers.temporal.WINDOW` sub-frames and its cache key (None where
    none is shipped)."""
    from codedvideo.data import shipped
    from codedvideo.formats.store import load_dictionary
    from codedvideo.solvers.dictionaries import prepare_dictionary

    path = shipped.verified(temporal.WINDOW)
    if path is None:
        return None
    D, meta = load_dictionary(path)
    prepared = prepare_dictionary(D, str(path))
    return prepared, meta.get("sha256", "") if prepared is D else ""


def _windows_apply(options: CaptureSettings, mask: np.ndarray) -> bool:
    """Whether a capture under ``mask`` is windowed (:func:`codedvideo.solvers.temporal.applies`): with the
    dictionary shipped for its N (one given by the user is theirs alone) and one shipped for the windows."""
    from codedvideo.data import shipped

    n = mask.shape[0]
    if n <= temporal.WINDOW or options.dictionary_name != str(shipped.path_for(n)):
        return False  # (before the code is read: the paper's N = 8 pays nothing for the windows)
    return temporal.applies(mask, guard.sparse_weight(mask)[0]) and _window_dictionary() is not None


def _windowed(job: _Job, i: int, used: tuple, volume: np.ndarray, info: dict) -> tuple[np.ndarray, dict]:
    """A sparse-coded capture's result blended with its windows' (:mod:`codedvideo.solvers.temporal`) where its
    code has short exposures at N above the window's: the windows' captures reconstructed as one job as the
    capture is (its method, adaptation and refinement) with the window's shipped dictionary, combined and
    blended with ``volume`` (working units; the pixels only still patches cover keep their still answer), what
    was done in the record (``windows``).  ``used``: the capture's coded image, mask and still pixels (working
    units)."""
    from codedvideo.data import shipped

    coded, mask, still = used
    o = job.options
    if not _windows_apply(o, mask):
        return volume, info
    t0 = time.perf_counter()
    D, key = _window_dictionary()
    scale = job.inputs.scale
    first = temporal.starts(mask.shape[0])
    parts = [temporal.window_capture(coded, mask, s) for s in first]
    options = dataclasses.replace(o, dictionary=D, dictionary_key=key, trace=None, still_regions=False,
                                  dictionary_name=str(shipped.path_for(temporal.WINDOW)))
    volumes: list = [None] * len(first)
    # muted: a window's pixels outside it are never open by design, and what else it would say, the capture says
    with doors.muted():
        results = reconstruct_captures(options, [part / scale for part, _ in parts], lambda j: parts[j][1])
        with contextlib.closing(results):
            for j, part, _ in results:
                volumes[j] = part * scale
    windows = temporal.combined(volumes, first, mask.shape[0])
    result = _keeping_still(volume, still, lambda v: temporal.blended(v, windows))
    seconds = dict(info.get("seconds", {}), windows=time.perf_counter() - t0)
    return result, dict(info, windows=dict(temporal.recipe(), starts=first), seconds=seconds)


def _clipped(job: _Job, i: int) -> np.ndarray:
    """Capture ``i``'s pixels at or above the white level."""
    return np.asarray(job.inputs.codeds[i]) >= np.float32(job.options.white_level)


def _still_weight(job: _Job, used: tuple, volume: np.ndarray, excluded: np.ndarray | None,
                  taken: np.ndarray | None = None) -> tuple:
    """``(weight, seconds)``: where a sparse-coded capture's result ``volume`` is moved toward the still estimate
    (:func:`codedvideo.solvers.stillness.still_weight`, working units; saturated pixels, ``excluded``, keep
    theirs; ``taken``: the misfit that the non-local method's projection took away), None where no pixel is: the
    job does not ask for it, a Bayer capture's stacked colours (``blocks``), a capture of a stream with pixels
    whose still answer other captures gave (``used``'s still pixels: those told still from moving pixel by
    pixel).  ``used``: the capture's coded image, mask and still pixels."""
    coded, mask, still = used
    o = job.options
    if not o.still_regions or o.blocks != 1 or still is not None:
        return None, 0.0
    t0 = time.perf_counter()
    weight = stillness.still_weight(volume, coded, mask, noise_sigma=float(o.noise_sigma) * float(job.inputs.scale),
                                    excluded=excluded, taken=taken)
    return weight, time.perf_counter() - t0


def _still_regions(job: _Job, used: tuple, volume: np.ndarray, info: dict, judged: tuple) -> tuple[np.ndarray, dict]:
    """A sparse-coded capture's result moved toward the still estimate by ``judged`` (:func:`_still_weight`:
    found on the result, or on it before its refinement, which brings it to the measurement), the share of the
    frame it moved in the record (``still_regions``).  ``used``: the capture's coded image, mask and still
    pixels (working units)."""
    weight, seconds = judged
    if weight is None:
        return volume, info
    t0 = time.perf_counter()
    share = float(weight.mean())
    result = stillness.blended(volume, used[0], used[1], weight) if share > 0 else volume
    seconds = dict(info.get("seconds", {}), still_regions=seconds + time.perf_counter() - t0)
    return result, dict(info, still_regions=dict(share=round(share, 4)), seconds=seconds)


def _seconds_so_far(job: _Job, i: int, info: dict) -> float:
    """Capture ``i``'s seconds before its refinement: its passes, and its first pass and adaptation."""
    earlier = job.records.get(i)
    first = earlier["first_pass"]["seconds"] + earlier["seconds"] if earlier else 0.0
    return float(first + sum(v for v in info.get("seconds", {}).values() if isinstance(v, (int, float))))


def _sparse_info(job: _Job, i: int, solved_info: dict, mask_used) -> dict:
    """A sparse-coded capture's record: its method and dictionary, its adaptation and the earlier jobs' time,
    and whether the non-local method could solve it (a code it cannot gives the default's answer: said once)."""
    o = job.options
    info = dict(solved_info, method=o.method, dictionary_atoms=int(o.dictionary.shape[1]))
    if i in job.records:  # the first job's and the adaptation's time beside the second's
        record = info["adapted"] = job.records.pop(i)
        info["seconds"] = dict(first_pass=record["first_pass"]["seconds"], adapt=record["seconds"], **info["seconds"])
        work = record["first_pass"]["tile_seconds"] + record["seconds"] + info["seconds_total"]
        info["patches_per_second"] = info.get("patches_computed", 0.0) / max(work, 1e-9)
    problem = job.nonlocal_problem(mask_used) if o.method == "nonlocal" else None
    if problem:  # its tiles gave the default's answer: said, not hidden
        info.update(method="omp", nonlocal_unavailable=problem)
        if not job.warned_nonlocal:
            adapted = " with the adapted dictionary" if info.get("adapted") else ""
            doors.warn(f"{doors.name('method')} nonlocal ({o.where}): {problem}; the result is the per-patch "
                       f"OMP's{adapted} (for every capture with such a code: nonlocal_unavailable in the metrics)")
            job.warned_nonlocal = True
    return info


def _refined(job: _Job, i: int, used: tuple, volume: np.ndarray, info: dict) -> tuple[np.ndarray, dict]:
    """Capture ``i``'s result after the job's ``config.refine`` iterations of :func:`codedvideo.solvers.refine.refine`
    (working units, the read noise too; ``blocks``, the videos stacked in its frames), its info with what the
    refinement did; ``used``: its coded image, mask and still pixels as reconstructed (:meth:`_Inputs.used`), the
    pixels that only still patches cover keeping their values.  The job's ``trace(i, iterations, estimate,
    seconds, rows)`` is shown the estimates along the way, a band of rows at a time where the refinement goes in
    bands (:class:`CaptureSettings`), from the capture's seconds before the refinement.  ``volume`` may be
    overwritten by the result (a refinement in bands writes into it)."""
    o, inputs = job.options, job.inputs
    coded, mask, still = used
    iterations, trace = o.config.refine, None if o.trace is None else functools.partial(o.trace, i)
    noise_sigma, blocks, where = float(o.noise_sigma) * float(inputs.scale), o.blocks, o.where
    inner = None if still is None else erode_to_patches(still, PATCH)  # (the refinement keeps their values)
    watch, spent = None, _seconds_so_far(job, i, info)
    if trace is not None:
        trace(0, volume, spent, slice(0, volume.shape[1]))
        share = lambda rows: (rows.stop - rows.start) / volume.shape[1]  # noqa: E731  (a band's part of `spent`)
        watch = lambda done, estimate, seconds, rows: trace(  # noqa: E731
            done, estimate, spent * share(rows) + seconds, rows)
    steps = iterations * len(refinement.bands(volume.shape))
    with progress_bar(steps, f"refine {i + 1}/{inputs.count}") if o.progress else contextlib.nullcontext() as bar:
        refined, record = refinement.refine(coded, mask, volume, iterations=iterations, noise_sigma=noise_sigma,
                                            known=inner, blocks=blocks,
                                            run=refinement.RefineRun(
                                                tick=None if bar is None else (lambda: bar.update(1)),
                                                watch=watch, overwrite=True))
    if not np.isfinite(refined).all():  # (never seen: the start and the measurements are finite)
        raise OutputError(f"{where}: the refinement gave non-finite values; run without {doors.name('refine')}")
    seconds = dict(info.get("seconds", {}), refine=record["seconds"])
    return refined, dict(info, refine=record, seconds=seconds)


def reconstruct_stream(options: CaptureSettings, codeds, mask_of, *, join: bool, still: bool = True, cuts=None,
                       spill: str | Path | None = None) -> Iterator[tuple[int, np.ndarray, dict]]:
    """A stream of captures (a coded camera's frames, or a benchmark file's measurements) -> their videos, in
    order: :func:`reconstruct_captures` as one job and, with ``join`` and more than one capture, the still
    answers shared with agreeing neighbours (:func:`codedvideo.model.sequence.still_values`) and the step from one
    capture to the next smoothed (:func:`codedvideo.model.sequence.joined`), except across the boundaries ``cuts``
    (:class:`codedvideo.model.sequence.Cuts`, made here when None) finds are no boundary of one scene.  ``still``:
    share still answers (False for a benchmark file's measurements, each of its own scene).  ``spill``: a
    folder where the captures the join holds wait on disk (:func:`codedvideo.formats.volumes.spilled`: the same bits,
    read a few frames at a time), or None to hold them in memory.  What the command line and the Python API
    (:func:`codedvideo.api.reconstruct`) both run; ``options``: the method and its options
    (:class:`CaptureSettings`); its ``noise_sigma`` and ``white_level`` are the still answers' too."""
    count = len(codeds)
    if not join or count < 2:
        return reconstruct_captures(options, codeds, mask_of)
    from codedvideo.model.sequence import Cuts, joined, still_values

    scale, white_level = options.data_range.scale, options.white_level
    cut = Cuts(codeds, mask_of, scale=scale, white_level=white_level) if cuts is None else cuts
    # what did not change since the capture before or until the one after (asked again by the join)
    still_of = functools.lru_cache(maxsize=4)(
        lambda i: still_values(codeds, mask_of, i, sigma=options.noise_sigma, scale=scale,
                               white_level=white_level, cut=cut)) if still else None
    results = reconstruct_captures(options, codeds, mask_of, still_of=still_of)
    if spill is not None:
        from codedvideo.formats.volumes import spilled

        results = spilled(results, spill)
    # the step from one capture to the next smoothed along the motion, both measurements kept
    return joined(results, codeds, mask_of, data_range=options.data_range.value, still_of=still_of,
                  white_level=white_level, cut=cut)


def _nonlocal_unavailable(mask: np.ndarray, D: np.ndarray) -> str | None:
    """Why the non-local method cannot solve a capture with this mask (it then gives the default's answer,
    :func:`codedvideo.solvers.nonlocal_sc.nonlocal_region`), or None."""
    from codedvideo.solvers.omp import pixel_patterns
    from codedvideo.solvers.omp_kernel import table_fits

    patterns, _ = pixel_patterns(mask)
    if table_fits(len(patterns), D, PATCH * PATCH):
        return None
    return (f"the code has {len(patterns)} distinct pixel shutter patterns, more than the table its groups are "
            "solved through holds")


def reconstruct_capture(options: CaptureSettings, coded: np.ndarray, mask: np.ndarray, *,
                        still: np.ndarray | None = None) -> tuple[np.ndarray, dict]:
    """One capture in its own units -> its video in the same units: a job of one (:func:`reconstruct_captures`);
    ``still``: its still values in working units, NaN where not still (:func:`codedvideo.model.sequence.still_values`)."""
    if still is not None and not np.issubdtype(np.asarray(still).dtype, np.floating):
        raise TypeError(f"still: the still values (float, NaN where not still), not {np.asarray(still).dtype} "
                        "(a map of still pixels: sequence.still_values gives the values)")
    results = reconstruct_captures(options, [coded], lambda i: mask,
                                   still_of=None if still is None else (lambda i: still))
    with contextlib.closing(results):
        (_, volume, info), = results  # to its end: the job's cache budget is applied there
    return volume, info


def sparse_method(method: str, settings: OmpSettings, dictionary: np.ndarray | None, dictionary_key: str,
                  dictionary_name: str, *, frames: int) -> tuple[OmpSettings, np.ndarray, str]:
    """The settings, dictionary and its cache key a sparse method runs with.

    ``omp`` and ``nonlocal`` use ``dictionary`` (required), ``dct`` the
    complete 3D DCT.  Atoms of any nonzero norm give the same answer: they go
    through :func:`~codedvideo.solvers.dictionaries.prepare_dictionary` (unit norm,
    zero atoms dropped with a warning, all-zero refused), and a changed
    dictionary is keyed by its own contents.
    """
    from codedvideo.solvers.dictionaries import dct_dictionary, prepare_dictionary

    entry = methods.method(method)
    used = dataclasses.replace(settings, method=entry.solver)
    if not entry.dictionary:  # (dct: its own atoms)
        atoms, key = dct_dictionary(frames), ""
    elif dictionary is None:
        raise InputError(f"method {method}: needs a dictionary ({doors.name('dictionary')} DICT.zarr)")
    else:
        atoms, key = dictionary, dictionary_key
    prepared = prepare_dictionary(atoms, dictionary_name or f"of method {method}")
    if prepared is not atoms:  # the caller's key names the given atoms: key the cache by the used ones
        return used, prepared, ""
    return used, atoms, key


def reconstruct_method(
    method: str,
    coded: np.ndarray,
    mask: np.ndarray,
    *,
    dictionary: np.ndarray | None = None,
    dictionary_key: str = "",
    dictionary_name: str = "",
    settings=None,
    run: Execution = Execution(progress=False),
) -> tuple[np.ndarray, dict]:
    """Reconstruct with any method of :data:`codedvideo.engine.methods.METHOD_NAMES` on the same forward model.

    ``omp`` runs :func:`codedvideo.engine.windows.reconstruct_volume` with
    ``dictionary``; ``dct`` runs it with the complete 3D DCT
    (:func:`codedvideo.solvers.dictionaries.dct_dictionary`); ``thinout``,
    ``interp`` and ``gaptv`` run those of :mod:`codedvideo.solvers.baselines` with their
    defaults.

    Parameters
    ----------
    method : str
        One of :data:`codedvideo.engine.methods.METHOD_NAMES`.
    coded : ndarray of shape (H, W)
    mask : ndarray of shape (N, H, W)
    dictionary : ndarray of shape (N * 49, K), optional
        Required for ``omp``; ignored otherwise.  Atoms of any nonzero norm
        give the same answer: it goes through
        :func:`~codedvideo.solvers.dictionaries.prepare_dictionary` (unit norm, zero
        atoms dropped with a warning, all-zero refused).
    dictionary_name : str
        Names the dictionary in those messages (e.g. its path).
    dictionary_key, settings, run
        Passed to :func:`~codedvideo.engine.windows.reconstruct_volume` (``settings``
        an :class:`~codedvideo.solvers.region.OmpSettings`, default settings when None; ``run`` an
        :class:`~codedvideo.engine.windows.Execution`, without a progress bar unless it says so).

    Returns
    -------
    volume : ndarray of shape (N, H, W), float32
    info : dict
        ``method``, ``patches``, ``patches_per_second``, ``seconds``
        (``reconstruct``: wall time) and ``measurement_residual_rms``;
        for ``omp``/``dct`` everything :func:`reconstruct_volume` reports.
    """
    physics.check_pair(np.shape(coded), np.shape(mask))
    if methods.method(method).sparse:
        used, atoms, key = sparse_method(method, settings or OmpSettings(), dictionary, dictionary_key,
                                         dictionary_name, frames=mask.shape[0])
        volume, info = reconstruct_volume(coded, mask, atoms, settings=used, run=run, dictionary_key=key)
        return volume, dict(info, method=method, dictionary_atoms=int(atoms.shape[1]))
    solve = methods.solver(method)
    t0 = time.perf_counter()
    volume = solve(coded, mask)
    seconds = time.perf_counter() - t0
    residual = physics.forward(volume, mask) - np.asarray(coded, np.float32)
    info = dict(method=method, patches=0, patches_per_second=0.0, seconds=dict(reconstruct=seconds),
                measurement_residual_rms=float(np.sqrt(np.mean(residual.astype(np.float64) ** 2))))
    return volume, info


def result_recipe(method: str, *, adapt: bool = False, adapt_rounds: int = 1, refine: int = 0) -> dict:
    """What a method's result depends on beside its inputs, its OMP settings and its dictionary: the version of
    the sparse code's solver (or a baseline's source and defaults), the adaptation's and the refinement's
    settings.  A record of a result is keyed by it, so that a changed recipe is computed again; the adaptation
    and the refinement appear only when used (and a second round only when asked), so that the keys of results
    without them stand."""
    import inspect

    from codedvideo.engine.adaptation import ADAPT_ITERATIONS, ADAPT_SAMPLES, ADAPT_SPARSITY, KEEP_UNUSED
    from codedvideo.engine.cache import RECON_VERSION
    from codedvideo.solvers import baselines

    entry = methods.method(method)
    if entry.sparse:
        recipe: dict = dict(version=RECON_VERSION, windows=temporal.recipe(), still_regions=stillness.recipe())
        if adapt:
            recipe["adapt"] = dict(samples=ADAPT_SAMPLES, iterations=ADAPT_ITERATIONS, sparsity=ADAPT_SPARSITY,
                                   unused=KEEP_UNUSED,
                                   **(dict(survey_step=ADAPT_SURVEY_STEP, refine_step=ADAPT_REFINE_STEP)
                                      if method == "nonlocal" else {}))
            if adapt_rounds != 1:
                recipe["adapt"].update(rounds=adapt_rounds, last_step=ADAPT_LAST_STEP)
    else:
        fn = methods.solver(method)
        recipe = dict(version=content_key(inspect.getsource(baselines)),
                      defaults={k: v.default for k, v in inspect.signature(fn).parameters.items()
                                if v.default is not inspect.Parameter.empty})
    if refine:
        recipe["refine"] = dict(refinement.recipe(), iterations=refine)
    return recipe
