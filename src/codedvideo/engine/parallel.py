"""Dask wiring: the tile plan, the task graph and its executors.

This is the only module that imports dask.  The plan is plain data
(:func:`plan_tiles`); the graph of a window of a job's captures is one
``dask.delayed`` task per distinct tile content over their working stores
(:func:`build_graph`), and the same graph runs on the local threaded scheduler
(default: both cores), the synchronous scheduler (tests, debugging) or a
dask.distributed scheduler given by address (a cluster started by hand, or by
dask-jobqueue on Slurm/PBS).  A job's windows run one after another as one
stream of work while the caller takes the captures in order as each is
complete (:class:`GraphRunner`).

A tile task reads its region *with a halo of* ``patch - 1`` pixels from the Zarr
working store, reconstructs it, keeps the core (whose pixels then see exactly
the patches they see in the whole image) and writes the core and a statistics
row back to the store (to every store with a tile of equal content).  Tiles are
the store's chunks, so concurrent tasks never write the same chunk, and a rerun
skips the tiles whose digests check out.  The non-local method's final tile
tasks stand on two stages of their own (:func:`_nonlocal_tasks`).
"""

from __future__ import annotations

import contextlib
import hashlib
import logging
import os
import queue
import sys
import threading
import time
import uuid
from concurrent.futures import ThreadPoolExecutor
from collections.abc import Iterator
from dataclasses import dataclass

import dask
import dask.local
import dask.threaded
import numpy as np
from dask.highlevelgraph import HighLevelGraph

from codedvideo.model import physics
from codedvideo.model.errors import CodedVideoError, SchedulerError
from codedvideo.solvers.region import STAT_NAMES, OmpSettings, Placement, reconstruct_region, tile_halo
from codedvideo.formats.store import WorkStore, write_tiles
from codedvideo.model.patches import PATCH

log = logging.getLogger("codedvideo")

#: The local pool: dask's, which carries the submitting thread's context variables into its threads (dask 2025
#: and later); before it, the standard pool (the same on the Pythons whose warnings do not live in contextvars).
THREAD_POOL = getattr(dask.threaded, "ContextAwareThreadPoolExecutor", ThreadPoolExecutor)

#: Rounds of computing the tiles that fail their check before giving up.
MAX_ATTEMPTS = 3


@dataclass(frozen=True)
class Tile:
    """One tile of the plan: its index, its core and its halo region (y0, y1, x0, x1)."""

    index: int
    core: tuple[int, int, int, int]
    halo: tuple[int, int, int, int]


def plan_tiles(shape: tuple[int, int], tile: int, *, patch: int = PATCH, halo: int | None = None) -> list[Tile]:
    """Cut an image into ``tile x tile`` cores (the last ones smaller) with halos.

    The halo is ``patch - 1`` pixels on every side (or ``halo``:
    :func:`codedvideo.solvers.region.tile_halo`), clipped at the image border, so
    every patch that covers a core pixel lies inside the tile's halo region.
    """
    h, w = shape
    if tile < 1:
        raise ValueError(f"tile size must be >= 1, got {tile}")
    reach = patch - 1 if halo is None else halo
    tiles = []
    for y0 in range(0, h, tile):
        for x0 in range(0, w, tile):
            y1, x1 = min(y0 + tile, h), min(x0 + tile, w)
            region = (max(0, y0 - reach), min(h, y1 + reach), max(0, x0 - reach), min(w, x1 + reach))
            tiles.append(Tile(len(tiles), (y0, y1, x0, x1), region))
    return tiles


_WORKER_LIMITED = False


def _one_blas_thread_in_worker() -> None:
    """In a dask.distributed worker process, limit BLAS to one thread for the process's life.

    Each task is one core, and the same single-threaded kernels give the same bits
    everywhere.  Local runs are limited (and restored) around the whole graph by
    :func:`stream_graph`; a per-task context would race between concurrent tasks, since
    the limit is process-wide.
    """
    global _WORKER_LIMITED
    if _WORKER_LIMITED:
        return
    if "distributed" not in sys.modules:  # a local run never imports it (0.5 s of start-up)
        return
    try:
        from distributed import get_worker

        get_worker()
    except (ImportError, ValueError):
        return  # not inside a distributed worker
    from threadpoolctl import threadpool_limits

    threadpool_limits(limits=1, user_api="blas")
    _WORKER_LIMITED = True


def _estimate(store_path: str, tile: Tile, D: np.ndarray, settings: OmpSettings, patch: int
              ) -> tuple[np.ndarray, np.ndarray]:
    """The per-patch estimate of a tile's core from the store's inputs over its halo region: (volume, stats)."""
    hy0, hy1, hx0, hx1 = tile.halo
    y0, y1, x0, x1 = tile.core
    store = WorkStore.opened(store_path)
    coded, mask, still = store.read_inputs(hy0, hy1, hx0, hx1)
    _one_blas_thread_in_worker()
    try:
        volume, stats = reconstruct_region(coded, mask, D, settings, patch=patch,
                                           place=Placement((hy0, hx0), store.array("coded").shape),
                                           still=still.astype(bool))
    except Exception as exc:  # name the tile, keep the cause
        raise RuntimeError(f"tile {tile.index} (rows {y0}:{y1}, cols {x0}:{x1}) of {store_path}: {exc}") from exc
    return volume[:, y0 - hy0 : y1 - hy0, x0 - hx0 : x1 - hx0], stats


def _tile_task(places: tuple, D: np.ndarray, settings: OmpSettings, patch: int) -> np.ndarray:
    """Solve one tile's content and write its core into every working store that has a tile of that content.

    ``places`` are ``(store_path, Tile)`` pairs whose halo inputs are equal bit
    for bit (:func:`tile_content`): the first is read and solved, the core is
    written to each.
    """
    core, stats = _estimate(*places[0], D, settings, patch)
    write_tiles([(WorkStore.opened(path), tile.index, tile.core) for path, tile in places], core, stats)
    return stats


# -- the non-local method: three stages ---------------------------------------------------------------
#
# A group's members land up to ``window`` pixels from its reference and cover ``patch - 1`` more, so a
# tile that solved every group reaching its core would solve the groups near its edges again for its
# neighbours (1.3 to 1.9 times the work) and its own first estimate over a 24-pixel halo (1.3 to 1.9
# times the default's).  Instead: (1) the default's tiles give the first estimate; (2) blocks of half a
# tile each solve the groups of the references whose corners they hold, from the first estimate around
# them, and return the summed estimates and weights; (3) each tile adds the sums of the blocks that
# reach it (in block order: deterministic), divides, projects onto its measurements (when they are exact: no
# read noise; the misfit the projection took away is kept beside it), and is written.


#: Key prefixes of the stage tasks (counted by the progress bar beside the tiles).
STAGE_PREFIXES = ("first-", "groups-")


def _first_task(store_path: str, tile: Tile, D: np.ndarray, settings: OmpSettings, patch: int) -> tuple:
    """Stage 1: a tile's first estimate (the default's), its core and statistics."""
    volume, stats = _estimate(store_path, tile, D, settings, patch)
    return tile.core, volume.copy(), stats  # a copy: the halo around the core is not kept while blocks use it


def _stored_first_task(first_path: str, tile: Tile) -> tuple:
    """Stage 1 from another job's result: the core of the same tile in the working store ``first_path`` (a
    first pass of ``--adapt``), checked against its digest, as the first estimate; its counts are that tile's,
    its seconds this read's (the first pass's are counted by its own job)."""
    t0 = time.perf_counter()
    volume, stats = WorkStore.opened(first_path).read_tile(tile.index, tile.core)
    stats = np.where([name.startswith("seconds") for name in STAT_NAMES], 0.0, stats)
    stats[STAT_NAMES.index("seconds_total")] = time.perf_counter() - t0
    return tile.core, volume, stats


def _paste(region: tuple[int, int, int, int], box: tuple[int, int, int, int], values: np.ndarray, out: np.ndarray,
           add: bool = False) -> None:
    """Put (or add) ``values``, which cover ``box``, into ``out``, which covers ``region``, where they meet."""
    ry0, ry1, rx0, rx1 = region
    by0, by1, bx0, bx1 = box
    y0, y1, x0, x1 = max(ry0, by0), min(ry1, by1), max(rx0, bx0), min(rx1, bx1)
    if y0 >= y1 or x0 >= x1:
        return
    src = values[..., y0 - by0 : y1 - by0, x0 - bx0 : x1 - bx0]
    dst = (Ellipsis, slice(y0 - ry0, y1 - ry0), slice(x0 - rx0, x1 - rx0))
    if add:
        out[dst] += src
    else:
        out[dst] = src


def _groups_task(store_path: str, block: Tile, firsts: list, D: np.ndarray, settings: OmpSettings, patch: int):
    """Stage 2: the groups of the references whose corners lie in ``block.core``, solved over
    ``block.halo`` (what their candidates cover): (region, summed, weight, seconds), or None where the
    code's patterns do not fit a table (the tile then keeps its first estimate)."""
    from codedvideo.solvers.nonlocal_sc import NonlocalOptions, nonlocal_region

    t0 = time.perf_counter()
    ey0, ey1, ex0, ex1 = region = block.halo
    by0, by1, bx0, bx1 = block.core
    store = WorkStore.opened(store_path)
    coded, mask, still = store.read_inputs(ey0, ey1, ex0, ex1)
    first = np.full((mask.shape[0], ey1 - ey0, ex1 - ex0), np.nan, np.float32)
    for core, volume, _ in firsts:
        _paste(region, core, volume, first)
    try:
        place = NonlocalOptions(patch=patch, origin=(ey0, ex0), image_shape=store.array("coded").shape, sums=True,
                                refs=(by0 - ey0, by1 - ey0, bx0 - ex0, bx1 - ex0))
        out = nonlocal_region(coded, mask, D, first, settings, place, still=still.astype(bool))
    except Exception as exc:
        raise RuntimeError(f"block rows {by0}:{by1}, cols {bx0}:{bx1} of {store_path}: {exc}") from exc
    if out is None:
        return None
    summed, weight, _ = out
    return region, summed, weight[None], time.perf_counter() - t0


def _combine_task(places: tuple, first: tuple, parts: list, owned: list[bool], settings: OmpSettings,
                  patch: int) -> np.ndarray:
    """Stage 3: a tile's core from the sums of the blocks that reach it, projected onto its measurements where
    they are exact (``settings.exact``; the misfit the projection took away written beside it; pixels that only
    wholly still patches cover: the still answer), written to every place; its statistics are the first
    estimate's plus the time of the blocks it owns."""
    from codedvideo.solvers.nonlocal_sc import finish, keep_still, project_measurements

    t0 = time.perf_counter()
    core, volume, stats = first
    stats, misfit = stats.copy(), None
    if all(part is not None for part in parts):
        summed = np.zeros_like(volume)
        weight = np.zeros((1, *volume.shape[1:]), np.float32)
        for region, s, w, _ in parts:
            _paste(core, region, s, summed, add=True)
            _paste(core, region, w, weight, add=True)
        store = WorkStore.opened(places[0][0])
        (h, w), (y0, y1, x0, x1) = store.array("coded").shape, core
        around = (max(0, y0 - patch + 1), min(h, y1 + patch - 1), max(0, x0 - patch + 1), min(w, x1 + patch - 1))
        coded, mask, still = store.read_inputs(*around)  # the core and every patch over it
        inside = (slice(y0 - around[0], y1 - around[0]), slice(x0 - around[2], x1 - around[2]))
        core_coded, core_mask = coded[inside], mask[(slice(None), *inside)]
        volume = finish(summed, weight[0], core_coded, core_mask, project=False, first=volume)
        if settings.exact:  # the misfit the projection takes away is kept: the still regions judge by it
            misfit = core_coded - physics.forward(volume, core_mask)
            volume = project_measurements(volume, core_coded, core_mask)
        keep_still(volume, coded, mask, still.astype(bool), patch, *inside)
    owned_seconds = sum(part[3] for part, mine in zip(parts, owned) if mine and part is not None)
    stats[STAT_NAMES.index("seconds_total")] += owned_seconds + time.perf_counter() - t0
    write_tiles([(WorkStore.opened(path), tile.index, tile.core) for path, tile in places], volume, stats, misfit)
    return stats


def _meeting(boxes: np.ndarray, box: tuple[int, int, int, int]) -> np.ndarray:
    """Indices of the boxes (rows ``y0, y1, x0, x1``) that share a pixel with ``box``."""
    y0, y1, x0, x1 = box
    return np.flatnonzero((boxes[:, 0] < y1) & (y0 < boxes[:, 1]) & (boxes[:, 2] < x1) & (x0 < boxes[:, 3]))


def nonlocal_blocks(shape: tuple[int, int], tile: int, patch: int) -> list[Tile]:
    """The blocks of stage 2 (half a tile each): ``core`` holds their references' corners, ``halo`` is
    the region their groups are solved over (what the references' candidates cover: the search window
    before, the window and a patch after), clipped to the image."""
    from codedvideo.solvers.nonlocal_sc import WINDOW

    (h, w), before, after = shape, WINDOW, WINDOW + patch - 1
    return [Tile(b.index, b.core, (max(0, b.core[0] - before), min(h, b.core[1] + after),
                                   max(0, b.core[2] - before), min(w, b.core[3] + after)))
            for b in plan_tiles(shape, max(tile // 2, patch), patch=patch, halo=0)]


def nonlocal_reach(tile: Tile, blocks: list[Tile], shape: tuple[int, int], patch: int) -> tuple[int, int, int, int]:
    """Every pixel a non-local tile's answer reads: the regions of the blocks that reach its core, with
    the ``patch - 1`` pixels their first estimates read around them, clipped to the image.

    Wider than the tile's halo: a block's sums depend, in their last bits and so in which of two
    equally similar patches joins a group, on all of the block's region (its distances are running sums
    from the region's corner), so two tiles are the same work only when all of this is the same.
    """
    regions = np.array([b.halo for b in blocks])
    regions, m = regions[_meeting(regions, tile.core)], patch - 1
    return (max(0, int(regions[:, 0].min()) - m), min(shape[0], int(regions[:, 1].max()) + m),
            max(0, int(regions[:, 2].min()) - m), min(shape[1], int(regions[:, 3].max()) + m))


def _nonlocal_tasks(places: dict, d_nodes: dict, settings: OmpSettings, patch: int, run: str,
                    first_stores: dict) -> list:
    """The final (stage 3) task of every distinct tile content, with the stages it needs (see above).

    ``places`` maps ``(dictionary token, content)`` to the (store, tile) pairs, ``d_nodes`` a token to its node,
    ``first_stores`` a store to the store whose result is its first estimate (:attr:`TileWork.first`)."""
    first_task = dask.delayed(_first_task, pure=False)
    stored_first_task = dask.delayed(_stored_first_task, pure=False)
    groups_task = dask.delayed(_groups_task, pure=False)
    combine_task = dask.delayed(_combine_task, pure=False)
    firsts: dict = {}  # (store, tile index) -> its stage 1 task
    blocks: dict = {}  # (store, block index) -> its stage 2 task
    grids: dict = {}  # store -> (blocks, the default's tiles, their regions and cores as arrays)
    last = len(places) - 1
    out = []
    for i, ((token, _), where) in enumerate(places.items()):
        D_node = d_nodes[token]
        path, tile = where[0]
        if path not in grids:
            store = WorkStore.opened(path)
            shape, size = store.array("coded").shape, int(store.group.attrs["tile"])
            grid = nonlocal_blocks(shape, size, patch)
            first_tiles = plan_tiles(shape, size, patch=patch)
            grids[path] = (grid, first_tiles, np.array([b.halo for b in grid]), np.array([t.core for t in first_tiles]))
        grid, first_tiles, regions, cores = grids[path]

        def first_of(t: Tile):
            key = (path, t.index)
            if key not in firsts:
                name = f"first-{run}-{last - i:09d}-{t.index}"
                firsts[key] = (first_task(path, t, D_node, settings, patch, dask_key_name=name)
                               if first_stores.get(path) is None else
                               stored_first_task(first_stores[path], t, dask_key_name=name))
            return firsts[key]

        parts, owned = [], []
        for b in (grid[k] for k in _meeting(regions, tile.core)):
            key = (path, b.index)
            if key not in blocks:
                needed = [first_of(first_tiles[k]) for k in _meeting(cores, b.halo)]
                blocks[key] = groups_task(path, b, needed, D_node, settings, patch,
                                          dask_key_name=f"groups-{run}-{last - i:09d}-{b.index}")
            parts.append(blocks[key])
            owned.append(tile.core[0] <= b.core[0] < tile.core[1] and tile.core[2] <= b.core[2] < tile.core[3])
        own_first = first_of(first_tiles[tile.index])
        out.append(combine_task(tuple(where), own_first, parts, owned, settings, patch,
                                dask_key_name=f"tile-{run}-{last - i:09d}"))
    return out


def _still_reach(still: np.ndarray, core: tuple[int, int, int, int], patch: int) -> tuple | None:
    """The core with every patch over it, when all of that is still: the core is then the still answer,
    which these pixels alone decide (:func:`codedvideo.solvers.nonlocal_sc.keep_still`); otherwise None."""
    (h, w), (y0, y1, x0, x1), m = still.shape, core, patch - 1
    box = (max(0, y0 - m), min(h, y1 + m), max(0, x0 - m), min(w, x1 + m))
    return box if still[box[0] : box[1], box[2] : box[3]].all() else None


def tile_content(coded: np.ndarray, mask: np.ndarray, still: np.ndarray, tile: Tile, *, stride: int = 1,
                 reach: tuple[int, int, int, int] | None = None) -> str:
    """A digest of what a tile's answer depends on: its inputs over ``reach`` (default: its halo) and
    where its core lies in that region.

    Two tiles with the same digest have the same answer bit for bit, so one
    is solved and both are written: a still background under a repeating code
    across captures, or flat regions (black borders, sky) inside one.  With a
    patch stride above 1 the patches taken depend on the position in the
    image, which then joins the digest.
    """
    hy0, hy1, hx0, hx1 = tile.halo if reach is None else reach
    y0, y1, x0, x1 = tile.core
    h = hashlib.blake2b(digest_size=16)
    h.update(np.asarray([y0 - hy0, y1 - hy0, x0 - hx0, x1 - hx0, hy1 - hy0, hx1 - hx0], np.int64).tobytes())
    if stride > 1:
        h.update(np.asarray([hy0, hx0, *coded.shape], np.int64).tobytes())
    h.update(np.ascontiguousarray(coded[hy0:hy1, hx0:hx1]).tobytes())
    m = np.ascontiguousarray(mask[:, hy0:hy1, hx0:hx1])
    h.update(m.dtype.str.encode())
    h.update(m.tobytes())
    h.update(np.ascontiguousarray(still[hy0:hy1, hx0:hx1], dtype=np.uint8).tobytes())
    return h.hexdigest()


@dataclass(frozen=True)
class TileWork:
    """The tiles of one working store still to compute, with the digest of each tile's content."""

    store: str
    tiles: tuple[Tile, ...]
    contents: tuple[str, ...]
    #: The non-local method from a finished job's result (``--adapt``'s second pass): the path of the working
    #: store, of the same tiles, whose volume is the first estimate (None: the default's tiles give it).
    first: str | None = None


def build_graph(works: list[TileWork], D: np.ndarray | list[np.ndarray], settings: OmpSettings, *, patch: int = PATCH):
    """One delayed task per distinct tile content over every store, one node per distinct dictionary.

    ``D`` is the dictionary of every store, or a list of one per work (a
    dictionary adapted to each capture): tiles are shared only between stores
    with equal contents and the same dictionary.  Returns ``(tasks, needs)``:
    ``needs[j]`` lists the tasks that store ``j`` waits for.  Task names are
    unique to this graph: a distributed scheduler shared by several runs (or
    by two rounds of one run) never takes one run's tile for another's.
    """
    dictionaries = D if isinstance(D, list) else [D] * len(works)
    d_nodes: dict[str, object] = {}
    token_of: dict[int, str] = {}  # (a job's one dictionary is hashed once)
    tokens = []
    for Dw in dictionaries:
        if id(Dw) not in token_of:
            token_of[id(Dw)] = token = dask.base.tokenize(Dw)
            d_nodes.setdefault(token, dask.delayed(Dw, pure=True, name="dictionary-" + token))
        tokens.append(token_of[id(Dw)])
    task = dask.delayed(_tile_task, pure=False)
    run = uuid.uuid4().hex[:12]
    places: dict[tuple[str, str], list] = {}
    seen = set()  # (store, tile): a store listed twice (equal captures) is written once
    for work, token in zip(works, tokens):
        for tile, content in zip(work.tiles, work.contents):
            if (work.store, tile.index) not in seen:
                seen.add((work.store, tile.index))
                places.setdefault((token, content), []).append((work.store, tile))
    order = {key: i for i, key in enumerate(places)}
    # dask's local scheduler runs sibling tasks in descending order of their names: named so that the first
    # captures' tiles run first and the captures complete in order (the test of streaming checks it)
    last = len(places) - 1
    if settings.method == "nonlocal":
        tasks = _nonlocal_tasks(places, d_nodes, settings, patch, run, {work.store: work.first for work in works})
    else:
        tasks = [task(tuple(where), d_nodes[token], settings, patch, dask_key_name=f"tile-{run}-{last - i:09d}")
                 for i, ((token, _), where) in enumerate(places.items())]
    needs = [sorted({order[token, c] for c in work.contents}) for work, token in zip(works, tokens)]
    return tasks, needs


@contextlib.contextmanager
def _single_threaded_blas(enabled: bool):
    """Limit BLAS to one thread: each dask worker thread is one core."""
    if not enabled:
        yield
        return
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:  # pragma: no cover - threadpoolctl is a dependency
        yield
        return
    with threadpool_limits(limits=1, user_api="blas"):
        yield


class _Cancelled(Exception):
    """The consumer of a streamed graph stopped early: the remaining tasks are not started."""


def progress_bar(total: int, desc: str):
    """A progress bar of ``total`` iterations (K-SVD's, the refinement's), gone when it closes."""
    from tqdm.auto import tqdm

    return tqdm(total=total, desc=desc, unit="it", leave=False)


def _grow_bar(bar, total: int) -> None:
    """Set a progress bar's length, keeping its count and its clock (its rate, hence its ETA)."""
    bar.total = total
    container = getattr(bar, "container", None)  # a notebook's bar: its widget holds the length too
    if container is not None:
        with contextlib.suppress(Exception):
            container.children[1].max = total
    bar.refresh()


class GraphRunner:
    """Runs a job's graphs, one after another, as one stream of work: both cores (or a cluster) busy throughout.

    A long job is planned and computed in windows of captures (a graph each,
    :func:`codedvideo.engine.windows.sparse_volumes`), so that its first tiles start
    after one window is planned, and what the plans hold and the locks kept
    do not grow with its length.  :meth:`offer` hands over the next window's
    graph while the one before it runs: locally it starts as soon as the one
    before it has no more than one task per worker left (the tasks of both
    share one pool of worker threads, so no core waits at a window's end and
    none is oversubscribed); a dask.distributed scheduler takes it at once
    (it runs earlier graphs first).  :meth:`wait` blocks until a group of a
    graph's tasks has finished and raises a task's error.  One progress bar
    with an ETA counts the tasks of the whole job (locally, the stages the
    tiles stand on too: the non-local method's first estimates and blocks);
    its length is estimated from the windows planned so far.

    Parameters
    ----------
    scheduler : None, "threads", "sync" or a dask.distributed address
        None and "threads" run on the local threaded scheduler (one BLAS
        thread per worker thread); "sync" runs in a thread of its own, one
        task at a time; anything else is a scheduler address.
    workers : int, optional
        Local worker threads (default: the number of cores).
    """

    def __init__(self, *, scheduler: str | None = None, workers: int | None = None, progress: bool = True,
                 desc: str = "reconstruct"):
        self.distributed = bool(scheduler) and scheduler not in ("threads", "sync")
        self.scheduler, self.workers = scheduler, workers or os.cpu_count() or 1
        # the next graph starts once no more tasks are left than worker threads (sync: once this one is done)
        self.margin = 0 if scheduler == "sync" else self.workers
        self.progress, self.desc = progress, desc
        self.bar = None  # made with the first task (a job all in the cache shows none)
        self.graphs: list[dict] = []  # per graph: tasks, needs, finished, left, drained, share
        self.events: queue.Queue = queue.Queue()  # (graph, task index | -1 (a stage) | None (the end) | its error)
        self.lock = threading.Lock()
        self.stop = threading.Event()
        self.threads: list[threading.Thread] = []
        self.launched = 0
        self.share = 0.0  # the job's share the graphs offered so far cover
        self.offered = 0  # tasks offered so far (stages included)
        self.forgotten = 0  # tasks of the graphs let go of (:meth:`forget`), all finished
        self.pool = self.client = None
        self.limits = contextlib.ExitStack()
        self.quiet: list = []
        self.counted = 0

    def __enter__(self) -> "GraphRunner":
        if self.distributed:
            try:
                self._open_client()
            except BaseException:
                self.close()  # (the loggers quietened for the client are restored)
                raise
        else:
            self.limits.enter_context(_single_threaded_blas(self.scheduler != "sync"))  # one core per worker thread
            if self.scheduler != "sync":
                self.pool = THREAD_POOL(self.workers)
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        """Cancel what has not started, wait for what runs, and let go of the pool or the client."""
        self.stop.set()
        for thread in self.threads:
            thread.join()
        if self.pool is not None:
            self.pool.shutdown(wait=True)
            self.pool = None
        if self.client is not None:
            with contextlib.suppress(Exception):  # (a scheduler that is gone cancels nothing)
                self.client.cancel([f for g in self.graphs for f in g.get("futures", ()) if not f.done()])
            with contextlib.suppress(Exception):
                self.client.close()
            self.client = None
        for q, level in self.quiet:  # (also when the client could not be made)
            q.setLevel(level)
        self.quiet = []
        self.limits.close()
        if self.bar is not None:
            self.bar.close()

    # -- handing over and waiting --------------------------------------------------------------------
    def offer(self, tasks: list, needs: list[list[int]], share: float = 1.0) -> int:
        """Hand over a graph (``needs[j]``: the tasks that group ``j`` waits for), covering ``share`` of the
        job (its length is estimated from it); returns its number for :meth:`wait`."""
        g = len(self.graphs)
        stages = set()
        if tasks and not self.distributed:
            graph = HighLevelGraph.merge(*(task.__dask_graph__() for task in tasks))
            stages = {k for k in graph.keys() if isinstance(k, str) and k.startswith(STAGE_PREFIXES)}
        self.graphs.append(dict(tasks=tasks, needs=needs, finished=np.zeros(len(tasks), bool),
                                index={task.key: i for i, task in enumerate(tasks)}, stages=stages,
                                left=len(tasks) + len(stages), drained=not tasks))
        self.share = min(1.0, self.share + share)
        self.offered += len(tasks) + len(stages)
        if self.offered and self.bar is None:
            from tqdm.auto import tqdm

            self.bar = tqdm(total=0, desc=self.desc, unit="task", disable=not self.progress, leave=False)
        if self.bar is not None:
            _grow_bar(self.bar, max(self.offered, round(self.offered / self.share)) if self.share > 0 else self.offered)
        if self.distributed:
            self._submit(g)
        else:
            with self.lock:
                self._launch_ready()
        return g

    def forget(self, g: int) -> None:
        """Let go of graph ``g``'s tasks (and a cluster's results) once every group of it has been waited for,
        so that what a long job holds does not grow with its windows; :meth:`wait` on it still answers."""
        graph = self.graphs[g]
        if graph.get("forgotten"):
            return
        graph.update(tasks=[], index={}, stages=set(), forgotten=True)
        futures = graph.pop("futures", None)
        if futures:
            self.forgotten += len(futures)
            with contextlib.suppress(Exception):
                self.client.cancel([f for f in futures if not f.done()])  # (none: every group was waited for)
        self.threads = [t for t in self.threads if t.is_alive()]

    def wait(self, g: int, j: int) -> None:
        """Block until the tasks that group ``j`` of graph ``g`` needs have finished; raise a task's error."""
        graph = self.graphs[g]
        need = graph["needs"][j]
        if self.distributed:
            if not graph.get("forgotten"):  # (a graph let go of was waited for whole)
                self._wait_distributed(graph, need)
            return
        while not graph["finished"][need].all():
            if "error" in graph:  # (a task of this graph failed: what this group needs will not finish)
                raise graph["error"]
            h, i = self.events.get()
            if isinstance(i, BaseException):  # raised by a wait on graph h, not on one before it still running
                self.graphs[h]["error"] = i
                continue
            if i is None:  # graph h ended: all of it is done
                self.graphs[h]["finished"][:] = True
                continue
            if i >= 0:
                self.graphs[h]["finished"][i] = True
            self.bar.update(1)  # (a task finished: the bar was made when it was offered)

    # -- local: dask's threaded scheduler, one pool for all graphs -------------------------------------
    def _launch_ready(self) -> None:
        """Start the next graph when it is offered and the one before it is drained (under the lock)."""
        while self.launched < len(self.graphs) and (self.launched == 0 or self.graphs[self.launched - 1]["drained"]):
            g = self.launched
            self.launched += 1
            if self.graphs[g]["tasks"]:
                thread = threading.Thread(target=self._run, args=(g,), name=f"codedvideo-graph-{g}", daemon=True)
                self.threads.append(thread)
                thread.start()
            if self.graphs[g]["left"] <= self.margin:  # too few tasks to keep the workers busy: the next one too
                self.graphs[g]["drained"] = True

    def _drained(self, g: int) -> None:
        with self.lock:
            if not self.graphs[g]["drained"]:
                self.graphs[g]["drained"] = True
                self._launch_ready()

    def _run(self, g: int) -> None:
        from dask.callbacks import Callback

        graph = self.graphs[g]
        index, stages = graph["index"], graph["stages"]

        def pretask(key, dsk, state):
            if self.stop.is_set():
                raise _Cancelled()

        def posttask(key, result, dsk, state, worker_id):
            if key in index:
                self.events.put((g, index[key]))
            elif key in stages:
                self.events.put((g, -1))  # a stage: the bar moves
            else:
                return
            with self.lock:
                graph["left"] -= 1
                ready = graph["left"] <= self.margin
            if ready:
                self._drained(g)

        try:
            if self.scheduler == "sync":
                dask.compute(*graph["tasks"], scheduler=dask.local.get_sync,
                             callbacks=[Callback(pretask=pretask, posttask=posttask)._callback])
            else:
                # the scheduler as a function: a name would make dask import distributed (0.1 to 0.5 s)
                # to look for a client first
                dask.compute(*graph["tasks"], scheduler=dask.threaded.get, pool=self.pool,
                             callbacks=[Callback(pretask=pretask, posttask=posttask)._callback])
            self.events.put((g, None))
        except BaseException as exc:  # handed to the consumer's wait on this graph
            self.events.put((g, exc))
        finally:
            self._drained(g)  # (a graph that failed lets the next one start; its error waits for the wait on it)

    # -- dask.distributed -------------------------------------------------------------------------------
    _LOST: tuple = ()

    def _open_client(self) -> None:
        import asyncio
        import concurrent.futures

        from distributed import Client
        from distributed.comm.core import CommClosedError

        # (not OSError at large: a task's own error, a full disk on a worker say, is raised as it is)
        self._LOST = (CommClosedError, asyncio.CancelledError, concurrent.futures.CancelledError, ConnectionError)
        # the client's own log of a lost connection is pages of tracebacks: the one line of SchedulerError says it
        names = ["distributed", "tornado", "asyncio"] + [
            name for name in list(logging.root.manager.loggerDict) if name.startswith(("distributed.", "tornado."))]
        self.quiet = [(logging.getLogger(name), logging.getLogger(name).level) for name in names]
        for q, _ in self.quiet:
            q.setLevel(logging.CRITICAL)
        with self._lost_connection():
            self.client = Client(self.scheduler)

    @contextlib.contextmanager
    def _lost_connection(self):
        try:
            yield
        except CodedVideoError:
            raise
        except self._LOST as exc:  # the scheduler went away: the finished tiles are in the cache
            raise SchedulerError(f"scheduler {self.scheduler}: the connection was lost mid-run "
                                 f"({type(exc).__name__}); the tiles finished are kept: run again to resume from "
                                 "the cache") from exc

    def _submit(self, g: int) -> None:
        graph = self.graphs[g]
        with self._lost_connection():
            graph["futures"] = self.client.compute(graph["tasks"]) if graph["tasks"] else []

    def _wait_distributed(self, graph: dict, need: list[int]) -> None:
        from distributed import wait

        futures = graph["futures"]
        with self._lost_connection():
            wait([futures[i] for i in need])
            for i in need:
                futures[i].result()  # raises the task's error
        done = self.forgotten + sum(f.done() for g in self.graphs if not g.get("forgotten")
                                    for f in g.get("futures", ()))
        if self.bar is not None:
            self.bar.update(done - self.counted)
        self.counted = done


def stream_graph(
    tasks: list,
    needs: list[list[int]],
    *,
    scheduler: str | None = None,
    workers: int | None = None,
    progress: bool = True,
    desc: str = "reconstruct",
) -> Iterator[int]:
    """Run one graph and yield ``j = 0, 1, ...`` in order, each as soon as the tasks ``needs[j]`` have finished
    (:class:`GraphRunner` with one graph).  A caller that stops early cancels the tasks not yet started."""
    with GraphRunner(scheduler=scheduler, workers=workers, progress=progress, desc=desc) as runner:
        g = runner.offer(tasks, needs)
        for j in range(len(needs)):
            runner.wait(g, j)
            yield j


@dataclass(frozen=True)
class StorePlan:
    """What one working store needs: all its tiles, those found damaged, and the work left (:class:`TileWork`)."""

    tiles: tuple[Tile, ...]
    damaged: np.ndarray
    work: TileWork


def plan_store(store: WorkStore, coded: np.ndarray, mask: np.ndarray, still: np.ndarray | None,
               settings: OmpSettings, *, tile: int, patch: int = PATCH, first: str | None = None) -> StorePlan:
    """Plan a working store's tiles from its inputs in memory (as :meth:`WorkStore.create` was given them).

    A store made afresh has no tile done; a reused one has each tile that
    claims to be done checked against its digest (a damaged one is logged and
    computed again).  The tiles left are keyed by their content
    (:func:`tile_content`), so that equal tiles of any store are solved once.
    With ``first`` (:attr:`TileWork.first`) a tile's answer also depends on that
    store's result around it, so its content is keyed by that store's key and the tile's place.
    """
    from codedvideo.formats.store import workstore_inputs

    coded_in, mask_in, still_in = workstore_inputs(coded, mask, still)
    tiles = tuple(plan_tiles(tuple(coded_in.shape), tile, patch=patch, halo=tile_halo(settings, patch)))
    if store.created:
        ok = damaged = np.zeros(len(tiles), bool)
    else:
        ok, damaged, *_ = store.read_verified(tiles, assemble=False)
        if damaged.any():
            log.warning("cache entry %s: tiles %s failed their checksum or lost it (damaged); computing them again",
                        store.path, np.flatnonzero(damaged).tolist())
    todo = tuple(t for t in tiles if not ok[t.index])
    stride, reach = settings.stride, [None] * len(todo)
    if settings.method == "nonlocal":  # its reference patches lie on a grid of the image too; its blocks reach far
        from codedvideo.solvers.nonlocal_sc import STEP

        stride = max(stride, settings.group_step or STEP)
        blocks = nonlocal_blocks(tuple(coded_in.shape), tile, patch)
        reach = [_still_reach(still_in, t.core, patch) or nonlocal_reach(t, blocks, tuple(coded_in.shape), patch)
                 for t in todo]
    contents = tuple(tile_content(coded_in, mask_in, still_in, t, stride=stride, reach=r) for t, r in zip(todo, reach))
    if first is not None:
        first_key = WorkStore.opened(first).key
        contents = tuple(f"{c}-{first_key}-{t.index}" for c, t in zip(contents, todo))
    return StorePlan(tiles, damaged, TileWork(str(store.path), todo, contents, first))


def store_volume(store: WorkStore, plan: StorePlan, D: np.ndarray, settings: OmpSettings, *, patch: int = PATCH,
                 scheduler: str | None = None, workers: int | None = None) -> tuple[np.ndarray, dict]:
    """A working store's volume once the tasks of its plan have finished, and its summary.

    Its tiles are read back and checked against their digests; any that fail
    are computed again (up to :data:`MAX_ATTEMPTS` rounds).  The summary holds
    the tiles computed now, reused and found damaged, the summed statistics
    and ``seconds_verify``, the time spent reading tiles back and checking
    them, and, where the non-local method projected its tiles onto the coded
    image, ``misfit_taken``: the (H, W) map of the measurement misfit that
    the projection took away (:func:`_combine_task`; for the still regions,
    :func:`codedvideo.solvers.stillness.still_weight`).  The caller holds the
    store's lock.
    """
    volume, misfit, summary = _verified_volume(store, plan, D, settings, patch=patch, scheduler=scheduler,
                                               workers=workers)
    if misfit.any():
        summary["misfit_taken"] = misfit
    return volume, dict(summary, tiles_damaged=int(plan.damaged.sum()))


def _verified_volume(store: WorkStore, plan: StorePlan, D, settings, *, patch, scheduler,
                     workers) -> tuple[np.ndarray, np.ndarray, dict]:
    """Read every tile of a store back, checked against its digest; compute the ones that fail again (those of
    ``plan``'s work were computed in this run): the volume, its misfit map and the summary."""
    tiles, computed, first = list(plan.tiles), {t.index for t in plan.work.tiles}, plan.work.first
    t0 = time.perf_counter()
    ok, _, volume, stats, misfit = store.read_verified(tiles)
    seconds_verify = time.perf_counter() - t0
    stats = np.where(ok[:, None], stats, np.nan)
    for _ in range(MAX_ATTEMPTS - 1):
        todo = tuple(t for t in tiles if not ok[t.index])
        if not todo:
            break
        log.warning("cache entry %s: tiles %s did not read back as written; computing them again",
                    store.path, [t.index for t in todo])
        work = TileWork(str(store.path), todo, tuple(f"{store.path}:{t.index}" for t in todo), first)
        tasks, needs = build_graph([work], D, settings, patch=patch)
        for _ in stream_graph(tasks, needs, scheduler=scheduler, workers=workers, progress=False):
            pass
        computed.update(t.index for t in todo)
        t0 = time.perf_counter()
        ok_now, _, _, read_stats, _ = store.read_verified(todo, volume, misfit=misfit)
        seconds_verify += time.perf_counter() - t0
        stats[ok_now] = read_stats[ok_now]
        ok |= ok_now
    if not ok.all():
        missing = np.flatnonzero(~ok).tolist()
        raise RuntimeError(f"working store {store.path}: tiles {missing} did not finish or do not read back as "
                           f"written after {MAX_ATTEMPTS} attempts")
    totals = dict(zip(STAT_NAMES, stats.sum(0).tolist()))
    now = np.zeros(len(tiles), bool)
    now[sorted(computed)] = True
    for k, name in enumerate(STAT_NAMES):  # seconds: this run's work only (a tile reused cost nothing now)
        if name.startswith("seconds"):
            totals[name] = float(stats[now, k].sum())
    totals["patches_computed"] = float(stats[now, STAT_NAMES.index("patches")].sum())
    return volume, misfit, dict(tiles=len(tiles), tiles_computed=len(computed),
                                tiles_reused=len(tiles) - len(computed), seconds_verify=seconds_verify, **totals)
