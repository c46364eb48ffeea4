"""Scenes: ``synth:NAME`` (generated motion), ``footage:NAME`` (held-out real clips), video files, training sets."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from codedvideo.model import doors
from codedvideo.formats import io as cio
from codedvideo.data import manifest
from codedvideo.data import synth
from codedvideo.model.errors import InputError
from codedvideo.model.patches import PATCH

log = logging.getLogger(__name__)


def load_video(spec: str, *, frames: int, size: tuple[int, int] | None, seed: int = 0, start: int = 0) -> np.ndarray:
    """A scene as (frames, H, W) float32: ``synth:NAME``, ``footage:NAME`` (held-out real clips,
    :mod:`codedvideo.data.footage`) or a video / frame-sequence path.

    Files are centre-cropped to ``size`` when they are larger.
    """
    if spec.startswith("synth:"):
        name = spec.split(":", 1)[1]
        manifest.verify_ids(manifest.SCENE_PHOTOS.get(name, synth.TEST_PHOTOS))
        return synth.make_scene(name, frames=frames, size=tuple(size or (256, 256)), seed=seed)
    if spec.startswith("footage:"):
        from codedvideo.data.footage import footage_scene

        return footage_scene(spec.split(":", 1)[1], frames=frames, size=size)
    return read_clip(spec, frames=frames, size=size, start=start)


def read_clip(spec: str, *, frames: int, size: tuple[int, int] | None, start: int = 0, color: str = "luma") -> np.ndarray:
    """``frames`` frames of a video / frame-sequence file from ``start``, centre-cropped to ``size``:
    (frames, H, W), or (C, frames, H, W) with ``color="channels"``, float32."""
    video = cio.read_video(resolve_data(spec), max_frames=frames, start=start, color=color)
    if video.shape[-3] < frames:
        raise InputError(f"video {spec}: has {video.shape[-3]} frames from frame {start}, need {frames}")
    return np.ascontiguousarray(_centre_crop(video, size, spec)[..., :frames, :, :], dtype=np.float32)


def _centre_crop(frames: np.ndarray, size: tuple[int, int] | None, spec: str) -> np.ndarray:
    """The centre ``size`` of the last two axes (None: as they are); frames smaller than it are an error."""
    if size is None:
        return frames
    h, w = size
    if frames.shape[-2] < h or frames.shape[-1] < w:
        raise InputError(f"video {spec}: frames {frames.shape[-2:]} smaller than the requested size {tuple(size)}")
    y0, x0 = (frames.shape[-2] - h) // 2, (frames.shape[-1] - w) // 2
    return frames[..., y0 : y0 + h, x0 : x0 + w]


def iter_clips(spec: str, *, frames: int, captures: int, size: tuple[int, int] | None, start: int = 0):
    """:func:`read_clip`'s ``frames * captures`` frames, ``frames`` at a time (N, H, W): a video file or a folder
    or pattern of images is decoded as it goes, so a long stream is never held whole."""
    path = resolve_data(spec)
    is_video = str(path).lower().endswith(cio.VIDEO_SUFFIXES)
    files = None if is_video else cio.frame_files(path)
    if not is_video and files is None:  # a .npy or a multi-page file: read whole
        video = read_clip(spec, frames=frames * captures, size=size, start=start)
        yield from (video[t * frames : (t + 1) * frames] for t in range(captures))
        return
    source = cio.iter_video(path, start=start) if is_video else (cio.read_image(f) for f in files[start:])
    clip, done, first = [], 0, None
    for frame in source:
        first = frame.shape if first is None else first
        if frame.shape != first:
            raise InputError(f"video {spec}: frames differ in shape ({first} and {frame.shape})")
        clip.append(_centre_crop(frame, size, spec))
        if len(clip) == frames:
            yield np.ascontiguousarray(np.stack(clip), dtype=np.float32)
            clip, done = [], done + 1
            if done == captures:
                return
    raise InputError(f"video {spec}: has {done * frames + len(clip)} frames from frame {start}, "
                     f"need {frames * captures}")


def count_frames(spec: str, *, start: int = 0) -> int:
    """Frames of a video file or image sequence from ``start``, counted without holding them."""
    path = resolve_data(spec)
    if str(path).lower().endswith(cio.VIDEO_SUFFIXES):
        return sum(1 for _ in cio.iter_video(path, start=start))
    files = cio.frame_files(path)
    if files is not None:
        return max(len(files) - start, 0)
    return cio.read_video(path, start=start).shape[0]


#: Pixels of a user's training video read at most (512 MB as float32): its first frames up to this.
TRAINING_PIXELS = 2**27


def training_videos(specs: list[str], *, frames: int, clips: int, seed: int, max_speed: float = synth.MAX_SPEED,
                    patch: int = PATCH) -> tuple[list[np.ndarray], list[str]]:
    """Training clips: ``synth:train`` (generated) and/or user video paths; and the sources used.

    A user's video is taken in working units (:mod:`codedvideo.model.units`: its data range, found from its
    values, scaled to 255), so that [0, 1] floats, 8-bit, 12-bit and 16-bit videos train alike and can
    be mixed.  Its frames are read up to :data:`TRAINING_PIXELS` (said when that cuts it short).  A
    video with fewer than ``frames`` frames, or smaller than a patch, is left out with a warning; none
    usable is an :class:`InputError` that names each and why.
    """
    videos: list[np.ndarray] = []
    used: list[str] = []
    problems: list[str] = []
    for spec in specs:
        if spec == "synth:train":
            manifest.verify_ids(synth.TRAIN_PHOTOS)
            videos.extend(synth.training_videos(frames=frames, count=clips, seed=seed, max_speed=max_speed))
            used.append(spec)
            continue
        if spec.startswith(("synth:", "footage:")):  # test scenes and held-out clips: never trained on
            raise InputError(f"training video {spec}: a test scene, never trained on; the synthetic training set is "
                             "synth:train, or give your own video files")
        path = resolve_data(spec)
        if Path(path).suffix.lower() in cio.VIDEO_SUFFIXES:  # decoded frame by frame: no more than the limit
            first = cio.read_video(path, max_frames=1)
            limit = max(frames, TRAINING_PIXELS // max(first.shape[-2] * first.shape[-1], 1))
            video = cio.read_video(path, max_frames=limit + 1)
        else:  # a stack is read whole
            video = cio.read_video(path)
            limit = max(frames, TRAINING_PIXELS // max(video.shape[-2] * video.shape[-1], 1))
        if video.shape[0] > limit:
            video = video[:limit]
            doors.warn(f"training video {spec}: only its first {limit} frames are used (at most "
                          f"{TRAINING_PIXELS // 2**20} M pixels a video)")
        f, h, w = video.shape
        if f < frames or min(h, w) < patch:
            problems.append(f"{spec} ({f} frames of {h}x{w})")
            continue
        videos.append(working_units(video, what=f"training video {spec}"))
        used.append(spec)
    need = f"{frames} frames (N) of at least {patch}x{patch} pixels"
    if not videos:
        raise InputError(f"training: no video is usable, each needs {need}: " + "; ".join(problems)
                         if problems else "training: no training video given")
    if problems:
        doors.warn(f"training videos left out, each needs {need}: " + "; ".join(problems))
    return videos, used


def working_units(video: np.ndarray, *, what: str = "video") -> np.ndarray:
    """A float32 video scaled in place to working units (its data range, found from its values, to 255)."""
    from codedvideo.model.units import OUTLIER_SHARE, infer_data_range

    # a reconstruction overshoots its range: a few values above 1 (or 255) are outliers, as in a capture
    units = infer_data_range(float(video.max()), what="frame values", outlier_ranges=(1.0, 255.0),
                             quantile=lambda: float(np.quantile(video[:, ::3, ::3], 1 - OUTLIER_SHARE)))
    if units.scale != 1:
        np.multiply(video, np.float32(units.scale), out=video)  # in place: ``video *= ...``
    log.info("%s: data range %g (%s)", what, units.value, units.source)
    return video


def resolve_data(spec: str) -> str:
    """``manifest:ID`` -> the verified file of that data_manifest entry; a path stays a path."""
    if spec.startswith("manifest:"):
        entry = manifest.lookup(spec.split(":", 1)[1])
        return str(manifest.verify(entry))
    return spec

