"""Training a dictionary: the one a config describes, shipped, cached or trained (K-SVD)."""

from __future__ import annotations

import logging
import time
from pathlib import Path

import numpy as np

from codedvideo.data.scenes import training_videos
from codedvideo.data.shipped import init_dictionary
from codedvideo.formats.store import check_dictionary
from codedvideo.engine.cache import dictionary_entry, dictionary_key
from codedvideo.engine.config import PipelineConfig
from codedvideo.engine.parallel import progress_bar
from codedvideo.formats import io as cio
from codedvideo.formats.store import entry_lock, load_dictionary, save_dictionary
from codedvideo.model.errors import ConfigError, InputError
from codedvideo.model.patches import PATCH
from codedvideo.solvers.dictionaries import dct_dictionary, learn_dictionary

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
        check_dictionary(meta, cfg.frames, dc.path, D, needs="frames: asks for")
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
    cached = dictionary_entry(cfg.cache, key)
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
                    bar = progress_bar(dc.iterations, "K-SVD") if progress else None
                    D, meta = learn_dictionary(
                        videos,
                        frames=cfg.frames,
                        settings=dc.ksvd(),
                        seed=cfg.seed,
                        progress=(lambda it, rmse: (bar.update(1), bar.set_postfix(rmse=f"{rmse:.2f}"))) if bar else None,
                        init=None if dc.init is None else init_dictionary(dc.init, cfg.frames)[0],
                    )
                    if dc.init is not None:
                        meta["init"] = dc.init
                    if bar:
                        bar.close()
                    meta["training_set"] = used  # (videos too short or too small were left out, with a warning)
                    meta["training_given"] = list(dc.training)  # (a later run's names, when it reuses this one)
                    if SYNTH_TRAIN in dc.training:
                        meta["clips"] = dc.clips
                meta["settings_key"] = key
                save_dictionary(cached, D, meta)
                D, meta = load_dictionary(cached)  # read back and checked against its sha256, under the lock
                cached_ok = False
    if found is not None:
        (D, meta), cached_ok = found, True
        meta = _named_for(meta, dc.training)
        log.info("dictionary: reusing %s", cached)
    result = cached
    if output is not None and Path(output) != result:
        save_dictionary(output, D, {k: v for k, v in meta.items() if k not in ("atoms", "sha256", "kind", "format_version")})
        result = Path(output)
        _, meta = load_dictionary(result)
    return result, dict(meta, reused=cached_ok, seconds=time.perf_counter() - t0)


#: The generated training clips' name among ``dictionary.training``.
SYNTH_TRAIN = "synth:train"


def _named_for(meta: dict, training: list[str]) -> dict:
    """A reused dictionary's record with this run's names of its training videos: the cache key holds their
    contents, not their names, so a run on copies under other names reuses it (the videos at the places the
    first run used, by their order in ``dictionary.training``)."""
    given = meta.get("training_given")
    if "training_set" not in meta or given is None or len(given) != len(training):
        return meta
    used = set(meta["training_set"])
    return dict(meta, training_set=[now for was, now in zip(given, training) if was in used],
                training_given=list(training))


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


def _check_training_memory(samples: int, frames: int) -> None:
    """Refuse, before any work, a number of training samples whose patches would not fit in memory: K-SVD
    draws three candidate blocks a sample and keeps the samples and their residuals, float32 (10 M samples
    at N = 64 ended in a MemoryError traceback after 50 s)."""
    need = 5 * 4 * samples * frames * PATCH * PATCH
    free = cio.available_memory()
    if free is not None and need > 0.75 * free:
        raise ConfigError(f"dictionary.samples {samples} (--samples): {samples} training patches of 7x7x{frames} "
                          f"need about {need / 2**30:.1f} GiB, {free / 2**30:.1f} GiB are free; give fewer samples")
