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

