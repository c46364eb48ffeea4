"""Dask wiring: the tile plan, the task graph and its executors.

This is the only module that imports dask.  The plan is plain data
(:func:`plan_tiles`), the graph is one ``dask.delayed`` task per tile, and the
same graph runs on the local threaded scheduler (default: both cores), the
synchronous scheduler (tests, debugging) or a dask.distributed scheduler given
by address (a cluster started by hand, or by dask-jobqueue on Slurm/PBS).

A tile task reads its region *with a halo of* ``patch - 1`` pixels from the Zarr
working store, reconstructs it, keeps the core (whose pixels then see exactly
the patches they see in the whole image) and writes the core and a statistics
row back to the store.  Tiles are the store's chunks, so concurrent tasks never
write the same chunk, and a rerun skips the tiles whose statistics exist.
"""

from __future__ import annotations

import contextlib
import logging
import os
import sys
import time
import uuid
from dataclasses import dataclass

import dask
import numpy as np

from .reconstruct import STAT_NAMES, OmpSettings, reconstruct_region
from .store import WorkStore

log = logging.getLogger("codedvideo")

#: Rounds of computing the tiles that fail their check before giving up.
MAX_ATTEMPTS = 3


@dataclass(frozen=True)
class Tile:
    """One tile of the plan: its index, its core and its halo region (y0, y1, x0, x1)."""

    index: int
    core: tuple[int, int, int, int]
    halo: tuple[int, int, int, int]


def plan_tiles(shape: tuple[int, int], tile: int, *, patch: int = 7) -> list[Tile]:
    """Cut an image into ``tile x tile`` cores (the last ones smaller) with halos.

    The halo is ``patch - 1`` pixels on every side, clipped at the image border,
    so every patch that covers a core pixel lies inside the tile's halo region.
    """
    h, w = shape
    if tile < 1:
        raise ValueError(f"tile size must be >= 1, got {tile}")
    halo = patch - 1
    tiles = []
    for y0 in range(0, h, tile):
        for x0 in range(0, w, tile):
            y1, x1 = min(y0 + tile, h), min(x0 + tile, w)
            region = (max(0, y0 - halo), min(h, y1 + halo), max(0, x0 - halo), min(w, x1 + halo))
            tiles.append(Tile(len(tiles), (y0, y1, x0, x1), region))
    return tiles


_WORKER_LIMITED = False


def _one_blas_thread_in_worker() -> None:
    """In a dask.distributed worker process, limit BLAS to one thread for the process's life.

    Each task is one core, and the same single-threaded kernels give the same bits
    everywhere.  Local runs are limited (and restored) around the whole graph by
    :func:`run_graph`; a per-task context would race between concurrent tasks, since
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


def _tile_task(store_path: str, tile: Tile, D: np.ndarray, settings: OmpSettings, patch: int) -> np.ndarray:
    store = WorkStore(store_path)
    hy0, hy1, hx0, hx1 = tile.halo
    y0, y1, x0, x1 = tile.core
    coded, mask = store.read_inputs(hy0, hy1, hx0, hx1)
    _one_blas_thread_in_worker()
    try:
        volume, stats = reconstruct_region(coded, mask, D, settings, patch=patch, origin=(hy0, hx0),
                                           image_shape=store.group["coded"].shape)
    except Exception as exc:  # name the tile, keep the cause
        raise RuntimeError(f"tile {tile.index} (rows {y0}:{y1}, cols {x0}:{x1}): {exc}") from exc
    core = volume[:, y0 - hy0 : y1 - hy0, x0 - hx0 : x1 - hx0]
    store.write_tile(tile.index, tile.core, core, stats)
    return stats


def build_graph(store_path: str, tiles: list[Tile], D: np.ndarray, settings: OmpSettings, *, patch: int = 7):
    """One delayed task per tile, sharing a single dictionary node.

    Task names are unique to this graph: a distributed scheduler shared by
    several runs (or by two rounds of one run) never takes one run's tile for
    another's.
    """
    d_node = dask.delayed(D, pure=True, name="dictionary-" + dask.base.tokenize(D))
    task = dask.delayed(_tile_task, pure=False)
    run = uuid.uuid4().hex[:12]
    return [task(store_path, t, d_node, settings, patch, dask_key_name=f"tile-{run}-{t.index}") for t in tiles]


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


def run_graph(
    tasks: list,
    *,
    scheduler: str | None = None,
    workers: int | None = None,
    progress: bool = True,
) -> list:
    """Execute tile tasks and return their results in order.

    Parameters
    ----------
    scheduler : None, "threads", "sync" or a dask.distributed address
        None and "threads" run on the local threaded scheduler; "sync" runs
        in this thread; anything containing "://" or ":" is a scheduler address.
    workers : int, optional
        Local worker threads (default: the number of cores).
    progress : bool
        Show a progress bar.
    """
    if not tasks:
        return []
    if scheduler and scheduler not in ("threads", "sync"):
        from distributed import Client, progress as dprogress

        with Client(scheduler) as client:
            futures = client.compute(tasks)
            if progress:
                dprogress(futures)
            return client.gather(futures)
    from dask.diagnostics import ProgressBar

    n_workers = workers or os.cpu_count() or 1
    bar = ProgressBar(dt=0.5) if progress else contextlib.nullcontext()
    if scheduler == "sync":
        with bar:
            return list(dask.compute(*tasks, scheduler="sync"))
    with bar, _single_threaded_blas(True):  # one core per worker thread
        return list(dask.compute(*tasks, scheduler="threads", num_workers=n_workers))


def reconstruct_tiles(
    store: WorkStore,
    D: np.ndarray,
    settings: OmpSettings,
    *,
    tile: int,
    patch: int = 7,
    scheduler: str | None = None,
    workers: int | None = None,
    progress: bool = True,
) -> tuple[np.ndarray, dict]:
    """Reconstruct every tile of a working store that is not done yet, and assemble the volume.

    Every tile that claims to be done is read back and checked against its
    digest; those that pass are reused, the others (never finished, damaged,
    truncated, deleted, copied over) are computed, then read back and checked
    in turn -- up to :data:`MAX_ATTEMPTS` rounds.  The volume is assembled
    from verified reads only.  The caller holds the entry's lock.

    Returns
    -------
    volume : ndarray (N, H, W) float32
    summary : dict
        Tiles computed now, reused and found damaged, the summed statistics
        and ``seconds_verify``, the time spent reading tiles back and checking them.
    """
    shape = tuple(store.group["coded"].shape)
    tiles = plan_tiles(shape, tile, patch=patch)
    t0 = time.perf_counter()
    ok, damaged, volume, read_stats = store.read_verified(tiles)
    seconds_verify = time.perf_counter() - t0
    stats = np.where(ok[:, None], read_stats, np.nan)
    if damaged.any():
        log.warning("cache entry %s: tiles %s failed their checksum (damaged); computing them again",
                    store.path, np.flatnonzero(damaged).tolist())
    computed: set[int] = set()
    for attempt in range(MAX_ATTEMPTS):
        todo = [t for t in tiles if not ok[t.index]]
        if not todo:
            break
        if attempt:
            log.warning("cache entry %s: tiles %s did not read back as written; computing them again",
                        store.path, [t.index for t in todo])
        run_graph(build_graph(str(store.path), todo, D, settings, patch=patch), scheduler=scheduler, workers=workers,
                  progress=progress)
        computed.update(t.index for t in todo)
        t0 = time.perf_counter()
        ok_now, _, _, read_stats = store.read_verified(todo, volume)
        seconds_verify += time.perf_counter() - t0
        stats[ok_now] = read_stats[ok_now]
        ok |= ok_now
    if not ok.all():
        missing = np.flatnonzero(~ok).tolist()
        raise RuntimeError(f"working store {store.path}: tiles {missing} did not finish or do not read back as "
                           f"written after {MAX_ATTEMPTS} attempts")
    totals = dict(zip(STAT_NAMES, stats.sum(0).tolist()))
    return volume, dict(tiles=len(tiles), tiles_computed=len(computed), tiles_reused=len(tiles) - len(computed),
                        tiles_damaged=int(damaged.sum()), seconds_verify=seconds_verify, **totals)
