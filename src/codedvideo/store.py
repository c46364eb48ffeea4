"""Zarr storage: dictionaries and the chunked working stores of reconstruction.

This is the only module that imports zarr.  Every store carries a format
version and the resolved settings in its attributes.  Whole stores that are
written in one go (dictionaries) are written under a temporary name and
renamed, so a reader never sees a half-written store; working stores of a
reconstruction are filled tile by tile and a tile counts as done only once its
statistics row -- written after its volume chunk -- exists, which is what a
resumed run relies on.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import uuid
from pathlib import Path

import numpy as np
import zarr

from .errors import InputError, OutputError

FORMAT_VERSION = 1
DICTIONARY_KIND = "codedvideo-dictionary"
WORKSTORE_KIND = "codedvideo-reconstruction"


def _tmp_sibling(path: Path) -> Path:
    return path.with_name(f".{path.name}.tmp-{os.getpid()}-{uuid.uuid4().hex[:8]}")


def _replace_dir(tmp: Path, path: Path) -> None:
    if path.exists():
        old = _tmp_sibling(path)
        os.replace(path, old)
        os.replace(tmp, path)
        shutil.rmtree(old, ignore_errors=True)
    else:
        os.replace(tmp, path)


def save_dictionary(path: str | os.PathLike, D: np.ndarray, meta: dict) -> Path:
    """Write a dictionary ``D`` (features x atoms) and its metadata, atomically.

    ``meta`` must hold at least ``patch`` and ``frames``; the number of atoms,
    the format version and a content hash are added here.
    """
    path = Path(path)
    D = np.ascontiguousarray(D, dtype=np.float32)
    for key in ("patch", "frames"):
        if key not in meta:
            raise ValueError(f"dictionary metadata lacks {key!r}")
    if D.shape[0] != meta["frames"] * meta["patch"] ** 2:
        raise ValueError(f"dictionary rows {D.shape[0]} != frames * patch^2")
    attrs = dict(meta)
    attrs.update(
        kind=DICTIONARY_KIND,
        format_version=FORMAT_VERSION,
        atoms=int(D.shape[1]),
        sha256=hashlib.sha256(D.tobytes()).hexdigest(),
    )
    tmp = _tmp_sibling(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        group = zarr.open_group(str(tmp), mode="w")
        arr = group.create_array("atoms", shape=D.shape, chunks=D.shape, dtype="float32")
        arr[:] = D
        group.attrs.update(json.loads(json.dumps(attrs)))
        _replace_dir(tmp, path)
    except OSError as exc:
        shutil.rmtree(tmp, ignore_errors=True)
        raise OutputError(f"dictionary {path}: cannot write ({exc.strerror or exc})") from exc
    return path


def load_dictionary(path: str | os.PathLike) -> tuple[np.ndarray, dict]:
    """Read a dictionary written by :func:`save_dictionary`.

    Returns
    -------
    D : ndarray of shape (frames * patch**2, atoms), float32
    meta : dict
    """
    path = Path(path)
    if not path.exists():
        raise InputError(f"dictionary {path}: no such file or directory")
    try:
        group = zarr.open_group(str(path), mode="r")
        meta = dict(group.attrs)
        D = np.asarray(group["atoms"][:], dtype=np.float32)
    except (KeyError, ValueError, OSError, TypeError) as exc:
        raise InputError(f"dictionary {path}: not a readable codedvideo dictionary ({exc})") from exc
    except Exception as exc:  # zarr raises its own types for corrupt metadata
        raise InputError(f"dictionary {path}: corrupt store ({type(exc).__name__}: {exc})") from exc
    if meta.get("kind") != DICTIONARY_KIND:
        raise InputError(f"dictionary {path}: not a codedvideo dictionary (kind={meta.get('kind')!r})")
    if meta.get("sha256") != hashlib.sha256(D.tobytes()).hexdigest():
        raise InputError(f"dictionary {path}: atoms do not match their recorded checksum (corrupt)")
    if not np.isfinite(D).all():
        raise InputError(f"dictionary {path}: contains NaN or Inf")
    return D, meta


class WorkStore:
    """The chunked working store of one reconstruction.

    Arrays: ``coded`` (H, W) float32, ``mask`` (N, H, W) uint8 and ``volume``
    (N, H, W) float32, all chunked by the same ``tile x tile`` grid, and
    ``stats`` (n_tiles, n_stats) float64 with one chunk per tile.
    """

    def __init__(self, path: str | os.PathLike):
        self.path = Path(path)
        self.group = zarr.open_group(str(self.path), mode="r+")

    @classmethod
    def create(
        cls,
        path: str | os.PathLike,
        coded: np.ndarray,
        mask: np.ndarray,
        *,
        tile: int,
        n_stats: int,
        n_tiles: int,
        attrs: dict,
    ) -> "WorkStore":
        """Create (or reopen, when its key matches) the working store."""
        path = Path(path)
        key = attrs.get("key")
        if path.exists():
            try:
                existing = zarr.open_group(str(path), mode="r")
                if existing.attrs.get("key") == key and existing.attrs.get("complete_inputs"):
                    return cls(path)
            except Exception:  # unreadable leftovers are replaced below
                pass
            shutil.rmtree(path)
        n, h, w = mask.shape
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            group = zarr.open_group(str(path), mode="w")
            group.create_array("coded", shape=(h, w), chunks=(tile, tile), dtype="float32")[:] = coded
            group.create_array("mask", shape=(n, h, w), chunks=(n, tile, tile), dtype="uint8")[:] = mask
            group.create_array("volume", shape=(n, h, w), chunks=(n, tile, tile), dtype="float32", fill_value=np.nan)
            group.create_array("stats", shape=(n_tiles, n_stats), chunks=(1, n_stats), dtype="float64", fill_value=np.nan)
            group.attrs.update(json.loads(json.dumps(dict(attrs, kind=WORKSTORE_KIND, format_version=FORMAT_VERSION))))
            group.attrs["complete_inputs"] = True
        except OSError as exc:
            raise OutputError(f"working store {path}: cannot write ({exc.strerror or exc})") from exc
        return cls(path)

    # -- tile access, used inside tasks -------------------------------------------------
    def read_inputs(self, y0: int, y1: int, x0: int, x1: int) -> tuple[np.ndarray, np.ndarray]:
        coded = self.group["coded"][y0:y1, x0:x1]
        mask = self.group["mask"][:, y0:y1, x0:x1]
        return np.asarray(coded), np.asarray(mask)

    def write_tile(self, index: int, region: tuple[int, int, int, int], volume: np.ndarray, stats: np.ndarray) -> None:
        y0, y1, x0, x1 = region
        self.group["volume"][:, y0:y1, x0:x1] = volume
        self.group["stats"][index : index + 1, :] = np.asarray(stats, dtype=np.float64)[None]

    def done_tiles(self) -> np.ndarray:
        """Boolean per tile: its statistics row exists (so its volume does too)."""
        stats = np.asarray(self.group["stats"][:])
        return np.isfinite(stats).all(1)

    def stats(self) -> np.ndarray:
        return np.asarray(self.group["stats"][:])

    def volume(self) -> np.ndarray:
        return np.asarray(self.group["volume"][:])

    @property
    def volume_array(self):
        """The zarr array itself (for streaming reads and dask.array.from_zarr)."""
        return self.group["volume"]


def save_array(path: str | os.PathLike, array: np.ndarray, *, chunks=None, attrs: dict | None = None) -> Path:
    """Write one array as a Zarr store, atomically."""
    path = Path(path)
    tmp = _tmp_sibling(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        arr = zarr.create_array(str(tmp), shape=array.shape, chunks=chunks or array.shape, dtype=array.dtype)
        arr[...] = array
        if attrs:
            arr.attrs.update(json.loads(json.dumps(dict(attrs, format_version=FORMAT_VERSION))))
        _replace_dir(tmp, path)
    except OSError as exc:
        shutil.rmtree(tmp, ignore_errors=True)
        raise OutputError(f"{path}: cannot write Zarr array ({exc.strerror or exc})") from exc
    return path


def load_array(path: str | os.PathLike) -> np.ndarray:
    """Read a Zarr array (or the ``volume`` array of a working store)."""
    path = Path(path)
    if not path.exists():
        raise InputError(f"{path}: no such file or directory")
    try:
        node = zarr.open(str(path), mode="r")
        if isinstance(node, zarr.Group):
            node = node["volume"]
        return np.asarray(node[...])
    except Exception as exc:
        raise InputError(f"{path}: not a readable Zarr array ({type(exc).__name__}: {exc})") from exc
