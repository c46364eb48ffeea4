"""Image, image-sequence, video and array files: the one place the rest of codedvideo reads and writes them.

Each family of formats has its own module, as xarray's backends do: :mod:`~codedvideo.formats.images`
(OpenImageIO: images, multi-page stacks, folders of frames), :mod:`~codedvideo.formats.video` (PyAV: H.264,
FFV1, GIF), :mod:`~codedvideo.formats.arrays` (.npy), :mod:`~codedvideo.formats.tiff` (TIFF page chains) and
:mod:`~codedvideo.formats.pixels` (the colour policy below); this module gathers their functions and tells a
file's stored type whatever its family (:func:`stored_dtype`).

Arrays are time-first ``(N, H, W)`` float32 inside the project; values keep
the units of the file (0..255 for 8-bit, 0..65535 for 16-bit).  Every writer
goes through :func:`codedvideo.formats.atomic.atomic_output`: a temporary name in the target's folder,
renamed onto the target only when writing succeeded.

Colour is an explicit choice of every reader (``color=``):

``"luma"`` (default)
    Rec.601 luma of the first three channels, so an image is ``(H, W)``, a
    stack or a video ``(N, H, W)``.
``"channels"``
    The channels kept apart, first: an image is ``(C, H, W)``, a stack or a
    video ``(C, N, H, W)``.  Grey files give ``C = 1``; an alpha channel
    (grey+alpha or RGBA) is dropped.
``"error"``
    Refuse colour input (grey files only), shapes as for ``"luma"``.

Writers take the same layouts: ``(H, W)`` or ``(C, H, W)`` images and
``(N, H, W)`` or ``(C, N, H, W)`` frames, with ``C`` = 1 or 3.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from codedvideo.formats.arrays import npy_layout, npy_writer, read_array, write_array  # noqa: F401
from codedvideo.formats.atomic import atomic_output, check_cache, check_writable  # noqa: F401 (the writers' API here)
from codedvideo.formats.images import (FRAMES_SIDECAR, IMAGE_SUFFIXES, frame_files, frames_writer,  # noqa: F401
                                       is_pattern, natural_key, pattern_frames, pixel_dtype, read_frames_scale,
                                       read_image, read_page, read_stack, stack_writer, write_frames, write_image,
                                       write_multipage_tiff, write_stack)
from codedvideo.formats.memory import available_memory  # noqa: F401
from codedvideo.formats.pixels import COLOR_CHOICES, LUMA, check_color, frames_of  # noqa: F401
from codedvideo.formats.tiff import tiff_page_count  # noqa: F401
from codedvideo.formats.video import (GIF_MAX_FPS, LOSSLESS_CODECS, SIZE_TAG, VIDEO_SUFFIXES,  # noqa: F401
                                      gif_rate_problem, iter_video, lossy_codec, read_video, video_writer,
                                      write_video)
from codedvideo.model.errors import InputError

__all__ = ["COLOR_CHOICES", "FRAMES_SIDECAR", "GIF_MAX_FPS", "IMAGE_SUFFIXES", "LOSSLESS_CODECS", "LUMA", "SIZE_TAG",
           "VIDEO_SUFFIXES", "atomic_output", "available_memory", "check_cache", "check_color", "check_writable",
           "frame_files", "frames_of", "frames_writer", "gif_rate_problem", "is_pattern", "iter_video", "lossy_codec",
           "npy_layout", "npy_writer", "read_array", "read_frames_scale", "read_image", "read_page", "read_stack",
           "read_video", "stack_writer", "stored_dtype", "tiff_page_count", "video_writer", "write_array",
           "write_frames", "write_image", "write_multipage_tiff", "write_stack", "write_video"]


def stored_dtype(path: str | os.PathLike) -> np.dtype:
    """The numpy type the file stores its values in (readers return float32; the data range needs this).

    .npy: its header; images: OpenImageIO's pixel format; videos: uint8;
    a folder or printf pattern of frames: its first file's.
    """
    file = Path(path)
    suffix = file.suffix.lower()
    if suffix == ".npy":
        try:
            return np.load(file, mmap_mode="r", allow_pickle=False).dtype  # the header only
        except (OSError, ValueError, AttributeError) as exc:
            raise InputError(f"array {file}: not a readable .npy file ({exc})") from exc
    if suffix in VIDEO_SUFFIXES:
        return np.dtype(np.uint8)
    if file.is_dir() or (is_pattern(str(file)) and not file.exists()):
        files = (pattern_frames(str(file)) if not file.is_dir() else
                 sorted((f for f in file.iterdir() if f.suffix.lower() in IMAGE_SUFFIXES and not f.name.startswith(".")),
                        key=natural_key))
        if not files:
            raise InputError(f"frames {file}: the folder holds no image files")
        return stored_dtype(files[0])
    return pixel_dtype(file)
