"""Image files through OpenImageIO: single images, multi-page stacks (TIFF pages, EXR parts) and folders or
printf patterns of frames, read and written (the only importer of OpenImageIO)."""

from __future__ import annotations

import contextlib
import json
import os
import re
from pathlib import Path

import numpy as np

from codedvideo.formats.arrays import read_npy, write_array
from codedvideo.formats.atomic import atomic_output
from codedvideo.formats.atomic import one_line as _one_line
from codedvideo.formats.pixels import check_channels, check_color, finite, frames_of, to_gray, to_uint8
from codedvideo.formats.tiff import tiff_page_count
from codedvideo.model import doors
from codedvideo.model.errors import InputError, OutputError
from codedvideo.model.units import EIGHT_BIT


IMAGE_SUFFIXES = (".png", ".tif", ".tiff", ".exr", ".dpx", ".jpg", ".jpeg")


#: Written beside frames by write_frames: the data_range that was mapped to the files' full scale.
FRAMES_SIDECAR = "codedvideo-frames.json"


# pixel types read as they are stored (anything else is read as float)
_NATIVE = ("uint8", "int8", "uint16", "int16", "uint32", "int32", "float", "half", "double")


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
            pages.append(to_gray(np.asarray(data), path, color))
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
    return finite(_oiio_read_all(file, color, first_only=True, page=page)[0], file)


_OIIO_DTYPES = {"uint8": "uint8", "int8": "int8", "uint16": "uint16", "int16": "int16", "uint32": "uint32",
                "int32": "int32", "half": "float16", "float": "float32", "double": "float64"}


def pixel_dtype(path: Path) -> np.dtype:
    """The numpy type of an image file's pixels as OpenImageIO reads its header (float32 for any other format)."""
    import OpenImageIO as oiio

    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        raise InputError(f"image {path}: cannot read ({_one_line(oiio.geterror() or 'unknown format or corrupt file')})")
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
        arr = read_npy(file)
        if arr.ndim == 3 and arr.shape[-1] in (1, 2, 3, 4):
            arr = to_gray(arr, file, color)
        elif arr.ndim == 2 and color == "channels":
            arr = arr[None]
        if arr.ndim != (3 if color == "channels" else 2):
            raise InputError(f"image {file}: expected shape (H, W) or (H, W, C), got {arr.shape}")
        if color == "channels":
            check_channels(arr, file, "image", "(C, H, W)")
        return finite(arr.astype(np.float32), file)
    return finite(_oiio_read_all(file, color, first_only=True)[0], file)


_PATTERN = re.compile(r"%0?\d*d")


def is_pattern(spec: str | os.PathLike) -> bool:
    """True for a printf-style frame pattern such as ``frames/%04d.png``."""
    return len(_PATTERN.findall(Path(spec).name)) == 1


def pattern_frames(pattern: str) -> list[Path]:
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


def natural_key(path: Path):
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
        arr = read_npy(source)
        if color == "channels" and arr.ndim == 3:
            arr = arr[None]
        if arr.ndim != (4 if color == "channels" else 3):
            raise InputError(f"stack {source}: expected shape (N, H, W), got {arr.shape}")
        if color == "channels":
            check_channels(arr, source, "stack", "(C, N, H, W)")
        return finite(arr.astype(np.float32), source, "stack")
    else:
        frames = _oiio_read_all(source, color, first_only=False)
    shapes = {f.shape for f in frames}
    if len(shapes) != 1:
        odd = next(i for i, f in enumerate(frames) if f.shape != frames[0].shape)
        which = f"{files[odd].name} is {frames[odd].shape}, {files[0].name} {frames[0].shape}" if files is not None \
            else f"page {odd + 1} is {frames[odd].shape}, page 1 {frames[0].shape}"
        raise InputError(f"stack {source}: frames differ in shape ({which})")
    stack = np.stack(frames, axis=1 if color == "channels" else 0)
    return finite(stack.astype(np.float32), source, "stack")


def frame_files(path: str | os.PathLike) -> list[Path] | None:
    """The image files of a folder of frames (natural order: ``f_2`` before ``f_10``) or a printf pattern
    (``frames/%04d.png``: numbers from 0 or 1 up to the first gap); None for any other path."""
    spath = str(path)
    source = Path(path)
    if is_pattern(spath) and not source.exists():
        files = pattern_frames(spath)
        if not files:
            raise InputError(f"frames {spath}: no file matches the pattern")
        return files
    if source.is_dir():
        files = sorted((f for f in source.iterdir()
                        if f.suffix.lower() in IMAGE_SUFFIXES and not f.name.startswith(".")), key=natural_key)
        if not files:
            raise InputError(f"frames {source}: the folder holds no image files")
        return files
    return None


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
                    arr = to_uint8(frame, data_range)
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
