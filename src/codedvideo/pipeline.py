"""The application layer: stages that read files, cache results and report metrics.

Stages (train, simulate, reconstruct, evaluate) are functions of their settings
and inputs; each result is cached under a key that hashes both, so a rerun
reuses a dictionary, a simulated capture or finished reconstruction tiles
instead of recomputing them.  Every reconstruction writes a metrics JSON beside
its output: seconds per stage, patches per second, atoms used, and PSNR/SSIM
when the truth is known (no-reference statistics otherwise).
"""

from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import json
import logging
import time
import warnings
from pathlib import Path

import numpy as np
from scipy import ndimage

from . import io as cio
from . import patches as P
from .patches import PATCH
from . import manifest, physics, synth
from .codes import make_code
from .config import PipelineConfig
from .dictionaries import dct_dictionary, learn_dictionary
from .errors import InputError
from .metrics import evaluate
from .parallel import plan_tiles, reconstruct_tiles
from .reconstruct import STAT_NAMES, OmpSettings
from .store import WorkStore, entry_lock, load_array, load_dictionary, save_array, save_dictionary

log = logging.getLogger("codedvideo")

#: Part of every reconstruction cache key: bump it when the per-tile algorithm changes
#: its output, so that tiles computed by an older version are never reused.
RECON_VERSION = "recon-v4"  # v4: per-tile digests in the working store
VIDEO_SUFFIXES = cio.VIDEO_SUFFIXES


# ----------------------------------------------------------------------------- hashing
def content_key(*parts) -> str:
    """A short sha256 over settings (JSON-able) and arrays."""
    h = hashlib.sha256()
    for part in parts:
        if isinstance(part, np.ndarray):
            h.update(str((part.shape, part.dtype.str)).encode())
            h.update(np.ascontiguousarray(part).tobytes())
        else:
            h.update(json.dumps(part, sort_keys=True, default=str).encode())
    return h.hexdigest()[:16]


def _write_json(path: Path, payload: dict) -> Path:
    from .metrics import json_safe

    with cio.atomic_output(path) as tmp:  # strict JSON: an infinite PSNR is null
        Path(tmp).write_text(json.dumps(json_safe(payload), indent=2, default=_json_default, allow_nan=False) + "\n")
    return path


def _json_default(o):
    if isinstance(o, (np.integer,)):
        return int(o)
    if isinstance(o, (np.floating,)):
        return float(o)
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


# ----------------------------------------------------------------------------- inputs
def load_video(spec: str, *, frames: int, size: tuple[int, int] | None, seed: int = 0, start: int = 0) -> np.ndarray:
    """A scene as (frames, H, W) float32: ``synth:NAME``, ``footage:NAME`` (held-out real clips,
    :mod:`codedvideo.footage`) or a video / frame-sequence path.

    Files are centre-cropped to ``size`` when they are larger.
    """
    if spec.startswith("synth:"):
        name = spec.split(":", 1)[1]
        manifest.verify_ids(manifest.SCENE_PHOTOS.get(name, synth.TEST_PHOTOS))
        return synth.make_scene(name, frames=frames, size=tuple(size or (256, 256)), seed=seed)
    if spec.startswith("footage:"):
        from .footage import footage_scene

        return footage_scene(spec.split(":", 1)[1], frames=frames, size=size)
    return read_clip(spec, frames=frames, size=size, start=start)


def read_clip(spec: str, *, frames: int, size: tuple[int, int] | None, start: int = 0, color: str = "luma") -> np.ndarray:
    """``frames`` frames of a video / frame-sequence file from ``start``, centre-cropped to ``size``:
    (frames, H, W), or (C, frames, H, W) with ``color="channels"``, float32."""
    video = cio.read_video(resolve_data(spec), max_frames=frames, start=start, color=color)
    if video.shape[-3] < frames:
        raise InputError(f"video {spec}: has {video.shape[-3]} frames from frame {start}, need {frames}")
    if size is not None:
        h, w = size
        if video.shape[-2] < h or video.shape[-1] < w:
            raise InputError(f"video {spec}: frames {video.shape[-2:]} smaller than the requested size {tuple(size)}")
        y0, x0 = (video.shape[-2] - h) // 2, (video.shape[-1] - w) // 2
        video = video[..., y0 : y0 + h, x0 : x0 + w]
    return np.ascontiguousarray(video[..., :frames, :, :], dtype=np.float32)


def training_videos(specs: list[str], *, frames: int, clips: int, seed: int, max_speed: float = synth.MAX_SPEED) -> list[np.ndarray]:
    """Training clips: ``synth:train`` (generated) and/or user video paths."""
    videos: list[np.ndarray] = []
    for spec in specs:
        if spec == "synth:train":
            manifest.verify_ids(synth.TRAIN_PHOTOS)
            videos.extend(synth.training_videos(frames=frames, count=clips, seed=seed, max_speed=max_speed))
        else:
            videos.append(cio.read_video(resolve_data(spec), max_frames=max(frames * 16, 64)))
    return videos


def resolve_data(spec: str) -> str:
    """``manifest:ID`` -> the verified file of that data_manifest entry; a path stays a path."""
    if spec.startswith("manifest:"):
        entry = manifest.lookup(spec.split(":", 1)[1])
        return str(manifest.verify(entry))
    return spec


# ----------------------------------------------------------------------------- train
def dictionary_key(cfg: PipelineConfig) -> str:
    """The key of the training settings of ``cfg`` (cache entries and shipped dictionaries carry it)."""
    settings = dict(cfg.dictionary.model_dump(exclude={"path"}), frames=cfg.frames, seed=cfg.seed, patch=PATCH)
    return content_key("dictionary-v1", settings)


def train_dictionary(cfg: PipelineConfig, *, output: str | Path | None = None, progress: bool = True,
                     retrain: bool = False) -> tuple[Path, dict]:
    """Train the dictionary the config describes, or reuse it: shipped (:mod:`codedvideo.shipped`) or cached.

    ``retrain`` trains even when a shipped dictionary has these settings (`make train`).
    """
    from . import shipped

    dc = cfg.dictionary
    if dc.path:
        D, meta = load_dictionary(dc.path)
        _check_dictionary(meta, cfg.frames, dc.path)
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
    videos = None
    if found is None and dc.kind != "dct":  # read (and so check) the training videos before touching the cache
        videos = training_videos(dc.training, frames=cfg.frames, clips=dc.clips, seed=cfg.seed, max_speed=dc.max_speed)
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
                    )
                    if bar:
                        bar.close()
                    meta["training_set"] = list(dc.training)
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


def _check_dictionary(meta: dict, frames: int, path) -> None:
    if meta.get("patch") != PATCH:
        raise InputError(f"dictionary {path}: patch size {meta.get('patch')} != {PATCH}")
    if meta.get("frames") != frames:
        raise InputError(f"dictionary {path}: built for N = {meta.get('frames')} sub-frames, the mask has N = {frames}")


def _progress_bar(total: int, desc: str):
    from tqdm.auto import tqdm

    return tqdm(total=total, desc=desc, unit="it", leave=False)


# ----------------------------------------------------------------------------- simulate
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
        The code (:func:`codedvideo.codes.make_code`; ``code_path`` for ``file``).
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
    (N, H, W) uint8, or (T, N, H, W) with a new code per capture; ``truth``
    (T * N, H, W) float32
    """
    if captures < 1 or video.shape[0] % captures:
        raise InputError(f"video of {video.shape[0]} frames: not {captures} captures of equal length")
    n = video.shape[0] // captures
    ss = np.random.SeedSequence(seed)
    code_rng, noise_rng = (np.random.default_rng(s) for s in ss.spawn(2))
    masks = [make_code(code, video.shape[1:], frames=n, bump=bump, p=p, rng=code_rng, path=code_path)
             for _ in range(captures if new_code_per_capture else 1)]
    if sensor is not None:
        sensor = dataclasses.replace(sensor, read_sigma=sigma)
    coded = []
    for t in range(captures):  # one noise stream, drawn capture after capture
        clip, mask = video[t * n : (t + 1) * n], masks[t % len(masks)]
        coded.append(physics.simulate(clip, mask, sigma=sigma, rng=noise_rng) if sensor is None
                     else physics.simulate(clip, mask, rng=noise_rng, sensor=sensor))
    return dict(coded=coded[0] if captures == 1 else np.stack(coded),
                mask=masks[0] if len(masks) == 1 else np.stack(masks), truth=np.asarray(video, np.float32))


def sensor_model(noise) -> physics.SensorModel | None:
    """The :class:`~codedvideo.physics.SensorModel` of a ``NoiseConfig`` (None: read noise only)."""
    if not noise.shot_noise and noise.bits is None and noise.white_level is None and not noise.black_level:
        return None
    return physics.SensorModel(shot_noise=noise.shot_noise, full_well=noise.full_well, gain=noise.gain,
                               read_sigma=noise.sigma, bits=noise.bits, white_level=noise.white_level,
                               black_level=noise.black_level)


def drop_saturated(coded: np.ndarray, mask: np.ndarray, white_level: float) -> tuple[np.ndarray, np.ndarray, int]:
    """Saturated pixels as missing measurements (:func:`codedvideo.physics.saturated_as_missing`).

    Returns the coded image with saturated pixels set to 0 (so that the
    measurement residual ignores them), the mask without them, and their count.
    """
    mask_used, count = physics.saturated_as_missing(coded, mask, white_level)
    if count:
        coded = np.where(coded >= np.float32(white_level), np.float32(0), coded).astype(np.float32)
    return coded, mask_used, count


#: The files :func:`write_capture` writes into its folder.
CAPTURE_FILES = ("coded.npy", "mask.npy", "truth.npy", "coded.tif")


def write_capture(capture: dict[str, np.ndarray], outdir: str | Path) -> dict[str, Path]:
    """Write coded.npy, mask.npy, truth.npy and coded.tif (:data:`CAPTURE_FILES`) into ``outdir``."""
    outdir = Path(outdir)
    paths = {}
    for name in ("coded", "mask", "truth"):
        paths[name] = outdir / f"{name}.npy"
        cio.write_array(paths[name], capture[name])
    paths["coded_tif"] = outdir / "coded.tif"
    if capture["coded"].ndim == 3:  # several captures: one page each
        cio.write_stack(paths["coded_tif"], capture["coded"], dtype=np.float32)
    else:
        cio.write_image(paths["coded_tif"], capture["coded"])
    return paths


# ----------------------------------------------------------------------------- reconstruct
def read_coded(path: str | Path, *, color: str = "luma") -> np.ndarray:
    """A coded image (H, W) float32, or (C, H, W) with ``color="channels"`` (see :mod:`codedvideo.io`)."""
    coded = cio.read_image(path, color=color)
    if not np.isfinite(coded).all():
        raise InputError(f"coded image {path}: contains NaN or Inf")
    return coded


def read_coded_stack(path: str | Path) -> np.ndarray:
    """Coded images (T, H, W) float32: a .npy (H, W) or (T, H, W), a (multi-page) image, a folder or
    printf pattern of images, or a lossless video (one coded image per video frame)."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix == ".npy":
        arr = cio.read_array(path)
        if arr.ndim not in (2, 3):
            raise InputError(f"coded image {path}: expected shape (H, W) or (T, H, W), got {arr.shape}")
        coded = arr.astype(np.float32).reshape((-1, *arr.shape[-2:]))
    elif suffix in VIDEO_SUFFIXES:
        coded = cio.read_video(path)
    else:
        coded = cio.read_stack(path)
    if not np.isfinite(coded).all():
        raise InputError(f"coded image {path}: contains NaN or Inf")
    return coded


def read_masks(path: str | Path) -> np.ndarray:
    """A mask (N, H, W), or one mask per capture (T, N, H, W) from a .npy (see :func:`read_mask`)."""
    if Path(path).suffix.lower() == ".npy":
        arr = cio.read_array(path)
        if arr.ndim == 4:
            return np.stack([_checked_mask(m, path) for m in arr])
    return read_mask(path)


def read_mask(path: str | Path) -> np.ndarray:
    return _checked_mask(cio.read_stack(path), path)


def _checked_mask(mask: np.ndarray, path) -> np.ndarray:
    """A binary code (uint8), or a calibrated mask: each pixel's measured response per sub-frame in [0, 1] (float32)."""
    from .omp import is_binary

    mask = np.asarray(mask)
    if not np.isfinite(mask).all():
        raise InputError(f"mask {path}: contains NaN or Inf")
    outside = (mask < 0) | (mask > 1)
    if outside.any():
        bad = np.unique(mask[outside])[:3].tolist()
        raise InputError(f"mask {path}: values outside [0, 1] (e.g. {bad}); a mask is 0/1, or a calibrated "
                         "response per sub-frame in [0, 1]")
    if not mask.any():
        raise InputError(f"mask {path}: no pixel is ever open (all zeros); there is nothing to reconstruct")
    return mask.astype(np.uint8) if is_binary(mask) else mask.astype(np.float32)


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
    """Reconstruct a coded image through the Zarr working store and the dask graph.

    Returns the volume (N, H, W) float32 and a dict of statistics and timings.

    When every pixel has the same shutter pattern (open in every sub-frame:
    bump length N, the global shutter, N = 1; or a global flutter sequence) no
    pixel tells one instant from another, so per-patch sparse coding can only
    invent motion (measured: a flutter code fell 6 dB below the static
    estimate): the result is then the static estimate ``coded / open count``
    itself (``method: "static"`` in
    the statistics), computed directly without tiles.  Patches that stopped
    early because their next atom was numerically dependent on the chosen
    ones are counted (``dependent_stops``) and reported by a warning.

    The working store is the cache entry ``cache/recon-KEY.zarr``, shared by
    every run with the same inputs and settings: runs on one entry take its
    lock in turn (a second run waits, then reuses the finished tiles); an
    entry whose metadata or inputs are damaged is rebuilt, and a tile that
    fails its checksum when read back is computed again, never returned
    (``tiles_damaged`` in the statistics).
    """
    physics.check_pair(coded.shape, mask.shape)
    n, h, w = mask.shape
    if D.shape[0] != n * PATCH * PATCH:
        raise InputError(f"dictionary has {D.shape[0]} rows, the mask needs N*49 = {n * PATCH * PATCH} (N = {n})")
    if h < PATCH or w < PATCH:
        raise InputError(f"coded image {h}x{w} is smaller than one {PATCH}x{PATCH} patch")
    never_open = int((~mask.astype(bool).any(0)).sum())
    if never_open == h * w:
        raise InputError("mask: no pixel is ever open; there is nothing to reconstruct")
    if never_open:
        warnings.warn(f"{never_open} pixels are never open; they are filled from their neighbours", stacklevel=2)
    if (mask == mask[:, :1, :1]).all():  # one shutter pattern for all pixels: no temporal information
        return _static_volume(coded, mask)
    timings = {}
    t0 = time.perf_counter()
    tiles = plan_tiles((h, w), tile, patch=PATCH)
    key = content_key(RECON_VERSION, coded, mask, dictionary_key or content_key(D), settings.__dict__, tile)
    entry = Path(cache) / f"recon-{key}.zarr"
    # One run at a time per entry (processes, threads, clients of one dask cluster): a second run
    # waits here, then reuses the tiles the first one finished.  Every tile is checked against its
    # digest as it is read back; a damaged entry is rebuilt, a damaged tile computed again.
    with entry_lock(entry):
        store = WorkStore.create(
            entry, coded, mask, tile=tile, n_stats=len(STAT_NAMES), n_tiles=len(tiles),
            attrs=dict(key=key, settings=settings.__dict__, tile=tile, version=RECON_VERSION),
        )
        timings["store_inputs"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        volume, summary = reconstruct_tiles(store, D, settings, tile=tile, patch=PATCH, scheduler=scheduler,
                                            workers=workers, progress=progress)
    timings["assemble"] = summary.pop("seconds_verify")  # reading every tile back and checking its digest
    timings["reconstruct"] = time.perf_counter() - t0 - timings["assemble"]
    if summary.get("dependent_stops"):
        warnings.warn(f"{int(summary['dependent_stops'])} of {int(summary['patches'])} patches stopped early: their "
                      "next atom was numerically dependent on the chosen ones (near-duplicate or degenerate "
                      "dictionary atoms)", stacklevel=2)
    holes = P.uncovered_pixels(mask.astype(bool).any(0), PATCH, settings.stride)
    if not np.isfinite(volume[:, ~holes]).all():
        raise RuntimeError(f"working store {store.path}: volume has unwritten or non-finite pixels")
    if holes.any():  # no measured patch covers them: the nearest reconstructed pixel
        _, (iy, ix) = ndimage.distance_transform_edt(holes, return_indices=True)
        volume[:, holes] = volume[:, iy[holes], ix[holes]]
    residual = physics.forward(volume, mask) - coded
    info = dict(
        summary,
        never_open_pixels=never_open,
        filled_pixels=int(holes.sum()),
        atoms_mean=summary["atoms_total"] / max(summary["patches"] - summary["patches_static"], 1),
        static_fraction=summary["patches_static"] / max(summary["patches"], 1),
        patches_per_second=summary["patches"] / max(summary["seconds_total"], 1e-9) * (summary["tiles_computed"] > 0),
        measurement_residual_rms=float(np.sqrt(np.mean(residual.astype(np.float64) ** 2))),
        work_store=str(store.path),
        seconds=timings,
        method="sparse",
    )
    return volume, info


def reconstruct_capture(
    method: str,
    coded: np.ndarray,
    mask: np.ndarray,
    *,
    data_range,
    settings: OmpSettings,
    dictionary: np.ndarray | None = None,
    dictionary_key: str = "",
    dictionary_name: str = "",
    white_level: float | None = None,
    still: np.ndarray | None = None,
    where: str = "coded image",
    tile: int = 128,
    cache: str | Path = "cache",
    scheduler: str | None = None,
    workers: int | None = None,
    progress: bool = True,
) -> tuple[np.ndarray, dict]:
    """One capture in its own units -> its video in the same units, by any method.

    The capture is scaled to working units (:class:`codedvideo.units.DataRange`,
    ``settings`` already in them), reconstructed and scaled back, so the same
    capture in other units gives the same video times the scale.  Pixels at
    or above ``white_level`` (capture units; None: trust every pixel) are
    missing measurements.  Pixels of ``still`` (:func:`codedvideo.sequence.still_pixels`)
    take ``coded / open count`` in every sub-frame, and the patches over them
    are left out of the sparse coding.
    """
    from .baselines import reconstruct_method

    coded_used, mask_used, saturated = coded, mask, 0
    if white_level is not None:
        coded_used, mask_used, saturated = drop_saturated(coded, mask, white_level)
        if saturated and not mask_used.any():
            raise InputError(f"{where}: every measured pixel is at or above --white-level {white_level}; "
                             "nothing is left to reconstruct (--trust-saturated uses them anyway)")
    scale = np.float32(data_range.scale)
    if scale != 1:
        coded_used = np.asarray(coded_used, np.float32) * scale
    n_still = 0
    if still is not None:
        still = still & np.asarray(mask_used).any(0)
        n_still = int(still.sum())
    if n_still == still_total(mask_used) and n_still:  # nothing moves: no sparse coding at all
        volume, info = _static_volume(coded_used, mask_used)
    else:
        if n_still:  # the still pixels' patches: left out (no measurement, so no patch estimate)
            mask_used = np.where(still[None], 0, mask_used).astype(mask_used.dtype)
            coded_used = np.where(still, 0, coded_used).astype(np.float32)
        with warnings.catch_warnings():
            if n_still:
                warnings.filterwarnings("ignore", message=".*pixels are never open.*")
            volume, info = reconstruct_method(method, coded_used, mask_used, dictionary=dictionary, settings=settings,
                                              tile=tile, cache=cache, scheduler=scheduler, workers=workers,
                                              progress=progress, dictionary_key=dictionary_key,
                                              dictionary_name=dictionary_name)
    if n_still:
        from .sequence import normalised

        q = normalised(coded, mask)[0] * scale
        volume[:, still] = q[still]
    info["still_pixels"] = n_still
    if scale != 1:
        volume = volume / scale
        if info.get("measurement_residual_rms") is not None:
            info["measurement_residual_rms"] = float(info["measurement_residual_rms"]) / float(scale)
    info["saturated_pixels"] = saturated
    return volume, info


def still_total(mask: np.ndarray) -> int:
    """Pixels that are open at least once."""
    return int(np.asarray(mask).any(0).sum())


def _static_volume(coded: np.ndarray, mask: np.ndarray) -> tuple[np.ndarray, dict]:
    """The static estimate of a mask with one pattern for all pixels, with the statistics of :func:`reconstruct_volume`."""
    t0 = time.perf_counter()
    volume = physics.static_estimate(coded, mask)
    residual = physics.forward(volume, mask) - np.asarray(coded, np.float32)
    seconds = time.perf_counter() - t0
    info = dict(
        {name: 0.0 for name in STAT_NAMES},
        tiles=0, tiles_computed=0, tiles_reused=0, never_open_pixels=0, filled_pixels=0, atoms_mean=0.0,
        static_fraction=1.0, patches_per_second=0.0,
        measurement_residual_rms=float(np.sqrt(np.mean(residual.astype(np.float64) ** 2))),
        work_store=None, seconds=dict(store_inputs=0.0, reconstruct=seconds, assemble=0.0), method="static",
    )
    return volume, info


@contextlib.contextmanager
def volume_writer(output: str | Path, shape: tuple, *, data_range: float = 255.0, fps: int = 30):
    """Write a volume part by part, as its parts are reconstructed: yields ``put(index, part)``.

    Parts come in order (``volume[index] = part``, the indices consecutive
    along the first axis).  ``.npy`` outputs are streamed: the header, then
    each part appended to a temporary file, renamed onto ``output`` when the
    block ends complete, so memory does not grow with the number of captures
    (a memory map would: the pages written stay in the process's resident
    set).  Other formats gather the parts and go through :func:`write_volume`
    at the end.
    """
    output = Path(output)
    if output.suffix.lower() == ".npy":
        total = int(np.prod(shape)) * 4
        with cio.atomic_output(output) as tmp:
            with open(tmp, "wb") as fh:
                np.lib.format.write_array_header_2_0(fh, dict(descr="<f4", fortran_order=False, shape=tuple(shape)))
                start = fh.tell()

                def put(index, part):
                    fh.write(np.ascontiguousarray(part, dtype="<f4").tobytes())

                yield put
                if fh.tell() - start != total:
                    raise RuntimeError(f"output {output}: {fh.tell() - start} of {total} bytes written")
        return
    volume = np.empty(tuple(shape), np.float32)

    def gather(index, part):
        volume[index] = part

    yield gather
    write_volume(volume, output, data_range=data_range, fps=fps)


def write_volume(volume: np.ndarray, output: str | Path, *, data_range: float = 255.0, fps: int = 30) -> Path:
    """Write a volume by the output's suffix.

    Parameters
    ----------
    volume : ndarray of shape (N, H, W), or (C, N, H, W) for colour
    output : str or Path
        ``.npy`` (float32, as given), ``.zarr`` (float32 Zarr array), ``.mat``
        (MATLAB v5, ``recon`` (H, W, N) single), ``.tif``/``.tiff``
        (multi-page float32), ``.mp4`` (H.264), ``.mkv``/``.avi`` (FFV1,
        lossless 8-bit), ``.gif``, or a name without suffix (or ``.d``): a
        folder of 16-bit TIFF frames.  Videos and frames scale ``data_range``
        to full scale.
    """
    output = Path(output)
    suffix = output.suffix.lower()
    volume = np.asarray(volume)
    if suffix == ".npy":
        cio.write_array(output, volume.astype(np.float32))
    elif suffix == ".zarr":
        save_array(output, volume.astype(np.float32), chunks=volume.shape[:-2] + (256, 256),
                   attrs=dict(kind="codedvideo-volume"))
    elif suffix == ".mat":
        from .cacti import write_mat_volume

        write_mat_volume(output, volume)
    elif suffix in (".tif", ".tiff"):
        cio.write_stack(output, volume, dtype=np.float32)
    elif suffix in VIDEO_SUFFIXES:
        cio.write_video(output, volume, data_range=data_range, fps=fps)
    elif suffix in ("", ".d"):
        cio.write_frames(output, volume, fmt="tiff16", data_range=data_range)
    else:
        raise InputError(f"output {output}: unknown format {suffix!r} "
                         "(use .npy, .zarr, .mat, .tif, .mp4, .mkv, .gif or a folder)")
    return output


#: Suffixes :func:`write_volume` writes ("" and ".d": a folder of 16-bit TIFF frames).
OUTPUT_SUFFIXES = (".npy", ".zarr", ".mat", ".tif", ".tiff", ".mp4", ".mkv", ".avi", ".gif", "", ".d")


def output_kind(output: str | Path) -> str:
    """``"file"`` or ``"folder"``: what :func:`write_volume` writes at ``output`` (an unknown suffix is an error)."""
    if Path(output).name in ("", ".", ".."):
        raise InputError(f"output {output}: names no file or folder of its own; give a new name such as out.npy")
    suffix = Path(output).suffix.lower()
    if suffix not in OUTPUT_SUFFIXES:
        raise InputError(f"output {output}: unknown format {suffix!r} "
                         "(use .npy, .zarr, .mat, .tif, .mp4, .mkv, .avi, .gif or a folder)")
    return "folder" if suffix in (".zarr", "", ".d") else "file"


def check_size(shape: tuple, path, patch: int = PATCH) -> None:
    """Raise :class:`InputError` naming ``path`` when an (H, W) image is smaller than one patch.

    One-pixel-wide strips (and anything narrower than ``patch`` pixels) are
    refused: no ``patch x patch`` patch fits, so the sparse model has nothing
    to work on.
    """
    h, w = shape[-2:]
    if h < patch or w < patch:
        raise InputError(f"coded image {path}: {h}x{w} pixels is smaller than one {patch}x{patch} patch "
                         f"(at least {patch} rows and {patch} columns are needed)")


def metrics_path(output: str | Path) -> Path:
    output = Path(output)
    return output.with_name((output.stem if output.suffix else output.name) + ".metrics.json")


def read_volume(path: str | Path, *, color: str = "luma") -> np.ndarray:
    """Read a volume written by :func:`write_volume` (or any stack :func:`codedvideo.io.read_stack` reads).

    A ``.mat`` file gives its ``recon`` variable, else ``orig`` (a CACTI
    file's ground truth).  ``.npy``, ``.zarr`` and ``.mat`` give the array as
    stored (N, H, W) or (C, N, H, W); images and videos follow ``color``.

    Returns
    -------
    ndarray of shape (N, H, W) (or (C, N, H, W)), float32
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix == ".zarr":
        return load_array(path)
    if suffix == ".mat":
        from .cacti import read_mat_volume

        return read_mat_volume(path)
    if suffix == ".npy":
        arr = cio.read_array(path)
        if arr.ndim not in (3, 4):
            raise InputError(f"volume {path}: expected shape (N, H, W) or (C, N, H, W), got {arr.shape}")
        if not np.isfinite(arr).all():
            raise InputError(f"volume {path}: contains NaN or Inf")
        return arr.astype(np.float32)
    if suffix in VIDEO_SUFFIXES:
        return cio.read_video(path, color=color)
    if path.is_dir():  # a frame folder written by write_frames reads back in frame units
        return cio.read_stack(path, color=color) * np.float32(cio.read_frames_scale(path))
    return cio.read_stack(path, color=color)


def trivial_estimate(coded: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Every sub-frame = coded / open count: the baseline a method must beat."""
    return physics.static_estimate(coded, mask)


def run_pipeline(cfg: PipelineConfig, *, progress: bool = True, config_path: str | Path | None = None) -> dict:
    """Run the stages the config names; return the metrics written.

    Every output is checked before any work (:func:`codedvideo.outputs.check_outputs`):
    none may touch the config file, the scene, the code file, the dictionary,
    the training videos or the cache.
    """
    from .config import omp_settings
    from .outputs import Output, check_outputs, mark_written

    out = Path(cfg.output.dir)
    outputs = [Output(out, "place", "output.dir"), Output(out / cfg.output.video, "file", "output.video"),
               Output(out / "recon.npy", "file"), Output(metrics_path(out / cfg.output.video), "file", "metrics"),
               Output(out / "capture", "place", "capture folder")]
    outputs += [Output(out / "capture" / name, "file") for name in CAPTURE_FILES]
    if cfg.output.frames != "none":
        outputs.append(Output(out / "frames", "folder", "frames folder"))
    check_outputs(outputs, dict(config=config_path, scene=cfg.scene.video, code=cfg.code.path,
                                dictionary=cfg.dictionary.path, training=list(cfg.dictionary.training), cache=cfg.cache),
                  overwrite=cfg.output.overwrite)  # before any work
    from .config import check_scheduler

    check_scheduler(cfg.reconstruct.scheduler)
    report: dict = dict(config=cfg.model_dump(mode="json"), seconds={})
    dict_path = None
    if "train" in cfg.stages or "reconstruct" in cfg.stages:
        t0 = time.perf_counter()
        dict_path, dmeta = train_dictionary(cfg, progress=progress)
        report["seconds"]["train"] = time.perf_counter() - t0
        report["dictionary"] = dict(path=str(dict_path), reused=dmeta["reused"], atoms=dmeta["atoms"],
                                    method=dmeta.get("method"), final_rmse=dmeta.get("final_rmse"))
    capture = None
    written: list[Path] = []
    if "simulate" in cfg.stages or "reconstruct" in cfg.stages:
        t0 = time.perf_counter()
        video = load_video(cfg.scene.video, frames=cfg.frames, size=cfg.scene.size, seed=cfg.seed, start=cfg.scene.start)
        capture = simulate_capture(video, code=cfg.code.name, bump=cfg.code.bump, sigma=cfg.noise.sigma, seed=cfg.seed,
                                   p=cfg.code.p, code_path=cfg.code.path, sensor=sensor_model(cfg.noise))
        capture_paths = write_capture(capture, out / "capture")
        written += capture_paths.values()
        report["capture"] = {k: str(v) for k, v in capture_paths.items()}
        report["seconds"]["simulate"] = time.perf_counter() - t0
    if "reconstruct" in cfg.stages:
        D, dmeta = load_dictionary(dict_path)
        _check_dictionary(dmeta, cfg.frames, dict_path)
        from .units import infer_data_range, static_peak

        rc = cfg.reconstruct
        sensor = sensor_model(cfg.noise)
        # with shot noise / quantisation: the RMS noise at the mean coded level
        sigma = sensor.noise_sigma(float(capture["coded"].mean())) if sensor else cfg.noise.sigma
        units = infer_data_range(static_peak(capture["coded"], capture["mask"]), given=cfg.output.data_range)
        report["data_range"] = units.as_dict()
        t0 = time.perf_counter()
        # saturated pixels (noise.white_level) are missing measurements
        volume, info = reconstruct_capture(
            "omp", capture["coded"], capture["mask"], data_range=units, settings=omp_settings(rc, sigma, scale=units.scale),
            dictionary=D, dictionary_key=dmeta["sha256"], dictionary_name=str(dict_path),
            white_level=cfg.noise.white_level, where="simulated capture", tile=rc.tile, cache=cfg.cache,
            scheduler=rc.scheduler, workers=rc.workers, progress=progress)
        report["seconds"]["reconstruct"] = time.perf_counter() - t0
        report["reconstruction"] = info
        t0 = time.perf_counter()
        video_path = write_volume(volume, out / cfg.output.video, fps=cfg.output.fps, data_range=units.value)
        written.append(video_path)
        report["outputs"] = dict(video=str(video_path))
        if cfg.output.frames != "none":
            report["outputs"]["frames"] = str(out / "frames")
            cio.write_frames(out / "frames", volume, fmt=cfg.output.frames, data_range=units.value)
        written.append(cio.write_array(out / "recon.npy", volume))
        report["outputs"]["volume"] = str(out / "recon.npy")
        report["seconds"]["write"] = time.perf_counter() - t0
        if "evaluate" in cfg.stages:
            t0 = time.perf_counter()
            report["quality"] = evaluate(volume, capture["truth"], data_range=units.value)
            report["trivial"] = evaluate(trivial_estimate(capture["coded"], capture["mask"]), capture["truth"],
                                         data_range=units.value)
            report["seconds"]["evaluate"] = time.perf_counter() - t0
    report["seconds"]["total"] = sum(report["seconds"].values())
    written.append(_write_json(metrics_path(out / cfg.output.video), report))
    for path in written:
        mark_written(path)
    report["metrics_path"] = str(metrics_path(out / cfg.output.video))
    return report
