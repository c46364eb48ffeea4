"""pipeline.yaml: every parameter of a run, validated on load.

Unknown or mistyped keys are errors (pydantic ``extra="forbid"``), and every
error names the file and the key.
"""

from __future__ import annotations

from pathlib import Path
from typing import Literal

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from .errors import ConfigError
from .physics import SensorModel

STAGES = ("train", "simulate", "reconstruct", "evaluate")


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class SceneConfig(_Strict):
    #: ``synth:NAME`` for a generated scene, or a path to a video / frame sequence.
    video: str = "synth:default"
    size: tuple[int, int] = (256, 256)
    #: First frame taken from a video file.
    start: int = Field(0, ge=0)


#: The names of :data:`codedvideo.codes.CODE_NAMES` (a test keeps them equal).
CodeName = Literal[
    "hitomi", "hitomi-tiled", "rowwise", "thinout", "grid", "flutter", "bernoulli", "shifting", "global", "file"
]


class CodeConfig(_Strict):
    #: A code of :func:`codedvideo.codes.make_code`; ``file`` reads ``path``.
    name: CodeName = "hitomi"
    bump: int = Field(2, ge=1)
    p: float = Field(0.5, gt=0, le=1)
    #: The mask file (.npy (N, H, W) or multi-page TIFF) of code ``file``.
    path: str | None = None

    @model_validator(mode="after")
    def _path_with_file(self) -> "CodeConfig":
        if self.name == "file" and not self.path:
            raise ValueError("code 'file' needs code.path (a .npy or multi-page TIFF mask)")
        if self.name != "file" and self.path:
            raise ValueError(f"code.path is only used with name: file (name is {self.name!r})")
        return self


class NoiseConfig(_Strict):
    """Noise and sensor of the simulated capture (:class:`codedvideo.physics.SensorModel`).

    The defaults (read noise ``sigma`` only) reproduce the plain read-noise model.
    """

    #: Gaussian read noise, standard deviation in grey levels (frame units).
    sigma: float = Field(0.0, ge=0)
    #: Poisson photon noise on the clean coded image.
    shot_noise: bool = False
    #: Full-well capacity, electrons (with shot_noise).
    full_well: float = Field(SensorModel.full_well, gt=0)
    #: Electrons per grey level (with shot_noise).
    gain: float = Field(SensorModel.gain, gt=0)
    #: Quantise the coded image to this many bits (null: no quantisation).
    bits: int | None = Field(None, ge=1, le=32)
    #: Clip the coded image at this grey level; reconstruction then treats
    #: pixels at or above it as missing (null: no saturation).
    white_level: float | None = Field(None, gt=0)


class DictionaryConfig(_Strict):
    kind: Literal["learned", "dct"] = "learned"
    atoms: int = Field(512, ge=1)
    samples: int = Field(40000, ge=100)
    iterations: int = Field(20, ge=0)
    sparsity: int = Field(6, ge=1)
    #: ``synth:train`` (synthetic motion of the training photographs) or video paths.
    training: list[str] = ["synth:train"]
    clips: int = Field(72, ge=1)
    #: An existing dictionary to use instead of training one.
    path: str | None = None


class ReconstructConfig(_Strict):
    max_atoms: int = Field(8, ge=1, le=49)
    #: RMS residual tolerance per measured pixel; "auto" derives it from the noise.
    tol_rms: float | Literal["auto"] = "auto"
    #: Still-scene test: atoms of the 2D DCT allowed before a patch goes to full OMP (0: off).
    static_atoms: int = Field(8, ge=0, le=49)
    tile: int = Field(128, ge=8)
    batch: int = Field(4096, ge=1)
    scheduler: str | None = None
    workers: int | None = Field(None, ge=1)


class OutputConfig(_Strict):
    dir: str = "out/run"
    video: str = "recon.mp4"
    frames: Literal["tiff16", "exr", "none"] = "tiff16"
    fps: int = Field(30, ge=1)


class PipelineConfig(_Strict):
    seed: int = 0
    frames: int = Field(8, ge=1, le=64)
    cache: str = "cache"
    stages: list[Literal["train", "simulate", "reconstruct", "evaluate"]] = list(STAGES)
    scene: SceneConfig = SceneConfig()
    code: CodeConfig = CodeConfig()
    noise: NoiseConfig = NoiseConfig()
    dictionary: DictionaryConfig = DictionaryConfig()
    reconstruct: ReconstructConfig = ReconstructConfig()
    output: OutputConfig = OutputConfig()

    @field_validator("stages")
    @classmethod
    def _known_order(cls, v: list[str]) -> list[str]:
        return [s for s in STAGES if s in v]


def auto_tolerance(sigma: float) -> float:
    """Default RMS residual tolerance of Eq. 3 for read noise ``sigma``.

    Without noise a floor of 2 grey levels stops OMP on patches that are
    already explained: on the default scenes it costs under 0.02 dB against
    0.5 and saves about 10 % of the atoms (measured, see README).
    """
    return float(max(sigma, 2.0))


def load_config(path: str | Path) -> PipelineConfig:
    """Read and validate pipeline.yaml; raise :class:`ConfigError` naming the key."""
    path = Path(path)
    if not path.exists():
        raise ConfigError(f"config {path}: no such file")
    try:
        raw = yaml.safe_load(path.read_text()) or {}
    except yaml.YAMLError as exc:
        raise ConfigError(f"config {path}: not valid YAML ({str(exc).splitlines()[0]})") from exc
    if not isinstance(raw, dict):
        raise ConfigError(f"config {path}: expected a mapping at the top level")
    try:
        return PipelineConfig.model_validate(raw)
    except ValidationError as exc:
        err = exc.errors()[0]
        where = ".".join(str(p) for p in err["loc"]) or "(top level)"
        msg = "unknown key" if err["type"] == "extra_forbidden" else err["msg"]
        more = f" (and {len(exc.errors()) - 1} more)" if len(exc.errors()) > 1 else ""
        raise ConfigError(f"config {path}: {where}: {msg}{more}") from exc
