"""MATLAB .mat files: CACTI benchmark files and reconstructed volumes.

This is the only module that imports scipy.io and h5py.

The snapshot-compressive-imaging benchmarks (DeSCI, GAP-TV, PnP-SCI, ...)
distribute simulated CACTI captures as .mat files holding

``orig`` (H, W, F), optional
    The ground-truth frames, usually uint8.
``mask`` (H, W, N)
    The binary shutter code of the N sub-frames of one measurement; the same
    code for every measurement.
``meas`` (H, W, Q)
    Q = F // N coded measurements; measurement q is the plain sum
    ``sum_t mask[:, :, t] * orig[:, :, q*N + t]`` -- codedvideo's sum
    convention (see :mod:`codedvideo.model.physics`).

MATLAB v5 files (``save -v7`` and older) are read with :func:`scipy.io.loadmat`,
v7.3 files (HDF5) with h5py.  HDF5 stores MATLAB's column-major arrays with
their axes reversed, so h5py sees ``orig`` as (F, W, H); :func:`read_mat_arrays`
undoes that, so both versions give MATLAB's (H, W, F).  Inside codedvideo the
arrays are time-first: :class:`CactiData` holds ``mask`` (N, H, W),
``meas`` (Q, H, W) and ``orig`` (Q*N, H, W).

Reconstructions written for MATLAB users (:func:`write_mat_volume`) are v5
files with one variable, ``recon`` (H, W, N) single -- or (H, W, C, N) for
colour, MATLAB's layout of a colour video.  A grey sequence is written frame
by frame as it is reconstructed (:func:`mat_writer`: the same v5 layout,
compressed as :func:`scipy.io.savemat` does), so memory does not grow with it.
"""

from __future__ import annotations

import contextlib
import os
import struct
import time
import zlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from codedvideo.model.errors import InputError, OutputError
from codedvideo.formats.atomic import atomic_output
from codedvideo.formats.io import frames_of

CACTI_KEYS = ("orig", "mask", "meas")
VOLUME_KEYS = ("recon", "orig")


# ----------------------------------------------------------------------------- layouts
def from_matlab(arr: np.ndarray) -> np.ndarray:
    """MATLAB's (H, W), (H, W, F) or (H, W, C, F) -> time-first (1, H, W), (F, H, W) or (C, F, H, W)."""
    if arr.ndim == 2:
        return arr[None]
    if arr.ndim == 3:
        return np.moveaxis(arr, -1, 0)
    if arr.ndim == 4:
        return arr.transpose(2, 3, 0, 1)
    raise ValueError(f"expected a 2-, 3- or 4-D array, got shape {arr.shape}")


def to_matlab(arr: np.ndarray) -> np.ndarray:
    """Time-first (F, H, W) or (C, F, H, W) -> MATLAB's (H, W, F) or (H, W, C, F)."""
    if arr.ndim == 3:
        return np.moveaxis(arr, 0, -1)
    if arr.ndim == 4:
        return arr.transpose(2, 3, 0, 1)
    raise ValueError(f"expected an (F, H, W) or (C, F, H, W) array, got shape {arr.shape}")


# ----------------------------------------------------------------------------- reading
def _mat_version(path: Path) -> int:
    """1 for MATLAB v5 (v6/v7), 2 for v7.3 (HDF5); InputError otherwise."""
    from scipy.io.matlab import matfile_version

    if not path.exists():
        raise InputError(f"mat file {path}: no such file")
    if path.is_dir():
        raise InputError(f"mat file {path}: is a folder, not a .mat file")
    try:
        major, _ = matfile_version(str(path))
    except Exception as exc:  # scipy raises ValueError, IndexError, MatReadError ...
        raise InputError(f"mat file {path}: not a MATLAB .mat file or truncated ({_msg(exc)})") from exc
    if major == 0:
        raise InputError(f"mat file {path}: MATLAB v4 files are not supported (save with -v7 or -v7.3)")
    return major


def _msg(exc: BaseException) -> str:
    text = "; ".join(line.strip() for line in str(exc).splitlines() if line.strip())
    return f"{type(exc).__name__}: {text}" if text else type(exc).__name__


def read_mat_arrays(path: str | os.PathLike, keys: tuple[str, ...]) -> dict[str, np.ndarray]:
    """The numeric variables ``keys`` of a v5 or v7.3 .mat file, in MATLAB's axis order.

    Variables that are absent are left out of the result; a variable that is
    not a real numeric or logical array is an :class:`InputError`.

    Returns
    -------
    dict of name -> ndarray in MATLAB's layout (e.g. ``orig`` (H, W, F))
    """
    file = Path(path)
    version = _mat_version(file)
    out: dict[str, np.ndarray] = {}
    if version == 1:
        import scipy.io

        try:
            data = scipy.io.loadmat(str(file), variable_names=list(keys), squeeze_me=False)
        except Exception as exc:  # truncated or corrupt: OSError, ValueError, IndexError, zlib.error ...
            raise InputError(f"mat file {file}: corrupt or truncated ({_msg(exc)})") from exc
        for key in keys:
            if key in data:
                out[key] = _numeric(data[key], file, key)
    else:
        import h5py

        try:
            with h5py.File(str(file), "r") as fh:
                for key in keys:
                    if key not in fh:
                        continue
                    node = fh[key]
                    if not isinstance(node, h5py.Dataset):
                        raise InputError(f"mat file {file}: variable {key!r} is a struct or cell, not a numeric array")
                    out[key] = _numeric(np.asarray(node[()]).T, file, key)  # HDF5 holds MATLAB arrays reversed
        except InputError:
            raise
        except Exception as exc:  # OSError for truncated files, KeyError/RuntimeError for damaged ones
            raise InputError(f"mat file {file}: corrupt or truncated v7.3 (HDF5) file ({_msg(exc)})") from exc
    return out


def _numeric(arr, path: Path, key: str) -> np.ndarray:
    values = np.asarray(arr)
    if values.dtype.kind not in "biuf":
        raise InputError(f"mat file {path}: variable {key!r} is not a real numeric array (dtype {values.dtype})")
    if values.dtype.kind == "f" and not np.isfinite(values).all():
        raise InputError(f"mat file {path}: variable {key!r} contains NaN or Inf")
    return values


def _keys_present(path: Path) -> list[str]:
    """Names of the variables in a .mat file (for error messages)."""
    try:
        if _mat_version(path) == 1:
            import scipy.io

            return [name for name, _, _ in scipy.io.whosmat(str(path))]
        import h5py

        with h5py.File(str(path), "r") as fh:
            return [k for k in fh.keys() if not k.startswith("#")]
    except Exception:
        return []


def read_mat_volume(path: str | os.PathLike, keys: tuple[str, ...] = VOLUME_KEYS) -> np.ndarray:
    """A volume from a .mat file: the first of ``keys`` present (``recon``, then ``orig``).

    Returns
    -------
    ndarray of shape (F, H, W), or (C, F, H, W) for an (H, W, C, F) variable, float32
    """
    file = Path(path)
    arrays = read_mat_arrays(file, keys)
    for key in keys:
        if key in arrays:
            arr = arrays[key]
            if arr.ndim not in (2, 3, 4):
                raise InputError(f"mat file {file}: {key!r} has shape {arr.shape}, expected (H, W, F)")
            return np.ascontiguousarray(from_matlab(arr), dtype=np.float32)
    raise InputError(f"mat file {file}: holds none of the variables {', '.join(keys)} "
                     f"(found: {', '.join(_keys_present(file)) or 'none'})")


@dataclass(frozen=True)
class CactiData:
    """One CACTI benchmark file, time-first.

    Attributes
    ----------
    mask : ndarray of shape (N, H, W), uint8 (0 or 1)
    meas : ndarray of shape (Q, H, W), float32
    orig : ndarray of shape (K*N, H, W), float32, or None
        The truth of the first K <= Q measurements (the field's test files hold it for the first only); frames
        beyond K*N in the file (F not a multiple of N) are dropped.
    path : Path or None
    """

    mask: np.ndarray
    meas: np.ndarray
    orig: np.ndarray | None = None
    path: Path | None = None

    @property
    def frames(self) -> int:
        """N, sub-frames per measurement."""
        return int(self.mask.shape[0])

    @property
    def measurements(self) -> int:
        """Q, the number of measurements."""
        return int(self.meas.shape[0])

    @property
    def scored(self) -> int:
        """K, the measurements ``orig`` holds the truth of (the first K)."""
        return 0 if self.orig is None else int(self.orig.shape[0]) // self.frames

    def truth(self, q: int) -> np.ndarray | None:
        """The N frames of measurement ``q`` (0-based), (N, H, W) float32, or None where ``orig`` does not cover it."""
        if q >= self.scored:
            return None
        n = self.frames
        return self.orig[q * n : (q + 1) * n]


def check_cacti(mask: np.ndarray, meas: np.ndarray, orig: np.ndarray | None, *, where: str) -> tuple:
    """Validate time-first CACTI arrays; return (mask uint8, meas float32, orig float32 or None).

    ``orig`` with F frames is the truth of the first F // N measurements, 1 to Q (the field's test files hold
    it for the first only); frames beyond a whole number of measurements are dropped.
    """
    mask_arr, meas_arr = np.asarray(mask), np.asarray(meas)
    named = (("mask", mask_arr), ("meas", meas_arr)) + ((("orig", np.asarray(orig)),) if orig is not None else ())
    for name, arr in named:
        if arr.ndim != 3:
            raise InputError(f"{where}: {name} must be (frames, H, W) time-first here, got shape {arr.shape}")
        if arr.dtype.kind not in "biuf":
            raise InputError(f"{where}: {name} is not numeric (dtype {arr.dtype})")
        if arr.dtype.kind == "f" and not np.isfinite(arr).all():
            raise InputError(f"{where}: {name} contains NaN or Inf")
    n, h, w = mask_arr.shape
    q = meas_arr.shape[0]
    if n == 0 or q == 0:
        raise InputError(f"{where}: empty mask ({n} frames) or meas ({q} measurements)")
    if not np.isin(mask_arr, (0, 1)).all():
        raise InputError(f"{where}: mask is not binary (values other than 0 and 1)")
    if meas_arr.shape[1:] != (h, w):
        raise InputError(f"{where}: meas is {meas_arr.shape[1]}x{meas_arr.shape[2]} pixels, mask is {h}x{w}")
    truth = None
    if orig is not None:
        orig_arr = np.asarray(orig)
        f = orig_arr.shape[0]
        if orig_arr.shape[1:] != (h, w):
            raise InputError(f"{where}: orig is {orig_arr.shape[1]}x{orig_arr.shape[2]} pixels, mask is {h}x{w}")
        if not 1 <= f // n <= q:
            raise InputError(f"{where}: orig has {f} frames = {f // n} measurements of N = {n} (the mask's frames), "
                             f"but meas holds {q}")
        truth = np.ascontiguousarray(orig_arr[: (f // n) * n], dtype=np.float32)
    return mask_arr.astype(np.uint8), np.ascontiguousarray(meas_arr, dtype=np.float32), truth


def read_cacti(path: str | os.PathLike) -> CactiData:
    """Read a CACTI benchmark .mat file (MATLAB v5 or v7.3).

    Parameters
    ----------
    path : .mat holding ``mask`` (H, W, N), ``meas`` (H, W, Q) and optionally
        ``orig`` (H, W, F), the truth of the first F // N (1 to Q) measurements.  A 2-D ``meas`` is one
        measurement.

    Returns
    -------
    CactiData
        ``mask`` (N, H, W) uint8, ``meas`` (Q, H, W) float32, ``orig``
        (K*N, H, W) float32 or None.
    """
    file = Path(path)
    arrays = read_mat_arrays(file, CACTI_KEYS)
    missing = [k for k in ("mask", "meas") if k not in arrays]
    if missing:
        raise InputError(f"cacti {file}: lacks {' and '.join(repr(k) for k in missing)} "
                         f"(found: {', '.join(_keys_present(file)) or 'no variables'})")
    converted = {}
    for key, arr in arrays.items():
        if arr.ndim not in (2, 3):
            raise InputError(f"cacti {file}: {key!r} has shape {arr.shape}, expected (H, W) or (H, W, frames)")
        converted[key] = from_matlab(arr)
    mask, meas, orig = check_cacti(converted["mask"], converted["meas"], converted.get("orig"), where=f"cacti {file}")
    return CactiData(mask=mask, meas=meas, orig=orig, path=file)


# ----------------------------------------------------------------------------- writing
def _savemat(path: Path, variables: dict[str, np.ndarray]) -> Path:
    import scipy.io

    with atomic_output(path) as tmp:
        try:
            with open(tmp, "wb") as fh:  # a file object: scipy would otherwise append ".mat" to odd names
                scipy.io.savemat(fh, variables, do_compression=True, oned_as="column")
        except OSError as exc:
            raise OutputError(f"mat file {path}: cannot write ({exc.strerror or exc})") from exc
    return path


def write_cacti(
    path: str | os.PathLike, *, mask: np.ndarray, meas: np.ndarray, orig: np.ndarray | None = None
) -> Path:
    """Write a CACTI benchmark .mat file (MATLAB v5, compressed), atomically.

    Parameters
    ----------
    path : str or PathLike
    mask : ndarray of shape (N, H, W), binary
        Written as ``mask`` (H, W, N) double, as in the benchmark files.
    meas : ndarray of shape (Q, H, W)
        Written as ``meas`` (H, W, Q) double.
    orig : ndarray of shape (Q*N, H, W), optional
        Written as ``orig`` (H, W, Q*N): uint8 when every value is an integer
        in 0..255 (as in the benchmark files), double otherwise.
    """
    target = Path(path)
    checked_mask, checked_meas, checked_orig = check_cacti(mask, meas, orig, where=f"cacti {target}")
    variables = dict(mask=to_matlab(checked_mask).astype(np.float64), meas=to_matlab(checked_meas).astype(np.float64))
    if checked_orig is not None:
        integral = (checked_orig.min() >= 0 and checked_orig.max() <= 255
                    and np.array_equal(checked_orig, np.rint(checked_orig)))
        variables["orig"] = to_matlab(checked_orig).astype(np.uint8 if integral else np.float64)
    return _savemat(target, variables)


def write_mat_volume(path: str | os.PathLike, volume: np.ndarray, *, key: str = "recon") -> Path:
    """Write a volume as a v5 .mat file for MATLAB users, atomically.

    Parameters
    ----------
    volume : ndarray of shape (N, H, W), or (C, N, H, W) for colour
        Written as ``key`` (H, W, N) or (H, W, C, N), single precision.
    """
    data = np.asarray(volume)
    if data.ndim not in (3, 4):
        raise InputError(f"mat file {path}: expected a volume (N, H, W) or (C, N, H, W), got shape {data.shape}")
    check_mat_size(path, data.shape)
    return _savemat(Path(path), {key: to_matlab(data).astype(np.float32)})


# MAT-file v5 element types and the single-precision class (MathWorks, "MAT-File Format", the v5 chapter)
_MI_INT8, _MI_INT32, _MI_UINT32, _MI_SINGLE, _MI_MATRIX, _MI_COMPRESSED = 1, 5, 6, 7, 14, 15
_MX_SINGLE_CLASS = 7


#: A v5 .mat element's length is a 32-bit count of bytes.
MAT_ELEMENT_BYTES = 2**32


def check_mat_size(path: str | os.PathLike, shape: tuple) -> None:
    """OutputError when a single-precision volume of ``shape`` may be past what a v5 .mat file holds (its
    elements' lengths are 32-bit: 4 GiB): frames zlib cannot shrink come out up to 0.03 % longer
    (zlib's compressBound), so 0.1 % and a header are kept free."""
    nbytes = 4 * int(np.prod(shape, dtype=np.int64))
    if nbytes + nbytes // 1000 + 1024 >= MAT_ELEMENT_BYTES:
        raise OutputError(f"mat file {path}: {nbytes / 2**30:.1f} GiB of frames is past a v5 .mat file's 4 GiB; "
                          "write .npy, .zarr or .tif instead")


def _element(mi_type: int, data: bytes) -> bytes:
    """A v5 data element: its 8-byte tag, the data, zeros to the next 8-byte boundary."""
    return struct.pack("<II", mi_type, len(data)) + data + bytes(-len(data) % 8)


@contextlib.contextmanager
def mat_writer(path: str | os.PathLike, shape: tuple[int, int, int], *, key: str = "recon"):
    """Write a grey volume (F, H, W) into a v5 .mat file part by part, as ``key`` (H, W, F) single.

    Yields ``write(part)`` for consecutive parts (n, H, W) along the first axis.
    MATLAB's arrays are column-major, so frame ``f`` of ``key`` is one
    contiguous run of its bytes: each frame is compressed as it comes into
    one zlib stream (the file's one ``miCOMPRESSED`` element, whose length is
    filled in at the end), so only a part is ever held.  Written to a
    temporary that replaces ``path`` only when all ``F`` frames were given;
    read back by :func:`scipy.io.loadmat` as :func:`write_mat_volume`'s file.
    """
    target = Path(path)
    f_count, h, w = (int(v) for v in shape)
    data_bytes = 4 * f_count * h * w
    head = (_element(_MI_UINT32, struct.pack("<II", _MX_SINGLE_CLASS, 0))
            + _element(_MI_INT32, struct.pack("<iii", h, w, f_count))
            + _element(_MI_INT8, key.encode("ascii")))
    matrix_bytes = len(head) + 8 + data_bytes + (-data_bytes % 8)
    check_mat_size(target, shape)
    text = f"MATLAB 5.0 MAT-file, Platform: codedvideo, Created on: {time.asctime()}".encode("ascii")
    with atomic_output(target) as tmp:
        with open(tmp, "wb") as fh:
            fh.write(text[:116].ljust(116) + bytes(8) + struct.pack("<H", 0x0100) + b"IM")
            start = fh.tell()
            fh.write(struct.pack("<II", _MI_COMPRESSED, 0))  # its length once known
            z = zlib.compressobj()
            fh.write(z.compress(struct.pack("<II", _MI_MATRIX, matrix_bytes) + head
                                + struct.pack("<II", _MI_SINGLE, data_bytes)))
            written = 0

            def write(part):
                nonlocal written
                block = part if hasattr(part, "shape") else np.asarray(part, dtype="<f4")
                if len(block.shape) != 3 or tuple(block.shape[1:]) != (h, w) or written + block.shape[0] > f_count:
                    raise ValueError(f"mat file {target}: part of shape {block.shape} after {written} of {f_count} "
                                     f"frames of {h}x{w}")
                for frame in frames_of(block):  # converted a frame at a time: no copy of the part
                    fh.write(z.compress(np.ascontiguousarray(np.asarray(frame, dtype="<f4").T).tobytes()))  # column-major (H, W)
                written += block.shape[0]

            yield write
            if written != f_count:
                raise RuntimeError(f"mat file {target}: {written} of {f_count} frames written")
            fh.write(z.compress(bytes(-data_bytes % 8)) + z.flush())
            end = fh.tell()
            if end - start - 8 >= MAT_ELEMENT_BYTES:  # frames zlib could not shrink, just under the limit (checked before)
                raise OutputError(f"mat file {target}: the compressed frames came to {(end - start) / 2**30:.2f} GiB, "
                                  "past a v5 .mat file's 4 GiB; write .npy, .zarr or .tif instead")
            fh.seek(start + 4)
            fh.write(struct.pack("<I", end - start - 8))
    return target
