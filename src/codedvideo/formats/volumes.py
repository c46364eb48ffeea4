"""Volumes and captures on disk, by suffix: coded images, masks, reconstructed videos, metrics JSON.

Readers check what they read (finite values, mask weights in [0, 1]) and
name the file in their errors; writers go through a temporary name
(:func:`codedvideo.formats.atomic.atomic_output`), so nothing is left half-written.
"""

from __future__ import annotations

import contextlib
import json
import os
from pathlib import Path

import numpy as np

from codedvideo.model import doors
from codedvideo.formats import io as cio
from codedvideo.model.errors import InputError
from codedvideo.formats.io import VIDEO_SUFFIXES
from codedvideo.model.patches import PATCH
from codedvideo.formats.store import array_writer, load_array
from codedvideo.model.units import EIGHT_BIT
from codedvideo.model.codes import is_binary


def write_json(path: Path, payload: dict) -> Path:
    from codedvideo.model.metrics import json_safe

    with cio.atomic_output(path) as tmp:  # strict JSON: an infinite PSNR is null
        Path(tmp).write_text(json.dumps(json_safe(payload), indent=2, default=_json_default, allow_nan=False) + "\n")
    return path


def _json_default(o):
    if isinstance(o, (np.integer,)):
        return int(o)
    if isinstance(o, (np.floating,)):
        return float(o)
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


#: The files :func:`write_capture` writes into its folder.
CAPTURE_FILES = ("coded.npy", "mask.npy", "truth.npy", "coded.tif")


def capture_paths(outdir: str | Path) -> dict[str, Path]:
    """Where a simulated capture's files go (:data:`CAPTURE_FILES`)."""
    folder = Path(outdir)
    return dict(coded=folder / "coded.npy", mask=folder / "mask.npy", truth=folder / "truth.npy",
                coded_tif=folder / "coded.tif")


def write_capture(capture: dict[str, np.ndarray], outdir: str | Path) -> dict[str, Path]:
    """Write coded.npy, mask.npy, truth.npy and coded.tif (:data:`CAPTURE_FILES`) into ``outdir``."""
    coded, mask, truth = capture["coded"], capture["mask"], capture["truth"]
    count = coded.shape[0] if coded.ndim == 3 else 1
    truths = np.split(truth, count) if count > 1 else [truth]  # a colour truth (3, N, H, W): one capture
    with capture_writer(outdir, coded_shape=coded.shape, mask_shape=mask.shape, truth_shape=truth.shape) as put:
        for t in range(count):
            put(coded[t] if coded.ndim == 3 else coded, mask[t] if mask.ndim == 4 else mask if t == 0 else None,
                truths[t])
    return capture_paths(outdir)


@contextlib.contextmanager
def capture_writer(outdir: str | Path, *, coded_shape: tuple, mask_shape: tuple, truth_shape: tuple):
    """Write a simulated stream's files (:func:`write_capture`) capture by capture: yields ``put(coded, mask,
    truth)``.

    ``coded`` is one capture's coded image (H, W), ``mask`` its code (N, H, W)
    (None once a repeating code has been written), ``truth`` its frames, all in
    order; the shapes are those of the whole files.  Nothing holds more than
    one capture, and each file appears only when the block ends complete.
    """
    paths = capture_paths(outdir)
    pages = coded_shape[0] if len(coded_shape) == 3 else 1
    with contextlib.ExitStack() as files:
        coded_out = files.enter_context(cio.npy_writer(paths["coded"], coded_shape))
        truth_out = files.enter_context(cio.npy_writer(paths["truth"], truth_shape))
        tif_out = files.enter_context(cio.stack_writer(paths["coded_tif"], pages, dtype=np.float32))
        mask_out = None

        def put(coded: np.ndarray, mask: np.ndarray | None, truth: np.ndarray) -> None:
            nonlocal mask_out
            coded_out(coded)
            tif_out(np.asarray(coded)[None])
            truth_out(truth)
            if mask is not None:
                if mask_out is None:  # the code's own type: binary uint8, or calibrated float weights
                    mask_out = files.enter_context(cio.npy_writer(paths["mask"], mask_shape, dtype=mask.dtype))
                mask_out(mask)

        yield put


def read_coded(path: str | Path, *, color: str = "luma") -> np.ndarray:
    """A coded image (H, W) float32, or (C, H, W) with ``color="channels"`` (see :mod:`codedvideo.formats.io`)."""
    return check_coded(cio.read_image(path, color=color), f"coded image {path}")


class _LazyStack:
    """What the stacks read a few images at a time share: ``shape``, ``len``, iteration, bounds and a check."""

    shape: tuple[int, int, int]

    def __len__(self) -> int:
        return self.shape[0]

    def _index(self, i) -> int:
        if not isinstance(i, (int, np.integer)):
            raise TypeError(f"{type(self).__name__}: index with a number")
        if not -len(self) <= i < len(self):
            raise IndexError(f"image {i} of {len(self)}")
        return int(i) % len(self)

    def check(self) -> None:
        """Read every image once: an unreadable one, one of another size or a NaN is an error before any work."""
        for i in range(len(self)):
            self[i]

    def __iter__(self):
        return (self[i] for i in range(len(self)))

    def __array__(self, dtype=None, copy=None):
        return np.stack(list(self)).astype(dtype or np.float32)


class NpyStack(_LazyStack):
    """The images (T, H, W) of a .npy file, read a few at a time: a long stream is never held whole.

    Indexing with a number reads that image, with a slice (step 1) those
    images, as float32, checked finite; ``shape`` and ``dtype`` are those of
    the file.  ``what`` names the file in errors ("coded image", "truth").
    """

    def __init__(self, path: Path, shape: tuple[int, int, int], dtype: np.dtype, offset: int, *,
                 what: str = "coded image"):
        self.path, self.shape, self.dtype, self._offset, self.what = path, shape, dtype, offset, what
        self._count = shape[1] * shape[2]

    def __getitem__(self, i):
        if isinstance(i, slice):
            start, stop, step = i.indices(len(self))
            if step != 1:
                raise TypeError("NpyStack: slices of consecutive images only")
            return self._read(start, max(stop - start, 0))
        return self._read(self._index(i), 1)[0]

    def _read(self, start: int, count: int) -> np.ndarray:
        part = np.fromfile(self.path, dtype=self.dtype, count=count * self._count,
                           offset=self._offset + start * self._count * self.dtype.itemsize)
        part = part.reshape((count, *self.shape[1:])).astype(np.float32)
        if not np.isfinite(part).all():
            bad = start + int(np.flatnonzero(~np.isfinite(part).reshape(count, -1).all(1))[0])
            what = "capture" if self.what == "coded image" else "frame"
            raise InputError(f"{self.what} {self.path}: {what} {bad + 1} contains NaN or Inf")
        return part

    def check(self, block: int = 1) -> None:
        """Read the whole file ``block`` images at a time: a NaN anywhere is an error before any work."""
        for start in range(0, len(self), block):
            self[start : start + block]


class ImageStack(_LazyStack):
    """Coded images a file each (a folder or printf pattern) or a page each (a multi-page TIFF), read one at a
    time, as :class:`NpyStack`."""

    def __init__(self, source: Path, *, files: list[Path] | None = None, pages: int | None = None):
        self.path, self.files = source, None if files is None else list(files)
        first = self._read(0)
        count = len(self.files) if self.files is not None else int(pages)
        self.shape, self.dtype = (count, *first.shape), first.dtype

    def _read(self, i: int) -> np.ndarray:
        return cio.read_image(self.files[i]) if self.files is not None else cio.read_page(self.path, i)

    def __getitem__(self, i):
        index = self._index(i)
        image = self._read(index)
        if image.shape != self.shape[1:]:
            name = self.files[index] if self.files is not None else f"{self.path} (page {index + 1})"
            raise InputError(f"coded image {name}: {image.shape[0]}x{image.shape[1]} pixels, but the "
                             f"first image of {self.path} has {self.shape[1]}x{self.shape[2]}")
        return image.astype(np.float32)


class VideoStack(_LazyStack):
    """The coded images of a (lossless) video, a frame each, decoded on demand: a long stream is never held whole.

    Frames are decoded forward and the last :data:`KEEP` kept, so the access
    of a job (each capture with its neighbours, in order, twice) decodes the
    video about twice; a capture further back starts the decoding again.
    """

    #: Decoded frames kept (a capture and its neighbours).
    KEEP = 4

    def __init__(self, path: Path):
        self.path = path
        count, first = 0, None
        for frame in cio.iter_video(path):  # the whole file checked before any work
            first = frame if first is None else first
            count += 1
        if first is None:
            raise InputError(f"video {path}: no frames decoded")
        self.shape, self.dtype = (count, *first.shape), first.dtype
        self._frames, self._next, self._kept = None, 0, {}

    def __getitem__(self, i):
        index = self._index(i)
        if index in self._kept:
            return self._kept[index].copy()
        if self._frames is None or index < self._next:
            if self._frames is not None:
                self._frames.close()
            self._frames, self._next = cio.iter_video(self.path), 0
        while self._next <= index:
            try:
                self._kept[self._next] = next(self._frames)
            except StopIteration:  # the file changed since it was checked
                raise InputError(f"coded image {self.path}: ends at frame {self._next} of {len(self)}") from None
            self._kept.pop(self._next - self.KEEP, None)
            self._next += 1
        return self._kept[index].copy()

    def __del__(self):
        if getattr(self, "_frames", None) is not None:
            self._frames.close()


def read_truth_stack(path: str | Path, frames: int, *, what: str = "truth") -> np.ndarray | NpyStack:
    """A video (T*N, H, W), a truth or a reconstruction: a long .npy stream is read ``frames`` at a time
    (checked whole first, part by part); anything else whole (:func:`read_volume`)."""
    source = Path(path)
    layout = cio.npy_layout(source) if source.suffix.lower() == ".npy" else None
    if layout is not None and len(layout[0]) == 3 and layout[0][0] > frames:
        stack = NpyStack(source, *layout, what=what)
        stack.check(frames)
        return stack
    return read_volume(source)


def read_coded_stack(path: str | Path) -> np.ndarray | NpyStack | ImageStack | VideoStack:
    """Coded images (T, H, W) float32: a .npy (H, W) or (T, H, W), a (multi-page) image, a folder or
    printf pattern of images, or a lossless video (one coded image per video frame).  A .npy (H, W, 3) or
    (H, W, 4) is a colour image, taken as its luma like a colour PNG or TIFF (as a stack it would be images
    3 or 4 pixels wide, narrower than a patch)."""
    source = Path(path)
    suffix = source.suffix.lower()
    layout = cio.npy_layout(source) if suffix == ".npy" else None
    if layout is not None and len(layout[0]) == 3 and layout[0][-1] in (3, 4) and layout[0][-1] < PATCH:
        return cio.read_image(source, color="luma")[None]
    if layout is not None and len(layout[0]) == 3 and layout[0][0] > 1:  # a stream: read capture by capture
        stack = NpyStack(source, *layout)
        stack.check()  # before any work, one capture at a time
        return stack
    files = None if suffix == ".npy" else cio.frame_files(source)
    pages = cio.tiff_page_count(source) if files is None and suffix in (".tif", ".tiff") else 1
    if (files is not None and len(files) > 1) or pages > 1:  # images a capture each: read capture by capture
        stack = ImageStack(source, files=files, pages=pages)
        stack.check()
        return stack
    if suffix == ".npy":
        arr = cio.read_array(source)
        if arr.ndim not in (2, 3):
            raise InputError(f"coded image {source}: expected shape (H, W) or (T, H, W), got {arr.shape}")
        coded = arr.astype(np.float32).reshape((-1, *arr.shape[-2:]))
    elif suffix in VIDEO_SUFFIXES:  # a frame a capture: decoded capture by capture
        codec = cio.lossy_codec(source)
        if codec:
            doors.warn(f"coded image {source}: a {codec} video, whose compression changes the values the sensor "
                          "recorded; give a lossless video (FFV1 in .mkv), image files or a .npy")
        stack = VideoStack(source)
        return stack if len(stack) > 1 else stack[0][None]
    else:
        coded = cio.read_stack(source)
    return check_coded(coded, f"coded image {source}")


def read_masks(path: str | Path) -> np.ndarray:
    """A mask (N, H, W), or one mask per capture (T, N, H, W) from a .npy (see :func:`read_mask`)."""
    if Path(path).suffix.lower() == ".npy":
        arr = cio.read_array(path)
        if arr.ndim == 4:
            return np.stack([check_mask(m, f"mask {path}") for m in arr])
    return read_mask(path)


#: A mask image whose largest value lies below this fraction of its full scale is refused: no shutter opens that
#: little at its brightest, and it is what a mask of fewer bits saved in a wider type reads as (0/1 in 8 bits,
#: 0/255 or 0/4095 in 16).  A calibrated response that low belongs in a .npy of its own weights.
MASK_PEAK_MIN = 1 / 8


def read_mask(path: str | Path) -> np.ndarray:
    """A mask (N, H, W) from a .npy (its values as they are: 0/1, or weights in [0, 1]) or from images (a
    multi-page TIFF, a folder or pattern of frames), read as a fraction of the image's full scale, as
    scikit-image reads images: an 8-bit 255 or a 16-bit 65535 is 1.0, so a 0/255 PNG mask is a binary code."""
    stack = cio.read_stack(path)
    if Path(path).suffix.lower() != ".npy":
        full = full_scale(cio.stored_dtype(path))
        if full != 1.0:
            stack = stack / np.float32(full)
            top = float(stack.max(initial=0.0))
            if 0 < top < MASK_PEAK_MIN:  # 0/1 saved as 8-bit, 0/255 as 16-bit: every shutter read as nearly closed
                raise InputError(f"mask {path}: its values reach only {top * full:g} of the image's full scale "
                                 f"{full:g}; mask images are read as a fraction of full scale, so a binary mask image "
                                 f"holds 0 and {full:g} (a .npy mask holds 0 and 1)")
    return check_mask(stack, f"mask {path}")


def full_scale(dtype) -> float:
    """The value an image of this stored type holds at full scale: 255 (8-bit), 65535 (16-bit), ... (1: floats)."""
    kind = np.dtype(dtype)
    return float(np.iinfo(kind).max) if kind.kind in "iu" else 1.0


def check_mask(mask, where: str) -> np.ndarray:
    """A mask as both doors take it: a binary code (uint8), or a calibrated mask, each pixel's measured response
    per sub-frame in [0, 1] (float32).  ``where`` names it in the one-line error (``mask m.npy``, or the API's
    argument); NaN or Inf, values outside [0, 1] and an all-zero mask are refused."""
    arr = np.asarray(mask)
    if arr.dtype.kind not in "biuf":
        raise InputError(f"{where}: values of type {arr.dtype}; a mask holds numbers (0/1, or weights in [0, 1])")
    if not np.isfinite(arr).all():
        raise InputError(f"{where}: contains NaN or Inf")
    outside = (arr < 0) | (arr > 1)
    if outside.any():
        bad = np.unique(arr[outside])[:3].tolist()
        raise InputError(f"{where}: values outside [0, 1] (e.g. {bad}); a mask is 0/1, or a calibrated "
                         "response per sub-frame in [0, 1]")
    if not arr.any():
        raise InputError(f"{where}: no pixel is ever open (all zeros); there is nothing to reconstruct")
    return arr.astype(np.uint8) if is_binary(arr) else arr.astype(np.float32)


def check_coded(coded, where: str, *, unit: str = "capture") -> np.ndarray:
    """A coded image (or a stack) as both doors take it: numbers, finite; float32 (its stored type is the
    caller's to record: 8-bit integers are 0..255 whatever they hold).  In a stack the first ``unit`` (image of
    the first axis) holding NaN or Inf is named, as the command line names a file's capture."""
    arr = np.asarray(coded)
    if arr.dtype.kind not in "biuf":
        raise InputError(f"{where}: values of type {arr.dtype}; a coded image holds numbers")
    finite = np.isfinite(arr)
    if not finite.all():
        bad = f" ({unit} {int(np.argmin(finite.reshape(len(arr), -1).all(1))) + 1} of {len(arr)})" \
            if arr.ndim >= 3 else ""
        raise InputError(f"{where}: contains NaN or Inf{bad}")
    return arr.astype(np.float32, copy=False)


@contextlib.contextmanager
def volume_writer(output: str | Path, shape: tuple, *, data_range: float = EIGHT_BIT, fps: int = 30,
                  part: int | None = None):
    """Write a volume part by part, as its parts are reconstructed: yields ``put(index, part)``.

    Parts come in order (``volume[index] = part``, the indices consecutive
    along the first axis).  A grey volume (N, H, W) is written as its parts
    come, in every format of :func:`write_volume`, so memory does not grow
    with the number of captures: ``.npy`` (the header, then each part
    appended; a memory map would keep the pages written in the process's
    resident set), videos (encoded part by part), multi-page TIFF (page by
    page), a folder of frames (file by file), ``.zarr`` (chunks of ``part``
    frames: a capture's N) and ``.mat`` (frames compressed into the file as
    they come, :func:`codedvideo.formats.cacti.mat_writer`).  Each appears under
    ``output`` only when the block ends complete.  Colour volumes gather the
    parts and go through :func:`write_volume` at the end.
    """
    target = Path(output)
    suffix = target.suffix.lower()
    grey = len(shape) == 3
    streamed = None
    if suffix == ".npy":
        streamed = cio.npy_writer(target, shape)
    elif grey and suffix in VIDEO_SUFFIXES:
        streamed = cio.video_writer(target, tuple(shape[1:]), data_range=data_range, fps=fps)
    elif grey and suffix in (".tif", ".tiff"):
        streamed = cio.stack_writer(target, shape[0], dtype=np.float32)
    elif grey and suffix in ("", ".d"):
        streamed = cio.frames_writer(target, fmt="tiff16", data_range=data_range, total=shape[0])
    elif grey and suffix == ".mat":
        from codedvideo.formats.cacti import mat_writer

        streamed = mat_writer(target, shape)
    if streamed is not None:
        with streamed as write:
            yield lambda index, part: write(part)
        return
    if grey and suffix == ".zarr":
        chunks = (min(part or shape[0], shape[0]), *(min(256, s) for s in shape[1:]))
        with array_writer(target, shape, np.float32, chunks=chunks, attrs=dict(kind="codedvideo-volume")) as arr:
            def put(index, part):
                # a chunk at a time, each written once and whole: no float copy of the part (a part kept on
                # disk, a FrameFile, is read a band of chunk rows at a time)
                for top in range(0, shape[1], chunks[1]):
                    rows = slice(top, top + chunks[1])
                    band = np.asarray(part[:, rows], dtype=np.float32)
                    for left in range(0, shape[2], chunks[2]):
                        cols = slice(left, left + chunks[2])
                        arr[index, rows, cols] = band[:, :, cols]
                    del band  # (not held while the next band is read)

            yield put
        return
    gathered = []  # (a whole volume given at once, as a Bayer mosaic's is, is kept as given: no copy)

    def gather(index, part):
        if not gathered and index == slice(None) and isinstance(part, np.ndarray) and part.shape == tuple(shape) \
                and part.dtype == np.float32:
            gathered.append(part)
            return
        if not gathered:
            gathered.append(np.empty(tuple(shape), np.float32))
        gathered[0][index] = part

    yield gather
    write_volume(gathered[0] if gathered else np.empty(tuple(shape), np.float32), target, data_range=data_range, fps=fps)


def write_volume(volume: np.ndarray, output: str | Path, *, data_range: float = EIGHT_BIT, fps: int = 30) -> Path:
    """Write a volume by the output's suffix.

    Parameters
    ----------
    volume : ndarray of shape (N, H, W), or (C, N, H, W) for colour
    output : str or Path
        ``.npy`` (float32, as given), ``.zarr`` (float32 Zarr array), ``.mat``
        (MATLAB v5, ``recon`` (H, W, N) single), ``.tif``/``.tiff``
        (multi-page float32), ``.mp4`` (H.264), ``.mkv``/``.avi`` (FFV1,
        lossless 8-bit), ``.gif``, or a name without suffix (or ``.d``): a
        folder of 16-bit TIFF frames.  Videos and frames scale ``data_range``
        to full scale.
    """
    target = Path(output)
    suffix = target.suffix.lower()
    data = np.asarray(volume)
    if suffix == ".npy":  # (a float32 volume written as it is: no copy)
        cio.write_array(target, np.asarray(data, np.float32))
    elif suffix == ".zarr":  # a chunk at a time, each written once and whole: no float copy of the volume
        chunks = data.shape[:-2] + (256, 256)
        with array_writer(target, data.shape, np.float32, chunks=chunks, attrs=dict(kind="codedvideo-volume")) as arr:
            for top in range(0, data.shape[-2], 256):
                for left in range(0, data.shape[-1], 256):
                    where = (Ellipsis, slice(top, top + 256), slice(left, left + 256))
                    arr[where] = np.asarray(data[where], np.float32)
    elif suffix == ".mat":
        from codedvideo.formats.cacti import write_mat_volume

        write_mat_volume(target, data)
    elif suffix in (".tif", ".tiff"):
        cio.write_stack(target, data, dtype=np.float32)
    elif suffix in VIDEO_SUFFIXES:
        cio.write_video(target, data, data_range=data_range, fps=fps)
    elif suffix in ("", ".d"):
        cio.write_frames(target, data, fmt="tiff16", data_range=data_range)
    else:
        raise InputError(f"output {target}: unknown format {suffix!r} "
                         "(use .npy, .zarr, .mat, .tif, .mp4, .mov, .mkv, .avi, .gif or a folder)")
    return target


#: Suffixes :func:`write_volume` writes ("" and ".d": a folder of 16-bit TIFF frames).
OUTPUT_SUFFIXES = (".npy", ".zarr", ".mat", ".tif", ".tiff", ".mp4", ".mov", ".mkv", ".avi", ".gif", "", ".d")


def output_kind(output: str | Path) -> str:
    """``"file"`` or ``"folder"``: what :func:`write_volume` writes at ``output`` (an unknown suffix is an error)."""
    if Path(output).name in ("", ".", ".."):
        raise InputError(f"output {output}: names no file or folder of its own; give a new name such as out.npy")
    suffix = Path(output).suffix.lower()
    if suffix not in OUTPUT_SUFFIXES:
        raise InputError(f"output {output}: unknown format {suffix!r} "
                         "(use .npy, .zarr, .mat, .tif, .mp4, .mov, .mkv, .avi, .gif or a folder)")
    return "folder" if suffix in (".zarr", "", ".d") else "file"


def check_size(shape: tuple, path, patch: int = PATCH) -> None:
    """Raise :class:`InputError` naming ``path`` when an (H, W) image is smaller than one patch.

    One-pixel-wide strips (and anything narrower than ``patch`` pixels) are
    refused: no ``patch x patch`` patch fits, so the sparse model has nothing
    to work on.
    """
    h, w = shape[-2:]
    if h < patch or w < patch:
        raise InputError(f"coded image {path}: {h}x{w} pixels is smaller than one {patch}x{patch} patch "
                         f"(at least {patch} rows and {patch} columns are needed)")


def metrics_path(output: str | Path) -> Path:
    target = Path(output)
    return target.with_name((target.stem if target.suffix else target.name) + ".metrics.json")


def read_scored(path: str | Path, what: str):
    """A reconstruction or truth to score: a .npy, .zarr or .mat as stored (a long .npy read a block at a
    time); any other file with its channels, (3, N, H, W) when it holds colour (it was read as luma, so
    that a colour truth's score depended on its container), else (N, H, W)."""
    from codedvideo.model.metrics import EVALUATE_BLOCK

    if Path(path).suffix.lower() in (".npy", ".zarr", ".mat"):
        return read_truth_stack(path, EVALUATE_BLOCK, what=what)
    channels = read_volume(path, color="channels")
    if channels.ndim == 4 and (channels.shape[0] == 1 or ((channels[0] == channels[1]).all()
                                                          and (channels[1] == channels[2]).all())):
        return channels[0]  # grey (or grey stored as RGB)
    return channels


def read_volume(path: str | Path, *, color: str = "luma") -> np.ndarray:
    """Read a volume written by :func:`write_volume` (or any stack :func:`codedvideo.formats.io.read_stack` reads).

    A ``.mat`` file gives its ``recon`` variable, else ``orig`` (a CACTI
    file's ground truth).  ``.npy``, ``.zarr`` and ``.mat`` give the array as
    stored (N, H, W) or (C, N, H, W); images and videos follow ``color``.

    Returns
    -------
    ndarray of shape (N, H, W) (or (C, N, H, W)), float32
    """
    source = Path(path)
    suffix = source.suffix.lower()
    if suffix == ".zarr":
        return load_array(source)
    if suffix == ".mat":
        from codedvideo.formats.cacti import read_mat_volume

        return read_mat_volume(source)
    if suffix == ".npy":
        arr = cio.read_array(source)
        if arr.ndim not in (3, 4):
            raise InputError(f"volume {source}: expected shape (N, H, W) or (C, N, H, W), got {arr.shape}")
        if not np.isfinite(arr).all():
            raise InputError(f"volume {source}: contains NaN or Inf")
        return arr.astype(np.float32)
    if suffix in VIDEO_SUFFIXES:
        return cio.read_video(source, color=color)
    if source.is_dir():  # a frame folder written by write_frames reads back in frame units
        return cio.read_stack(source, color=color) * np.float32(cio.read_frames_scale(source))
    return cio.read_stack(source, color=color)



class FrameFile:
    """A grey volume (N, H, W) kept in an unnamed temporary file: read and written a range of frames at a time.

    What a stream of captures holds between captures (:func:`spilled`): the
    join reads and changes only the frames at a boundary, and the writers
    read one frame at a time (:func:`codedvideo.formats.io.frames_of`), so the volume
    is never in memory whole.  The file is read with plain reads, not mapped
    (mapped pages would count in the process's resident memory), and is gone
    when the object is (or the process ends).

    Indexing: ``vol[i]``, ``vol[a:b]`` and ``vol[a:b, rows, cols]`` (any index
    after the first) read those frames into a new array; ``vol[a:b, ...] =
    values`` writes them back; ``np.asarray(vol)`` reads it whole.
    """

    def __init__(self, volume: np.ndarray, folder: str | Path | None = None):
        import tempfile

        data = np.asarray(volume)
        if data.ndim != 3:
            raise ValueError(f"FrameFile: a volume (N, H, W), not {data.shape}")
        if folder is not None:
            Path(folder).mkdir(parents=True, exist_ok=True)
        self.shape, self.dtype = tuple(data.shape), data.dtype
        self._frame_bytes = int(np.prod(self.shape[1:])) * self.dtype.itemsize
        self._fh = tempfile.TemporaryFile(dir=folder, prefix=".codedvideo-frames-")
        for frame in data:
            self._fh.write(np.ascontiguousarray(frame).data)
        self._fh.flush()

    ndim = 3

    def __len__(self) -> int:
        return self.shape[0]

    @property
    def size(self) -> int:
        return int(np.prod(self.shape))

    @property
    def nbytes(self) -> int:
        return self.size * self.dtype.itemsize

    def _frames(self, key) -> range:
        n = self.shape[0]
        if isinstance(key, (int, np.integer)):
            i = int(key) + (n if key < 0 else 0)
            if not 0 <= i < n:
                raise IndexError(f"frame {key} of {n}")
            return range(i, i + 1)
        if isinstance(key, slice):
            return range(*key.indices(n))
        raise TypeError(f"FrameFile: frames by an int or a slice, not {type(key).__name__}")

    def _read(self, frames: range, rows: slice = slice(None)) -> np.ndarray:
        """Frames ``frames``, rows ``rows`` (step 1) of each: only those bytes are read."""
        top, bottom, _ = rows.indices(self.shape[1])
        bottom = max(bottom, top)
        out = np.empty((len(frames), bottom - top, *self.shape[2:]), self.dtype)
        row_bytes = self._frame_bytes // self.shape[1]
        want = (bottom - top) * row_bytes
        for k, f in enumerate(frames):
            view = memoryview(out[k].reshape(-1).view(np.uint8))
            got = os.preadv(self._fh.fileno(), [view], f * self._frame_bytes + top * row_bytes) if want else 0
            if got != want:
                raise OSError(f"FrameFile: read {got} of {want} bytes of frame {f}")
        return out

    def _write(self, frames: range, values: np.ndarray) -> None:
        for k, f in enumerate(frames):
            data = np.ascontiguousarray(values[k], dtype=self.dtype)
            os.pwrite(self._fh.fileno(), data.data.cast("B"), f * self._frame_bytes)

    def __getitem__(self, key):
        index = key if isinstance(key, tuple) else (key,)
        frames = self._frames(index[0])
        if len(index) > 1 and isinstance(index[1], slice) and index[1].step in (None, 1):  # only those rows read
            out, index = self._read(frames, index[1]), (index[0], slice(None), *index[2:])
        else:
            out = self._read(frames)
        if isinstance(index[0], (int, np.integer)):
            return out[0][index[1:]]
        return out[(slice(None), *index[1:])]

    def __setitem__(self, key, values) -> None:
        index = key if isinstance(key, tuple) else (key,)
        frames = self._frames(index[0])
        if isinstance(index[0], (int, np.integer)):
            current = self._read(frames)
            current[0][index[1:]] = values
        elif len(index) == 1:
            current = np.broadcast_to(np.asarray(values, self.dtype), (len(frames), *self.shape[1:]))
        else:
            current = self._read(frames)
            current[(slice(None), *index[1:])] = values
        self._write(frames, current)

    def __iter__(self):
        for f in range(self.shape[0]):
            yield self._read(range(f, f + 1))[0]

    def __array__(self, dtype=None, copy=None):
        out = self._read(range(self.shape[0]))
        return out if dtype is None else out.astype(dtype, copy=False)

    def close(self) -> None:
        self._fh.close()

    def __del__(self) -> None:  # its file closed with it, as said (not left to the collector's ResourceWarning)
        fh = getattr(self, "_fh", None)
        if fh is not None:
            fh.close()


def spilled(results, folder: str | Path | None = None):
    """A stream of ``(i, volume, info)`` with each (N, H, W) volume moved to a :class:`FrameFile` as it comes.

    What holds a capture while the next one is reconstructed (the join of
    :func:`codedvideo.model.sequence.joined`) then holds a file, not its memory;
    the values are the same bits.  Closing the stream closes ``results``.
    """
    try:
        for i, volume, info in results:
            if isinstance(volume, np.ndarray) and volume.ndim == 3:
                volume = FrameFile(volume, folder)
            yield i, volume, info
            del volume
    finally:
        getattr(results, "close", lambda: None)()


def load_code_file(
    path: str | os.PathLike,
    *,
    frames: int | None = None,
    shape: tuple[int, int] | None = None,
) -> np.ndarray:
    """A user-supplied code: a .npy ``(N, H, W)`` array or a multi-page TIFF; or a .npy ``(K, N, H, W)`` of K codes,
    one per capture in turn (a calibrated code that changes per capture; capture ``t`` takes code ``t mod K``).

    Parameters
    ----------
    path : str or path
    frames : int, optional
        Required number of sub-frames N.
    shape : (H, W), optional
        Required image size.

    Returns
    -------
    mask : ndarray of shape (N, H, W) or (K, N, H, W), uint8 (float32 when calibrated)

    Raises
    ------
    InputError
        Naming the file when it is missing, unreadable, not binary, or its
        N or (H, W) differ from the ones asked for.
    """
    mask = read_masks(path)
    if frames is not None and mask.shape[-3] != frames:
        raise InputError(f"code file {path}: has N = {mask.shape[-3]} sub-frames, expected N = {frames}")
    if shape is not None and tuple(mask.shape[-2:]) != tuple(shape):
        raise InputError(f"code file {path}: size {tuple(mask.shape[-2:])} does not match the video {tuple(shape)}")
    return mask
