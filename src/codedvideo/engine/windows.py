"""Sparse-coding captures over tiles, as one job in windows of captures: :func:`sparse_volumes`.

A job's captures are planned a capture at a time into plain data (:func:`plan_capture`: its inputs,
dictionary, tiles, or how it is done without tiles), then into windows (:class:`_Planner`: each capture's
working store locked and made, its tiles planned, a window's tiles one graph handed to the workers), and the
windows' volumes are read back, finished and yielded in order (:func:`_window_volumes`).
"""

from __future__ import annotations

import contextlib
import dataclasses
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from codedvideo.model import doors
from codedvideo.engine.cache import RECON_VERSION, CacheBudget, cache_room_problem, content_key, recon_entry, recon_key
from codedvideo.engine.config import DEFAULT_CACHE, DEFAULT_TILE
from codedvideo.engine.locks import Busy, EntryLocks
from codedvideo.engine.parallel import GraphRunner, build_graph, plan_store, plan_tiles, store_volume
from codedvideo.formats.store import WorkStore
from codedvideo.model import patches as P
from codedvideo.model import physics
from codedvideo.model.errors import InputError
from codedvideo.model.patches import PATCH
from codedvideo.solvers.region import STAT_NAMES, OmpSettings


#: A job's captures are planned and computed in windows of at least this many tiles (a graph each, run back to
#: back on the same workers: :class:`codedvideo.engine.parallel.GraphRunner`).  A long stream's first tiles start once one
#: window is planned (not all of its captures), the next window is planned while one runs, and what the plans and
#: the graph hold, and the cache locks kept, do not grow with its length.  Equal tiles are shared within a window.
WINDOW_TILES = 64


@dataclasses.dataclass(frozen=True)
class Execution:
    """Where and how a job's sparse coding runs: its tiles, its cache folder, its dask scheduler and its progress.

    Attributes
    ----------
    tile : int
        Tile side in pixels (the unit of the graph and of the working store).
    cache : str or Path
        The cache folder holding the working stores (``recon-KEY.zarr``).
    scheduler : str, optional
        A dask.distributed address, or ``"threads"`` / ``"sync"`` (None: the local threads).
    workers : int, optional
        Local worker threads (None: every core).
    progress : bool
        Show a progress bar.
    desc : str
        The progress bar's label.
    """

    tile: int = DEFAULT_TILE
    cache: str | Path = DEFAULT_CACHE
    scheduler: str | None = None
    workers: int | None = None
    progress: bool = True
    desc: str = "reconstruct"


@dataclasses.dataclass
class _Window:
    """Captures ``start ..`` of a job, planned: per capture how it is done (None: the caller's, "static", or the
    ``(window, store index)`` whose volume is its own), and the stores it made, with their plans and dictionaries."""

    start: int
    how: list = dataclasses.field(default_factory=list)
    stores: list = dataclasses.field(default_factory=list)
    plans: list = dataclasses.field(default_factory=list)
    dictionaries: list = dataclasses.field(default_factory=list)
    keys: list = dataclasses.field(default_factory=list)
    seconds_plan: list = dataclasses.field(default_factory=list)
    tile_tasks: int = 0
    graph: int = -1


@dataclasses.dataclass(frozen=True, eq=False)
class CapturePlan:
    """How capture ``index`` of a job is done, as plain data (:func:`plan_capture`): nothing locked or made yet.

    ``kind``: None (not sparse-coded: the caller's), ``"static"`` (one shutter pattern for all pixels: the static
    estimate, without tiles) or ``"sparse"`` (its ``tiles`` solved in a working store, from its inputs ``coded``,
    ``mask``, ``still`` with ``dictionary`` keyed ``dictionary_key``, matched on the working store ``first``)."""

    index: int
    kind: str | None
    never_open: int = 0
    coded: np.ndarray | None = None
    mask: np.ndarray | None = None
    still: np.ndarray | None = None
    dictionary: np.ndarray | None = None
    dictionary_key: str = ""
    first: str | None = None
    tiles: int = 0


def plan_capture(i: int, inputs, D, dictionary_key: str, *, tile: int, first_of=None) -> CapturePlan:
    """Capture ``i`` planned: ``inputs`` is ``capture(i)`` of :func:`sparse_volumes` (``(coded, mask, still)`` or
    None), ``D`` and ``dictionary_key`` the job's dictionary and its key, or ``D`` a callable giving capture
    ``i``'s own; ``first_of`` as there.  Raises :class:`InputError` for a capture that cannot be sparse-coded."""
    if inputs is None:
        return CapturePlan(i, None)
    coded, mask, still = inputs
    Di, dkey = D(i) if callable(D) else (D, dictionary_key)
    never_open = check_capture(coded, mask, Di)
    if (mask == mask[:, :1, :1]).all():  # one shutter pattern for all pixels: no temporal information
        return CapturePlan(i, "static", never_open)
    first = first_of(i) if first_of is not None else None
    return CapturePlan(i, "sparse", never_open, coded, mask, still, Di, dkey or content_key(Di), first,
                       len(plan_tiles(coded.shape, tile, patch=PATCH)))


class _Planner:
    """A job's captures planned into windows, in order: each capture's plan (:func:`plan_capture`) taken into the
    window -- the working stores it reads locked, its own made (or shared with an earlier capture of a window not
    yet done), its tiles planned -- and each window's tiles handed to the workers as one graph."""

    def __init__(self, count: int, capture, D, dictionary_key: str, *, settings: OmpSettings, tile: int, cache,
                 first_of):
        self.count, self.capture, self.D, self.per_capture = count, capture, D, callable(D)
        self.dictionary_key = "" if self.per_capture else dictionary_key or content_key(D)
        self.settings, self.tile, self.cache, self.first_of = settings, tile, cache, first_of
        self.locks = EntryLocks(cache)
        self.live: dict[str, tuple[_Window, int]] = {}  # key -> the window and store of a capture planned, not done
        self.unopened: list[int] = []  # never-open pixels of each capture that has some: one warning for the job
        self.position = 0  # the next capture to plan

    def take(self, plan: CapturePlan, window: _Window) -> int:
        """Capture ``plan`` into ``window``: how it is done (None: the caller's; "static"; or a store, locked, with
        its tiles planned -- a store that an earlier capture of a window not yet done has is shared); its tiles."""
        if plan.kind != "sparse":
            self.unopened.extend([plan.never_open] if plan.never_open else [])
            window.how.append(plan.kind)
            return 0
        if plan.first is not None:  # kept as it is while its result is read
            self.locks.take(Path(plan.first), window)
        key = recon_key(plan.coded, plan.mask, plan.dictionary_key, self.settings, self.tile, still=plan.still,
                        first_key=None if plan.first is None else WorkStore.opened(plan.first).key)
        entry = recon_entry(self.cache, key)
        # One run at a time per entry (processes, threads, clients of one dask cluster): a second run waits
        # for it (once this job holds no other entry), then reuses the tiles the first one finished.
        self.locks.take(entry, window)
        self.unopened.extend([plan.never_open] if plan.never_open else [])
        if key not in self.live:
            store = WorkStore.create(
                entry, plan.coded, plan.mask, tile=self.tile, n_stats=len(STAT_NAMES), n_tiles=plan.tiles,
                attrs=dict(key=key, settings=self.settings.__dict__, tile=self.tile, version=RECON_VERSION),
                still=plan.still)
            # its tiles planned from the inputs in hand (not read back from the store)
            window.stores.append(store)
            window.plans.append(plan_store(store, plan.coded, plan.mask, plan.still, self.settings, tile=self.tile,
                                           patch=PATCH, first=plan.first))
            window.dictionaries.append(plan.dictionary)
            self.live[key] = window, len(window.stores) - 1
            window.keys.append(key)
        window.how.append(self.live[key])
        return plan.tiles

    def next_window(self, runner: GraphRunner) -> _Window | None:
        """The next captures, planned until they hold :data:`WINDOW_TILES` tiles (at least one capture), their
        graph offered to ``runner``; None when every capture is planned, or when the first is busy."""
        if self.position >= self.count:
            return None
        window, tiles = _Window(start=self.position), 0
        while self.position < self.count and (tiles < WINDOW_TILES or not window.how):
            t0 = time.perf_counter()
            i = self.position
            try:
                tiles += max(1, self.take(plan_capture(i, self.capture(i), self.D, self.dictionary_key,
                                                       tile=self.tile, first_of=self.first_of), window))
            except Busy:  # another run holds its entry: planned once this job holds none (the window ends here)
                if not window.how:
                    self.locks.release(window)
                    return None
                break
            window.seconds_plan.append(time.perf_counter() - t0)
            self.position += 1
        if self.position >= self.count and self.unopened:
            unopened, count = self.unopened, self.count
            where = "" if count == 1 else (f" in {len(unopened)} of {count} captures ({min(unopened)} to "
                                           f"{max(unopened)} each)")
            doors.warn(f"{sum(unopened)} pixels are never open{where} (or were left out as saturated or defective); "
                          "they are filled from their neighbours")
        tasks, needs = build_graph([plan.work for plan in window.plans],
                                   window.dictionaries if self.per_capture else self.D, self.settings, patch=PATCH)
        window.tile_tasks = len(tasks)
        window.graph = runner.offer(tasks, needs, share=len(window.how) / self.count)
        return window

    def done(self, window: _Window, runner: GraphRunner, budget: CacheBudget | None) -> None:
        """``window``'s captures yielded: its stores let go (later captures with the same inputs lock them
        afresh), its graph forgotten, and the budget told."""
        for key in window.keys:
            del self.live[key]
        self.locks.release(window)
        runner.forget(window.graph)
        if budget is not None:
            budget.finished((store.path for store in window.stores), busy=self.locks.held)


def _window_volumes(window: _Window, capture, runner: GraphRunner, settings: OmpSettings, *, scheduler, workers):
    """The volumes of ``window``'s captures, in order, each once its tiles are solved: ``(i, volume, info)``, or
    ``(i, None, None)`` for a capture that is the caller's."""
    t_wait = time.perf_counter()
    for k, how in enumerate(window.how):
        i = window.start + k
        if how is None:
            yield i, None, None
            continue
        coded, mask, _ = capture(i)
        if how == "static":
            yield i, *static_volume(coded, mask)
            continue
        owner, j = how
        runner.wait(owner.graph, j)
        t_solved = time.perf_counter()
        volume, summary = store_volume(owner.stores[j], owner.plans[j], owner.dictionaries[j], settings,
                                       patch=PATCH, scheduler=scheduler, workers=workers)
        summary["tile_tasks"] = owner.tile_tasks
        volume, info = _finish_sparse(volume, summary, coded, mask, settings, owner.stores[j].path)
        info["seconds"] = dict(store_inputs=window.seconds_plan[k], reconstruct=t_solved - t_wait,
                               assemble=time.perf_counter() - t_solved)
        del coded, mask
        # handed over from a list emptied as it is yielded: this frame holds no reference while the
        # consumer works on it (a 4K N = 18 volume is 600 MB; a join held it twice)
        handed = [(i, volume, info)]
        del volume
        yield handed.pop()
        t_wait = time.perf_counter()


def sparse_volumes(
    count: int,
    capture,
    D: np.ndarray,
    *,
    settings: OmpSettings,
    run: Execution = Execution(),
    dictionary_key: str = "",
    first_of=None,
    budget: CacheBudget | None = None,
) -> Iterator[tuple[int, np.ndarray | None, dict | None]]:
    """Sparse-code ``count`` captures as one job, in windows of captures; yield the volumes in order.

    The captures are planned (locked, their working stores made, their tiles
    keyed) a window at a time (:data:`WINDOW_TILES`), each window's tiles one
    graph over (capture, tile) in which equal tiles are solved once; the
    graphs run back to back on the same workers (:class:`GraphRunner`), the
    next window planned while one runs.

    Parameters
    ----------
    count : int
        T, the number of captures.
    capture : callable
        ``capture(i)`` -> ``(coded (H, W), mask (N, H, W), still)`` in
        working units, ``still`` an (H, W) bool map of pixels known to be
        still (their wholly still patches take the still answer,
        :func:`codedvideo.solvers.region.reconstruct_region`) or None; or None
        for a capture that is not sparse-coded (yielded as ``(i, None,
        None)`` for the caller to fill in).  It is called twice
        per capture (to plan, then to finish), so that no more than one
        capture's inputs are held at a time.
    D : ndarray of shape (N * 49, K), or a callable ``D(i)`` giving capture ``i``'s own
        dictionary and its cache key (a dictionary adapted to each capture,
        :func:`codedvideo.engine.adaptation.adapt_dictionary`; an empty key: keyed by its contents)
    settings : OmpSettings
        The sparse code's settings, in working units.
    run : Execution
        The tiles, cache folder, scheduler and progress bar of the job.
    dictionary_key : str
        ``D``'s cache key (empty: keyed by its contents).
    first_of : callable, optional
        The non-local method: ``first_of(i)`` -> the working store of an earlier
        job on capture ``i`` (same tiles) whose result is the first estimate its
        groups are matched on and solved from, in place of the default's tiles
        (``--adapt``'s second pass), or None.  That store is locked while the capture is done, too.
    budget : CacheBudget, optional
        Told of each window's stores once the window is done, and keeps the
        cache's working stores within its bytes (the least recently used removed).

    Yields
    ------
    i : int
    volume : ndarray of shape (N, H, W), float32
    info : dict
        The statistics of :func:`reconstruct_volume`; where the non-local method brought its tiles to the
        measurement, also ``misfit_taken``, the (H, W) map of the misfit that this took away
        (:func:`codedvideo.engine.parallel.store_volume`), for the caller to pop.

    Each capture's working store is the cache entry ``cache/recon-KEY.zarr``,
    shared by every run with the same inputs and settings (equal captures of
    one job share it too): runs on one entry take its lock in turn (a second
    run waits, then reuses the finished tiles); an entry whose metadata or
    inputs are damaged is rebuilt, and a tile that fails its checksum when
    read back is computed again, never returned (``tiles_damaged``).  When
    every pixel has the same shutter pattern (open in every sub-frame: bump
    length N, the global shutter, N = 1; or a global flutter sequence) no
    pixel tells one instant from another, so per-patch sparse coding can only
    invent motion (docs/sampling.md, "Sampling schemes and sensor model"):
    that capture's result is the static estimate ``coded / open
    count`` itself (``method: "static"``), computed without tiles.
    """
    planner = _Planner(count, capture, D, dictionary_key, settings=settings, tile=run.tile, cache=run.cache,
                       first_of=first_of)
    with contextlib.closing(planner.locks), GraphRunner(scheduler=run.scheduler, workers=run.workers,
                                                        progress=run.progress, desc=run.desc) as runner:
        # (holding nothing: it waits for a busy entry)
        windows = [w for w in (planner.next_window(runner),) if w is not None]
        while windows:
            window = windows[0]
            if len(windows) == 1:  # the next window planned (and handed to the workers) while this one runs
                following = planner.next_window(runner)
                if following is not None:
                    windows.append(following)
            yield from _window_volumes(window, capture, runner, settings, scheduler=run.scheduler,
                                       workers=run.workers)
            windows.pop(0)
            planner.done(window, runner, budget)
            if not windows and planner.position < count:  # the next window put off (an entry busy): nothing is held now
                windows.append(planner.next_window(runner))



def reconstruct_volume(
    coded: np.ndarray,
    mask: np.ndarray,
    D: np.ndarray,
    *,
    settings: OmpSettings,
    run: Execution = Execution(),
    dictionary_key: str = "",
) -> tuple[np.ndarray, dict]:
    """Reconstruct one coded image (working units) through the Zarr working store and the dask graph.

    A job of one capture (:func:`sparse_volumes`).  Returns the volume
    (N, H, W) float32 and a dict of statistics and timings.  Patches that
    stopped early because their next atom was numerically dependent on the
    chosen ones are counted (``dependent_stops``) and reported by a warning.
    """
    coded32 = np.asarray(coded, np.float32)
    results = sparse_volumes(1, lambda i: (coded32, mask, None), D, settings=settings, run=run,
                             dictionary_key=dictionary_key)
    with contextlib.closing(results):
        _, volume, info = next(results)
    info.pop("misfit_taken", None)  # (for the still regions of a job of captures)
    return volume, info


def cache_room(cache, count: int, shape: tuple[int, int, int], *, tile: int, budget: int | None,
               adapt: bool = False, adapt_rounds: int = 1) -> str | None:
    """Why the disk under ``cache`` may not hold the working stores of a job of ``count`` captures of
    ``shape`` (N, H, W) (None: it may; :func:`codedvideo.engine.cache.cache_room_problem`).  With ``adapt`` a
    capture makes one more a round; with a budget the job holds at most three windows' stores beside it."""
    n, h, w = shape
    window = -(-WINDOW_TILES // len(plan_tiles((h, w), tile, patch=PATCH)))  # captures a window
    return cache_room_problem(cache, count * (1 + adapt_rounds if adapt else 1), n, h, w, budget, in_use=3 * window)


def check_capture(coded: np.ndarray, mask: np.ndarray, D: np.ndarray) -> int:
    """Raise :class:`InputError` when a capture cannot be sparse-coded; return its count of never-open pixels."""
    physics.check_pair(coded.shape, mask.shape)
    n, h, w = mask.shape
    if D.shape[0] != n * PATCH * PATCH:
        raise InputError(f"dictionary has {D.shape[0]} rows, the mask needs N*49 = {n * PATCH * PATCH} (N = {n})")
    if h < PATCH or w < PATCH:
        raise InputError(f"coded image {h}x{w} is smaller than one {PATCH}x{PATCH} patch")
    never_open = int((~mask.astype(bool).any(0)).sum())
    if never_open == h * w:
        raise InputError("mask: no pixel is ever open; there is nothing to reconstruct")
    return never_open


def static_volume(coded: np.ndarray, mask: np.ndarray) -> tuple[np.ndarray, dict]:
    """The static estimate (a mask with one pattern for all pixels, or a capture in which nothing moves),
    pixels never open (or left out as saturated) filled from the nearest open one, with the statistics of
    :func:`reconstruct_volume`."""
    t0 = time.perf_counter()
    volume = physics.static_estimate(coded, mask)
    holes = ~(np.asarray(mask) > 0).any(0)
    if holes.any() and not holes.all():  # no measurement: the nearest measured pixel's still value
        _fill_nearest(volume, holes)
    residual = physics.forward(volume, mask) - np.asarray(coded, np.float32)
    seconds = time.perf_counter() - t0
    info = dict(
        {name: 0.0 for name in STAT_NAMES},
        tiles=0, tiles_computed=0, tiles_reused=0, never_open_pixels=int(holes.sum()),
        filled_pixels=int(holes.sum()) * (not holes.all()), atoms_mean=0.0,
        static_fraction=1.0, patches_per_second=0.0,
        measurement_residual_rms=float(np.sqrt(np.mean(residual.astype(np.float64) ** 2))),
        work_store=None, seconds=dict(store_inputs=0.0, reconstruct=seconds, assemble=0.0), method="static",
    )
    return volume, info


def _fill_nearest(volume: np.ndarray, holes: np.ndarray) -> None:
    """Every frame's pixels at ``holes`` (H, W) take the value of the nearest pixel that is not one, in place."""
    from scipy import ndimage  # lazy: holes are rare

    _, (iy, ix) = ndimage.distance_transform_edt(holes, return_indices=True)
    volume[:, holes] = volume[:, iy[holes], ix[holes]]


def _finish_sparse(volume: np.ndarray, summary: dict, coded: np.ndarray, mask: np.ndarray, settings: OmpSettings,
                   store_path) -> tuple[np.ndarray, dict]:
    """A capture's solved tiles -> its volume: pixels no patch covers filled from the nearest; the statistics."""
    if summary.get("dependent_stops"):
        doors.warn(f"{int(summary['dependent_stops'])} of {int(summary['patches'])} patches stopped early: their "
                      "next atom was numerically dependent on the chosen ones (near-duplicate or degenerate "
                      "dictionary atoms)")
    holes = P.uncovered_pixels(mask.astype(bool).any(0), PATCH, settings.stride)
    for frame in volume:  # one frame at a time: no copy of the whole volume
        if not np.isfinite(frame[~holes]).all():
            raise RuntimeError(f"working store {store_path}: volume has unwritten or non-finite pixels")
    if holes.any():  # no measured patch covers them: the nearest reconstructed pixel
        _fill_nearest(volume, holes)
    residual = physics.forward(volume, mask) - coded
    never_open = int((~mask.astype(bool).any(0)).sum())
    info = dict(
        summary,
        never_open_pixels=never_open,
        filled_pixels=int(holes.sum()),
        atoms_mean=summary["atoms_total"] / max(summary["patches"] - summary["patches_static"], 1),
        static_fraction=summary["patches_static"] / max(summary["patches"], 1),
        patches_per_second=summary["patches_computed"] / max(summary["seconds_total"], 1e-9),
        measurement_residual_rms=float(np.sqrt(np.mean(residual.astype(np.float64) ** 2))),
        work_store=str(store_path),
        method="sparse",
    )
    return volume, info
