""".npy files: read whole, written atomically, written part by part, and their layout for reading in parts."""

from __future__ import annotations

import contextlib
import os
from pathlib import Path

import numpy as np

from codedvideo.formats.atomic import atomic_output
from codedvideo.formats.pixels import frames_of
from codedvideo.model.errors import InputError


def read_npy(path: Path) -> np.ndarray:
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
    return read_npy(Path(path))


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
