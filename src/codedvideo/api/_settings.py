"""The settings of a reconstruction, as one object both doors build: the command line from its options, the
Python API from its keyword arguments.  :func:`resolve` checks them before any work and resolves the preset,
the method, the tolerance and the sensor settings, naming each setting as the door the caller came through
calls it (``--noise-sigma`` on the command line, ``noise_sigma`` in Python)."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, fields
from pathlib import Path

from codedvideo.engine.config import (PRESET_KEYS, NoiseConfig, OutputConfig, ReconstructConfig, budget_of,
                                      check_scheduler, preset_record, resolve_preset, validated)
from codedvideo.engine.methods import WITH_DICTIONARY
from codedvideo.formats.atomic import check_cache
from codedvideo.model.doors import name as setting_name, through
from codedvideo.model.errors import ConfigError

@dataclass(frozen=True)
class ReconstructSettings:
    """Every setting of a reconstruction (None: the default, or the preset's).

    The fields are the keyword arguments of :func:`codedvideo.reconstruct` and the options of
    ``codedvideo reconstruct`` (``noise_sigma`` is ``--noise-sigma``); pipeline.yaml's ``reconstruct:`` and
    ``noise:`` sections hold the same values.  Values are in the capture's units.
    """

    preset: str | None = None
    method: str | None = None
    adapt: bool | None = None
    adapt_rounds: int | None = None
    refine: int | None = None
    #: (N*49, K) array, a path to a dictionary store, or None for the one shipped for N (omp, nonlocal).
    dictionary: object = None
    max_atoms: int | None = None
    tol_rms: float | None = None
    noise_sigma: float = 0.0
    data_range: float | None = None
    white_level: float | None = None
    trust_saturated: bool = False
    black_level: float = 0.0
    bits: int | None = None
    #: Defective pixels: a file (text rows 'y x', .npy (K, 2) or an (H, W) map), or such an array.
    bad_pixels: object = None
    detect_bad_pixels: bool = False
    stride: int | None = None
    weighting: str | None = None
    static_atoms: int | None = None
    tile: int | None = None
    batch: int | None = None
    scheduler: str | None = None
    workers: int | None = None
    #: A folder for the resumable cache; None: a temporary folder, removed afterwards.
    cache: str | Path | None = None
    cache_budget: str | int | None = None
    independent_captures: bool = False
    #: The capture is a Bayer mosaic of this pattern (RGGB, BGGR, GRBG, GBRG).
    bayer: str | None = None
    progress: bool = False


@dataclass(frozen=True)
class Resolved:
    """Checked settings: the ``reconstruct:`` and ``noise:`` models, the data range given (None: found from the
    values), the preset's record and the settings they came from."""

    settings: ReconstructSettings
    rc: ReconstructConfig
    noise: NoiseConfig
    data_range: float | None
    preset: dict | None
    method: str
    door: str

    def __getattr__(self, name):  # the settings' own fields (cache, bayer, bad_pixels, ...)
        return getattr(self.settings, name)


#: The settings whose config field is named otherwise.
_FIELDS = {"sigma": "noise_sigma"}


def _names(door: str) -> dict[str, str]:
    """Config field -> the name of its setting in ``door``."""
    names = {f.name: setting_name(f.name, door) for f in fields(ReconstructSettings)}
    names.update({k: setting_name(v, door) for k, v in _FIELDS.items()})
    return names


def resolve(settings: ReconstructSettings, *, door: str = "api") -> Resolved:
    """Check ``settings`` before any work and resolve the preset; a bad value raises one line naming it."""
    with through(door):  # (its messages name the settings as ``door`` does)
        return _resolve(settings, door)


def _given(s: ReconstructSettings) -> dict:
    """The settings a preset may set that were given beside it."""
    return {k: getattr(s, k) for k in PRESET_KEYS if getattr(s, k) is not None}


def _resolve(s: ReconstructSettings, door: str) -> Resolved:
    names = _names(door)
    given = _given(s)
    options, left_out = resolve_preset(s.preset, given, bayer=s.bayer)  # (an option given and refused: an error)
    preset = preset_record(s.preset, options, given, left_out)
    method = options["method"]
    if s.dictionary is not None and method not in WITH_DICTIONARY:
        shown = s.dictionary if isinstance(s.dictionary, (str, Path)) else "(an array)"
        raise ConfigError(f"option {names['dictionary']} {shown}: used by method {' and '.join(WITH_DICTIONARY)} only "
                          f"(method {method} {'has its own DCT atoms' if method == 'dct' else 'has no dictionary'})")
    chosen = dict(static_atoms=s.static_atoms, weighting=s.weighting, tile=s.tile, batch=s.batch, workers=s.workers,
                  cache_budget=s.cache_budget)
    rc = validated(ReconstructConfig, dict(
        {k: v for k, v in chosen.items() if v is not None}, tol_rms="auto" if s.tol_rms is None else s.tol_rms,
        scheduler=s.scheduler, **{k: options[k] for k in PRESET_KEYS if k != "method"}), names)
    budget = budget_of(s.cache, rc.cache_budget)  # (the default folder's when none is given)
    if budget != rc.cache_budget:
        rc = rc.model_copy(update=dict(cache_budget=budget))
    noise = validated(NoiseConfig, dict(sigma=s.noise_sigma, white_level=s.white_level, bits=s.bits,
                                        black_level=s.black_level), names)
    if s.trust_saturated and noise.white_level is None and noise.bits is None:  # a setting the run would ignore
        raise ConfigError(f"option {names['trust_saturated']}: keeps the pixels {names['white_level']} or "
                          f"{names['bits']} marks saturated; neither is given, so it would change nothing")
    data_range = validated(OutputConfig, dict(data_range=s.data_range), names).data_range
    if s.cache is not None:
        check_cache(s.cache)
    check_scheduler(rc.scheduler)
    return Resolved(s, rc, noise, data_range, preset, method, door)


def for_noise(r: Resolved, noise: float, blind: str = "", lattice: str = "") -> Resolved:
    """``r`` once the capture's read noise is known in working units (``noise``): the preset resolved again with
    it (:func:`codedvideo.engine.config.resolve_preset`; ``blind``: why the capture's code leaves its patches
    blind, ``lattice``: why it samples each sub-frame on a coarse lattice, each empty where it does not), the keys
    it leaves out said in a warning; ``r`` itself when nothing changes."""
    s = r.settings
    if s.preset is None:
        return r
    given = _given(s)
    options, left_out = resolve_preset(s.preset, given, bayer=s.bayer, noise=noise, blind=blind, lattice=lattice)
    if left_out.keys() == r.preset["left_out"].keys():
        return r
    rc = r.rc.model_copy(update={k: options[k] for k in PRESET_KEYS if k != "method"})
    record = preset_record(s.preset, options, given, left_out, said=r.preset["left_out"])
    return dataclasses.replace(r, rc=rc, method=options["method"], preset=record)


def replaced(settings: ReconstructSettings, **changes) -> ReconstructSettings:
    """``settings`` with ``changes`` (unknown names refused, as the API refuses them)."""
    unknown = set(changes) - {f.name for f in fields(ReconstructSettings)}
    if unknown:
        raise ConfigError(f"reconstruct: unknown setting{'s' if len(unknown) > 1 else ''} "
                          f"{', '.join(sorted(unknown))}")
    return dataclasses.replace(settings, **changes)
