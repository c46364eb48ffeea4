"""Scenes: ``synth:NAME`` (generated motion), ``footage:NAME`` (held-out real clips), video files, training sets."""

from __future__ import annotations

import numpy as np

from . import io as cio
from . import manifest, synth
from .errors import InputError


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

