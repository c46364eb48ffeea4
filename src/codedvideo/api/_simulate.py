"""The simulation job both doors run: a video (``synth:NAME``, ``footage:NAME`` or a file) seen through a shutter
code and a sensor, with every setting checked before any work (:func:`plan_simulation`), and the capture made
whole (:func:`simulate_whole`) or, for a video file, one capture at a time (:func:`simulate_captures`)."""

from __future__ import annotations

from dataclasses import dataclass

from codedvideo.model import doors
from codedvideo.api._settings import setting_name
from codedvideo.engine.config import (BUMP_CODES, P_CODES, CodeConfig, NoiseConfig, PipelineConfig, SceneConfig,
                                      validated)
from codedvideo.model.errors import ConfigError, InputError

#: The synthetic scenes and the shipped footage are made whole in memory; any other source is a file.
MADE_SOURCES = ("synth:", "footage:")


@dataclass(frozen=True)
class SimulateSettings:
    """Every setting of a simulation: the options of ``codedvideo simulate`` (``noise_sigma`` is
    ``--noise-sigma``; None: the default)."""

    video: str
    frames: int
    code: str | None = None
    code_file: str | None = None
    bump: int | None = None
    p: float | None = None
    noise_sigma: float = 0.0
    shot_noise: bool = False
    full_well: float | None = None
    gain: float | None = None
    bits: int | None = None
    white_level: float | None = None
    black_level: float = 0.0
    bayer: str | None = None
    seed: int = 0
    size: tuple[int, int] | None = None
    start: int = 0
    captures: int | str = 1
    new_code_per_capture: bool = False


@dataclass(frozen=True)
class SimulationPlan:
    """A checked simulation: its settings, the code and sensor models, the crop and the number of captures."""

    settings: SimulateSettings
    code: CodeConfig
    noise: NoiseConfig
    size: tuple[int, int] | None
    captures: int | str
    file_codes: int
    #: Whether the code file holds a binary code (0 and 1 only; True without a code file).
    binary: bool = True

    @property
    def streamed(self) -> bool:
        """A video file, read and coded capture by capture (never held whole)."""
        s = self.settings
        return not (s.bayer or s.video.startswith(MADE_SOURCES))

    def options(self) -> dict:
        """The keywords of :func:`codedvideo.engine.simulation.simulate_capture` but the number of captures (a
        Bayer capture is one colour capture: a new code per capture does not reach it)."""
        from codedvideo.engine.simulation import sensor_model

        s = self.settings
        return dict(code=self.code, sigma=self.noise.sigma, seed=s.seed, sensor=sensor_model(self.noise),
                    new_code_per_capture=s.new_code_per_capture and not s.bayer)


def _code(s: SimulateSettings, door: str) -> CodeConfig:
    name = s.code or ("file" if s.code_file else "hitomi")
    opt = lambda k: setting_name(k, door)  # noqa: E731
    if s.code_file and name != "file":
        raise InputError(f"{opt('code_file')} {s.code_file}: only used with {opt('code')} file (got {opt('code')} "
                         f"{name})")
    defaults = CodeConfig()
    # an option the code would ignore is refused, not dropped in silence (its default changes nothing)
    unused = ([f"{opt('bump')} {s.bump}"] if s.bump is not None and s.bump != defaults.bump
              and name not in BUMP_CODES else []) \
        + ([f"{opt('p')} {s.p:g}"] if s.p is not None and s.p != defaults.p and name not in P_CODES else [])
    if unused:
        raise ConfigError(f"option {' and '.join(unused)}: {opt('code')} {name} does not use it ({opt('bump')}: "
                          f"{', '.join(BUMP_CODES)}; {opt('p')}: {', '.join(P_CODES)})")
    given = {k: v for k, v in dict(bump=s.bump, p=s.p).items() if v is not None}
    return validated(CodeConfig, dict(name=name, path=s.code_file, **given), {"path": opt("code_file")})


def _captures(s: SimulateSettings, door: str) -> int | str:
    captures = s.captures
    if captures != "all":
        try:
            captures = int(captures)
        except (TypeError, ValueError):
            raise ConfigError(f"option {setting_name('captures', door)} {s.captures!r}: a whole number of captures, "
                              "or all") from None
        if not 1 <= captures <= 100_000:
            raise ConfigError(f"option {setting_name('captures', door)} {captures}: Input should be between 1 and "
                              "100000")
    elif s.video.startswith(MADE_SOURCES):
        raise ConfigError(f"option {setting_name('captures', door)} all: only for a video file (give a number for "
                          f"{s.video})")
    return captures


def plan_simulation(s: SimulateSettings, *, door: str = "api", clashes: dict | None = None) -> SimulationPlan:
    """Check every setting before any work; the code file is read (and checked) here.  ``clashes``: options of
    the door that a code file of several codes (one per capture) does not take, name -> given."""
    opt = lambda k: setting_name(k, door)  # noqa: E731
    validated(PipelineConfig, dict(frames=s.frames, seed=s.seed), {"frames": opt("frames")})
    if not s.shot_noise and (s.full_well is not None or s.gain is not None):
        raise ConfigError(f"options {opt('full_well')} and {opt('gain')} describe the shot noise: give "
                          f"{opt('shot_noise')} with them")
    code = _code(s, door)
    given = {k: v for k, v in dict(full_well=s.full_well, gain=s.gain).items() if v is not None}
    noise = validated(NoiseConfig, dict(sigma=s.noise_sigma, shot_noise=s.shot_noise, bits=s.bits,
                                        white_level=s.white_level, black_level=s.black_level, **given),
                      {"sigma": opt("noise_sigma")})
    size = tuple(s.size) if s.size else ((256, 256) if s.video.startswith("synth:") else None)
    validated(SceneConfig, dict(video=s.video, start=s.start, **({"size": size} if size else {})),
              {"start": opt("start")})
    captures = _captures(s, door)
    file_codes, binary = _file_codes(code, s, door, clashes or {})
    if s.bayer:
        from codedvideo.engine.bayer import check_even

        if captures != 1:
            raise ConfigError(f"option {opt('bayer')} {s.bayer}: makes one capture with a colour truth; "
                              f"{opt('captures')} does not apply")
        if size is not None:
            check_even(size, f"option {opt('size')} {size[0]} {size[1]}")
    return SimulationPlan(s, code, noise, size, captures, file_codes, binary)


def _file_codes(code: CodeConfig, s: SimulateSettings, door: str, clashes: dict) -> tuple[int, bool]:
    """(the codes in the code file (several: one per capture, in turn), whether they are binary), read and
    checked before any work."""
    if not code.path:
        return 1, True
    from codedvideo.formats.volumes import read_masks
    from codedvideo.model.codes import is_binary

    file_mask = read_masks(code.path)
    count = file_mask.shape[0] if file_mask.ndim == 4 else 1
    clash = [o for o, on in ((setting_name("new_code_per_capture", door), s.new_code_per_capture),
                             *clashes.items(), (setting_name("bayer", door), s.bayer)) if on]
    if count > 1 and clash:
        raise ConfigError(f"option {clash[0]}: the code file {code.path} holds {count} codes, one per capture in "
                          f"turn, which {clash[0]} does not take")
    return count, is_binary(file_mask)


def captures_of(plan: SimulationPlan) -> int:
    """The number of captures: as given, or (``all``) as many whole captures as the video holds from its start."""
    s = plan.settings
    if plan.captures != "all":
        return plan.captures
    from codedvideo.data.scenes import count_frames

    total = count_frames(s.video, start=s.start)
    captures, left = divmod(total, s.frames)
    if captures < 1:
        raise InputError(f"video {s.video}: fewer than N = {s.frames} frames from frame {s.start}")
    if left:
        doors.warn(f"video {s.video}: {total} frames from frame {s.start} make {captures} captures of N = "
                      f"{s.frames}; its last {left} frames are left out")
    return captures


def simulate_whole(plan: SimulationPlan, captures: int) -> dict:
    """The capture of a synthetic scene, shipped footage or (``bayer``) a colour video, made whole: ``coded``,
    ``mask`` and ``truth`` (:func:`codedvideo.engine.simulation.simulate_capture`)."""
    s = plan.settings
    if s.bayer:  # the colour video through the filter: coded the mosaic, truth (3, N, H, W)
        from codedvideo.engine.bayer import load_color_video, simulate_bayer

        return simulate_bayer(load_color_video(s.video, frames=s.frames, size=plan.size, seed=s.seed, start=s.start),
                              s.bayer, where=f"video {s.video}", **plan.options())
    from codedvideo.data.scenes import load_video
    from codedvideo.engine.simulation import simulate_capture

    _check_in_memory(s.video, s.frames * captures, plan.size)
    video = load_video(s.video, frames=s.frames * captures, size=plan.size, seed=s.seed, start=s.start)
    return simulate_capture(video, captures=captures, **plan.options())


def simulate_captures(plan: SimulationPlan, captures: int):
    """A video file's captures one at a time: ``(first clip, stream of (coded, mask, clip))`` (the same bits as
    :func:`simulate_whole` of the whole clip; the first clip read, so its size is known before any output)."""
    import itertools

    from codedvideo.data.scenes import iter_clips
    from codedvideo.engine.simulation import simulate_stream

    s = plan.settings
    clips = iter_clips(s.video, frames=s.frames, captures=captures, size=plan.size, start=s.start)
    first = next(clips)
    return first, simulate_stream(itertools.chain([first], clips), captures=captures, **plan.options())


def _check_in_memory(video: str, frames: int, size) -> None:
    """A synthetic scene (or footage clip) is made whole in memory, with the capture: refuse one that would not
    fit, before any work (a video file is simulated capture by capture instead)."""
    if size is None:
        return
    from codedvideo.formats.io import available_memory

    need = 3 * 4 * frames * size[0] * size[1]  # the float32 frames, the truth and the coded work (measured ~2.9x)
    free = available_memory()
    if free is None:
        return
    if need > 0.75 * free:  # (a quarter kept for the rest of the process and the machine)
        raise ConfigError(f"option --captures: {video} is made whole in memory, {frames} frames of {size[0]}x{size[1]} "
                          f"need about {need / 2**30:.1f} GiB, {free / 2**30:.1f} GiB are free; give fewer captures "
                          "(a video file is simulated capture by capture)")
