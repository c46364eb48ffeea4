"""The training job both doors run: settings checked before any work (:func:`plan_training`), then the
dictionary learned (or reused from the cache) and stored (:func:`train_dictionary`)."""

from __future__ import annotations

from pathlib import Path

from codedvideo.api._settings import setting_name
from codedvideo.engine.config import DEFAULT_CACHE, DictionaryConfig, PipelineConfig, validated
from codedvideo.engine.training import train_dictionary
from codedvideo.model.errors import ConfigError

__all__ = ["plan_training", "train_dictionary"]

#: File types a dictionary is never stored as (it is a Zarr store: a folder, or a zipped one).
NOT_A_STORE = (".npy", ".npz", ".mat", ".json", ".h5", ".hdf5", ".tif", ".tiff", ".txt", ".csv")


#: The dictionary options of a training run (``codedvideo train``'s), and those only a learned dictionary takes.
TRAINING_KEYS = ("kind", "videos", "atoms", "iterations", "samples", "sparsity", "max_speed", "init", "augment")
_LEARNED_ONLY = ("atoms", "iterations", "samples", "sparsity", "max_speed")


def plan_training(*, frames: int, dictionary: dict, seed: int = 0, cache: str | Path = DEFAULT_CACHE,
                  output: str | Path | None = None, door: str = "api") -> PipelineConfig:
    """The pipeline config of a training run, checked before any work: a 3D DCT dictionary takes none of the
    learned one's settings, and ``output`` is a store.  ``dictionary``: the dictionary's options of
    :data:`TRAINING_KEYS` (``codedvideo train``'s: ``kind`` "learned" or "dct", the training ``videos``, ``atoms``,
    ``iterations``, ``samples``, ``sparsity``, ``max_speed``, ``init``, ``augment``); one left out or None: its
    default."""
    unknown = sorted(set(dictionary) - set(TRAINING_KEYS))
    if unknown:
        raise ConfigError(f"train: unknown option{'s' if len(unknown) > 1 else ''} {', '.join(unknown)}")
    opt = lambda k: setting_name(k, door)  # noqa: E731
    kind, videos, init = dictionary.get("kind") or "learned", dictionary.get("videos") or (), dictionary.get("init")
    augment = dictionary.get("augment") is not False
    given = {k: dictionary[k] for k in _LEARNED_ONLY if dictionary.get(k) is not None}
    if kind == "dct" and (given or videos or init or not augment):
        named = [opt(k) for k in given] + (["VIDEO" if door == "cli" else "videos"] if videos else []) \
            + ([opt("init")] if init else []) + ([] if augment else ["--no-augment" if door == "cli" else "augment"])
        raise ConfigError(f"train {opt('kind')} dct: {', '.join(named)} {'is' if len(named) == 1 else 'are'} for "
                          "learned dictionaries only (a 3D DCT one has N x 49 atoms and is not trained)")
    names = {k: opt(k) for k in ("max_speed", "init", "kind", "atoms", "samples")}
    checked = validated(DictionaryConfig, dict(kind=kind, training=list(videos) or ["synth:train"], init=init,
                                               augment=augment, **given),
                        dict(names, training="VIDEO" if door == "cli" else "videos"))
    if output is not None and Path(output).suffix.lower() in NOT_A_STORE:
        raise ConfigError(f"dictionary output {output}: a dictionary is a Zarr store (a folder, .zarr) or a zipped "
                          f"one (.zip), not {Path(output).suffix.lower()}")
    return validated(PipelineConfig, dict(frames=frames, seed=seed, cache=str(cache), dictionary=checked), names)
