"""The stages of a run: train, simulate and reconstruct, each a function of its settings, and :func:`run_pipeline`.

The command line, ``codedvideo run`` and the ``tasks/`` scripts call these
functions.  Each result is cached under a key that hashes its settings and
inputs (:mod:`codedvideo.engine.cache`), so a rerun reuses a dictionary or finished
reconstruction tiles instead of recomputing them.  Every reconstruction
writes a metrics JSON beside its output: seconds per stage, patches per
second, atoms used, and PSNR/SSIM when the truth is known.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import logging
import time
import warnings
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from codedvideo.solvers import baselines
from codedvideo.solvers import refine as refinement
from codedvideo.formats import io as cio
from codedvideo.model import patches as P
from codedvideo.model import physics
from codedvideo.engine.cache import RECON_VERSION, CacheBudget, cache_room_problem, content_key, dictionary_key
from codedvideo.model.codes import make_code
from codedvideo.engine.config import PipelineConfig
from codedvideo.solvers.dictionaries import dct_dictionary, learn_dictionary
from codedvideo.model.errors import ConfigError, InputError, OutputError
from codedvideo.model.metrics import evaluate
from codedvideo.engine.parallel import GraphRunner, build_graph, plan_store, plan_tiles, store_volume
from codedvideo.model.patches import PATCH
from codedvideo.model.sequence import erode_to_patches, normalised
from codedvideo.solvers.region import STAT_NAMES, OmpSettings
from codedvideo.data.scenes import load_video, training_videos
from codedvideo.data.shipped import check_dictionary, init_dictionary
from codedvideo.formats.store import WorkStore, entry_lock, load_dictionary, save_dictionary
from codedvideo.formats.volumes import CAPTURE_FILES, load_code_file, metrics_path, write_capture, write_json, write_volume

log = logging.getLogger("codedvideo")


def train_dictionary(cfg: PipelineConfig, *, output: str | Path | None = None, progress: bool = True,
                     retrain: bool = False) -> tuple[Path, dict]:
    """Train the dictionary the config describes, or reuse it: shipped (:mod:`codedvideo.data.shipped`) or cached.

    ``retrain`` trains even when a shipped dictionary has these settings (`make train`).
    """
    from codedvideo.data import shipped

    dc = cfg.dictionary
    if dc.path:
        D, meta = load_dictionary(dc.path)
        check_dictionary(meta, cfg.frames, dc.path)
        return Path(dc.path), dict(meta, reused=True, seconds=0.0)
    key = dictionary_key(cfg)
    t0 = time.perf_counter()
    ship = None if retrain else shipped.matching(cfg.frames, key)
    if ship is not None:
        D, meta = load_dictionary(ship)
        if output is not None:
            save_dictionary(output, D, {k: v for k, v in meta.items() if k not in ("atoms", "sha256", "kind", "format_version")})
            ship = Path(output)
        return ship, dict(meta, reused=True, shipped=True, seconds=time.perf_counter() - t0)
    cached = Path(cfg.cache) / f"dict-{key}.zarr"
    # One trainer at a time per entry: a second process with the same settings waits, then reuses
    # the dictionary the first one saved (whole, renamed into place, checked by its sha256 on load).
    found = _cached_dictionary(cached, key)  # a finished entry needs no lock: it appeared by a rename
    videos = used = None
    if found is None and dc.kind != "dct":  # read (and so check) the training videos before touching the cache
        _check_training_memory(dc.samples, cfg.frames)
        videos, used = training_videos(dc.training, frames=cfg.frames, clips=dc.clips, seed=cfg.seed,
                                       max_speed=dc.max_speed)
    if found is None:
        with entry_lock(cached):
            found = _cached_dictionary(cached, key, warn=True)  # another run may have saved it meanwhile
            if found is None:
                if dc.kind == "dct":
                    D = dct_dictionary(cfg.frames)
                    meta = dict(patch=PATCH, frames=cfg.frames, method="dct3d", seed=cfg.seed, iterations=0)
                else:
                    bar = _progress_bar(dc.iterations, "K-SVD") if progress else None
                    D, meta = learn_dictionary(
                        videos,
                        frames=cfg.frames,
                        atoms=dc.atoms,
                        samples=dc.samples,
                        iterations=dc.iterations,
                        sparsity=dc.sparsity,
                        seed=cfg.seed,
                        progress=(lambda it, rmse: (bar.update(1), bar.set_postfix(rmse=f"{rmse:.2f}"))) if bar else None,
                        init=None if dc.init is None else init_dictionary(dc.init, cfg.frames)[0],
                        augment=dc.augment,
                    )
                    if dc.init is not None:
                        meta["init"] = dc.init
                    if bar:
                        bar.close()
                    meta["training_set"] = used  # (videos too short or too small were left out, with a warning)
                    meta["clips"] = dc.clips
                meta["settings_key"] = key
                save_dictionary(cached, D, meta)
                D, meta = load_dictionary(cached)  # read back and checked against its sha256, under the lock
                cached_ok = False
    if found is not None:
        (D, meta), cached_ok = found, True
        log.info("dictionary: reusing %s", cached)
    result = cached
    if output is not None and Path(output) != result:
        save_dictionary(output, D, {k: v for k, v in meta.items() if k not in ("atoms", "sha256", "kind", "format_version")})
        result = Path(output)
        _, meta = load_dictionary(result)
    return result, dict(meta, reused=cached_ok, seconds=time.perf_counter() - t0)


def _cached_dictionary(cached: Path, key: str, *, warn: bool = False) -> tuple[np.ndarray, dict] | None:
    """The dictionary cache entry ``cached`` when it is intact and made for settings ``key``; else None."""
    if not cached.exists():
        return None
    try:
        D, meta = load_dictionary(cached)  # checked against its sha256
        if meta.get("settings_key") != key:  # e.g. another entry copied over this one
            raise InputError(f"dictionary {cached}: made for settings {meta.get('settings_key')!r}, not {key}")
    except InputError as exc:
        if warn:
            log.warning("dictionary cache %s is unreadable (%s); training again", cached, exc)
        return None
    return D, meta


def _progress_bar(total: int, desc: str):
    from tqdm.auto import tqdm

    return tqdm(total=total, desc=desc, unit="it", leave=False)


def simulate_capture(
    video: np.ndarray,
    *,
    code: str,
    bump: int,
    sigma: float,
    seed: int,
    p: float = 0.5,
    code_path: str | Path | None = None,
    sensor: physics.SensorModel | None = None,
    captures: int = 1,
    new_code_per_capture: bool = False,
) -> dict[str, np.ndarray]:
    """Coded capture(s) of a video: mask, coded image(s) (noisy) and the truth.

    Parameters
    ----------
    video : ndarray of shape (T * N, H, W)
        ``captures`` consecutive captures of N sub-frames each.
    code, bump, p, code_path
        The code (:func:`codedvideo.model.codes.make_code`; ``code_path`` for ``file``).
    sigma : float
        Gaussian read noise, grey levels.
    seed : int
        Code and noise use independent streams spawned from it.
    sensor : SensorModel, optional
        Shot noise, quantisation and clipping; its ``read_sigma`` is replaced
        by ``sigma``.  None: read noise only.
    captures : int
        T, the number of coded images (a coded camera's stream).
    new_code_per_capture : bool
        A new code for every capture instead of the same code repeated (as a
        real sensor repeats its code).

    Returns
    -------
    dict with ``coded`` (H, W) float32 for one capture, else (T, H, W); ``mask``
    (N, H, W) uint8, or (T, N, H, W) with a new code per capture (or a code file
    of several codes, taken in turn); ``truth`` (T * N, H, W) float32
    """
    if captures < 1 or video.shape[0] % captures:
        raise InputError(f"video of {video.shape[0]} frames: not {captures} captures of equal length")
    n = video.shape[0] // captures
    stream = simulate_stream((video[t * n : (t + 1) * n] for t in range(captures)), code=code, bump=bump,
                             sigma=sigma, seed=seed, p=p, code_path=code_path, sensor=sensor, captures=captures,
                             new_code_per_capture=new_code_per_capture)
    coded, masks = [], []
    for one, mask, _ in stream:
        coded.append(one)
        masks.append(mask)
    repeating = all(m is masks[0] for m in masks)  # the same code every capture (a real sensor's)
    return dict(coded=coded[0] if captures == 1 else np.stack(coded),
                mask=masks[0] if repeating else np.stack(masks), truth=np.asarray(video, np.float32))


def simulate_stream(clips, *, code: str, bump: int, sigma: float, seed: int, p: float = 0.5,
                    code_path: str | Path | None = None, sensor: physics.SensorModel | None = None, captures: int = 1,
                    new_code_per_capture: bool = False,
                    codes: list | None = None) -> Iterator[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """:func:`simulate_capture` one capture at a time: ``clips`` yields the T clips (N, H, W) in order; yields
    ``(coded (H, W), mask (N, H, W), clip)`` for each, from the same seeded streams (the same captures bit for
    bit).  A repeating code is the same array every capture; a code file of K codes gives capture ``t`` its
    code ``t mod K``.  ``codes``: the masks themselves (the API's arrays), taken in turn as a code file's."""
    ss = np.random.SeedSequence(seed)
    code_rng, noise_rng = (np.random.default_rng(s) for s in ss.spawn(2))
    if sensor is not None:
        sensor = dataclasses.replace(sensor, read_sigma=sigma)
    masks = None if codes is None else list(codes)
    warned = False
    for t, clip in enumerate(clips):
        if masks is None:  # every code is drawn first, from its own stream
            masks = [load_code_file(code_path, frames=clip.shape[0], shape=clip.shape[1:]) if code == "file" else
                     make_code(code, clip.shape[1:], frames=clip.shape[0], bump=bump, p=p, rng=code_rng)
                     for _ in range(captures if new_code_per_capture else 1)]
            if masks[0].ndim == 4:  # a code file of one code per capture, in turn
                if new_code_per_capture:
                    raise InputError(f"code file {code_path}: holds {masks[0].shape[0]} codes, one per capture; "
                                     "a new code per capture does not apply")
                masks = list(masks[0])
            if not all(np.any(m) for m in masks):  # (a Bernoulli p of 1e-9, say): nothing would be measured
                raise InputError(f"code {code}{f' (p = {p:g})' if code == 'bernoulli' else ''}: opens no pixel in any "
                                 "sub-frame; nothing would be measured")
        mask = masks[t % len(masks)]
        # one noise stream, drawn capture after capture
        coded = (physics.simulate(clip, mask, sigma=sigma, rng=noise_rng) if sensor is None
                 else physics.simulate(clip, mask, rng=noise_rng, sensor=sensor))
        top = float(coded.max(initial=0.0))
        share = float(np.mean(coded >= top)) if sensor is not None and top > 0 else 0.0
        if share > 0.5 and not warned:  # the sensor's ceiling (full well / gain, white level, ADC) everywhere
            warnings.warn(f"{share:.0%} of the pixels of capture {t + 1} are at the sensor's ceiling ({top:g}: the "
                          "full well over the gain, --white-level or --bits): the capture is saturated; give the "
                          "sensor settings in the video's units (a 16-bit video needs --gain, --full-well, --bits)")
            warned = True
        yield coded, mask, clip


def sensor_model(noise) -> physics.SensorModel | None:
    """The :class:`~codedvideo.model.physics.SensorModel` of a ``NoiseConfig`` (None: read noise only)."""
    if not noise.shot_noise and noise.bits is None and noise.white_level is None and not noise.black_level:
        return None
    return physics.SensorModel(shot_noise=noise.shot_noise, full_well=noise.full_well, gain=noise.gain,
                               read_sigma=noise.sigma, bits=noise.bits, white_level=noise.white_level,
                               black_level=noise.black_level)


def _check_training_memory(samples: int, frames: int) -> None:
    """Refuse, before any work, a number of training samples whose patches would not fit in memory: K-SVD
    draws three candidate blocks a sample and keeps the samples and their residuals, float32 (10 M samples
    at N = 64 ended in a MemoryError traceback after 50 s)."""
    need = 5 * 4 * samples * frames * PATCH * PATCH
    free = cio.available_memory()
    if free is not None and need > 0.75 * free:
        raise ConfigError(f"dictionary.samples {samples} (--samples): {samples} training patches of 7x7x{frames} "
                          f"need about {need / 2**30:.1f} GiB, {free / 2**30:.1f} GiB are free; give fewer samples")


def drop_saturated(coded: np.ndarray, mask: np.ndarray, white_level: float) -> tuple[np.ndarray, np.ndarray, int]:
    """Saturated pixels as missing measurements (:func:`codedvideo.model.physics.saturated_as_missing`).

    Returns the coded image with saturated pixels set to 0 (so that the
    measurement residual ignores them), the mask without them, and their count.
    """
    mask_used, count = physics.saturated_as_missing(coded, mask, white_level)
    if count:
        coded = np.where(coded >= np.float32(white_level), np.float32(0), coded).astype(np.float32)
    return coded, mask_used, count


def _check_capture(coded: np.ndarray, mask: np.ndarray, D: np.ndarray) -> int:
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


def _allow_open_files(needed: int, cache) -> None:
    """Make room for ``needed`` open files (a job locks each working store of the windows it holds, 64
    kept for the rest): the soft limit raised toward the hard one (doubled, so that this is rare), or
    an OutputError, while planning and before any tile, where that is not allowed."""
    try:
        import resource
    except ImportError:  # not on this platform
        return
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    if soft == resource.RLIM_INFINITY or soft >= needed:
        return
    target = max(needed, 2 * soft) if hard == resource.RLIM_INFINITY else min(hard, max(needed, 2 * soft))
    try:
        if target < needed:
            raise ValueError(f"the hard limit is {hard}")
        resource.setrlimit(resource.RLIMIT_NOFILE, (target, hard))
    except (ValueError, OSError) as exc:
        raise OutputError(f"cache {cache}: this job locks a working store per capture of the windows it holds, "
                          f"{needed - 64} now, and cannot have more open files ({exc}; ulimit -n); raise the limit "
                          "or reconstruct fewer captures a job") from exc


def sparse_volumes(
    count: int,
    capture,
    D: np.ndarray,
    *,
    settings: OmpSettings,
    tile: int = 128,
    cache: str | Path = "cache",
    scheduler: str | None = None,
    workers: int | None = None,
    progress: bool = True,
    dictionary_key: str = "",
    desc: str = "reconstruct",
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
        dictionary and its cache key (a dictionary adapted to each capture, :func:`adapt_dictionary`;
        an empty key: keyed by its contents)
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
        The statistics of :func:`reconstruct_volume`.

    Each capture's working store is the cache entry ``cache/recon-KEY.zarr``,
    shared by every run with the same inputs and settings (equal captures of
    one job share it too): runs on one entry take its lock in turn (a second
    run waits, then reuses the finished tiles); an entry whose metadata or
    inputs are damaged is rebuilt, and a tile that fails its checksum when
    read back is computed again, never returned (``tiles_damaged``).  When
    every pixel has the same shutter pattern (open in every sub-frame: bump
    length N, the global shutter, N = 1; or a global flutter sequence) no
    pixel tells one instant from another, so per-patch sparse coding can only
    invent motion (measured: a flutter code fell 6 dB below the static
    estimate): that capture's result is the static estimate ``coded / open
    count`` itself (``method: "static"``), computed without tiles.
    """
    per_capture = callable(D)
    dkey = "" if per_capture else dictionary_key or content_key(D)
    locks = _EntryLocks(cache)
    live: dict[str, tuple[_Window, int]] = {}  # key -> the window and store of a capture planned and not yet done
    unopened: list[int] = []  # never-open pixels of each capture that has some: one warning for the job
    position = 0  # the next capture to plan

    def plan_capture(i: int, window: _Window) -> int:
        """Plan capture ``i`` into ``window``: how it is done (None: the caller's; "static"; or a store, locked,
        with its tiles planned -- a store that an earlier capture of a window not yet done has is shared); its tiles."""
        pair = capture(i)
        if pair is None:
            window.how.append(None)
            return 0
        coded, mask, still = pair
        Di, dkey_i = D(i) if per_capture else (D, dkey)
        never_open = _check_capture(coded, mask, Di)
        if (mask == mask[:, :1, :1]).all():  # one shutter pattern for all pixels: no temporal information
            unopened.extend([never_open] if never_open else [])
            window.how.append("static")
            return 0
        first = first_of(i) if first_of is not None else None
        if first is not None:  # kept as it is while its result is read
            locks.take(Path(first), window)
        key = content_key(RECON_VERSION, coded, mask, dkey_i or content_key(Di), settings.__dict__, tile,
                          *(() if still is None else (np.asarray(still, np.uint8),)),
                          *(() if first is None else (WorkStore.opened(first).key,)))
        # absolute: a dask.distributed worker started in another folder opens it too
        entry = Path(cache).absolute() / f"recon-{key}.zarr"
        # One run at a time per entry (processes, threads, clients of one dask cluster): a second run waits
        # for it (once this job holds no other entry), then reuses the tiles the first one finished.
        locks.take(entry, window)
        unopened.extend([never_open] if never_open else [])
        n_tiles = len(plan_tiles(coded.shape, tile, patch=PATCH))
        if key not in live:
            store = WorkStore.create(
                entry, coded, mask, tile=tile, n_stats=len(STAT_NAMES), n_tiles=n_tiles,
                attrs=dict(key=key, settings=settings.__dict__, tile=tile, version=RECON_VERSION), still=still)
            # its tiles planned from the inputs in hand (not read back from the store)
            window.stores.append(store)
            window.plans.append(plan_store(store, coded, mask, still, settings, tile=tile, patch=PATCH, first=first))
            window.dictionaries.append(Di)
            live[key] = window, len(window.stores) - 1
            window.keys.append(key)
        window.how.append(live[key])
        return n_tiles

    def plan_window() -> _Window | None:
        """The next captures, planned until they hold :data:`WINDOW_TILES` tiles (at least one capture)."""
        nonlocal position
        if position >= count:
            return None
        window, tiles = _Window(start=position), 0
        while position < count and (tiles < WINDOW_TILES or not window.how):
            t0 = time.perf_counter()
            try:
                tiles += max(1, plan_capture(position, window))
            except _Busy:  # another run holds its entry: planned once this job holds none (the window ends here)
                if not window.how:
                    locks.release(window)
                    return None
                break
            window.seconds_plan.append(time.perf_counter() - t0)
            position += 1
        if position >= count and unopened:
            where = "" if count == 1 else (f" in {len(unopened)} of {count} captures ({min(unopened)} to "
                                           f"{max(unopened)} each)")
            warnings.warn(f"{sum(unopened)} pixels are never open{where} (or were left out as saturated or defective); "
                          "they are filled from their neighbours", stacklevel=3)
        tasks, needs = build_graph([plan.work for plan in window.plans], window.dictionaries if per_capture else D,
                                   settings, patch=PATCH)
        window.tile_tasks = len(tasks)
        window.graph = runner.offer(tasks, needs, share=len(window.how) / count)
        return window

    with contextlib.closing(locks), GraphRunner(scheduler=scheduler, workers=workers, progress=progress,
                                                desc=desc) as runner:
        windows = [w for w in (plan_window(),) if w is not None]  # (holding nothing: it waits for a busy entry)
        while windows:
            window = windows[0]
            if len(windows) == 1:  # the next window planned (and handed to the workers) while this one runs
                following = plan_window()
                if following is not None:
                    windows.append(following)
            t_wait = time.perf_counter()
            for k, how in enumerate(window.how):
                i = window.start + k
                if how is None:
                    yield i, None, None
                    continue
                coded, mask, _ = capture(i)
                if how == "static":
                    yield i, *_static_volume(coded, mask)
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
            for key in window.keys:  # its stores done: later captures with the same inputs lock them afresh
                del live[key]
            locks.release(window)
            runner.forget(window.graph)
            windows.pop(0)
            if budget is not None:
                budget.finished((store.path for store in window.stores), busy=locks.held)
            if not windows and position < count:  # the next window put off (an entry busy): nothing is held now
                windows.append(plan_window())


#: A job's captures are planned and computed in windows of at least this many tiles (a graph each, run back to
#: back on the same workers: :class:`codedvideo.engine.parallel.GraphRunner`).  A long stream's first tiles start once one
#: window is planned (not all of its captures), the next window is planned while one runs, and what the plans and
#: the graph hold, and the cache locks kept, do not grow with its length.  Equal tiles are shared within a window.
WINDOW_TILES = 64


def cache_room(cache, count: int, shape: tuple[int, int, int], *, tile: int, budget: int | None,
               adapt: bool = False, adapt_rounds: int = 1) -> str | None:
    """Why the disk under ``cache`` may not hold the working stores of a job of ``count`` captures of
    ``shape`` (N, H, W) (None: it may; :func:`codedvideo.engine.cache.cache_room_problem`).  With ``adapt`` a
    capture makes one more a round; with a budget the job holds at most three windows' stores beside it."""
    n, h, w = shape
    window = -(-WINDOW_TILES // len(plan_tiles((h, w), tile, patch=PATCH)))  # captures a window
    return cache_room_problem(cache, count * (1 + adapt_rounds if adapt else 1), n, h, w, budget, in_use=3 * window)


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


class _Busy(Exception):
    """A cache entry another run holds, asked for while the job holds others (:meth:`_EntryLocks.take`)."""


class _EntryLocks:
    """The cache entries a job holds (:func:`codedvideo.formats.store.entry_lock`), each locked once however many
    captures of its windows use it, and let go when the last window that uses it is done."""

    def __init__(self, cache):
        self.cache = cache
        self.held: dict[str, list] = {}  # entry -> [its lock, the windows using it (with repeats)]

    def take(self, entry: Path, window: _Window) -> None:
        """Lock ``entry`` for ``window``.  While the job holds other entries it never waits for one that
        another run holds (two runs taking each other's entries in turn would wait for ever): it raises
        :class:`_Busy`, and the entry is asked for again once the job holds nothing."""
        name = str(entry)
        if name not in self.held:
            _allow_open_files(len(self.held) + 65, self.cache)
            lock = contextlib.ExitStack()
            if not lock.enter_context(entry_lock(entry, blocking=not self.held)):
                lock.close()
                raise _Busy(name)
            self.held[name] = [lock, []]
        self.held[name][1].append(id(window))

    def release(self, window: _Window) -> None:
        for name in list(self.held):
            lock, users = self.held[name]
            users[:] = [u for u in users if u != id(window)]
            if not users:
                lock.close()
                del self.held[name]

    def close(self) -> None:
        for lock, _ in self.held.values():
            lock.close()
        self.held.clear()


def _fill_nearest(volume: np.ndarray, holes: np.ndarray) -> None:
    """Every frame's pixels at ``holes`` (H, W) take the value of the nearest pixel that is not one, in place."""
    from scipy import ndimage  # lazy: holes are rare

    _, (iy, ix) = ndimage.distance_transform_edt(holes, return_indices=True)
    volume[:, holes] = volume[:, iy[holes], ix[holes]]


def _finish_sparse(volume: np.ndarray, summary: dict, coded: np.ndarray, mask: np.ndarray, settings: OmpSettings,
                   store_path) -> tuple[np.ndarray, dict]:
    """A capture's solved tiles -> its volume: pixels no patch covers filled from the nearest; the statistics."""
    if summary.get("dependent_stops"):
        warnings.warn(f"{int(summary['dependent_stops'])} of {int(summary['patches'])} patches stopped early: their "
                      "next atom was numerically dependent on the chosen ones (near-duplicate or degenerate "
                      "dictionary atoms)", stacklevel=4)
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
        patches_per_second=summary["patches"] / max(summary["seconds_total"], 1e-9) * (summary["tiles_computed"] > 0),
        measurement_residual_rms=float(np.sqrt(np.mean(residual.astype(np.float64) ** 2))),
        work_store=str(store_path),
        method="sparse",
    )
    return volume, info


def reconstruct_volume(
    coded: np.ndarray,
    mask: np.ndarray,
    D: np.ndarray,
    *,
    settings: OmpSettings,
    tile: int = 128,
    cache: str | Path = "cache",
    scheduler: str | None = None,
    workers: int | None = None,
    progress: bool = True,
    dictionary_key: str = "",
) -> tuple[np.ndarray, dict]:
    """Reconstruct one coded image (working units) through the Zarr working store and the dask graph.

    A job of one capture (:func:`sparse_volumes`).  Returns the volume
    (N, H, W) float32 and a dict of statistics and timings.  Patches that
    stopped early because their next atom was numerically dependent on the
    chosen ones are counted (``dependent_stops``) and reported by a warning.
    """
    coded = np.asarray(coded, np.float32)
    results = sparse_volumes(1, lambda i: (coded, mask, None), D, settings=settings, tile=tile, cache=cache,
                             scheduler=scheduler, workers=workers, progress=progress, dictionary_key=dictionary_key)
    with contextlib.closing(results):
        _, volume, info = next(results)
    return volume, info


#: Methods that sparse-code patches (through :func:`sparse_volumes`); the others are :mod:`codedvideo.solvers.baselines`.
SPARSE_METHODS = ("omp", "nonlocal", "dct")

#: Adapting the dictionary to a capture (``--adapt``): K-SVD started from the dictionary, its atoms kept,
#: for this many iterations on this many 7x7xN patches of the capture's own first reconstruction, taken as
#: they are (no rotations, flips or time reversal: they would spread the atoms over motions the scene
#: lacks).  Measured on the 24 held-out real cases (README), the non-local method alone 33.71 dB: one
#: iteration 34.36 (with augmentation 33.84), 2 34.45, 3 34.49, 4 34.52 (0.32 s at 256x256, against 0.19
#: for one), 4 on 14000 patches 34.54 (0.73 s); sparsity 4 or 8 no better.  A dictionary adapted to one
#: capture does not carry to the next (-1.3 to +1.4 dB a case, no gain on average): each gets its own.
ADAPT_SAMPLES, ADAPT_ITERATIONS, ADAPT_SPARSITY = 7000, 4, 6
#: ``nonlocal --adapt``: the first pass solves the groups of every 7th reference patch (a survey, 0.2 of the
#: groups of the non-local method's stride 3), the second pass the groups of every 4th from the survey's
#: result, with no per-patch tiles (:attr:`codedvideo.engine.parallel.TileWork.first`).  Measured on the 24
#: held-out real cases, in one thread (2026-11-26): surveys of every 5th or 7th reference gave the quality of
#: two full passes (GAP-TV + 3.80 dB with a second pass of every 3rd, against + 3.84), in 5.5 to 5.9x the
#: default's time against 9.2x; with a second pass of every 4th, + 3.66 dB in 4.3x (README).
ADAPT_SURVEY_STEP, ADAPT_REFINE_STEP = 7, 4
#: ``--adapt-rounds 2`` (``--preset best``): the dictionary adapted again to the second pass's result (K-SVD
#: started from the first adaptation, the same settings), then a third pass with it; the non-local method's
#: third pass solves the groups of every 3rd reference, matched on the second pass's result.  Measured in one
#: thread (tasks/research_best.py, 256x256, N = 8, hitomi L = 2 and Bernoulli, no noise; chosen on bikes-a and
#: carphone, 2026-11-27): over ``nonlocal --adapt`` +0.46 dB on those, +0.48 dB on bikes-b and bunny (every
#: case +0.18 or more) and +0.45 on their next 8 frames, in 1.8x its time; a third pass every 4th +0.38, a
#: third adaptation and a fourth pass +0.51 (worst case +0.10) in 2.1x, denser second passes +0.13 to +0.20.
ADAPT_LAST_STEP = 3


def adapt_dictionary(volume: np.ndarray, D: np.ndarray, *, seed: int = 0) -> tuple[np.ndarray, dict]:
    """``D`` adapted to one capture's first reconstruction ``volume`` (N, H, W), in working units.

    A volume with nothing to learn from (flat in space and time) keeps ``D``.
    Returns the dictionary and a record of the adaptation.
    """
    from threadpoolctl import threadpool_limits

    from codedvideo.solvers.dictionaries import prepare_dictionary

    t0 = time.perf_counter()
    volume = np.asarray(volume, np.float32)
    if not np.ptp(volume) > 1e-3 * max(1.0, float(np.abs(volume).max(initial=0.0))):
        return D, dict(adapted=False, reason="the first reconstruction is flat", seconds=time.perf_counter() - t0)
    try:
        # one BLAS thread: the same bits whatever the cores (products round otherwise with other thread counts);
        # the caller runs no graph meanwhile, whose own limit would change it midway (reconstruct_captures)
        with threadpool_limits(limits=1, user_api="blas"):
            Da, meta = learn_dictionary([volume], frames=volume.shape[0], init=D, augment=False,
                                        iterations=ADAPT_ITERATIONS, samples=ADAPT_SAMPLES, sparsity=ADAPT_SPARSITY,
                                        tol_rms=0.0, seed=seed)
    except InputError:  # every patch drawn is flat (a dark frame with a few bright pixels): nothing to learn
        return D, dict(adapted=False, reason="no patch drawn from the first reconstruction has texture",
                       seconds=time.perf_counter() - t0)
    Da = prepare_dictionary(Da, "adapted to the capture")
    return Da, dict(adapted=True, samples=meta["samples"], iterations=ADAPT_ITERATIONS, final_rmse=meta["final_rmse"],
                    seconds=time.perf_counter() - t0)


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

    settings = dataclasses.replace(settings, method="nonlocal" if method == "nonlocal" else "omp")
    if method == "dct":
        dictionary, dictionary_key = dct_dictionary(frames), ""
    elif dictionary is None:
        raise InputError(f"method {method}: needs a dictionary (--dictionary DICT.zarr)")
    prepared = prepare_dictionary(dictionary, dictionary_name or f"of method {method}")
    if prepared is not dictionary:  # the caller's key names the given atoms: key the cache by the used ones
        dictionary, dictionary_key = prepared, ""
    return settings, dictionary, dictionary_key


def reconstruct_captures(
    method: str,
    codeds,
    mask_of,
    *,
    data_range,
    settings: OmpSettings,
    dictionary: np.ndarray | None = None,
    dictionary_key: str = "",
    dictionary_name: str = "",
    white_level: float | None = None,
    still_of=None,
    where: str = "coded image",
    tile: int = 128,
    cache: str | Path = "cache",
    scheduler: str | None = None,
    workers: int | None = None,
    progress: bool = True,
    adapt: bool = False,
    adapt_rounds: int = 1,
    refine: int = 0,
    noise_sigma: float = 0.0,
    cache_budget: int | None = None,
) -> Iterator[tuple[int, np.ndarray, dict]]:
    """Captures in their own units -> their videos in the same units, by any method, in order, as one job.

    Parameters
    ----------
    codeds : sequence of T coded images (H, W), in the capture's units
    mask_of : callable ``mask_of(i)`` -> the (N, H, W) mask of capture ``i``
    data_range : :class:`codedvideo.model.units.DataRange`
        The captures are scaled to working units (``settings`` already in
        them), reconstructed and scaled back, so the same captures in other
        units give the same videos times the scale.
    white_level : float, optional
        Pixels at or above it (capture units) are missing measurements.
    still_of : callable, optional
        ``still_of(i)`` -> (H, W) float32 (:func:`codedvideo.model.sequence.still_values`):
        the still answer, in working units, of the pixels whose ``coded / open
        count`` agrees with a neighbouring capture, NaN elsewhere.  Patches wholly inside them take the still
        answer in every sub-frame without a dictionary search (that value where only still patches cover
        a pixel; elsewhere the capture's own, which the patches that move see); a capture in which every
        measured pixel agrees is the still estimate itself.  (Methods without
        patches: the pixels whose 13x13 neighbourhood agrees take it.)
    adapt : bool
        Sparse methods: reconstruct each capture (a job each), adapt the
        dictionary to its result (:func:`adapt_dictionary`), then reconstruct
        every capture again with its own (one job).  ``omp``: about twice the
        time; ``nonlocal``: a survey first (:data:`ADAPT_SURVEY_STEP`), about
        1.2x its time, +0.6 dB on held-out real footage (README).
    adapt_rounds : int
        With ``adapt``: 2 adapts the dictionary again to the second pass's result and reconstructs a
        third time with it (:data:`ADAPT_LAST_STEP`; ``--preset best``).
    refine : int
        Iterations of GAP with a low-rank prior on groups after each capture's result (0: none;
        :func:`codedvideo.solvers.refine.refine`, ``--preset best``), in the process, not cached; pixels that
        only still patches cover keep their still answer.
    noise_sigma : float
        The captures' read noise (capture units, ``--noise-sigma``): with ``refine``, a noisy capture's steps to
        its measurements are relaxed by it (:func:`codedvideo.solvers.refine.refine`).
    cache_budget : int, optional
        Bytes the cache's working stores may take (:class:`codedvideo.engine.cache.CacheBudget`): the least recently
        used are removed as the job's windows finish (with ``adapt``, the first passes' stores only after the
        job).  None: no limit.

    Yields
    ------
    ``(i, volume (N, H, W) float32, info)`` for i = 0 .. T-1, each as soon as
    it is done; the sparse methods run every capture's tiles in one graph.
    """
    if method not in baselines.METHODS:
        raise InputError(f"method {method!r}: unknown; choose one of {', '.join(baselines.METHODS)}")
    scale = np.float32(data_range.scale)
    count = len(codeds)

    blown: set[int] = set()  # captures saturated everywhere (warned once each)

    @functools.lru_cache(maxsize=1)  # the finishing step asks twice in a row; one capture's inputs held at most
    def used(i: int):
        """Capture i as reconstructed: working units, saturated pixels left out, the pixels only still patches
        cover measuring their still answer; its agreeing pixels (None: none), whether anything moves, its
        saturated count, and its own measurement where still answers changed it (else None)."""
        coded, mask = codeds[i], mask_of(i)
        coded_used, mask_used, saturated = coded, mask, 0
        if white_level is not None:
            coded_used, mask_used, saturated = drop_saturated(coded, mask, white_level)
            if saturated and not mask_used.any():
                if count == 1:
                    raise InputError(f"{where}: every measured pixel is at or above --white-level {white_level}; "
                                     "nothing is left to reconstruct (--trust-saturated uses them anyway)")
                # one blown-out capture of a stream (a flash, the sun): its clipped values, said, and the rest go on
                if i not in blown:
                    blown.add(i)
                    warnings.warn(f"{where}, capture {i + 1} of {count}: every measured pixel is at or above "
                                  f"--white-level {white_level}; it is reconstructed from its clipped values")
                coded_used, mask_used, saturated = coded, mask, 0
        coded_used = np.asarray(coded_used, np.float32) * scale if scale != 1 else np.asarray(coded_used, np.float32)
        still = measured = None
        if still_of is not None:  # asked again when the capture is finished (not kept: T maps of H x W)
            values = still_of(i)
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

    sparse = method in SPARSE_METHODS
    if sparse:
        settings, dictionary, dictionary_key = sparse_method(method, settings, dictionary, dictionary_key,
                                                             dictionary_name, frames=mask_of(0).shape[0])

    def for_sparse(i: int):
        coded_used, mask_used, still, moving, _, _ = used(i)
        return (coded_used, mask_used, still) if sparse and moving else None

    if adapt and not sparse:
        raise ConfigError(f"--adapt: method {method} has no dictionary to adapt (omp, nonlocal and dct have)")
    # --adapt with the non-local method: a first pass on a sparser grid of groups (a survey: what K-SVD learns
    # from and the groups of the second pass are matched on), then the groups solved from it (no default tiles);
    # with adapt_rounds 2 the second pass is learnt from and matched on in turn, and a third pass gives the result
    survey = settings.method == "nonlocal" and adapt
    steps = (ADAPT_SURVEY_STEP, ADAPT_REFINE_STEP, ADAPT_LAST_STEP)[:adapt_rounds + 1] if survey else ()
    pass_settings = [dataclasses.replace(settings, group_step=step) for step in steps] if survey \
        else [settings] * (adapt_rounds + 1)
    settings = pass_settings[-1]
    job = functools.partial(sparse_volumes, count, for_sparse, settings=settings, tile=tile, cache=cache,
                            scheduler=scheduler, workers=workers, progress=progress)
    budget = None if cache_budget is None or not sparse else CacheBudget(cache, cache_budget)
    nonlocal_checked: dict[str, str | None] = {}

    def nonlocal_problem(mask) -> str | None:
        """Why the non-local method cannot solve a capture with this mask, or None (a code's patterns are
        counted once: 3 s for a 4K mask, N = 18)."""
        code = content_key(np.asarray(mask))
        if code not in nonlocal_checked:
            nonlocal_checked[code] = _nonlocal_unavailable(mask, dictionary)
        return nonlocal_checked[code]

    adapted: dict[int, np.ndarray] = {}  # capture -> its adapted dictionary (until its last job is planned)
    records: dict[int, dict] = {}  # capture -> what its adaptation did, and the earlier jobs' seconds
    first_stores: dict[int, str] = {}  # capture -> the working store its last pass is matched on (the survey's)
    for i in range(count) if sparse and adapt else ():
        D_i, store, record = _adapt_capture(
            i, count, for_sparse, dictionary, dictionary_key, pass_settings[:adapt_rounds],
            matched=survey, nonlocal_problem=nonlocal_problem, budget=budget,
            run=functools.partial(sparse_volumes, tile=tile, cache=cache, scheduler=scheduler, workers=workers,
                                  progress=progress))
        if D_i is not dictionary:
            adapted[i] = D_i
        if store is not None:
            first_stores[i] = store
        if record is not None:
            records[i] = record
    if sparse and adapt:
        blown.clear()  # the warnings the first jobs swallowed are said by the second
        used.cache_clear()
    if budget is not None:
        job = functools.partial(job, budget=budget)
    # a capture not adapted (flat) keeps the dictionary and its key: its second job is the first's, from the cache
    # (with the survey, the method's own job at the second pass's stride)
    results = ((job(lambda i: (adapted.pop(i), "") if i in adapted else (dictionary, dictionary_key), desc="adapted",
                    first_of=first_stores.get if survey else None)
                if adapted else job(dictionary, dictionary_key=dictionary_key)) if sparse
               else ((i, None, None) for i in range(count)))
    warned_nonlocal = False
    with contextlib.closing(results) if sparse else contextlib.nullcontext():
        for i, volume, info in results:
            coded_used, mask_used, still, moving, saturated, measured = used(i)
            if not moving:  # nothing moves: no sparse coding at all
                volume, info = _static_volume(coded_used, mask_used)
            elif volume is None:
                volume, info = reconstruct_method(method, coded_used, mask_used)
            if refine and moving and info.get("method") != "static":
                volume, info = _refined(coded_used, mask_used, volume, info, refine, still=still, where=where,
                                        noise_sigma=float(noise_sigma) * float(scale), progress=progress,
                                        label=f"{i + 1}/{count}")
            if measured is not None:  # still answers averaged over captures: the residual of this capture's own
                residual = physics.forward(volume, mask_used) - measured
                info["measurement_residual_rms"] = float(np.sqrt(np.mean(residual.astype(np.float64) ** 2)))
            if sparse and info.get("method") != "static":  # (the static estimate says so)
                info = dict(info, method=method, dictionary_atoms=int(dictionary.shape[1]))
                if i in records:  # the first job's and the adaptation's time beside the second's
                    record = info["adapted"] = records.pop(i)
                    info["seconds"] = dict(first_pass=record["first_pass"]["seconds"], adapt=record["seconds"],
                                           **info["seconds"])
                    work = record["first_pass"]["tile_seconds"] + record["seconds"] + info["seconds_total"]
                    info["patches_per_second"] = info["patches"] / max(work, 1e-9) * (info["tiles_computed"] > 0)
                problem = nonlocal_problem(mask_used) if method == "nonlocal" else None
                if problem:  # its tiles gave the default's answer: said, not hidden
                    info.update(method="omp", nonlocal_unavailable=problem)
                    if not warned_nonlocal:
                        warnings.warn(f"--method nonlocal ({where}): {problem}; the result is the default per-patch "
                                      "OMP's (for every capture with such a code: nonlocal_unavailable in the metrics)")
                        warned_nonlocal = True
            if saturated:  # a saturated pixel recorded at least the white level: no frame sum below it
                info["saturated_raised"] = physics.raise_to_white(volume, np.asarray(codeds[i]) >= np.float32(white_level),
                                                                  mask_of(i), float(white_level) * float(scale))
            if still is not None and not sparse:  # no patches: the pixels whose every patch would be still
                inner = erode_to_patches(still, PATCH)
                volume[:, inner] = normalised(coded_used, mask_used)[0][inner]
            info["still_pixels"] = 0 if still is None else int(still.sum())
            if scale != 1:
                volume /= scale
                if info.get("measurement_residual_rms") is not None:
                    info["measurement_residual_rms"] = float(info["measurement_residual_rms"]) / float(scale)
            info["saturated_pixels"] = saturated
            del coded_used, mask_used, measured
            handed = [(i, volume, info)]  # (as sparse_volumes: not held while the consumer works on it)
            del volume
            yield handed.pop()
    if budget is not None and budget.keep:  # the job is over: the first passes' stores may go too
        budget.keep.clear()
        budget.finished([])


def _refined(coded: np.ndarray, mask: np.ndarray, volume: np.ndarray, info: dict, iterations: int, *,
             still: np.ndarray | None, where: str, noise_sigma: float, progress: bool,
             label: str) -> tuple[np.ndarray, dict]:
    """A capture's result after ``iterations`` of :func:`codedvideo.solvers.refine.refine` (working units, the
    read noise ``noise_sigma`` too), its info with what the refinement did; the pixels that only still patches
    cover keep their values."""
    with _progress_bar(iterations, f"refine {label}") if progress else contextlib.nullcontext() as bar:
        refined, record = refinement.refine(coded, mask, volume, iterations=iterations, noise_sigma=noise_sigma,
                                            tick=None if bar is None else (lambda: bar.update(1)))
    if not np.isfinite(refined).all():  # (never seen: the start and the measurements are finite)
        raise OutputError(f"{where}: the refinement gave non-finite values; run without --refine")
    if still is not None:
        inner = erode_to_patches(still, PATCH)
        refined[:, inner] = volume[:, inner]
    seconds = dict(info.get("seconds", {}), refine=record["seconds"])
    return refined, dict(info, refine=record, seconds=seconds)


def _adapt_capture(i: int, count: int, for_sparse, dictionary: np.ndarray, dictionary_key: str, pass_settings, *,
                   matched: bool, nonlocal_problem, budget: CacheBudget | None,
                   run) -> tuple[np.ndarray, str | None, dict | None]:
    """Capture ``i``'s passes before its last (``--adapt``), each a job of its own followed by an adaptation of
    the dictionary to its result (:func:`adapt_dictionary`), the next pass solved with that dictionary.

    One job at a time: no graph is in flight while K-SVD runs (a graph's thread limits BLAS threads, which changed
    an adaptation's bits when it ran beside one).  The passes' warnings (never-open pixels, dependent stops) are
    swallowed: the last job, which gives the result, says them.  ``pass_settings``: one per pass before the last;
    ``matched``: the non-local method's passes, each matched on and solved from the previous pass's working store
    (where the code's groups can be solved: ``nonlocal_problem(mask)`` is None); ``run``: :func:`sparse_volumes`
    with the job's tiles, cache and scheduler.  Stops early where a result has nothing to learn from.

    Returns the dictionary for the last pass (``dictionary`` itself if none was adapted), the working store the
    last pass is matched on (or None), and the record of the adaptations with the earlier jobs' seconds (or None).
    """
    D_i, store, done = dictionary, None, []
    for k, settings in enumerate(pass_settings):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            pass_job = run(1, lambda _: for_sparse(i), dictionary if k == 0 else (lambda _, D=D_i: (D, "")),
                           settings=settings, dictionary_key=dictionary_key,
                           first_of=None if store is None else (lambda _, s=store: s),
                           desc=f"pass {k + 1} of {i + 1}/{count}")
            with contextlib.closing(pass_job):  # closed here: the graph's thread has ended
                _, first, info = next(pass_job)
        learnt = first is not None and info.get("method") != "static"  # (one pattern for all pixels: no tiles)
        if learnt:
            Da, record = adapt_dictionary(first, D_i)
            done.append((info, record))
            learnt = record["adapted"]  # (a result with nothing to learn from keeps the dictionary)
        del first
        if learnt:
            D_i = Da
            # (a code the groups cannot solve: the survey is the default's result, and the later passes their
            # own per-patch OMP with the adapted dictionary, as with omp --adapt)
            if matched and nonlocal_problem(for_sparse(i)[1]) is None:
                store = info["work_store"]
                if budget is not None:  # the next job reads it: kept until the job ends
                    budget.keep.add(Path(store).absolute())
        if budget is not None and (info or {}).get("work_store"):  # (closed before its window ended)
            budget.finished([info["work_store"]])
        if not learnt:
            break
    if not done:
        return D_i, store, None
    record = dict(done[-1][1], first_pass=dict(seconds=sum(sum(inf["seconds"].values()) for inf, _ in done),
                                               tile_seconds=sum(inf["seconds_total"] for inf, _ in done)))
    if len(pass_settings) > 1:  # each round's K-SVD, and the adaptations' time together
        record.update(rounds=[r for _, r in done], seconds=sum(r["seconds"] for _, r in done),
                      adapted=any(r["adapted"] for _, r in done))
    return D_i, store, record


def reconstruct_stream(method: str, codeds, mask_of, *, join: bool, still: bool = True, cuts=None,
                       spill: str | Path | None = None, noise_sigma: float = 0.0, white_level: float | None = None,
                       data_range, **options) -> Iterator[tuple[int, np.ndarray, dict]]:
    """A stream of captures (a coded camera's frames, or a benchmark file's measurements) -> their videos, in
    order: :func:`reconstruct_captures` as one job and, with ``join`` and more than one capture, the still
    answers shared with agreeing neighbours (:func:`codedvideo.model.sequence.still_values`) and the step from one
    capture to the next smoothed (:func:`codedvideo.model.sequence.joined`), except across the boundaries ``cuts``
    (:class:`codedvideo.model.sequence.Cuts`, made here when None) finds are no boundary of one scene.  ``still``:
    share still answers (False for a benchmark file's measurements, each of its own scene).  ``spill``: a
    folder where the captures the join holds wait on disk (:func:`codedvideo.formats.volumes.spilled`: the same bits,
    read a few frames at a time), or None to hold them in memory.  What the command line and the Python API
    (:func:`codedvideo.api.reconstruct`) both run; ``options`` as :func:`reconstruct_captures`."""
    count = len(codeds)
    if not join or count < 2:
        return reconstruct_captures(method, codeds, mask_of, data_range=data_range, white_level=white_level,
                                    noise_sigma=noise_sigma, **options)
    from codedvideo.model.sequence import Cuts, joined, still_values

    if cuts is None:
        cuts = Cuts(codeds, mask_of, scale=data_range.scale, white_level=white_level)
    # what did not change since the capture before or until the one after (asked again by the join)
    still_of = functools.lru_cache(maxsize=4)(
        lambda i: still_values(codeds, mask_of, i, sigma=noise_sigma, scale=data_range.scale,
                               white_level=white_level, cut=cuts)) if still else None
    results = reconstruct_captures(method, codeds, mask_of, data_range=data_range, white_level=white_level,
                                   still_of=still_of, noise_sigma=noise_sigma, **options)
    if spill is not None:
        from codedvideo.formats.volumes import spilled

        results = spilled(results, spill)
    # the step from one capture to the next smoothed along the motion, both measurements kept
    return joined(results, codeds, mask_of, data_range=data_range.value, still_of=still_of, white_level=white_level,
                  cut=cuts)


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


def reconstruct_capture(method: str, coded: np.ndarray, mask: np.ndarray, *, still: np.ndarray | None = None,
                        **options) -> tuple[np.ndarray, dict]:
    """One capture in its own units -> its video in the same units: a job of one (:func:`reconstruct_captures`);
    ``still``: its still values in working units, NaN where not still (:func:`codedvideo.model.sequence.still_values`)."""
    if still is not None and not np.issubdtype(np.asarray(still).dtype, np.floating):
        raise TypeError(f"still: the still values (float, NaN where not still), not {np.asarray(still).dtype} "
                        "(a map of still pixels: sequence.still_values gives the values)")
    results = reconstruct_captures(method, [coded], lambda i: mask, still_of=None if still is None else (lambda i: still),
                                   **options)
    with contextlib.closing(results):
        (_, volume, info), = results  # to its end: the job's cache budget is applied there
    return volume, info


def _static_volume(coded: np.ndarray, mask: np.ndarray) -> tuple[np.ndarray, dict]:
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


def trivial_estimate(coded: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Every sub-frame = coded / open count: the baseline a method must beat."""
    return physics.static_estimate(coded, mask)


def run_pipeline(cfg: PipelineConfig, *, progress: bool = True, config_path: str | Path | None = None) -> dict:
    """Run the stages the config names; return the metrics written.

    Every output is checked before any work (:func:`codedvideo.formats.outputs.check_outputs`):
    none may touch the config file, the scene, the code file, the dictionary,
    the training videos or the cache.
    """
    from codedvideo.engine.config import omp_settings
    from codedvideo.formats.outputs import Output, check_outputs, mark_written

    out = Path(cfg.output.dir)
    outputs = [Output(out, "place", "output.dir"), Output(out / cfg.output.video, "file", "output.video"),
               Output(out / "recon.npy", "file"), Output(metrics_path(out / cfg.output.video), "file", "metrics"),
               Output(out / "capture", "place", "capture folder")]
    outputs += [Output(out / "capture" / name, "file") for name in (*CAPTURE_FILES, "metrics.json")]
    if cfg.output.frames != "none":
        outputs.append(Output(out / "frames", "folder", "frames folder"))
    check_outputs(outputs, dict(config=config_path, scene=cfg.scene.video, code=cfg.code.path,
                                dictionary=cfg.dictionary.path, training=list(cfg.dictionary.training), cache=cfg.cache),
                  overwrite=cfg.output.overwrite)  # before any work
    from codedvideo.engine.config import check_scheduler

    cio.check_cache(cfg.cache)
    check_scheduler(cfg.reconstruct.scheduler)
    report: dict = dict(config=cfg.model_dump(mode="json"), seconds={})
    dict_path = capture = None
    if "simulate" in cfg.stages or "reconstruct" in cfg.stages:
        # the scene and the code read (and so checked) and the capture simulated before any training: a missing,
        # short or too small video, or a code file that does not fit, ends the run in a second, not after K-SVD
        t0 = time.perf_counter()
        video = load_video(cfg.scene.video, frames=cfg.frames, size=cfg.scene.size, seed=cfg.seed, start=cfg.scene.start)
        capture = simulate_capture(video, code=cfg.code.name, bump=cfg.code.bump, sigma=cfg.noise.sigma, seed=cfg.seed,
                                   p=cfg.code.p, code_path=cfg.code.path, sensor=sensor_model(cfg.noise))
        del video
        report["seconds"]["simulate"] = time.perf_counter() - t0
    if "train" in cfg.stages or "reconstruct" in cfg.stages:
        t0 = time.perf_counter()
        dict_path, dmeta = train_dictionary(cfg, progress=progress)
        report["seconds"]["train"] = time.perf_counter() - t0
        report["dictionary"] = dict(path=str(dict_path), reused=dmeta["reused"], atoms=dmeta["atoms"],
                                    method=dmeta.get("method"), final_rmse=dmeta.get("final_rmse"))
    # each output is recorded as codedvideo's as soon as it is in place, so that a run that fails or is
    # stopped later does not leave files that the next run must refuse as the user's
    if capture is not None:
        t0 = time.perf_counter()
        capture_paths = write_capture(capture, out / "capture")
        for path in capture_paths.values():
            mark_written(path)
        report["capture"] = {k: str(v) for k, v in capture_paths.items()}
        report["seconds"]["simulate"] += time.perf_counter() - t0
    if "reconstruct" in cfg.stages:
        D, dmeta = load_dictionary(dict_path)
        check_dictionary(dmeta, cfg.frames, dict_path)
        from codedvideo.model.units import capture_units

        rc = cfg.reconstruct
        report["preset"] = rc.preset_used()
        sensor = sensor_model(cfg.noise)
        # with shot noise / quantisation: the RMS noise at the mean coded level
        sigma = sensor.noise_sigma(float(capture["coded"].mean())) if sensor else cfg.noise.sigma
        units = capture_units([capture["coded"]], lambda i: capture["mask"], given=cfg.output.data_range,
                              noise_sigma=cfg.noise.sigma, where="simulated capture",
                              levels={"noise.sigma": cfg.noise.sigma, "noise.white_level": cfg.noise.white_level,
                                      "reconstruct.tol_rms": rc.tol_rms if rc.tol_rms != "auto" else None})
        report["data_range"] = units.as_dict()
        t0 = time.perf_counter()
        # saturated pixels (noise.white_level) are missing measurements
        volume, info = reconstruct_capture(
            rc.method, capture["coded"], capture["mask"], data_range=units, settings=omp_settings(rc, sigma, scale=units.scale),
            dictionary=D, dictionary_key=dmeta["sha256"], dictionary_name=str(dict_path),
            white_level=cfg.noise.white_level, where="simulated capture", tile=rc.tile, cache=cfg.cache,
            scheduler=rc.scheduler, workers=rc.workers, progress=progress, adapt=rc.adapt, adapt_rounds=rc.adapt_rounds,
            refine=rc.refine, noise_sigma=sigma, cache_budget=rc.cache_budget)
        report["seconds"]["reconstruct"] = time.perf_counter() - t0
        report["reconstruction"] = info
        t0 = time.perf_counter()
        video_path = write_volume(volume, out / cfg.output.video, fps=cfg.output.fps, data_range=units.value)
        mark_written(video_path)
        report["outputs"] = dict(video=str(video_path))
        if cfg.output.frames != "none":
            report["outputs"]["frames"] = str(out / "frames")
            cio.write_frames(out / "frames", volume, fmt=cfg.output.frames, data_range=units.value)
            mark_written(out / "frames")
        mark_written(cio.write_array(out / "recon.npy", volume))
        report["outputs"]["volume"] = str(out / "recon.npy")
        report["seconds"]["write"] = time.perf_counter() - t0
        if "evaluate" in cfg.stages:
            t0 = time.perf_counter()
            report["quality"] = evaluate(volume, capture["truth"], data_range=units.value)
            report["trivial"] = evaluate(trivial_estimate(capture["coded"], capture["mask"]), capture["truth"],
                                         data_range=units.value)
            report["seconds"]["evaluate"] = time.perf_counter() - t0
    report["seconds"]["total"] = sum(report["seconds"].values())
    # a run that reconstructs nothing (`make simulate`) keeps its record beside the capture: it replaced the last
    # reconstruction's record (and its PSNR), and says that reconstruction is not of this capture
    mpath = metrics_path(out / cfg.output.video) if "reconstruct" in cfg.stages else out / "capture" / "metrics.json"
    if "simulate" in cfg.stages and "reconstruct" not in cfg.stages:
        earlier = [p for p in (out / cfg.output.video, out / "recon.npy") if p.exists()]
        if earlier:
            warnings.warn(f"{', '.join(map(str, earlier))}: from an earlier run, not reconstructed from this capture "
                          "(run the reconstruct stage to replace them)", stacklevel=2)
    mark_written(write_json(mpath, report))
    report["metrics_path"] = str(mpath)
    return report


def reconstruct_method(
    method: str,
    coded: np.ndarray,
    mask: np.ndarray,
    *,
    dictionary: np.ndarray | None = None,
    dictionary_key: str = "",
    dictionary_name: str = "",
    settings=None,
    tile: int = 128,
    cache: str = "cache",
    scheduler: str | None = None,
    workers: int | None = None,
    progress: bool = False,
) -> tuple[np.ndarray, dict]:
    """Reconstruct with any method of :data:`codedvideo.solvers.baselines.METHODS` on the same forward model.

    ``omp`` runs :func:`codedvideo.engine.stages.reconstruct_volume` with
    ``dictionary``; ``dct`` runs it with the complete 3D DCT
    (:func:`codedvideo.solvers.dictionaries.dct_dictionary`); ``thinout``,
    ``interp`` and ``gaptv`` run the functions of this module with their
    defaults.

    Parameters
    ----------
    method : str
        One of :data:`codedvideo.solvers.baselines.METHODS`.
    coded : ndarray of shape (H, W)
    mask : ndarray of shape (N, H, W)
    dictionary : ndarray of shape (N * 49, K), optional
        Required for ``omp``; ignored otherwise.  Atoms of any nonzero norm
        give the same answer: it goes through
        :func:`~codedvideo.solvers.dictionaries.prepare_dictionary` (unit norm, zero
        atoms dropped with a warning, all-zero refused).
    dictionary_name : str
        Names the dictionary in those messages (e.g. its path).
    dictionary_key, settings, tile, cache, scheduler, workers, progress
        Passed to :func:`~codedvideo.engine.stages.reconstruct_volume` (``settings``
        an :class:`~codedvideo.solvers.region.OmpSettings`; default settings when None).

    Returns
    -------
    volume : ndarray of shape (N, H, W), float32
    info : dict
        ``method``, ``patches``, ``patches_per_second``, ``seconds``
        (``reconstruct``: wall time) and ``measurement_residual_rms``;
        for ``omp``/``dct`` everything :func:`reconstruct_volume` reports.
    """
    physics.check_pair(np.shape(coded), np.shape(mask))
    if method not in baselines.METHODS:
        raise InputError(f"method {method!r}: unknown; choose one of {', '.join(baselines.METHODS)}")
    if method in ("omp", "nonlocal", "dct"):
        settings, dictionary, dictionary_key = sparse_method(method, settings or OmpSettings(), dictionary,
                                                             dictionary_key, dictionary_name, frames=mask.shape[0])
        volume, info = reconstruct_volume(coded, mask, dictionary, settings=settings, tile=tile,
                                          cache=cache, scheduler=scheduler, workers=workers, progress=progress,
                                          dictionary_key=dictionary_key)
        return volume, dict(info, method=method, dictionary_atoms=int(dictionary.shape[1]))
    solve = dict(thinout=baselines.thinout, interp=baselines.interp, gaptv=baselines.gap_tv)[method]
    t0 = time.perf_counter()
    volume = solve(coded, mask)
    seconds = time.perf_counter() - t0
    residual = physics.forward(volume, mask) - np.asarray(coded, np.float32)
    info = dict(method=method, patches=0, patches_per_second=0.0, seconds=dict(reconstruct=seconds),
                measurement_residual_rms=float(np.sqrt(np.mean(residual.astype(np.float64) ** 2))))
    return volume, info
