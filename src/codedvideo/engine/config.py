"""pipeline.yaml: every parameter of a run, validated on load.

Unknown or mistyped keys are errors (pydantic ``extra="forbid"``), and every
error names the file and the key.
"""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Annotated, Literal

import platformdirs
import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, ValidationInfo, field_validator, model_validator

from codedvideo.model import doors
from codedvideo.engine.methods import ADAPTIVE, WITH_DICTIONARY
from codedvideo.model.errors import ConfigError
from codedvideo.model.patches import PATCH
from codedvideo.model.physics import SensorModel
from codedvideo.model.units import DATA_RANGE_MAX, DATA_RANGE_MIN, LEVEL_MAX, TOL_FLOOR
from codedvideo.solvers.dictionaries import KSVD_ATOMS, KSVD_ITERATIONS, KSVD_SAMPLES, KSVD_SPARSITY, KsvdSettings
from codedvideo.solvers.region import OmpSettings

STAGES = ("train", "simulate", "reconstruct", "evaluate")
#: The tile side in pixels (``reconstruct.tile``, ``--tile``) by default.
DEFAULT_TILE = 128
#: The cache folder (``cache``, ``--cache``) by default: the user's cache folder (``~/.cache/codedvideo`` on
#: Linux, ``$XDG_CACHE_HOME`` honoured; ``~/Library/Caches/codedvideo`` on macOS; ``%LOCALAPPDATA%`` on Windows).
DEFAULT_CACHE = platformdirs.user_cache_dir("codedvideo", appauthor=False)
#: The budget of the default cache folder's working stores (``--cache-budget``), in bytes: 20 GiB.
DEFAULT_CACHE_BUDGET = 20 * 2**30


def budget_of(cache, budget: int | None) -> int | None:
    """A cache folder's budget for working stores: ``budget`` when given; else :data:`DEFAULT_CACHE_BUDGET` for
    the default folder (a user who never chose a folder never fills a disk), and none for a folder of the user's
    own."""
    if budget is not None or cache is None:
        return budget
    return DEFAULT_CACHE_BUDGET if Path(cache).expanduser().absolute() == Path(DEFAULT_CACHE).absolute() else None
#: A method that takes a dictionary (:data:`codedvideo.engine.methods.WITH_DICTIONARY`): ``reconstruct.method``.
DictionaryMethod = Literal[WITH_DICTIONARY]


def _pair(v):
    """A list of two values (from Python or YAML) as the tuple a (H, W) field holds; strict types still apply."""
    return tuple(v) if isinstance(v, list) else v


class _Strict(BaseModel):
    # strict: no coercion ("8" or true for an int is an error); no inf or NaN for any number
    model_config = ConfigDict(extra="forbid", frozen=True, strict=True, allow_inf_nan=False)

    def _changed(self, *names: str) -> list[str]:
        """Those of ``names`` set to other than their defaults (a value the run would ignore is refused only
        when changed: pipeline.yaml lists every key with its default)."""
        return [n for n in names if getattr(self, n) != type(self).model_fields[n].default]


def _for_report(info: ValidationInfo) -> bool:
    """Whether the config is loaded for ``codedvideo report`` (:func:`load_config`), which reads ``code.p`` for its
    Bernoulli runs whatever ``code.name`` is, and trains its own dictionaries from the ``dictionary:`` section,
    leaving ``dictionary.path`` and ``init`` aside: refusing those as ignored there refused what it uses."""
    return (info.context or {}).get("use") == "report"


#: The codes that take a bump length, and those that take an open probability (:func:`codedvideo.model.codes.make_code`).
BUMP_CODES = ("hitomi", "hitomi-tiled", "rowwise")
P_CODES = ("bernoulli", "shifting")


class SceneConfig(_Strict):
    #: ``synth:NAME`` for a generated scene, or a path to a video / frame sequence.
    video: str = "synth:default"
    #: The centre crop taken; None: a synthetic scene or footage clip 256x256, a video file its whole frame.
    size: tuple[Annotated[int, Field(ge=PATCH, le=65536)], Annotated[int, Field(ge=PATCH, le=65536)]] | None = None
    #: First frame taken from a video file.
    start: int = Field(0, ge=0, le=2**31 - 1)

    @field_validator("size", mode="before")
    @classmethod
    def _list_as_tuple(cls, v):
        return _pair(v)

    @model_validator(mode="after")
    def _start_of_a_file(self) -> "SceneConfig":
        if self.start and self.video.startswith(("synth:", "footage:")):  # (its frames were made from frame 0)
            raise ValueError(f"{doors.key('scene.start')} {self.start}: {self.video} is made from its first frame; start applies to "
                             "a video file")
        return self


#: The names of :data:`codedvideo.model.codes.CODE_NAMES` (a test keeps them equal).
CodeName = Literal[
    "hitomi", "hitomi-tiled", "rowwise", "thinout", "grid", "flutter", "bernoulli", "shifting", "global", "file"
]


class CodeConfig(_Strict):
    #: A code of :func:`codedvideo.model.codes.make_code`; ``file`` reads ``path``.
    name: CodeName = "hitomi"
    bump: int = Field(2, ge=1, le=64)
    p: float = Field(0.5, gt=0, le=1)
    #: The mask file (.npy (N, H, W) or multi-page TIFF) of code ``file``.
    path: str | None = None

    @model_validator(mode="after")
    def _path_with_file(self, info: ValidationInfo) -> "CodeConfig":
        if self.name == "file" and not self.path:
            raise ValueError(f"code 'file' needs {doors.key('code.path')} (a .npy or multi-page TIFF mask)")
        if self.name != "file" and self.path:
            raise ValueError(f"{doors.key('code.path')} is only used with name: file (name is {self.name!r})")
        unused = [doors.key(f"code.{k}") for k, codes in (("bump", BUMP_CODES), ("p", P_CODES))
                  if self.name not in codes and k in self._changed(k) and not (k == "p" and _for_report(info))]
        if unused:
            raise ValueError(f"{' and '.join(unused)}: code {self.name!r} does not use it ({doors.key('code.bump')}: "
                             f"{', '.join(BUMP_CODES)}; {doors.key('code.p')}: {', '.join(P_CODES)})")
        return self


class NoiseConfig(_Strict):
    """Noise and sensor of the simulated capture (:class:`codedvideo.model.physics.SensorModel`).

    The defaults (read noise ``sigma`` only) reproduce the plain read-noise model.
    """

    #: Gaussian read noise, standard deviation in grey levels (frame units).
    sigma: float = Field(0.0, ge=0, le=LEVEL_MAX)
    #: Poisson photon noise on the clean coded image.
    shot_noise: bool = False
    #: Full-well capacity, electrons (with shot_noise).
    full_well: float = Field(SensorModel.full_well, gt=0, le=1e12)
    #: Electrons per grey level (with shot_noise).
    gain: float = Field(SensorModel.gain, ge=1e-6, le=1e12)  # (electrons / gain stays finite)
    #: Quantise the coded image to this many bits (null: no quantisation).
    bits: int | None = Field(None, ge=1, le=32)
    #: Clip the coded image at this grey level; reconstruction then takes
    #: pixels at or above it as recording at least it (null: no saturation).
    white_level: float | None = Field(None, gt=0, le=LEVEL_MAX)
    #: Raw black level: an offset added once per read-out (before clipping and quantising).
    black_level: float = Field(0.0, ge=0, le=LEVEL_MAX)

    @model_validator(mode="after")
    def _shot_noise_settings(self) -> "NoiseConfig":
        unused = self._changed("full_well", "gain")
        if unused and not self.shot_noise:
            on = ": true" if doors.key("noise.shot_noise").startswith("noise.") else ""
            raise ValueError(f"{' and '.join(doors.key('noise.' + k) for k in unused)} describe the shot noise, which "
                             f"is off: set {doors.key('noise.shot_noise')}{on}, or leave them at their defaults")
        return self


class DictionaryConfig(_Strict):
    kind: Literal["learned", "dct"] = "learned"
    atoms: int = Field(KSVD_ATOMS, ge=1, le=16384)
    samples: int = Field(KSVD_SAMPLES, ge=100, le=10_000_000)
    iterations: int = Field(KSVD_ITERATIONS, ge=0, le=1000)
    sparsity: int = Field(KSVD_SPARSITY, ge=1, le=PATCH * PATCH)
    #: ``synth:train`` (synthetic motion of the training photographs) or video paths.
    training: list[str] = ["synth:train"]
    clips: int = Field(144, ge=1, le=100_000)
    #: Fastest synthetic training motion, pixels per sub-frame (speeds are log-uniform from 0.2).
    max_speed: float = Field(4.0, gt=0.2, le=16.0)
    #: An existing dictionary to use instead of training one.
    path: str | None = None
    #: Start K-SVD from this dictionary ("shipped": the one shipped for N; a store path) instead of the
    #: 3D DCT topped up with samples: adapt it to a scene (train on its reconstruction; README).
    init: str | None = None
    #: Rotate, flip and reverse the training patches (the paper's augmentation); off to fit one scene.
    augment: bool = True

    def ksvd(self) -> KsvdSettings:
        """The solver's view of this section: its K-SVD settings (the solver's own defaults for the rest)."""
        return KsvdSettings(atoms=self.atoms, samples=self.samples, iterations=self.iterations,
                            sparsity=self.sparsity, augment=self.augment)

    @model_validator(mode="after")
    def _settings_used(self, info: ValidationInfo) -> "DictionaryConfig":
        report = _for_report(info)
        if self.init is not None and not report and (self.kind == "dct" or "atoms" in self._changed("atoms")):
            raise ValueError(f"{doors.key('dictionary.init')} starts K-SVD from a dictionary, with its atoms: "
                             f"{doors.key('dictionary.kind')} dct and {doors.key('dictionary.atoms')} do not apply")
        if self.kind == "dct" and self.path is None and not report:  # (as `train --kind dct` refuses them)
            unused = self._changed("atoms", "samples", "iterations", "sparsity", "training", "clips", "max_speed",
                                   "augment")
            if unused:
                raise ValueError(f"{doors.key('dictionary.kind')} dct: "
                                 f"{', '.join(doors.key('dictionary.' + k) for k in unused)} "
                                 f"{'is' if len(unused) == 1 else 'are'} for learned dictionaries only (a 3D DCT one "
                                 "has N x 49 atoms and is not trained)")
        if self.path is not None and not report:
            unused = self._changed("kind", "atoms", "samples", "iterations", "sparsity", "training", "clips",
                                   "max_speed", "init", "augment")
            if unused:
                raise ValueError(f"dictionary.path is used as it is, so "
                                 f"{', '.join(doors.key('dictionary.' + k) for k in unused)} "
                                 "would be ignored: leave them at their defaults, or drop dictionary.path")
        elif "synth:train" not in self.training:
            unused = self._changed("clips", "max_speed")
            if unused:
                raise ValueError(f"{' and '.join(doors.key('dictionary.' + k) for k in unused)} "
                                 f"{'describes' if len(unused) == 1 else 'describe'} the synthetic training clips, "
                                 "and dictionary.training names no synth:train")
        if self.kind == "learned" and self.path is None and self.atoms < self.sparsity:
            raise ValueError(f"{doors.key('dictionary.atoms')} = {self.atoms}: below {doors.key('dictionary.sparsity')} "
                             f"{self.sparsity}, the atoms K-SVD "
                             "codes every training patch with; give at least as many atoms")
        return self


#: The named settings of ``reconstruct`` (issue 31): ``--preset``, ``reconstruct.preset`` in pipeline.yaml and
#: ``codedvideo.reconstruct(preset=...)``, each the ``reconstruct:`` keys it sets (the rest keep their defaults).
#: A key given beside a preset wins over it.  Measured on held-out real footage: docs/quality.md, "Presets".
PRESETS: dict[str, dict] = {
    # the best mean PSNR among the settings measured at most about 0.6x the default's whole-process time
    "fast": dict(stride=2),
    # the paper's method, the defaults: nothing changed
    "default": {},
    # the best quality measured: nonlocal --adapt with a second round, then 32 iterations of GAP with a low-rank
    # prior on groups (docs/quality.md, "Presets" and "Refinement")
    "best": dict(method="nonlocal", adapt=True, adapt_rounds=2, refine=32),
}
#: The names of :data:`PRESETS` (a test keeps them equal).
PresetName = Literal["fast", "default", "best"]
#: The keys a preset may set, and the options that give them on the command line.
PRESET_KEYS = {"method": "--method", "adapt": "--adapt", "adapt_rounds": "--adapt-rounds", "refine": "--refine",
               "stride": "--stride", "max_atoms": "--max-atoms"}


class ReconstructConfig(_Strict):
    #: Named settings (:data:`PRESETS`): the keys it sets unless given here (null: none).
    preset: PresetName | None = None
    max_atoms: int = Field(OmpSettings.max_atoms, ge=1, le=PATCH * PATCH)
    #: RMS residual tolerance per measured pixel; "auto" derives it from the noise.
    tol_rms: Annotated[float, Field(ge=0, le=LEVEL_MAX)] | Literal["auto"] = "auto"  # (also within 1e6 data ranges)
    #: Still-scene test: atoms of the 2D DCT allowed before a patch goes to full OMP (0: off).
    static_atoms: int = Field(OmpSettings.static_atoms, ge=0, le=PATCH * PATCH)
    #: Patch stride: 1 solves every overlapping patch (the paper); s solves 1 in s**2 (faster).
    stride: int = Field(OmpSettings.stride, ge=1, le=PATCH)
    #: Average of overlapping estimates: "uniform" (the paper) or "fit" (weighted by misfit).
    weighting: Literal["uniform", "fit"] = OmpSettings.weighting
    #: "omp": every patch on its own (the paper); "nonlocal": then groups of similar patches solved together.
    method: DictionaryMethod = "omp"
    #: Adapt the dictionary to each capture: reconstruct, K-SVD (4 iterations) on that result, reconstruct again
    #: (omp: about twice the time; nonlocal: a sparse survey first, about 1.2x its time; README, "Adapting the
    #: dictionary").
    adapt: bool = False
    #: With ``adapt``: 2 adapts again to the second pass's result and reconstructs a third time (``best``;
    #: docs/research.md, "Spending `best`'s time").
    adapt_rounds: int = Field(1, ge=1, le=2)
    #: Iterations of GAP with a low-rank prior on groups of similar patches after the method's result (0: none;
    #: ``best``: 32; docs/quality.md, "Refinement").
    refine: int = Field(0, ge=0, le=200)
    #: Tile side in pixels (a tile of 4096 at N = 64 already holds 4 GiB of volume).
    tile: int = Field(DEFAULT_TILE, ge=8, le=4096)
    batch: int = Field(OmpSettings.batch, ge=1, le=1 << 20)
    #: A dask.distributed address (``tcp://host:port``, ``tls://...``), or "threads" / "sync".
    scheduler: str | None = None
    workers: int | None = Field(None, ge=1, le=1024)
    #: Bytes the cache's working stores may take while a job writes more (a size such as 20G; null: no limit).
    #: A long coded video makes a store per capture (about 550 MB each at 3840x2160, N = 18): the stores least
    #: recently used are removed as the job goes (a rerun computes their tiles again).
    cache_budget: int | None = None

    @model_validator(mode="after")
    def _preset(self) -> "ReconstructConfig":
        """A preset's keys under those given beside it, resolved as the command line resolves them
        (:func:`resolve_preset`: a key given wins; one of the preset's that the keys given void is left out, with
        a warning).  The keys given stay the section's ``model_fields_set``, so the record says which they were."""
        if self.preset is None:
            return self
        try:
            options, _ = resolve_preset(self.preset, self.given())
        except ConfigError:  # a key given that the run cannot take: said by the checks of the fields themselves
            return self
        for key, value in options.items():
            object.__setattr__(self, key, value)
        return self

    @model_validator(mode="after")
    def _rounds_of_adapt(self) -> "ReconstructConfig":
        if self.adapt_rounds != 1 and not self.adapt:  # (not ignored: what a run would ignore is refused)
            raise ValueError(f"adapt_rounds {self.adapt_rounds} applies with adapt: true only")
        return self

    def given(self) -> dict:
        """The keys of :data:`PRESET_KEYS` this section gives (beside its preset, or without one) and their values."""
        return {k: getattr(self, k) for k in PRESET_KEYS if k in self.model_fields_set}

    def preset_used(self) -> dict | None:
        """What the metrics say of this section's preset (:func:`preset_record`; None: no preset), as the command
        line says it: every key given beside the preset, and the preset's keys those void, left out."""
        options, left_out = resolve_preset(self.preset, self.given())
        return preset_record(self.preset, options, self.given(), left_out)

    @field_validator("cache_budget", mode="before")
    @classmethod
    def _size(cls, v):
        if v is None:
            return None
        size = parse_size(v)
        if size == 0:  # every store removed as soon as it is done: every run would compute everything again
            raise ValueError("a cache budget must be > 0 bytes (0 keeps nothing, so every run computes "
                             "everything again); leave it out for no limit")
        return size

    @field_validator("scheduler")
    @classmethod
    def _address(cls, v: str | None) -> str | None:
        if v is None or v in ("threads", "sync"):
            return v
        scheme, sep, rest = v.partition("://")
        host, _, port = (rest if sep else v).rpartition(":")
        if not host or not port.isdigit() or not 0 < int(port) < 65536:
            raise ValueError(f"scheduler {v!r}: expected an address such as tcp://host:8786 (or threads, sync)")
        return v


class OutputConfig(_Strict):
    dir: str = "out/run"
    video: str = "recon.mp4"
    frames: Literal["tiff16", "exr", "none"] = "tiff16"
    fps: int = Field(30, ge=1, le=1000)
    #: Peak value of the frames: PSNR and the full scale of videos and 16-bit frames
    #: (null: found from the capture, see codedvideo.model.units).
    data_range: float | None = Field(None, ge=DATA_RANGE_MIN, le=DATA_RANGE_MAX)
    #: Replace existing output files that codedvideo did not write (folders never).
    overwrite: bool = False

    @field_validator("dir")
    @classmethod
    def _dir_named(cls, v: str) -> str:
        if not v.strip():  # "" would write the run's files among those of the current folder
            raise ValueError("name a folder for the outputs (for example out/run)")
        return v

    @field_validator("video")
    @classmethod
    def _video_name(cls, v: str) -> str:
        if Path(v).name != v or Path(v).suffix.lower() not in (".mp4", ".mkv", ".avi", ".mov", ".gif"):
            raise ValueError(f"video {v!r}: a file name in output.dir ending in .mp4, .mkv, .avi, .mov or .gif")
        return v

    @model_validator(mode="after")
    def _gif_rate(self) -> "OutputConfig":
        from codedvideo.formats.io import gif_rate_problem

        if Path(self.video).suffix.lower() == ".gif" and gif_rate_problem(self.fps):
            raise ValueError(f"fps {self.fps} with video {self.video}: {gif_rate_problem(self.fps)}")
        return self


class ReportDictionaryConfig(_Strict):
    """Overrides of ``dictionary:`` for the report's learned dictionaries (null: the pipeline's value).

    The report trains one dictionary per N of the Fig. 7 sweep and one per
    size of the speed study (all cached); these defaults keep that short.
    """

    atoms: int | None = Field(None, ge=1)
    samples: int | None = Field(20000, ge=100)
    iterations: int | None = Field(10, ge=0)


class ReportConfig(_Strict):
    """``codedvideo report``: the paper's experiments, error against run time (:mod:`codedvideo.app.report`)."""

    #: Where report.html, report.csv, the figures and the video go.
    dir: str = "out/report"
    #: Test scenes (synth names, never ``train-K``) every number is averaged over.
    scenes: list[str] = Field(["default", "coins-translate", "camera-rotate"], min_length=1)
    size: tuple[int, int] = (96, 96)
    #: N of Table 1, Fig. 4, the speed study and the video.
    frames: int = Field(8, ge=2, le=64)
    #: Bump length of the hitomi / rowwise codes outside Table 1.
    bump: int = Field(2, ge=1)
    #: Table 1: bump lengths (rows) and read-noise sigmas in grey levels (columns).
    table_bumps: list[int] = Field([1, 2, 3, 4, 5, 6], min_length=1)
    table_sigmas: list[float] = Field([0, 1, 4, 8, 15, 40], min_length=1)
    #: Table 1 again at these N (none: left out), with GAP-TV and the still estimate (coded / open count) beside
    #: the default; the bump lengths of ``table_bumps`` and N / 2 and N - 2.
    table_frames: list[int] = [16, 18]
    #: Fig. 7: the N swept.
    fig7_frames: list[int] = Field([4, 8, 12], min_length=1)
    #: Speed study: OMP max_atoms and tol_rms values, dictionary sizes (atoms), codes.
    speed_max_atoms: list[int] = [2, 4, 8, 16]
    speed_tol_rms: list[float] = [1.0, 2.0, 4.0, 8.0]
    speed_atoms: list[int] = [128, 256]
    speed_codes: list[Literal["hitomi", "hitomi-tiled"]] = ["hitomi", "hitomi-tiled"]
    speed_strides: list[Annotated[int, Field(ge=1, le=PATCH)]] = [1, 2, 3]
    #: Speed study: the sparse methods besides the configured one, each a point with its default settings.
    speed_methods: list[DictionaryMethod] = list(WITH_DICTIONARY)
    #: Speed study: the sparse methods also timed with their dictionary adapted to each capture (``--adapt``).
    speed_adapt: list[DictionaryMethod] = ["nonlocal"]
    #: The scene of the frame strips and the side-by-side video.
    video_scene: str = "default"
    fps: int = Field(4, ge=1)
    #: Each wall time plotted (Fig. 7 and the speed study) is the best of this many runs.
    repeats: int = Field(3, ge=1)
    dictionary: ReportDictionaryConfig = ReportDictionaryConfig()

    @field_validator("scenes", "video_scene")
    @classmethod
    def _test_scenes(cls, v):
        for name in [v] if isinstance(v, str) else v:
            if name.startswith("train-") or name.startswith("synth:"):
                raise ValueError(f"scene {name!r}: give a synth test scene name (e.g. default, coins-translate); "
                                 "training scenes are never used for evaluation")
        return v

    @field_validator("table_frames")
    @classmethod
    def _frames(cls, v: list[int]) -> list[int]:
        if any(not 2 <= x <= 64 for x in v):
            raise ValueError(f"every N must be 2 to 64, got {v}")
        return v

    @field_validator("table_bumps", "fig7_frames", "speed_max_atoms", "speed_atoms", "speed_strides")
    @classmethod
    def _positive(cls, v: list[int]) -> list[int]:
        if any(x < 1 for x in v):
            raise ValueError(f"every value must be >= 1, got {v}")
        return v

    @field_validator("table_sigmas", "speed_tol_rms")
    @classmethod
    def _non_negative(cls, v: list[float]) -> list[float]:
        if any(not (x >= 0 and x < float("inf")) for x in v):
            raise ValueError(f"every value must be finite and >= 0, got {v}")
        return v

    @field_validator("size", mode="before")
    @classmethod
    def _list_as_tuple(cls, v):
        return _pair(v)

    @field_validator("size")
    @classmethod
    def _patch_size(cls, v: tuple[int, int]) -> tuple[int, int]:
        if min(v) < PATCH:
            raise ValueError(f"size {v}: at least one {PATCH}x{PATCH} patch is needed")
        return v

    @model_validator(mode="after")
    def _bumps_fit(self) -> "ReportConfig":
        if max(self.table_bumps) > self.frames or self.bump > self.frames:
            raise ValueError(f"bump lengths must be <= frames = {self.frames} (table_bumps {self.table_bumps}, bump {self.bump})")
        if max(self.fig7_frames) > 64 or self.bump * PATCH * PATCH < max(self.fig7_frames):
            raise ValueError(f"fig7_frames {self.fig7_frames}: need N <= 64 and N <= {PATCH * PATCH} * bump")
        if min(self.fig7_frames) < self.bump:
            raise ValueError(f"fig7_frames {self.fig7_frames}: every N must be >= bump = {self.bump}")
        if self.frames not in self.fig7_frames:  # its Fig. 7 runs give the video, the strips and the speed baselines
            raise ValueError(f"report.frames {self.frames} must be one of report.fig7_frames {self.fig7_frames} "
                             "(the side-by-side video, the strips and the speed study use its Fig. 7 runs)")
        return self


class PipelineConfig(_Strict):
    seed: int = Field(0, ge=0, le=2**63 - 1)
    frames: int = Field(8, ge=1, le=64)
    #: The cache folder; null: the user's cache folder (:data:`DEFAULT_CACHE`).
    cache: str = DEFAULT_CACHE
    stages: list[Literal["train", "simulate", "reconstruct", "evaluate"]] = list(STAGES)
    scene: SceneConfig = SceneConfig()
    code: CodeConfig = CodeConfig()
    noise: NoiseConfig = NoiseConfig()
    dictionary: DictionaryConfig = DictionaryConfig()
    reconstruct: ReconstructConfig = ReconstructConfig()
    output: OutputConfig = OutputConfig()
    report: ReportConfig = ReportConfig()

    @field_validator("cache", mode="before")
    @classmethod
    def _default_cache(cls, v):
        return DEFAULT_CACHE if v is None else v

    @field_validator("stages")
    @classmethod
    def _known_order(cls, v: list[str]) -> list[str]:
        if not v:  # a run that would do nothing and write an empty metrics file
            raise ValueError(f"no stage to run; give one or more of {', '.join(STAGES)}")
        twice = next((s for i, s in enumerate(v) if s in v[:i]), None)
        if twice:
            raise ValueError(f"{twice} is named twice; name each stage once")
        if v != [s for s in STAGES if s in v]:  # the stages run in pipeline order only: say so, not reorder
            raise ValueError(f"out of order; stages run in the order {', '.join(STAGES)} "
                             f"(give [{', '.join(s for s in STAGES if s in v)}])")
        if "evaluate" in v and "reconstruct" not in v:  # it scores this run's reconstruction, in memory
            raise ValueError(f"stages {v}: evaluate scores the reconstruction the run makes; add reconstruct "
                             "(codedvideo evaluate scores a reconstruction already written)")
        return [s for s in STAGES if s in v]

    @field_validator("cache")
    @classmethod
    def _cache_named(cls, v: str) -> str:
        if not v.strip():  # "" would put cache entries among the files of the current folder
            raise ValueError("cache '': name a folder for the cache (for example cache)")
        return v

    @model_validator(mode="after")
    def _fits_the_frames(self, info: ValidationInfo) -> "PipelineConfig":
        """Rules between the sub-frames and other keys (each message starts with its key = value)."""
        if _for_report(info):  # (the report's own N and codes: report.frames, report.bump)
            return self
        if self.frames == 1 and "train" in self.stages and self.dictionary.path is None:
            raise ValueError(f"stages = {self.stages}: with frames 1 every pixel opens alike and the capture is its "
                             "own still estimate, which needs no dictionary: leave train out of stages")
        bump = self.code.bump
        if "simulate" in self.stages and self.code.name in BUMP_CODES and not 1 <= bump <= self.frames:
            raise ValueError(f"{doors.key('code.bump')} = {bump}: a bump of 1 to {self.frames} sub-frames (frames "
                             f"{self.frames})")
        return self

    @model_validator(mode="after")
    def _atoms_from_samples(self) -> "PipelineConfig":
        d = self.dictionary
        beyond = d.atoms - self.frames * PATCH * PATCH  # K-SVD starts from the DCT atoms, then draws the rest among the samples
        if d.kind == "learned" and d.path is None and d.init is None and beyond > d.samples:
            raise ValueError(f"{doors.key('dictionary.atoms')} {d.atoms} with {doors.key('dictionary.samples')} "
                             f"{d.samples}: K-SVD starts from the "
                             f"{self.frames * PATCH * PATCH} DCT atoms and draws the other {beyond} among the training samples; "
                             f"give at least {beyond} samples or fewer atoms")
        r = self.report  # its dictionaries: the main one at every N it sweeps, and one per size of the speed study
        samples, main = r.dictionary.samples or d.samples, r.dictionary.atoms or d.atoms
        for frames, atoms, key in ([(n, main, "report.dictionary.atoms") for n in (*r.fig7_frames, *r.table_frames, r.frames)]
                                   + [(r.frames, a, "report.speed_atoms") for a in r.speed_atoms]):
            if atoms - frames * PATCH * PATCH > samples:
                raise ValueError(f"{key}: {atoms} atoms at N = {frames} start from {frames * PATCH * PATCH} DCT atoms and draw "
                                 f"the other {atoms - frames * PATCH * PATCH} among the {samples} training samples "
                                 "(report.dictionary.samples); give more samples or fewer atoms")
        return self


def omp_settings(rc: ReconstructConfig, sigma: float, *, scale: float = 1.0):
    """The sparse-coding settings (:class:`codedvideo.solvers.region.OmpSettings`) of a ``reconstruct:`` section.

    ``sigma`` is the noise standard deviation that ``tol_rms: auto`` follows,
    in the capture's units; ``scale`` takes the capture's units to working
    units (:mod:`codedvideo.model.units`), in which the settings are returned.
    """
    tol = auto_tolerance(sigma * scale) if rc.tol_rms == "auto" else float(rc.tol_rms) * scale
    return OmpSettings(max_atoms=rc.max_atoms, tol_rms=tol, batch=rc.batch, static_atoms=rc.static_atoms,
                       stride=rc.stride, weighting=rc.weighting, method=rc.method, exact=not sigma > 0)


def _refusal(key: str, options: dict) -> str | None:
    """Why the value of ``key`` in ``options`` cannot be used in a run (None: it can): ``adapt`` needs a method
    with a dictionary, ``adapt_rounds`` other than 1 needs ``adapt``."""
    method = options["method"]
    if key == "adapt_rounds" and options["adapt_rounds"] != 1 and not options["adapt"]:
        return f"applies with {doors.name('adapt')} only"
    if key == "adapt" and options["adapt"] and method not in ADAPTIVE:
        option = doors.name("method")
        return (f"adapts the dictionary of {option} {', '.join(ADAPTIVE[:-1])} or {ADAPTIVE[-1]} ({option} {method} "
                "has none)")
    return None


def as_option(key: str, value) -> str:
    """A preset's key as the door of the call gives it: ``--adapt``, ``--method nonlocal`` on the command line."""
    return doors.name(key) + ("" if value is True else f" {value}")


def preset_options(name: str) -> str:
    """Preset ``name``'s options as the command line gives them (``--method nonlocal --adapt``)."""
    return " ".join(as_option(k, v) for k, v in PRESETS[name].items())


#: Read noise from which ``best`` leaves out its non-local passes and its adaptation (keeping the refinement):
#: in working units (grey levels of a data range of 255).  From here on the refined per-patch OMP never lost to
#: the default, while the non-local recipe did on some crops of one clip at 35 and 40; at 25 and 30 it stayed
#: above the default (docs/research.md, "The non-local method under read noise").
NOISY_BEST = 30.0
#: The keys of a preset the noise rule leaves out (their defaults taken).
_NOISY_KEYS = ("method", "adapt", "adapt_rounds")


def resolve_preset(name: str | None, given: dict, *, bayer: str | None = None,
                   noise: float | None = None, blind: str = "", lattice: str = "") -> tuple[dict, dict[str, str]]:
    """The values of :data:`PRESET_KEYS` for a run: those ``given`` beside the preset, then preset ``name``'s
    (None: no preset), then the defaults of ``reconstruct:``.

    An option given that the run cannot take raises :class:`ConfigError` naming it, with or without a
    preset.  One the preset set is left out instead (its default taken): ``--preset best --method gaptv`` gives
    GAP-TV without ``adapt``, which it cannot take, rather than failing.  ``bayer``: the run's Bayer pattern
    (None: a grey capture); a Bayer mosaic takes every key a grey capture takes (``refine`` too: its groups
    within each colour channel, docs/quality.md, "Bayer mosaics").

    Returns
    -------
    options : dict
        Every key of :data:`PRESET_KEYS` and its value.
    left_out : dict
        The preset's keys left out, each with the reason (empty: none).

    ``noise``: the capture's read noise in working units, once it is known; from :data:`NOISY_BEST` on, the
    preset's non-local method and adaptation are left out (measured: under such noise they lose to the per-patch
    OMP, and the refinement alone gains on it, at every noise measured); an option given beside the preset
    stands.  ``blind``: why the capture's code leaves its patches blind to what they fit
    (:func:`codedvideo.solvers.guard.sparse_weight`; empty: it does not); the preset's non-local method and
    adaptation are then left out as under heavy noise (they fell below the default there, while the refinement
    gained on it: docs/research.md, "Long shutter bumps").  ``lattice``: why the code samples each sub-frame on
    a lattice too coarse for the non-local passes (:func:`codedvideo.solvers.guard.coarse_lattice`; empty: it
    does not); they and the adaptation are left out too (docs/research.md, "A grid code's repeating patterns").
    """
    if name is not None and name not in PRESETS:
        raise ConfigError(f"preset {name!r}: unknown; choose one of {', '.join(PRESETS)}")
    defaults = {k: ReconstructConfig.model_fields[k].default for k in PRESET_KEYS}
    options = {**defaults, **(PRESETS[name] if name else {}), **given}
    left_out = {}
    for key in PRESET_KEYS:  # method before adapt: adapt may be refused with the method left
        problem = _refusal(key, options)
        if problem is None:
            continue
        if key in given:
            raise ConfigError(f"option {as_option(key, given[key])}: {problem}")
        options[key] = defaults[key]
        left_out[key] = problem
    reasons = []  # (why the preset's non-local passes and adaptation are left out: the first that holds is said)
    if noise is not None and noise >= NOISY_BEST:
        reasons.append(f"read noise of {noise:.3g} grey levels (of a data range of 255) is {NOISY_BEST:g} or more, "
                       "where the per-patch OMP, refined, was measured better")
    if lattice:
        reasons.append(f"the code has {lattice}, where the non-local passes fell below the default on some "
                       "held-out scenes and the per-patch OMP, refined, on none")
    if blind:
        reasons.append(f"the code has {blind}, where the per-patch OMP blended with GAP-TV, refined, was measured "
                       "better")
    for why in reasons if name else ():
        for key in _NOISY_KEYS:
            if key in PRESETS[name] and key not in given and options[key] != defaults[key]:
                options[key] = defaults[key]
                left_out[key] = why
    return options, left_out


def preset_record(name: str | None, options: dict, given=(), left_out: dict | None = None,
                  said=()) -> dict | None:
    """What the metrics JSON says of a run's preset (None: no preset): its name, the options it resolved to, the
    keys given beside it, and the preset's keys left out with their reasons.  With ``left_out`` a warning says
    so, once (``said``: keys a warning named already)."""
    if name is None:
        return None
    by_reason: dict[str, list[str]] = {}  # (keys left out for one reason said together)
    for k, why in (left_out or {}).items():
        if k not in said:
            by_reason.setdefault(why, []).append(as_option(k, PRESETS[name][k]))
    if by_reason:
        doors.warn(f"preset {name}: " + "; ".join(f"{', '.join(keys)} {'is' if len(keys) == 1 else 'are'} left out: "
                                                     f"{why}" for why, keys in by_reason.items())
                      + "; the defaults are taken in their place (preset.left_out in the metrics)")
    return dict(name=name, options={k: options[k] for k in PRESET_KEYS}, given=sorted(given),
                left_out=dict(left_out or {}))


def auto_tolerance(sigma: float) -> float:
    """Default RMS residual tolerance of Eq. 3 for read noise ``sigma``, both in working units (data range 255).

    Without noise a floor of 2 grey levels stops OMP on patches that are
    already explained at almost no cost in quality (docs/research.md,
    "Dictionary and training").
    """
    return float(max(sigma, TOL_FLOOR))


class _UniqueKeyLoader(yaml.SafeLoader):
    """YAML loader that refuses a key given twice in one mapping (YAML would keep the last silently)."""


def _unique_mapping(loader: _UniqueKeyLoader, node: yaml.MappingNode, deep: bool = False):
    seen = set()
    for key_node, _ in node.value:
        key = loader.construct_object(key_node, deep=deep)
        if key in seen:
            raise yaml.constructor.ConstructorError(None, None, f"duplicate key {key!r}", key_node.start_mark)
        seen.add(key)
    return loader.construct_mapping(node, deep=deep)


_UniqueKeyLoader.add_constructor(yaml.resolver.BaseResolver.DEFAULT_MAPPING_TAG, _unique_mapping)


#: pydantic's errors of a number out of its range (or not finite): their message gains the whole range.
_NUMBER_ERRORS = {"greater_than", "greater_than_equal", "less_than", "less_than_equal", "finite_number"}


def allowed(model: type[BaseModel], loc) -> str | None:
    """The range a number field of ``model`` (at location ``loc``, or a field name) allows, as ``[0, 1e+12]``
    or ``(0, 1]`` (None: no bounds): the one statement of the bounds, for pipeline.yaml and the options."""
    field, section = None, model
    for part in (loc,) if isinstance(loc, str) else loc:
        if not isinstance(part, str) or section is None or part not in getattr(section, "model_fields", {}):
            continue
        field = section.model_fields[part]
        sub = field.annotation
        section = sub if isinstance(sub, type) and issubclass(sub, BaseModel) else None
    if field is None:
        return None
    found = {}
    items = list(field.metadata)
    for arg in getattr(field.annotation, "__args__", ()):  # float | "auto", tuple[Annotated[int, ...], ...]
        items += getattr(arg, "__metadata__", ())
        items += [m for a in getattr(arg, "__args__", ()) for m in getattr(a, "__metadata__", ())]
    for m in items:
        for key in ("ge", "gt", "le", "lt"):
            if getattr(m, key, None) is not None:
                found[key] = getattr(m, key)
        for sub in getattr(m, "metadata", ()):  # FieldInfo inside Annotated
            for key in ("ge", "gt", "le", "lt"):
                if getattr(sub, key, None) is not None:
                    found[key] = getattr(sub, key)
    if not found:
        return None
    lo = f"[{found['ge']:g}" if "ge" in found else f"({found['gt']:g}" if "gt" in found else "(-inf"
    hi = f"{found['le']:g}]" if "le" in found else f"{found['lt']:g})" if "lt" in found else "inf)"
    return f"{lo}, {hi}"


def _first_error(exc: ValidationError, model: type[BaseModel] | None = None) -> tuple[str, dict]:
    errors = exc.errors()
    # a union such as `float | "auto"` reports one error per branch: the literal's is the least useful
    err = next((e for e in errors if e["type"] != "literal_error"), errors[0])
    if len(errors) > 1 and all(e["loc"][:1] == err["loc"][:1] for e in errors):
        errors = [err]
    msg = "unknown key" if err["type"] == "extra_forbidden" else err["msg"]
    if err["type"] in _NUMBER_ERRORS and model is not None:  # the whole allowed range, not only the side broken
        bounds = allowed(model, err["loc"])
        if bounds:
            msg = f"{msg}; allowed {bounds}"

    more = f" (and {len(errors) - 1} more)" if len(errors) > 1 else ""
    return msg + more, err


def default_config_path() -> Path:
    """The built-in pipeline.yaml: every key at its default, with a comment on each (``codedvideo config`` prints
    it; ``codedvideo run`` with no file runs it)."""
    from importlib.resources import files

    return Path(str(files("codedvideo.data") / "pipeline.yaml"))


def load_config(path: str | Path, *, use: Literal["run", "report"] = "run") -> PipelineConfig:
    """Read and validate pipeline.yaml; raise :class:`ConfigError` naming the key.

    ``use``: the command it is for; a value refused as ignored by ``run`` may be one ``report`` uses
    (:func:`_for_report`).

    Strict: the file must be UTF-8 YAML holding a non-empty mapping, no key
    may appear twice, and values are not coerced (``frames: "8"`` or
    ``frames: true`` are errors, as are inf and NaN).  Its messages name pipeline.yaml's keys, whichever door
    reads the file.
    """
    with doors.through("config"):
        return _load_config(Path(path), use)


def _load_config(file: Path, use: str) -> PipelineConfig:
    """:func:`load_config`, in pipeline.yaml's terms."""
    if not file.exists():
        raise ConfigError(f"config {file}: no such file")
    if not file.is_file():
        raise ConfigError(f"config {file}: not a file (give the path of a pipeline.yaml)")
    try:
        text = file.read_text(encoding="utf-8")
    except UnicodeDecodeError as exc:
        raise ConfigError(f"config {file}: not UTF-8 text (byte {exc.start})") from exc
    except OSError as exc:
        raise ConfigError(f"config {file}: cannot read it ({exc.strerror or exc})") from exc
    try:
        raw = yaml.load(text, Loader=_UniqueKeyLoader)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        problem = getattr(exc, "problem", None) or " ".join(str(exc).split())
        where = f", line {mark.line + 1}" if mark is not None else ""
        raise ConfigError(f"config {file}: not valid YAML ({problem}{where})") from exc
    if raw is None:
        raise ConfigError(f"config {file}: empty; give at least the stages to run (see the README's pipeline.yaml)")
    if not isinstance(raw, dict):
        raise ConfigError(f"config {file}: expected a mapping at the top level")
    try:
        # JSON mode: YAML lists are valid tuples, and strict types still apply
        cfg = PipelineConfig.model_validate_json(json.dumps(raw, default=str), context=dict(use=use))
    except ValidationError as exc:
        msg, err = _first_error(exc, PipelineConfig)
        # the location without pydantic's names of union branches ("constrained-float", ...)
        where = ".".join(str(p) for p in err["loc"] if isinstance(p, int) or str(p).isidentifier()) or "(top level)"
        if re.match(r"[a-z_]+(\.[a-z_]+)* = ", msg.removeprefix("Value error, ")):
            raise ConfigError(f"config {file}: {msg.removeprefix('Value error, ')}") from exc  # (it names its key)
        # (a rule between keys names them itself: the whole section it was given is no help on one line)
        value = "" if err["type"] == "extra_forbidden" or isinstance(err.get("input"), dict) \
            else f" = {err.get('input')!r}"
        raise ConfigError(f"config {file}: {where}{value}: {msg.removeprefix('Value error, ')}") from exc
    name, section = cfg.reconstruct.preset, raw.get("reconstruct")
    beside = {k: v for k, v in section.items() if k in PRESETS.get(name, {}) and v != PRESETS[name][k]} \
        if name and isinstance(section, dict) else {}
    if beside:  # (a pipeline.yaml that lists every key at its default would leave the preset nothing to set)
        doors.warn(f"config {file}: " + ", ".join(f"reconstruct.{k} {v}" for k, v in beside.items())
                      + f" given beside reconstruct.preset {name} {'wins' if len(beside) == 1 else 'win'} over the "
                      + "preset's " + ", ".join(f"{PRESETS[name][k]}" for k in beside))
    return cfg


def validated(model: type[BaseModel], values: dict, options: dict[str, str] | None = None):
    """Build ``model`` from command-line values, with the same rules as pipeline.yaml.

    ``options`` maps field names to option names (default ``--field-name``);
    an invalid value raises :class:`ConfigError` naming the option, the value
    and the rule it breaks.
    """
    try:
        return model.model_validate(values)
    except ValidationError as exc:
        msg, err = _first_error(exc, model)
        if not err["loc"]:  # a rule between fields: its message names them as the door of the call does
            raise ConfigError(f"options: {msg.removeprefix('Value error, ')}") from exc
        field = str(err["loc"][0])
        option = (options or {}).get(field, doors.name(field))
        raise ConfigError(f"option {option} {values.get(field)!r}: {msg.removeprefix('Value error, ')}") from exc


def check_scheduler(address: str | None, timeout: float = 5.0) -> None:
    """Fail fast, with one line, when a dask.distributed scheduler address cannot be reached."""
    if not address or address in ("threads", "sync"):
        return
    import importlib.util
    import socket

    if importlib.util.find_spec("distributed") is None:
        raise ConfigError(f"scheduler {address}: needs dask.distributed, which is not installed "
                          "(pip install 'codedvideo[distributed]')")

    scheme, sep, rest = address.partition("://")
    if sep and scheme not in ("tcp", "tls"):
        return  # other transports (ucx, inproc) are left to dask.distributed
    host, _, port = (rest if sep else address).rpartition(":")
    try:
        with socket.create_connection((host.strip("[]"), int(port)), timeout=timeout):
            pass
    except OSError as exc:
        raise ConfigError(f"scheduler {address}: cannot connect within {timeout:g} s "
                          f"({getattr(exc, 'strerror', None) or exc}); is the scheduler running?") from exc


# ----------------------------------------------------------------------------- a budget for working stores
_SIZE = re.compile(r"^\s*(\d+(?:\.\d*)?|\.\d+)\s*(?:([kmgt])(?:ib|b)?|b)?\s*$", re.IGNORECASE)


def parse_size(text: str | int | float) -> int:
    """``"500M"``, ``"20G"``, ``"1.5T"`` (powers of 1024; a ``B`` or ``iB`` after the unit is allowed) or a
    number of bytes -> bytes.  Raises ValueError for anything else, or a size below 0."""
    if isinstance(text, (int, float)) and not isinstance(text, bool):
        value, unit = float(text), ""
    else:
        m = _SIZE.match(str(text))
        if not m:
            raise ValueError(f"{text!r} is not a size (for example 500M, 20G or 1.5T)")
        value, unit = float(m.group(1)), (m.group(2) or "").lower()
    if not value >= 0 or value != value or value == float("inf"):
        raise ValueError(f"{text!r}: a size is a number of bytes >= 0")
    return int(value * 1024 ** "_kmgt".index(unit or "_"))
