"""TIFF page chains, counted from the file's own IFDs (a cut chain would read as a shorter stack)."""

from __future__ import annotations

import os
from pathlib import Path

from codedvideo.model.errors import InputError


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
