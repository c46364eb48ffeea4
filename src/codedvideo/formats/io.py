"""Image, image-sequence and video files (the only importer of OpenImageIO and PyAV).

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

import contextlib
import json
import os
import re
from pathlib import Path

import numpy as np

from codedvideo.model import doors
from codedvideo.formats.atomic import atomic_output, check_cache, check_writable  # noqa: F401 (the writers' API here)
from codedvideo.formats.atomic import one_line as _one_line
from codedvideo.model.errors import InputError, OutputError
from codedvideo.model.units import EIGHT_BIT

IMAGE_SUFFIXES = (".png", ".tif", ".tiff", ".exr", ".dpx", ".jpg", ".jpeg")
#: Prefix of the container comment in which write_video records the frame size (H x W).
SIZE_TAG = "codedvideo size="
#: Written beside frames by write_frames: the data_range that was mapped to the files' full scale.
FRAMES_SIDECAR = "codedvideo-frames.json"
VIDEO_SUFFIXES = (".mp4", ".avi", ".mov", ".mkv", ".gif")
LUMA = np.array([0.299, 0.587, 0.114], np.float32)
COLOR_CHOICES = ("luma", "channels", "error")
# pixel types read as they are stored (anything else is read as float)
_NATIVE = ("uint8", "int8", "uint16", "int16", "uint32", "int32", "float", "half", "double")


def check_color(color: str) -> str:
    """Validate a colour policy (see the module docstring)."""
    if color not in COLOR_CHOICES:
        raise InputError(f"color: unknown choice {color!r} (use {', '.join(COLOR_CHOICES)})")
    return color


# ----------------------------------------------------------------------------- reading
def _finite(arr: np.ndarray, path, what: str = "image") -> np.ndarray:
    if not np.isfinite(arr).all():
        raise InputError(f"{what} {path}: contains NaN or Inf")
    return arr


def _to_channels(arr: np.ndarray) -> np.ndarray:
    """(H, W, C) or (H, W) pixels -> (C', H, W) float32, alpha dropped."""
    pixels = arr[..., None] if arr.ndim == 2 else arr
    c = pixels.shape[-1]
    keep = 1 if c <= 2 else 3  # grey(+alpha) or RGB(+alpha/extra)
    return np.moveaxis(pixels[..., :keep], -1, 0).astype(np.float32)


def _check_channels(arr: np.ndarray, path, what: str, layout: str) -> None:
    """A channels-first array read with ``color="channels"`` holds 1 or 3 channels (grey or colour, as the writers
    take them); any other count is another layout (a (T, H, W) stream of captures), refused before any work."""
    if arr.shape[0] not in (1, 3):
        raise InputError(f"{what} {path}: {arr.shape[0]} colour channels in {layout} {arr.shape}; colour is 1 or 3 "
                         "channels (a stack of captures is read without --color channels)")


def _to_gray(arr: np.ndarray, path, color: str) -> np.ndarray:
    """(H, W, C) or (H, W) -> (H, W) float32 (``"luma"``, ``"error"``) or (C, H, W) (``"channels"``)."""
    if color == "channels":
        return _to_channels(arr)
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


def _warn_planar(path: Path, channels: int) -> None:
    """Say that a TIFF of separate colour planes is read as one colour image: what numpy writes for a stack of 3
    or 4 frames saved as it is (tifffile stores a (3, H, W) or (4, H, W) array as planar RGB)."""
    doors.warn(f"image {path}: {channels} channels stored as separate planes, read as one colour image (its "
                  f"luma); if it holds {channels} frames or captures, save one page each (tifffile: "
                  "photometric='minisblack') or a .npy")


def _oiio_read_all(path: Path, color: str, first_only: bool, *, page: int = 0) -> list[np.ndarray]:
    """The pages of an image file from ``page`` on (``first_only``: that page alone)."""
    import OpenImageIO as oiio

    if not path.exists():
        raise InputError(f"image {path}: no such file")
    if path.is_dir():
        raise InputError(f"image {path}: is a folder, not an image file")
    config = oiio.ImageSpec()
    config.attribute("oiio:UnassociatedAlpha", 1)  # colour values as stored, not multiplied by alpha
    inp = oiio.ImageInput.open(str(path), config)
    if inp is None:
        raise InputError(f"image {path}: cannot read ({_one_line(oiio.geterror() or 'unknown format or corrupt file')})")
    pages = []
    try:
        sub = page
        while True:
            if sub > 0 and not inp.seek_subimage(sub, 0):
                if sub == page:
                    raise InputError(f"image {path}: has no page {page + 1}")
                break
            spec = inp.spec()
            native = spec.format
            if sub == page and color == "luma" and spec.nchannels in (3, 4) and \
                    spec.get_int_attribute("tiff:PlanarConfiguration") == 2:
                _warn_planar(path, spec.nchannels)
            data = inp.read_image(native if str(native) in _NATIVE else "float")
            if data is None or inp.has_error:
                raise InputError(f"image {path}: corrupt or truncated ({_one_line(inp.geterror() or oiio.geterror())})")
            pages.append(_to_gray(np.asarray(data), path, color))
            sub += 1
            if first_only:
                break
    finally:
        inp.close()
    if not first_only and page == 0 and path.suffix.lower() in (".tif", ".tiff"):
        expected = tiff_page_count(path)
        if expected != len(pages):  # a cut page chain reads as a shorter stack otherwise
            raise InputError(f"image {path}: corrupt or truncated (read {len(pages)} of {expected} TIFF pages)")
    return pages


def read_page(path: str | os.PathLike, page: int, *, color: str = "luma") -> np.ndarray:
    """Page ``page`` (from 0) of a multi-page image file, in the file's units, float32 (as :func:`read_image`)."""
    file = Path(path)
    check_color(color)
    return _finite(_oiio_read_all(file, color, first_only=True, page=page)[0], file)


def tiff_page_count(path: str | os.PathLike) -> int:
    """Pages in the main IFD chain of a (Big)TIFF; :class:`InputError` when the chain runs past the end."""
    import mmap

    file = Path(path)
    try:
        with open(file, "rb") as fh:  # mapped, not read: a long stack is not held to count its pages
            data = mmap.mmap(fh.fileno(), 0, access=mmap.ACCESS_READ) if os.fstat(fh.fileno()).st_size else b""
    except OSError as exc:
        raise InputError(f"image {file}: cannot read ({exc.strerror or exc})") from exc
    try:
        return _ifd_chain_length(data, file)
    finally:
        if isinstance(data, mmap.mmap):
            data.close()


def _ifd_chain_length(data, path: Path) -> int:
    import struct

    if len(data) < 8 or data[:2] not in (b"II", b"MM"):
        raise InputError(f"image {path}: not a TIFF file")
    e = "<" if data[:2] == b"II" else ">"
    big = struct.unpack(e + "H", data[2:4])[0] == 43
    fmt, size, count_fmt, entry = (e + "Q", 8, e + "Q", 20) if big else (e + "I", 4, e + "H", 12)
    offset = struct.unpack(fmt, data[8:16] if big else data[4:8])[0]
    pages, seen = 0, set()
    while offset:
        csize = struct.calcsize(count_fmt)
        if offset in seen or offset + csize > len(data):
            raise InputError(f"image {path}: corrupt or truncated (TIFF page {pages} lies past the end of the file)")
        seen.add(offset)
        n = struct.unpack(count_fmt, data[offset : offset + csize])[0]
        end = offset + csize + n * entry
        if end + size > len(data):
            raise InputError(f"image {path}: corrupt or truncated (TIFF page {pages} lies past the end of the file)")
        offset = struct.unpack(fmt, data[end : end + size])[0]
        pages += 1
    return pages


def _read_npy(path: Path) -> np.ndarray:
    if not path.exists():
        raise InputError(f"array {path}: no such file")
    try:
        arr = np.load(path, allow_pickle=False)
    except (ValueError, OSError, EOFError) as exc:
        raise InputError(f"array {path}: not a readable .npy file ({exc})") from exc
    if not isinstance(arr, np.ndarray):  # np.load opens .npz archives whatever their name
        arr.close()
        raise InputError(f"array {path}: is a .npz archive, not a .npy array (save it with numpy.save)")
    if arr.dtype.kind not in "biuf":
        raise InputError(f"array {path}: unsupported dtype {arr.dtype}")
    if arr.size == 0:
        raise InputError(f"array {path}: holds no values (shape {arr.shape})")
    return arr


_OIIO_DTYPES = {"uint8": "uint8", "int8": "int8", "uint16": "uint16", "int16": "int16", "uint32": "uint32",
                "int32": "int32", "half": "float16", "float": "float32", "double": "float64"}


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
        files = (_pattern_frames(str(file)) if not file.is_dir() else
                 sorted((f for f in file.iterdir() if f.suffix.lower() in IMAGE_SUFFIXES and not f.name.startswith(".")),
                        key=_natural_key))
        if not files:
            raise InputError(f"frames {file}: the folder holds no image files")
        return stored_dtype(files[0])
    import OpenImageIO as oiio

    inp = oiio.ImageInput.open(str(file))
    if inp is None:
        raise InputError(f"image {file}: cannot read ({_one_line(oiio.geterror() or 'unknown format or corrupt file')})")
    try:
        return np.dtype(_OIIO_DTYPES.get(str(inp.spec().format), "float32"))
    finally:
        inp.close()


def read_image(path: str | os.PathLike, *, color: str = "luma") -> np.ndarray:
    """One image in the file's units.

    Parameters
    ----------
    path : .npy, .png, .tif/.tiff (first page), .exr, .dpx, .jpg
        A .npy holds (H, W), or (H, W, C) with C in 1..4.
    color : {"luma", "channels", "error"}
        Convert colour to Rec.601 luma, keep the channels apart, or refuse
        colour input.

    Returns
    -------
    ndarray of shape (H, W), or (C, H, W) for ``color="channels"``, float32
    """
    file = Path(path)
    check_color(color)
    if file.suffix.lower() == ".npy":
        arr = _read_npy(file)
        if arr.ndim == 3 and arr.shape[-1] in (1, 2, 3, 4):
            arr = _to_gray(arr, file, color)
        elif arr.ndim == 2 and color == "channels":
            arr = arr[None]
        if arr.ndim != (3 if color == "channels" else 2):
            raise InputError(f"image {file}: expected shape (H, W) or (H, W, C), got {arr.shape}")
        if color == "channels":
            _check_channels(arr, file, "image", "(C, H, W)")
        return _finite(arr.astype(np.float32), file)
    return _finite(_oiio_read_all(file, color, first_only=True)[0], file)


_PATTERN = re.compile(r"%0?\d*d")


def is_pattern(spec: str | os.PathLike) -> bool:
    """True for a printf-style frame pattern such as ``frames/%04d.png``."""
    return len(_PATTERN.findall(Path(spec).name)) == 1


def _pattern_frames(pattern: str) -> list[Path]:
    """The files of a printf pattern: numbers from 0 (or 1) up to the first gap."""
    try:
        first = 0 if Path(pattern % 0).exists() else 1
        out = []
        i = first
        while Path(pattern % i).exists():
            out.append(Path(pattern % i))
            i += 1
    except (TypeError, ValueError) as exc:
        raise InputError(f"frames {pattern}: not a usable printf pattern ({exc})") from exc
    return out


def _natural_key(path: Path):
    """Sort frame_2 before frame_10."""
    return [(0, int(t), "") if t.isdigit() else (1, 0, t) for t in re.split(r"(\d+)", path.name)]


def read_stack(path: str | os.PathLike, *, color: str = "luma") -> np.ndarray:
    """A stack of frames in the file's units.

    Parameters
    ----------
    path : str or PathLike
        .npy (N, H, W) (or (C, N, H, W) with ``color="channels"``), a
        multi-page TIFF or multi-part EXR, a folder of image files (in
        natural order: ``f_2`` before ``f_10``) or a printf pattern such as
        ``frames/%04d.png`` (numbers from 0 or 1 up to the first gap).
    color : {"luma", "channels", "error"}

    Returns
    -------
    ndarray of shape (N, H, W), or (C, N, H, W) for ``color="channels"``, float32
    """
    check_color(color)
    files = frame_files(path)
    source = Path(path)
    if files is not None:
        frames = [read_image(f, color=color) for f in files]
    elif source.suffix.lower() == ".npy":
        arr = _read_npy(source)
        if color == "channels" and arr.ndim == 3:
            arr = arr[None]
        if arr.ndim != (4 if color == "channels" else 3):
            raise InputError(f"stack {source}: expected shape (N, H, W), got {arr.shape}")
        if color == "channels":
            _check_channels(arr, source, "stack", "(C, N, H, W)")
        return _finite(arr.astype(np.float32), source, "stack")
    else:
        frames = _oiio_read_all(source, color, first_only=False)
    shapes = {f.shape for f in frames}
    if len(shapes) != 1:
        odd = next(i for i, f in enumerate(frames) if f.shape != frames[0].shape)
        which = f"{files[odd].name} is {frames[odd].shape}, {files[0].name} {frames[0].shape}" if files is not None \
            else f"page {odd + 1} is {frames[odd].shape}, page 1 {frames[0].shape}"
        raise InputError(f"stack {source}: frames differ in shape ({which})")
    stack = np.stack(frames, axis=1 if color == "channels" else 0)
    return _finite(stack.astype(np.float32), source, "stack")


def frame_files(path: str | os.PathLike) -> list[Path] | None:
    """The image files of a folder of frames (natural order: ``f_2`` before ``f_10``) or a printf pattern
    (``frames/%04d.png``: numbers from 0 or 1 up to the first gap); None for any other path."""
    spath = str(path)
    source = Path(path)
    if is_pattern(spath) and not source.exists():
        files = _pattern_frames(spath)
        if not files:
            raise InputError(f"frames {spath}: no file matches the pattern")
        return files
    if source.is_dir():
        files = sorted((f for f in source.iterdir()
                        if f.suffix.lower() in IMAGE_SUFFIXES and not f.name.startswith(".")), key=_natural_key)
        if not files:
            raise InputError(f"frames {source}: the folder holds no image files")
        return files
    return None


def read_video(
    path: str | os.PathLike, *, max_frames: int | None = None, start: int = 0, color: str = "luma"
) -> np.ndarray:
    """Frames of a video file (PyAV) or an image sequence (:func:`read_stack`).

    Grey videos (gray, gray16le pixels, e.g. FFV1) are read exactly; colour
    ones through 8-bit RGB.

    Returns
    -------
    ndarray of shape (F, H, W), or (C, F, H, W) for ``color="channels"``, float32
    """
    check_color(color)
    source = Path(path)
    if source.suffix.lower() == ".npy":
        layout = npy_layout(source)
        if layout is not None and len(layout[0]) == 4:  # a colour video: (F, H, W, C) or (C, F, H, W)
            stack = _npy_colour_video(read_array(source), source, color)
            sl = slice(start, None if max_frames is None else start + max_frames)
            return stack[:, sl] if color == "channels" else stack[sl]
    if source.suffix.lower() not in VIDEO_SUFFIXES:
        stack = read_stack(source, color=color)
        sl = slice(start, None if max_frames is None else start + max_frames)
        return stack[:, sl] if color == "channels" else stack[sl]
    frames = []
    for frame in iter_video(source, color=color, start=start):
        frames.append(frame)
        if max_frames is not None and len(frames) >= max_frames:
            break
    if not frames:
        raise InputError(f"video {source}: no frames decoded (from frame {start})")
    return np.stack(frames, axis=1 if color == "channels" else 0).astype(np.float32)


def _npy_colour_video(arr: np.ndarray, path: Path, color: str) -> np.ndarray:
    """A 4-D .npy video, (F, H, W, C) with C in (3, 4) or (C, F, H, W) with C in (1, 3, 4) (as ``simulate
    --bayer`` writes its truth): (F, H, W) luma, or (C, F, H, W) for ``color="channels"``."""
    if arr.shape[-1] in (3, 4):  # (a grey video 3 or 4 pixels wide could not be used anyway)
        channels_first = np.moveaxis(arr, -1, 0)
    elif arr.shape[0] not in (1, 3, 4):
        raise InputError(f"video {path}: expected shape (F, H, W), (F, H, W, 3) or (3, F, H, W), got {arr.shape}")
    else:
        channels_first = arr
    video = _finite(channels_first.astype(np.float32), path, "video")
    channels = video[:1] if video.shape[0] == 1 else video[:3]  # (an alpha channel dropped)
    if color == "channels":
        return np.ascontiguousarray(channels)
    if channels.shape[0] == 1:
        return channels[0]
    if color == "error":
        raise InputError(f"video {path}: has {channels.shape[0]} channels; a single-channel video is required")
    if (channels[0] == channels[1]).all() and (channels[1] == channels[2]).all():
        return channels[0]
    return np.tensordot(LUMA, channels, axes=([0], [0]))


#: Video codecs that keep every value of the frames they hold (a GIF's palette keeps grey exactly).
LOSSLESS_CODECS = ("ffv1", "rawvideo", "png", "huffyuv", "ffvhuff", "utvideo", "gif", "qtrle", "apng")


def lossy_codec(path: str | os.PathLike) -> str | None:
    """The codec of a video file's first video stream when it is not one of :data:`LOSSLESS_CODECS` (H.264, VP9,
    MPEG-4: values changed by the compression), else None (or when the file cannot say: its reader will)."""
    import av

    try:
        with av.open(str(path)) as container:
            if not container.streams.video:
                return None
            name = container.streams.video[0].codec_context.name
    except (av.error.FFmpegError, OSError):
        return None
    return None if name in LOSSLESS_CODECS else name


def iter_video(path: str | os.PathLike, *, color: str = "luma", start: int = 0):
    """The frames of a video file one at a time (:func:`read_video`'s units), from frame ``start``.

    A GIF without its trailer, or a file that decodes to the end with fewer
    frames than its header promises, is an :class:`InputError`.
    """
    import av

    source = Path(path)
    if not source.exists():
        raise InputError(f"video {source}: no such file")
    if source.suffix.lower() == ".gif" and not _gif_complete(source):
        raise InputError(f"video {source}: truncated (no GIF trailer)")
    decoded = 0
    try:
        with av.open(str(source)) as container:
            if not container.streams.video:
                raise InputError(f"video {source}: has no video stream")
            stream = container.streams.video[0]
            # a GIF's frame delays are whole hundredths of a second (30 fps is stored as 3/100 s), so its
            # duration x rate misses the frame count; its trailer, checked above, tells a truncated one
            expected = None if source.suffix.lower() == ".gif" else _expected_frames(container, stream)
            size = _tagged_size(container)
            for i, frame in enumerate(container.decode(video=0)):
                decoded = i + 1
                if i < start:
                    continue
                grey = frame.format.name in ("gray", "gray8", "gray16le")
                if color == "error" and not grey:
                    raise InputError(f"video {source}: frames are in colour ({frame.format.name}); grey frames are required")
                pixels = frame.to_ndarray() if grey else frame.to_ndarray(format="rgb24")
                if size is not None:  # written by write_video: undo the encoder's padding
                    pixels = pixels[: size[0], : size[1]]
                yield _to_gray(pixels, source, "channels" if color == "channels" else "luma").astype(np.float32)
            if expected is not None and decoded < expected - 1:  # a stream that ends early was cut short
                raise InputError(f"video {source}: truncated (decoded {decoded} of {expected} frames)")
    except (av.error.FFmpegError, OSError) as exc:
        raise InputError(f"video {source}: cannot decode ({_one_line(exc)})") from exc


def _tagged_size(container) -> tuple[int, int] | None:
    """(H, W) recorded by :func:`write_video` in the container's comment, or None."""
    tag = str(container.metadata.get("comment", ""))
    if tag.startswith(SIZE_TAG):
        try:
            h, w = (int(v) for v in tag[len(SIZE_TAG):].split("x"))
            return h, w
        except ValueError:
            return None
    return None


def _expected_frames(container, stream) -> int | None:
    """Frame count from the container's header (duration x rate), or None when unknown.

    Streaming formats (Matroska) decode a truncated file without error;
    the duration recorded in the header tells how many frames there were
    (to within one frame).  Not for GIF (see :func:`iter_video`).
    """
    rate = stream.average_rate
    if container.duration and rate:
        return int(round(container.duration / 1e6 * float(rate)))
    return None


def _gif_complete(path: Path) -> bool:
    """A complete GIF ends with the trailer byte 0x3B."""
    with open(path, "rb") as fh:
        fh.seek(0, os.SEEK_END)
        if fh.tell() == 0:
            return False
        fh.seek(-1, os.SEEK_END)
        return fh.read(1) == b";"


# ----------------------------------------------------------------------------- writing
def _to_uint8(frames: np.ndarray, data_range: float) -> np.ndarray:
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


def _frames_last(frames: np.ndarray, path, what: str) -> np.ndarray:
    """(N, H, W) or (C, N, H, W) with C in (1, 3) -> (N, H, W) grey or (N, H, W, 3) colour (views, no copy)."""
    if not isinstance(frames, np.ndarray) and getattr(frames, "ndim", None) == 3:
        return frames  # frames read one at a time (frames_of)
    arr = np.asarray(frames)
    if arr.ndim == 4:
        if arr.shape[0] not in (1, 3):
            raise InputError(f"{what} {path}: colour frames need 1 or 3 channels, got shape {arr.shape}")
        return arr[0] if arr.shape[0] == 1 else np.moveaxis(arr, 0, -1)
    if arr.ndim != 3:
        raise InputError(f"{what} {path}: expected frames (N, H, W) or (C, N, H, W), got shape {arr.shape}")
    return arr


def write_video(path: str | os.PathLike, frames: np.ndarray, *, data_range: float = EIGHT_BIT, fps: int = 30) -> Path:
    """Write frames as a video: .mp4 (H.264), .mkv/.avi (FFV1, lossless), .gif.

    Parameters
    ----------
    frames : ndarray of shape (N, H, W), or (C, N, H, W) with C = 3 for colour
        Scaled so ``data_range`` maps to 255, then rounded to 8 bits.  FFV1
        stores the 8-bit frames exactly (grey, or RGB as bgr0); GIF is exact
        for grey and quantised to 3-3-2 bit RGB for colour.  H.264 in yuv420p
        needs even sizes: odd sizes are padded by repeating the last
        row/column, and the size is recorded in the container's comment so
        that :func:`read_video` crops the padding off again.
    """
    target = Path(path)
    data = _frames_last(frames, target, "video")
    with video_writer(target, data.shape[1:3], colour=data.ndim == 4, data_range=data_range, fps=fps) as write:
        write(data)
    return target


#: A GIF stores each frame's delay in whole hundredths of a second: no faster rate can be written.
GIF_MAX_FPS = 100


def gif_rate_problem(fps: int) -> str | None:
    """Why a GIF cannot be written at ``fps`` frames a second (None: it can)."""
    if fps > GIF_MAX_FPS:
        return (f"a GIF holds at most {GIF_MAX_FPS} frames a second (its frame delays are whole hundredths of a "
                f"second), not {fps}; choose a lower rate or another format")
    return None


@contextlib.contextmanager
def video_writer(path: str | os.PathLike, size: tuple[int, int], *, colour: bool = False, data_range: float = EIGHT_BIT,
                 fps: int = 30):
    """Encode a video part by part (:func:`write_video`'s formats): yields ``write(frames)``.

    ``frames`` are (n, H, W) grey or (n, H, W, 3) RGB, in order; each part is
    encoded as it comes, a frame at a time (converted to 8 bits one frame at
    a time: no float copy of the part), so a long video is never held whole.
    The file appears under ``path`` only when the block ends without an error.
    """
    import av

    target = Path(path)
    suffix = target.suffix.lower()
    height, width = size
    pad = (0, 0)
    if suffix in (".mp4", ".mov"):
        codec, pix_fmt, options = "libx264", "yuv420p", {"crf": "17", "preset": "medium"}
        pad = (height % 2, width % 2)
    elif suffix in (".mkv", ".avi"):
        codec, pix_fmt, options = "ffv1", "bgr0" if colour else "gray", {}
    elif suffix == ".gif":
        codec, pix_fmt, options = "gif", "rgb8" if colour else "gray", {}
    else:
        raise InputError(f"video {target}: unsupported container {suffix!r} (use .mp4, .mov, .mkv, .avi or .gif)")
    if suffix == ".gif" and fps > GIF_MAX_FPS:
        raise InputError(f"video {target}: {gif_rate_problem(fps)}")
    in_fmt = "rgb24" if colour else "gray"
    with atomic_output(target) as tmp:
        try:
            with av.open(str(tmp), mode="w", options={"fflags": "+bitexact"}) as container:
                # the size before any padding, so read_video returns the frames as given
                container.metadata["comment"] = f"{SIZE_TAG}{height}x{width}"
                stream = container.add_stream(codec, rate=fps)
                stream.width, stream.height = width + pad[1], height + pad[0]
                stream.pix_fmt = pix_fmt
                if options:
                    stream.options = options

                def write(frames: np.ndarray) -> None:
                    for img in frames_of(frames):
                        img = _to_uint8(img, data_range)
                        if any(pad):
                            img = np.pad(img, ((0, pad[0]), (0, pad[1])) + (((0, 0),) if colour else ()), mode="edge")
                        frame = av.VideoFrame.from_ndarray(np.ascontiguousarray(img), format=in_fmt)
                        for packet in stream.encode(frame):
                            container.mux(packet)

                yield write
                for packet in stream.encode(None):
                    container.mux(packet)
        except (av.error.FFmpegError, OSError) as exc:
            raise OutputError(f"video {target}: cannot write ({exc})") from exc


class _OiioPages:
    """An image file written page by page (one subimage each): ``add(page, fmt)``, then ``close()``.

    The file is opened at the first page, for ``pages`` subimages of that
    page's size and type; a file of several pages needs a format that holds
    them (TIFF, EXR).
    """

    def __init__(self, path: Path, pages: int):
        import OpenImageIO as oiio

        self.path, self.pages, self.written, self.spec = path, pages, 0, None
        self.out = oiio.ImageOutput.create(str(path))
        if self.out is None:
            raise OutputError(f"image {path}: no writer for this format ({_one_line(oiio.geterror())})")

    def add(self, page: np.ndarray, fmt: str) -> None:
        """One page of (H, W) or (C, H, W) pixels."""
        import OpenImageIO as oiio

        # OpenImageIO wants (H, W, C) pixels; a 2-D array is misread
        pixels = page[..., None] if page.ndim == 2 else np.moveaxis(page, 0, -1)
        if self.written >= self.pages:
            raise OutputError(f"image {self.path}: more than the {self.pages} pages announced")
        if self.spec is None:
            h, w, c = pixels.shape
            self.spec = oiio.ImageSpec(w, h, c, fmt)
            self.spec.attribute("DateTime", "")  # no time of writing: the same pixels give the same bytes
            if c in (2, 4):
                self.spec.attribute("oiio:UnassociatedAlpha", 1)  # colour values are not premultiplied by alpha
            if fmt == "float" and self.path.suffix.lower() in (".tif", ".tiff"):
                # deflate alone: the floating-point predictor (libtiff's default here) is a codec that tifffile and
                # scikit-image read only with the optional imagecodecs package
                self.spec.attribute("tiff:Predictor", 1)
            if self.pages > 1:
                if not self.out.supports("multiimage"):
                    raise OutputError(f"image {self.path}: the format cannot hold {self.pages} pages")
                ok = self.out.open(str(self.path), [self.spec] * self.pages)
            else:
                ok = self.out.open(str(self.path), self.spec)
            if not ok:
                raise OutputError(f"image {self.path}: cannot open for writing ({self.out.geterror()})")
        elif pixels.shape != (self.spec.height, self.spec.width, self.spec.nchannels):
            raise OutputError(f"image {self.path}: page {self.written + 1} is "
                              f"{pixels.shape[0]}x{pixels.shape[1]}x{pixels.shape[2]}, "
                              f"the first {self.spec.height}x{self.spec.width}x{self.spec.nchannels}")
        elif not self.out.open(str(self.path), self.spec, "AppendSubimage"):
            raise OutputError(f"image {self.path}: cannot append page {self.written} ({self.out.geterror()})")
        if not self.out.write_image(np.ascontiguousarray(pixels)):
            raise OutputError(f"image {self.path}: cannot write ({self.out.geterror()})")
        self.written += 1

    def close(self) -> None:
        self.out.close()


def _oiio_write(path: Path, pages: list[np.ndarray], fmt: str) -> None:
    """Write pages of (H, W) or (C, H, W) pixels (one subimage each)."""
    out = _OiioPages(path, len(pages))
    try:
        for page in pages:
            out.add(page, fmt)
    finally:
        out.close()


# suffix -> (pixel types it can hold, default)
_IMAGE_TYPES = {
    ".png": (("uint8", "uint16"), "uint8"),
    ".tif": (("uint8", "uint16", "float32"), "float32"),
    ".tiff": (("uint8", "uint16", "float32"), "float32"),
    ".exr": (("float16", "float32"), "float32"),
    ".dpx": (("uint8", "uint16", "float32"), "uint16"),
}
_OIIO_FMT = {"uint8": "uint8", "uint16": "uint16", "float16": "half", "float32": "float"}


def _pixels(path: Path, values: np.ndarray, dtype) -> tuple[np.ndarray, str]:
    """Values in the file's units -> (array of the pixel type, OpenImageIO type name)."""
    suffix = path.suffix.lower()
    if suffix not in _IMAGE_TYPES:
        raise InputError(f"image {path}: unsupported format {suffix!r} (use .png, .tif, .exr, .dpx or .npy)")
    allowed, default = _IMAGE_TYPES[suffix]
    dt = np.dtype(dtype or default)
    if dt.name not in allowed:
        raise InputError(f"image {path}: {suffix} cannot hold {dt.name} pixels (use {', '.join(allowed)})")
    if dt.kind == "f":
        arr = values.astype(dt)
    else:
        arr = np.clip(np.rint(values), 0, np.iinfo(dt).max).astype(dt)
    return arr, _OIIO_FMT[dt.name]


def write_image(path: str | os.PathLike, image: np.ndarray, *, dtype=None) -> Path:
    """Write one image, values in the file's units (no scaling; integers are rounded and clipped).

    Parameters
    ----------
    path : .png (uint8 or uint16), .tif/.tiff (float32, uint8 or uint16),
        .exr (float32 or float16), .dpx (uint16, uint8 or float32) or .npy
        (the array as given); the first type named is the default.
    image : ndarray of shape (H, W), or (C, H, W) with C in (1, 3, 4)
    dtype : pixel type, optional
    """
    target = Path(path)
    pixels = np.asarray(image)
    if target.suffix.lower() == ".npy":
        return write_array(target, pixels)
    if pixels.ndim not in (2, 3) or (pixels.ndim == 3 and pixels.shape[0] not in (1, 3, 4)):
        raise InputError(f"image {target}: expected shape (H, W) or (C, H, W), got {pixels.shape}")
    arr, fmt = _pixels(target, pixels, dtype)
    with atomic_output(target) as tmp:
        _oiio_write(tmp, [arr], fmt)
    return target


def write_stack(path: str | os.PathLike, stack: np.ndarray, *, dtype=None) -> Path:
    """Write an (N, H, W) stack as one multi-page file: TIFF pages or EXR parts.

    Values are stored in the file's units (no scaling).  ``dtype`` as for
    :func:`write_image` (TIFF: float32 by default, uint8 or uint16; EXR:
    float32 or float16).  A (C, N, H, W) colour stack gives C-channel pages.
    """
    data = np.asarray(stack)
    if data.ndim == 4:
        data = np.moveaxis(data, 0, 1)  # (N, C, H, W): one C-channel page per frame
    elif data.ndim != 3:
        raise InputError(f"stack {path}: expected shape (N, H, W) or (C, N, H, W), got {data.shape}")
    with stack_writer(path, len(data), dtype=dtype) as write:
        write(data)
    return Path(path)


@contextlib.contextmanager
def stack_writer(path: str | os.PathLike, pages: int, *, dtype=None):
    """Write a multi-page file (:func:`write_stack`'s formats) part by part: yields ``write(pages)``.

    ``pages`` parts of (n, H, W) (or (n, C, H, W)) come in order, each written
    as it comes, so a long stack is never held whole; the file appears under
    ``path`` only when the block ends with all ``pages`` pages written.
    """
    target = Path(path)
    if target.suffix.lower() not in (".tif", ".tiff", ".exr"):
        raise InputError(f"stack {target}: multi-page files are .tif/.tiff or .exr, not {target.suffix!r}")
    _pixels(target, np.zeros(1), dtype)  # the pixel type is checked before anything is written
    with atomic_output(target) as tmp:
        out = _OiioPages(tmp, pages)
        try:
            def write(part: np.ndarray) -> None:
                for page in frames_of(part):
                    out.add(*_pixels(target, page, dtype))

            yield write
        finally:
            out.close()
        if out.written != pages:
            raise OutputError(f"stack {target}: {out.written} of {pages} pages written")


def write_multipage_tiff(path: str | os.PathLike, stack: np.ndarray) -> Path:
    """Write an (N, H, W) stack (e.g. a mask) as a multi-page TIFF of its own type.

    uint8 and uint16 stay integer; anything else is written as float32 pages.
    Mask images are read as a fraction of full scale, so a binary mask for
    ``--mask`` is written as 0/255 (uint8) or 0/65535 (uint16).
    """
    data = np.asarray(stack)
    dtype = data.dtype if data.dtype in (np.uint8, np.uint16) else np.float32
    if data.dtype == bool:
        data, dtype = data.astype(np.uint8), np.uint8
    return write_stack(path, data, dtype=dtype)


def write_frames(
    directory: str | os.PathLike, frames: np.ndarray, *, fmt: str = "tiff16", data_range: float = EIGHT_BIT, prefix: str = "frame"
) -> list[Path]:
    """One file per frame in a folder, written as a whole (temporary folder, then rename).

    Parameters
    ----------
    frames : ndarray of shape (N, H, W), or (C, N, H, W) for colour (RGB files)
    fmt : {"tiff16", "exr", "png", "png16", "dpx"}
        "tiff16" (uint16, ``data_range`` -> 65535), "exr" (float32,
        ``data_range`` -> 1.0, the EXR convention for white; not clipped),
        "png" (8-bit, ``data_range`` -> 255), "png16" and "dpx" (16-bit,
        ``data_range`` -> 65535).  Files are numbered with at least 4 digits,
        as many as the last number needs (names sort in frame order).
    """
    data = np.asarray(frames)
    if data.ndim == 4:
        data = np.moveaxis(data, 0, 1)  # (N, C, H, W): one colour file per frame
    elif data.ndim != 3:
        raise InputError(f"frames {directory}: expected shape (N, H, W) or (C, N, H, W), got {data.shape}")
    with frames_writer(directory, fmt=fmt, data_range=data_range, prefix=prefix, total=data.shape[0]) as write:
        return write(data)


#: Frame formats of :func:`write_frames`: name -> (file extension, OpenImageIO type, the full scale data_range maps to)
_FRAME_FORMATS = {"tiff16": ("tif", "uint16", 65535.0), "exr": ("exr", "float", 1.0), "png": ("png", "uint8", 255.0),
                  "png16": ("png", "uint16", 65535.0), "dpx": ("dpx", "uint16", 65535.0)}


@contextlib.contextmanager
def frames_writer(directory: str | os.PathLike, *, fmt: str = "tiff16", data_range: float = EIGHT_BIT,
                  prefix: str = "frame", total: int | None = None):
    """Write a folder of frames (:func:`write_frames`) part by part: yields ``write(frames)`` -> their paths.

    Parts of (n, H, W) (or (n, C, H, W) colour) frames come in order and are
    numbered on, with as many digits as ``total`` frames need (at least 4; 6
    when it is not known), so that the names sort in frame order; the folder
    appears under ``directory`` only when the block ends without an error.
    """
    folder = Path(directory)
    if fmt not in _FRAME_FORMATS:
        raise InputError(f"frames {folder}: unknown frame format {fmt!r}")
    ext, ofmt, full = _FRAME_FORMATS[fmt]
    digits = max(4, len(str(max(total - 1, 0)))) if total is not None else 6
    with atomic_output(folder) as tmp:
        tmp.mkdir()
        count = 0

        def write(frames: np.ndarray) -> list[Path]:
            nonlocal count
            names = []
            for frame in frames_of(frames):
                if ofmt == "float":
                    arr = (frame * np.float32(full / data_range)).astype(np.float32)
                elif full == 255.0:
                    arr = _to_uint8(frame, data_range)
                else:
                    arr = np.clip(np.rint(frame * (full / data_range)), 0, full).astype(np.uint16)
                name = f"{prefix}_{count:0{digits}d}.{ext}"
                _oiio_write(tmp / name, [arr], ofmt)
                names.append(folder / name)
                count += 1
            return names

        yield write
        # how stored values map back to frame units, for read_frames_scale (the image files alone
        # do not say which data_range was mapped to their full scale)
        (tmp / FRAMES_SIDECAR).write_text(json.dumps(dict(format=fmt, data_range=data_range, full_scale=full)) + "\n")


def read_frames_scale(directory: str | os.PathLike) -> float:
    """Factor from a frame folder's stored values to frame units (1.0 without a sidecar, or for EXR frames
    written raw before they were scaled to 1.0: ``full_scale`` null)."""
    side = Path(directory) / FRAMES_SIDECAR
    if not side.is_file():
        return 1.0
    try:
        meta = json.loads(side.read_text())
        return 1.0 if meta.get("full_scale") is None else float(meta["data_range"]) / float(meta["full_scale"])
    except (ValueError, KeyError, TypeError) as exc:
        raise InputError(f"frames {directory}: unreadable {FRAMES_SIDECAR} ({exc})") from exc


def write_array(path: str | os.PathLike, array: np.ndarray) -> Path:
    """Write a .npy file atomically (the name is kept exactly)."""
    target = Path(path)
    with atomic_output(target) as tmp:
        with open(tmp, "wb") as fh:
            np.save(fh, np.asarray(array), allow_pickle=False)
    return target


@contextlib.contextmanager
def npy_writer(path: str | os.PathLike, shape: tuple, dtype="<f4"):
    """Write a .npy file part by part: yields ``write(part)``; parts in C order, appended as they come.

    The header first, then each part (as ``dtype``), to a temporary renamed onto
    ``path`` only when the block ends with exactly ``shape`` written, so memory
    does not grow with the file (a memory map would: its written pages stay in
    the process's resident set).
    """
    target = Path(path)
    np_dtype = np.dtype(dtype)
    total = int(np.prod(shape)) * np_dtype.itemsize
    with atomic_output(target) as tmp:
        with open(tmp, "wb") as fh:
            np.lib.format.write_array_header_2_0(fh, dict(descr=np.lib.format.dtype_to_descr(np_dtype),
                                                          fortran_order=False, shape=tuple(shape)))
            start = fh.tell()

            def write(part) -> None:
                if isinstance(part, np.ndarray) and part.dtype == np_dtype and part.flags.c_contiguous:
                    part.tofile(fh)  # no copy
                else:  # converted a frame at a time (no copy of the whole part)
                    for frame in frames_of(part):
                        np.ascontiguousarray(frame, dtype=np_dtype).tofile(fh)

            yield write
            if fh.tell() - start != total:
                raise RuntimeError(f"output {target}: {fh.tell() - start} of {total} bytes written")


def read_array(path: str | os.PathLike) -> np.ndarray:
    return _read_npy(Path(path))


def npy_layout(path: str | os.PathLike) -> tuple[tuple[int, ...], np.dtype, int] | None:
    """``(shape, dtype, data offset)`` of a C-ordered numeric .npy file whose size matches its header, so that
    its parts can be read one at a time; None for any other file (read it whole with :func:`read_array`,
    which names the problem)."""
    try:
        with open(path, "rb") as fh:
            version = np.lib.format.read_magic(fh)
            read_header = np.lib.format.read_array_header_1_0 if version == (1, 0) else np.lib.format.read_array_header_2_0
            shape, fortran, dtype = read_header(fh)
            offset = fh.tell()
    except (OSError, ValueError, EOFError):
        return None
    if fortran or dtype.kind not in "biuf" or dtype.hasobject or 0 in shape:
        return None
    if os.path.getsize(path) != offset + int(np.prod(shape, dtype=np.int64)) * dtype.itemsize:
        return None
    return tuple(shape), dtype, offset


def available_memory() -> int | None:
    """Bytes of memory available to a new allocation (Linux: MemAvailable, page cache included), or None."""
    try:
        with open("/proc/meminfo") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    try:
        return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError, AttributeError):  # not on this platform
        return None
