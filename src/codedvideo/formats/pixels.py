"""Pixels as the readers give them and the writers take them: the colour policy of every reader (``color=``,
:mod:`codedvideo.formats.io`), channels and luma, finite values, and 8-bit scaling."""

from __future__ import annotations

import numpy as np

from codedvideo.model.errors import InputError


LUMA = np.array([0.299, 0.587, 0.114], np.float32)


COLOR_CHOICES = ("luma", "channels", "error")


def check_color(color: str) -> str:
    """Validate a colour policy (see the module docstring)."""
    if color not in COLOR_CHOICES:
        raise InputError(f"color: unknown choice {color!r} (use {', '.join(COLOR_CHOICES)})")
    return color


def finite(arr: np.ndarray, path, what: str = "image") -> np.ndarray:
    if not np.isfinite(arr).all():
        raise InputError(f"{what} {path}: contains NaN or Inf")
    return arr


def to_channels(arr: np.ndarray) -> np.ndarray:
    """(H, W, C) or (H, W) pixels -> (C', H, W) float32, alpha dropped."""
    pixels = arr[..., None] if arr.ndim == 2 else arr
    c = pixels.shape[-1]
    keep = 1 if c <= 2 else 3  # grey(+alpha) or RGB(+alpha/extra)
    return np.moveaxis(pixels[..., :keep], -1, 0).astype(np.float32)


def check_channels(arr: np.ndarray, path, what: str, layout: str) -> None:
    """A channels-first array read with ``color="channels"`` holds 1 or 3 channels (grey or colour, as the writers
    take them); any other count is another layout (a (T, H, W) stream of captures), refused before any work."""
    if arr.shape[0] not in (1, 3):
        raise InputError(f"{what} {path}: {arr.shape[0]} colour channels in {layout} {arr.shape}; colour is 1 or 3 "
                         "channels (a stack of captures is read without --color channels)")


def to_gray(arr: np.ndarray, path, color: str) -> np.ndarray:
    """(H, W, C) or (H, W) -> (H, W) float32 (``"luma"``, ``"error"``) or (C, H, W) (``"channels"``)."""
    if color == "channels":
        return to_channels(arr)
    if arr.ndim == 2:
        return arr.astype(np.float32)
    if arr.shape[-1] == 1:
        return arr[..., 0].astype(np.float32)
    if color == "error":
        raise InputError(f"image {path}: has {arr.shape[-1]} channels; a single-channel image is required")
    if arr.shape[-1] in (2,):  # grey + alpha
        return arr[..., 0].astype(np.float32)
    rgb = arr[..., :3]
    if (rgb[..., 0] == rgb[..., 1]).all() and (rgb[..., 1] == rgb[..., 2]).all():
        return rgb[..., 0].astype(np.float32)  # grey stored as RGB (e.g. GIF): exact, no rounding of the weights
    return np.tensordot(rgb.astype(np.float32), LUMA, axes=([-1], [0]))


def to_uint8(frames: np.ndarray, data_range: float) -> np.ndarray:
    """Frames scaled so ``data_range`` maps to 255, rounded and clipped to uint8 (in float64, one copy, in place)."""
    values = np.asarray(frames)
    work = np.empty(values.shape, np.float64)
    work[...] = values
    np.multiply(work, 255.0 / data_range, out=work)
    np.rint(work, out=work)
    np.clip(work, 0, 255, out=work)
    return work.astype(np.uint8)


def frames_of(part):
    """The frames of a part ``(n, ...)`` one at a time, as arrays.

    A part need not be an ndarray: anything that yields its frames (e.g.
    :class:`codedvideo.formats.volumes.FrameFile`, a volume kept on disk) is read a
    frame at a time, never whole.
    """
    if isinstance(part, np.ndarray):
        yield from part
    else:
        for frame in part:
            yield np.asarray(frame)
