"""Image, image-sequence and video files (the only importer of OpenImageIO and PyAV).

Arrays are time-first ``(N, H, W)`` float32 inside the project; values keep
the units of the file (0..255 for 8-bit, 0..65535 for 16-bit).  Every writer
goes through :func:`atomic_output`: a temporary name in the target's folder,
renamed onto the target only when writing succeeded.
"""

from __future__ import annotations

import contextlib
import os
import re
import shutil
import uuid
from pathlib import Path

import numpy as np

from .errors import InputError, OutputError

IMAGE_SUFFIXES = (".png", ".tif", ".tiff", ".exr", ".dpx", ".jpg", ".jpeg")
VIDEO_SUFFIXES = (".mp4", ".avi", ".mov", ".mkv", ".gif")
LUMA = np.array([0.299, 0.587, 0.114], np.float32)


# ----------------------------------------------------------------------------- atomic writes
@contextlib.contextmanager
def atomic_output(path: str | os.PathLike):
    """Yield a temporary sibling of ``path``; rename it onto ``path`` on success.

    The temporary keeps ``path``'s suffix, so writers that choose a format by
    extension still work.  On an exception the temporary (file or folder) is
    removed and the exception re-raised; an existing ``path`` is untouched.
    """
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise OutputError(f"{path}: cannot create folder {path.parent} ({exc.strerror or exc})") from exc
    if not os.access(path.parent, os.W_OK):
        raise OutputError(f"{path}: folder {path.parent} is not writable")
    tmp = path.with_name(f".{path.stem}.tmp-{os.getpid()}-{uuid.uuid4().hex[:8]}{path.suffix}")
    try:
        yield tmp
        if tmp.is_dir():
            if path.exists():
                old = path.with_name(f".{path.name}.old-{uuid.uuid4().hex[:8]}")
                os.replace(path, old)
                os.replace(tmp, path)
                shutil.rmtree(old, ignore_errors=True) if old.is_dir() else old.unlink(missing_ok=True)
            else:
                os.replace(tmp, path)
        else:
            if path.is_dir():
                shutil.rmtree(path)
            os.replace(tmp, path)
    except BaseException:
        if tmp.is_dir():
            shutil.rmtree(tmp, ignore_errors=True)
        else:
            tmp.unlink(missing_ok=True)
        raise


# ----------------------------------------------------------------------------- reading
def _finite(arr: np.ndarray, path, what: str = "image") -> np.ndarray:
    if not np.isfinite(arr).all():
        raise InputError(f"{what} {path}: contains NaN or Inf")
    return arr


def _to_gray(arr: np.ndarray, path, color: str) -> np.ndarray:
    """(H, W, C) or (H, W) -> (H, W) float32."""
    if arr.ndim == 2:
        return arr.astype(np.float32)
    if arr.shape[-1] == 1:
        return arr[..., 0].astype(np.float32)
    if color == "error":
        raise InputError(f"image {path}: has {arr.shape[-1]} channels; a single-channel image is required")
    if arr.shape[-1] in (2,):  # grey + alpha
        return arr[..., 0].astype(np.float32)
    return np.tensordot(arr[..., :3].astype(np.float32), LUMA, axes=([-1], [0]))


def _oiio_read_all(path: Path, color: str, first_only: bool) -> list[np.ndarray]:
    import OpenImageIO as oiio

    if not path.exists():
        raise InputError(f"image {path}: no such file")
    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        raise InputError(f"image {path}: cannot read ({oiio.geterror() or 'unknown format or corrupt file'})")
    pages = []
    try:
        sub = 0
        while True:
            if sub > 0 and not inp.seek_subimage(sub, 0):
                break
            spec = inp.spec()
            native = spec.format
            data = inp.read_image(native if str(native) in ("uint8", "uint16", "float", "half") else "float")
            if data is None:
                raise InputError(f"image {path}: corrupt or truncated ({inp.geterror() or oiio.geterror()})")
            pages.append(_to_gray(np.asarray(data), path, color))
            sub += 1
            if first_only:
                break
    finally:
        inp.close()
    return pages


def _read_npy(path: Path) -> np.ndarray:
    if not path.exists():
        raise InputError(f"array {path}: no such file")
    try:
        arr = np.load(path, allow_pickle=False)
    except (ValueError, OSError, EOFError) as exc:
        raise InputError(f"array {path}: not a readable .npy file ({exc})") from exc
    if arr.dtype.kind not in "biuf":
        raise InputError(f"array {path}: unsupported dtype {arr.dtype}")
    return arr


def read_image(path: str | os.PathLike, *, color: str = "luma") -> np.ndarray:
    """One image as ``(H, W)`` float32 in the file's units.

    Parameters
    ----------
    path : .npy, .png, .tif/.tiff (first page), .exr, .dpx, .jpg
    color : {"luma", "error"}
        Convert colour to Rec.601 luma, or refuse colour input.
    """
    path = Path(path)
    if path.suffix.lower() == ".npy":
        arr = _read_npy(path)
        if arr.ndim == 3 and arr.shape[-1] in (3, 4):
            arr = _to_gray(arr, path, color)
        if arr.ndim != 2:
            raise InputError(f"image {path}: expected shape (H, W), got {arr.shape}")
        return _finite(arr.astype(np.float32), path)
    return _finite(_oiio_read_all(path, color, first_only=True)[0], path)


def _pattern_frames(pattern: str) -> list[Path]:
    first = 0 if Path(pattern % 0).exists() else 1
    out = []
    i = first
    while Path(pattern % i).exists():
        out.append(Path(pattern % i))
        i += 1
    return out


def read_stack(path: str | os.PathLike, *, color: str = "luma") -> np.ndarray:
    """A stack ``(N, H, W)`` float32: .npy, multi-page TIFF, a folder of frames or a printf pattern."""
    spath = str(path)
    path = Path(path)
    if re.search(r"%0?\d*d", spath):
        files = _pattern_frames(spath)
        if not files:
            raise InputError(f"frames {spath}: no file matches the pattern")
        frames = [read_image(f, color=color) for f in files]
    elif path.is_dir():
        files = sorted(f for f in path.iterdir() if f.suffix.lower() in IMAGE_SUFFIXES and not f.name.startswith("."))
        if not files:
            raise InputError(f"frames {path}: the folder holds no image files")
        frames = [read_image(f, color=color) for f in files]
    elif path.suffix.lower() == ".npy":
        arr = _read_npy(path)
        if arr.ndim != 3:
            raise InputError(f"stack {path}: expected shape (N, H, W), got {arr.shape}")
        return _finite(arr.astype(np.float32), path, "stack")
    else:
        frames = _oiio_read_all(path, color, first_only=False)
    shapes = {f.shape for f in frames}
    if len(shapes) != 1:
        raise InputError(f"stack {path}: frames differ in shape {sorted(shapes)}")
    return _finite(np.stack(frames).astype(np.float32), path, "stack")


def read_video(
    path: str | os.PathLike, *, max_frames: int | None = None, start: int = 0, color: str = "luma"
) -> np.ndarray:
    """Frames ``(F, H, W)`` float32 of a video file (PyAV) or an image sequence."""
    path = Path(path)
    if path.suffix.lower() not in VIDEO_SUFFIXES:
        stack = read_stack(path, color=color)
        return stack[start : None if max_frames is None else start + max_frames]
    import av

    if not path.exists():
        raise InputError(f"video {path}: no such file")
    frames = []
    try:
        with av.open(str(path)) as container:
            if not container.streams.video:
                raise InputError(f"video {path}: has no video stream")
            for i, frame in enumerate(container.decode(video=0)):
                if i < start:
                    continue
                if color == "error" and frame.format.name not in ("gray", "gray8", "gray16le"):
                    raise InputError(f"video {path}: frames are in colour ({frame.format.name}); grey frames are required")
                frames.append(_to_gray(frame.to_ndarray(format="rgb24"), path, "luma"))
                if max_frames is not None and len(frames) >= max_frames:
                    break
    except (av.error.FFmpegError, OSError) as exc:
        raise InputError(f"video {path}: cannot decode ({exc})") from exc
    if not frames:
        raise InputError(f"video {path}: no frames decoded (from frame {start})")
    return np.stack(frames).astype(np.float32)


# ----------------------------------------------------------------------------- writing
def _to_uint8(frames: np.ndarray, data_range: float) -> np.ndarray:
    return np.clip(np.rint(np.asarray(frames, np.float64) * (255.0 / data_range)), 0, 255).astype(np.uint8)


def write_video(path: str | os.PathLike, frames: np.ndarray, *, data_range: float = 255.0, fps: int = 30) -> Path:
    """Write (N, H, W) frames as a video: .mp4 (H.264), .mkv/.avi (FFV1, lossless), .gif.

    Frames are scaled so ``data_range`` maps to 255.  H.264 in yuv420p needs
    even sizes: odd sizes are padded by repeating the last row/column.
    """
    import av

    path = Path(path)
    suffix = path.suffix.lower()
    data = _to_uint8(frames, data_range)
    if suffix == ".mp4":
        codec, pix_fmt, options = "libx264", "yuv420p", {"crf": "17", "preset": "medium"}
        pad = ((0, 0), (0, data.shape[1] % 2), (0, data.shape[2] % 2))
        data = np.pad(data, pad, mode="edge")
    elif suffix in (".mkv", ".avi"):
        codec, pix_fmt, options = "ffv1", "gray", {}
    elif suffix == ".gif":
        codec, pix_fmt, options = "gif", "gray", {}
    else:
        raise InputError(f"video {path}: unsupported container {suffix!r} (use .mp4, .mkv, .avi or .gif)")
    with atomic_output(path) as tmp:
        try:
            with av.open(str(tmp), mode="w") as container:
                stream = container.add_stream(codec, rate=fps)
                stream.width, stream.height = data.shape[2], data.shape[1]
                stream.pix_fmt = pix_fmt
                if options:
                    stream.options = options
                for img in data:
                    for packet in stream.encode(av.VideoFrame.from_ndarray(img, format="gray")):
                        container.mux(packet)
                for packet in stream.encode(None):
                    container.mux(packet)
        except (av.error.FFmpegError, OSError) as exc:
            raise OutputError(f"video {path}: cannot write ({exc})") from exc
    return path


def _oiio_write(path: Path, pages: list[np.ndarray], fmt: str) -> None:
    import OpenImageIO as oiio

    out = oiio.ImageOutput.create(str(path))
    if out is None:
        raise OutputError(f"image {path}: no writer for this format ({oiio.geterror()})")
    h, w = pages[0].shape
    spec = oiio.ImageSpec(w, h, 1, fmt)
    try:
        if len(pages) > 1:
            if not out.supports("multiimage"):
                raise OutputError(f"image {path}: the format cannot hold {len(pages)} pages")
            ok = out.open(str(path), [spec] * len(pages))
        else:
            ok = out.open(str(path), spec)
        if not ok:
            raise OutputError(f"image {path}: cannot open for writing ({out.geterror()})")
        for i, page in enumerate(pages):
            if i > 0 and not out.open(str(path), spec, "AppendSubimage"):
                raise OutputError(f"image {path}: cannot append page {i} ({out.geterror()})")
            # OpenImageIO wants (H, W, C) pixels; a 2-D array is misread
            if not out.write_image(np.ascontiguousarray(page.reshape(h, w, 1))):
                raise OutputError(f"image {path}: cannot write ({out.geterror()})")
    finally:
        out.close()


def write_image(path: str | os.PathLike, image: np.ndarray, *, dtype=None) -> Path:
    """Write an (H, W) image: .tif (float32, or ``dtype``), .exr (float32), .png (uint8), .npy."""
    path = Path(path)
    suffix = path.suffix.lower()
    image = np.asarray(image)
    if suffix == ".npy":
        return write_array(path, image)
    if suffix == ".png":
        arr, fmt = np.clip(np.rint(image), 0, 255).astype(np.uint8), "uint8"
    elif suffix in (".tif", ".tiff"):
        dt = np.dtype(dtype or np.float32)
        arr = image.astype(dt) if dt.kind == "f" else np.clip(np.rint(image), 0, np.iinfo(dt).max).astype(dt)
        fmt = {"float32": "float", "uint16": "uint16", "uint8": "uint8"}[dt.name]
    elif suffix == ".exr":
        arr, fmt = image.astype(np.float32), "float"
    else:
        raise InputError(f"image {path}: unsupported format {suffix!r}")
    with atomic_output(path) as tmp:
        _oiio_write(tmp, [arr], fmt)
    return path


def write_multipage_tiff(path: str | os.PathLike, stack: np.ndarray) -> Path:
    """Write an (N, H, W) uint8 or uint16 stack (e.g. a mask) as a multi-page TIFF."""
    path = Path(path)
    stack = np.asarray(stack)
    fmt = "uint16" if stack.dtype == np.uint16 else "uint8"
    with atomic_output(path) as tmp:
        _oiio_write(tmp, [p.astype(fmt) for p in stack], fmt)
    return path


def write_frames(
    directory: str | os.PathLike, frames: np.ndarray, *, fmt: str = "tiff16", data_range: float = 255.0, prefix: str = "frame"
) -> list[Path]:
    """One file per frame in a folder, written as a whole (temporary folder, then rename).

    fmt : "tiff16" (uint16, ``data_range`` -> 65535), "exr" (float32, raw values) or "png" (8-bit).
    """
    directory = Path(directory)
    names = []
    with atomic_output(directory) as tmp:
        tmp.mkdir()
        for i, frame in enumerate(np.asarray(frames)):
            if fmt == "tiff16":
                name, arr, ofmt = f"{prefix}_{i:04d}.tif", np.clip(np.rint(frame * (65535.0 / data_range)), 0, 65535).astype(np.uint16), "uint16"
            elif fmt == "exr":
                name, arr, ofmt = f"{prefix}_{i:04d}.exr", frame.astype(np.float32), "float"
            elif fmt == "png":
                name, arr, ofmt = f"{prefix}_{i:04d}.png", _to_uint8(frame, data_range), "uint8"
            else:
                raise InputError(f"frames {directory}: unknown frame format {fmt!r}")
            _oiio_write(tmp / name, [arr], ofmt)
            names.append(directory / name)
    return names


def write_array(path: str | os.PathLike, array: np.ndarray) -> Path:
    """Write a .npy file atomically (the name is kept exactly)."""
    path = Path(path)
    with atomic_output(path) as tmp:
        with open(tmp, "wb") as fh:
            np.save(fh, np.asarray(array), allow_pickle=False)
    return path


def read_array(path: str | os.PathLike) -> np.ndarray:
    return _read_npy(Path(path))
