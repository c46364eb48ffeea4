"""Zarr storage: dictionaries and the chunked working stores of reconstruction.

This is the only module that imports zarr.  Every store carries a format
version and the resolved settings in its attributes.  Whole stores that are
written in one go (dictionaries) are written under a temporary name and
renamed, so a reader never sees a half-written store.

A working store of a reconstruction is a cache entry shared by every run with
the same inputs and settings.  Its inputs are written under a temporary name
and renamed into place, so the entry is never visible half-made; its tiles are
then filled one by one, each tile writing its volume chunk, its statistics row
(and, from the non-local method, its misfit map) and, last, a blake2b digest of them
(:func:`tile_digest`).  A tile counts as
done only when the digest matches what is read back, so a tile that was cut
short, damaged, truncated, deleted or copied over from another tile is
recomputed, never returned.  Runs on one entry are serialised by an exclusive
``fcntl.flock`` on a sibling ``.lock`` file (:func:`entry_lock`).
"""

from __future__ import annotations

import asyncio
import contextlib
import errno
import hashlib
import json
import logging
import os
import shutil
import threading
from collections import OrderedDict
from pathlib import Path

import numpy as np
import zarr
import zarr.api.asynchronous
from zarr.core.sync import sync  # zarr's own event loop, as its synchronous API uses

try:
    import fcntl
except ImportError:  # pragma: no cover - not POSIX: no locks, create-then-rename still holds
    fcntl = None

from codedvideo.formats.atomic import atomic_output
from codedvideo.formats.atomic import discard as _discard
from codedvideo.formats.atomic import (make_parents, remove_dead_temporaries, remove_made, replace_dir, temporaries_of,
                                      temporary_name)
from codedvideo.model.errors import InputError, OutputError
from codedvideo.model.patches import PATCH

log = logging.getLogger("codedvideo")

FORMAT_VERSION = 1
DICTIONARY_KIND = "codedvideo-dictionary"
WORKSTORE_KIND = "codedvideo-reconstruction"
#: Layout of a working store: 2 added the per-tile ``digest`` array, 3 the ``still`` map, 4 the ``misfit`` map.
WORKSTORE_FORMAT = 4
#: Bytes of a tile digest (blake2b).
DIGEST_SIZE = 32
#: The arrays of a working store.
WORKSTORE_ARRAYS = ("coded", "mask", "still", "volume", "misfit", "stats", "digest")


def lock_path(entry: str | os.PathLike) -> Path:
    """The lock file of a cache entry: ``recon-KEY.zarr`` -> ``recon-KEY.lock`` beside it."""
    entry_path = Path(entry)
    return entry_path.with_name(entry_path.name.removesuffix(".zarr") + ".lock")


def _acquire(lock: Path, blocking: bool):
    """An fd holding an exclusive flock on ``lock``; None when busy (non-blocking); -1 when no lock can be taken."""
    while True:
        try:
            fd = os.open(lock, os.O_RDWR | os.O_CREAT, 0o666)
        except OSError as exc:
            if exc.errno in (errno.EMFILE, errno.ENFILE):  # not a read-only cache: a job of too many captures
                raise OutputError(f"cache {lock}: too many open files to lock one more working store (a job locks "
                                  "one per capture); raise the limit (ulimit -n) or reconstruct fewer captures a "
                                  "job") from exc
            try:  # a read-only cache: lock the existing file, or go without
                fd = os.open(lock, os.O_RDONLY)
            except OSError:
                return -1
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | (0 if blocking else fcntl.LOCK_NB))
        except BlockingIOError:
            os.close(fd)
            return None
        except OSError as exc:  # e.g. ENOLCK on a file system without locks
            os.close(fd)
            log.warning("cache %s: cannot lock (%s); going on without the lock", lock, exc.strerror or exc)
            return -1
        try:  # clean_cache may have removed the file while we waited: then lock the new one
            st, fs = os.stat(lock), os.fstat(fd)
            if (st.st_dev, st.st_ino) == (fs.st_dev, fs.st_ino):
                return fd
        except FileNotFoundError:
            pass
        os.close(fd)


@contextlib.contextmanager
def entry_lock(entry: str | os.PathLike, *, blocking: bool = True):
    """Hold the exclusive lock of a cache entry (``fcntl.flock`` on :func:`lock_path`).

    Every process (and every thread: each call opens its own file) that
    creates, reuses, repairs or removes an entry holds its lock meanwhile, so
    a second run on the same entry waits and then reuses what the first one
    finished.  The kernel releases the lock when its holder dies.

    Yields True while the lock is held (or when none can be taken: no
    ``fcntl``, a read-only cache, a file system without locks), False when
    ``blocking`` is False and another process holds it.
    """
    if fcntl is None:  # pragma: no cover
        yield True
        return
    lock = lock_path(entry)
    with contextlib.suppress(OSError):  # an unwritable cache fails where the entry is written, with its own message
        lock.parent.mkdir(parents=True, exist_ok=True)
    fd = _acquire(lock, blocking=False)
    if fd is None and blocking:
        log.info("cache entry %s is in use by another run; waiting for it", entry)
        fd = _acquire(lock, blocking=True)
    if fd is None:
        yield False
        return
    try:
        yield True
    finally:
        if fd >= 0:
            os.close(fd)  # releases the flock


def remove_locked_entry(entry: Path) -> None:
    """Remove a cache entry (folder or file), its lock file and its temporaries; hold its lock."""
    entry_path = Path(entry)
    if entry_path.is_dir() and not entry_path.is_symlink():
        gone = temporary_name(entry_path, keep_suffix=False)
        os.replace(entry_path, gone)  # out of sight at once, then removed
        _discard(gone)
    elif os.path.lexists(entry_path):
        entry_path.unlink()
    remove_temporaries(entry_path)
    with contextlib.suppress(FileNotFoundError):
        lock_path(entry_path).unlink()  # waiters notice the new inode and lock afresh


def remove_temporaries(entry: Path) -> list[Path]:
    """Remove the temporaries ``.NAME.tmp-*`` a killed writer of ``entry`` left; hold its lock."""
    removed = []
    for tmp in temporaries_of(entry):
        _discard(tmp)
        removed.append(tmp)
    return removed


def save_dictionary(path: str | os.PathLike, D: np.ndarray, meta: dict) -> Path:
    """Write a dictionary ``D`` (features x atoms) and its metadata, atomically.

    ``meta`` must hold at least ``patch`` and ``frames``; the number of atoms,
    the format version and a content hash are added here.
    """
    target = Path(path)
    atoms = np.ascontiguousarray(D, dtype=np.float32)
    for key in ("patch", "frames"):
        if key not in meta:
            raise ValueError(f"dictionary metadata lacks {key!r}")
    if atoms.shape[0] != meta["frames"] * meta["patch"] ** 2:
        raise ValueError(f"dictionary rows {atoms.shape[0]} != frames * patch^2")
    attrs = dict(meta)
    attrs.update(
        kind=DICTIONARY_KIND,
        format_version=FORMAT_VERSION,
        atoms=int(atoms.shape[1]),
        sha256=hashlib.sha256(atoms.tobytes()).hexdigest(),
    )
    tmp = temporary_name(target, keep_suffix=False)
    zipped = target.suffix.lower() == ".zip"  # one file (the shipped dictionaries): a zipped Zarr store
    made = make_parents(target)
    try:
        remove_dead_temporaries(target)  # what a killed run left
        store = zarr.storage.ZipStore(tmp, mode="w") if zipped else str(tmp)
        group = zarr.open_group(store, mode="w", attributes=json.loads(json.dumps(attrs)))
        arr = group.create_array("atoms", shape=atoms.shape, chunks=atoms.shape, dtype="float32")
        arr[:] = atoms
        if zipped:
            store.close()
            os.replace(tmp, target)
        else:
            replace_dir(tmp, target)
    except OSError as exc:
        _discard(tmp)
        remove_made(made)
        raise OutputError(f"dictionary {target}: cannot write ({exc.strerror or exc})") from exc
    except BaseException:  # Ctrl-C, SIGTERM: no temporary left, nor a folder made for it
        _discard(tmp)
        remove_made(made)
        raise
    return target


def check_dictionary(meta: dict, frames: int, path, D: np.ndarray | None = None, *, needs: str = "the mask has") -> None:
    """Refuse a dictionary (its stored ``meta``, and its atoms ``D`` when given) made for another patch size or
    another N, naming ``path``; ``needs``: who asks for N sub-frames (``"training for"`` a K-SVD's start)."""
    patch, built = meta.get("patch"), meta.get("frames")
    if patch != PATCH:
        raise InputError(f"dictionary {path}: patch size {patch!r} != {PATCH}")
    if not isinstance(built, int) or isinstance(built, bool):
        raise InputError(f"dictionary {path}: its record's frames {built!r} is not a whole number of sub-frames")
    if built != frames:
        from codedvideo.model.codes import short_of

        raise InputError(f"dictionary {path}: built for N = {built} sub-frames, {needs} N = {frames}"
                         + (f": {short_of(frames, built)}" if needs == "the mask has" and built > frames else ""))
    if D is not None and D.shape[0] != frames * PATCH * PATCH:
        raise InputError(f"dictionary {path}: atoms of {D.shape[0]} rows; N = {frames} needs N x {PATCH * PATCH} = "
                         f"{frames * PATCH * PATCH}")


def load_dictionary(path: str | os.PathLike) -> tuple[np.ndarray, dict]:
    """Read a dictionary written by :func:`save_dictionary`.

    Returns
    -------
    D : ndarray of shape (frames * patch**2, atoms), float32
    meta : dict
    """
    source = Path(path)
    if not source.exists():
        raise InputError(f"dictionary {source}: no such file or directory")
    try:
        store = zarr.storage.ZipStore(source, mode="r") if source.suffix.lower() == ".zip" else str(source)
        group = zarr.open_group(store, mode="r")
        meta = dict(group.attrs)
        D = np.asarray(group["atoms"][:], dtype=np.float32)
        if not isinstance(store, str):
            store.close()
    except (KeyError, ValueError, OSError, TypeError) as exc:
        raise InputError(f"dictionary {source}: not a readable codedvideo dictionary ({exc})") from exc
    except Exception as exc:  # zarr raises its own types for corrupt metadata
        raise InputError(f"dictionary {source}: corrupt store ({type(exc).__name__}: {exc})") from exc
    if meta.get("kind") != DICTIONARY_KIND:
        raise InputError(f"dictionary {source}: not a codedvideo dictionary (kind={meta.get('kind')!r})")
    if meta.get("sha256") != hashlib.sha256(D.tobytes()).hexdigest():
        raise InputError(f"dictionary {source}: atoms do not match their recorded checksum (corrupt)")
    if not np.isfinite(D).all():
        raise InputError(f"dictionary {source}: contains NaN or Inf")
    return D, meta


def tile_digest(key: str, index: int, core: tuple[int, int, int, int], volume: np.ndarray,
                stats: np.ndarray, misfit: np.ndarray | None = None) -> np.ndarray:
    """The checksum of one finished tile: blake2b of its identity, volume core, statistics row and misfit core
    (None: all zero, as a tile that writes none leaves it).

    The identity (entry key, tile index, core region) is part of it, so a
    tile's chunks copied over another tile's -- digest included -- do not
    pass for that tile.  Returns ``DIGEST_SIZE`` bytes as uint8.
    """
    h = hashlib.blake2b(digest_size=DIGEST_SIZE, person=b"codedvideo-tile")
    v = np.ascontiguousarray(volume, dtype="<f4")
    h.update(json.dumps([str(key), int(index), [int(c) for c in core], list(v.shape)]).encode())
    h.update(v.data)
    h.update(np.ascontiguousarray(stats, dtype="<f8").data)
    m = np.zeros(v.shape[1:], "<f4") if misfit is None else np.ascontiguousarray(misfit, dtype="<f4")
    h.update(m.data)
    return np.frombuffer(h.digest(), dtype=np.uint8)


def mask_dtype(mask: np.ndarray) -> np.dtype:
    """How a working store holds a mask: uint8 for a binary code, float32 for calibrated weights."""
    from codedvideo.model.codes import is_binary

    return np.dtype("uint8") if is_binary(mask) else np.dtype("<f4")


def workstore_inputs(coded: np.ndarray, mask: np.ndarray, still: np.ndarray | None):
    """``(coded, mask, still)`` as a working store holds them: float32, :func:`mask_dtype`, uint8 (None: all 0)."""
    held_coded = np.asarray(coded, dtype=np.float32)
    held_mask = np.asarray(mask, dtype=mask_dtype(mask))
    held_still = np.zeros(held_coded.shape, np.uint8) if still is None else np.asarray(still, dtype=np.uint8)
    return held_coded, held_mask, held_still


def inputs_digest(coded: np.ndarray, mask: np.ndarray, still: np.ndarray) -> str:
    """blake2b of the inputs as a working store holds them (float32 coded image, mask as :func:`mask_dtype`,
    uint8 still map)."""
    h = hashlib.blake2b(digest_size=DIGEST_SIZE, person=b"codedvideo-in")
    for a in (np.ascontiguousarray(coded, dtype="<f4"), np.ascontiguousarray(mask, dtype=mask_dtype(mask)),
              np.ascontiguousarray(still, dtype=np.uint8)):
        h.update(str(a.shape).encode())
        h.update(a.data)
    return h.hexdigest()


class _TileRef:
    """A tile's index and core region (what :class:`WorkStore` needs of :class:`codedvideo.engine.parallel.Tile`)."""

    __slots__ = ("index", "core")

    def __init__(self, index: int, core: tuple[int, int, int, int]):
        self.index, self.core = index, core


def workstore_layout(n: int, h: int, w: int, *, tile: int, n_stats: int, n_tiles: int,
                     mask: np.dtype = np.dtype("uint8")) -> dict:
    """name -> (shape, chunks, dtype, fill value) of the arrays of a working store (``mask``: its dtype)."""
    return dict(
        coded=((h, w), (tile, tile), np.dtype("float32"), 0.0),
        mask=((n, h, w), (n, tile, tile), np.dtype(mask), 0),
        still=((h, w), (tile, tile), np.dtype("uint8"), 0),
        volume=((n, h, w), (n, tile, tile), np.dtype("float32"), np.nan),
        misfit=((h, w), (tile, tile), np.dtype("float32"), 0.0),
        stats=((n_tiles, n_stats), (1, n_stats), np.dtype("float64"), np.nan),
        digest=((n_tiles, DIGEST_SIZE), (1, DIGEST_SIZE), np.dtype("uint8"), 0),
    )


def _same_bits(a: np.ndarray, b: np.ndarray) -> bool:
    left, right = np.ascontiguousarray(a), np.ascontiguousarray(b)
    return (left.shape == right.shape and left.dtype == right.dtype
            and np.array_equal(left.view(np.uint8), right.view(np.uint8)))


def workstore_problem(group, *, key: str | None = None) -> str | None:
    """What makes an opened working store unusable as a whole (None: its layout is sound).

    Checks the kind, the layout version, the key (when given), that its
    inputs were completed, and every array's shape, chunks and dtype.  The
    input *values* are checked by :meth:`WorkStore.create` (against the
    inputs in memory) and by :func:`codedvideo.engine.cache.verify_cache` (against
    the recorded inputs digest).
    """
    attrs = dict(group.attrs)
    if attrs.get("kind") != WORKSTORE_KIND:
        return f"not a codedvideo working store (kind={attrs.get('kind')!r})"
    if attrs.get("format_version") != WORKSTORE_FORMAT:
        return f"layout version {attrs.get('format_version')!r}, this codedvideo uses {WORKSTORE_FORMAT}"
    if key is not None and attrs.get("key") != key:
        return f"key {attrs.get('key')!r} is not the key of these inputs and settings ({key})"
    if not attrs.get("complete_inputs"):
        return "its inputs were never completed"
    try:
        n, h, w = group["mask"].shape
        stored = group["mask"].dtype
        layout = workstore_layout(n, h, w, tile=int(attrs["tile"]), n_stats=group["stats"].shape[1],
                                  n_tiles=int(attrs["n_tiles"]),
                                  mask=stored if stored == np.dtype("<f4") else np.dtype("uint8"))
    except Exception as exc:
        return f"unreadable layout ({type(exc).__name__}: {exc})"
    for name, (shape, chunks, dtype, _) in layout.items():
        try:
            arr = group[name]
        except Exception as exc:
            return f"array {name!r} is missing or unreadable ({type(exc).__name__}: {exc})"
        if not isinstance(arr, zarr.Array) or tuple(arr.shape) != shape or tuple(arr.chunks) != chunks \
                or arr.dtype != dtype:
            return f"array {name!r} does not have the layout of a working store"
    return None


async def _build_entry(path: Path, layout: dict, inputs: dict[str, np.ndarray], attrs: dict) -> None:
    """A working store's arrays made and its inputs written concurrently (a dozen metadata and chunk
    writes: 15 ms a capture against 27 ms one by one), then its attributes, ``complete_inputs`` last."""
    group = await zarr.api.asynchronous.open_group(store=str(path), mode="w")
    arrays = await asyncio.gather(*(group.create_array(name, shape=shape, chunks=chunks, dtype=dtype, fill_value=fill)
                                    for name, (shape, chunks, dtype, fill) in layout.items()))
    arrays = dict(zip(layout, arrays))
    await asyncio.gather(*(arrays[name].setitem(Ellipsis, value) for name, value in inputs.items()))
    await group.update_attributes(attrs)


def write_tiles(places: list[tuple["WorkStore", int, tuple[int, int, int, int]]], volume: np.ndarray,
                stats: np.ndarray, misfit: np.ndarray | None = None) -> None:
    """Write one solved tile to each of its places ``(store, tile index, core region)``: every volume
    core, statistics row and misfit core (the measurement misfit that projecting the core onto the coded image
    took away, :func:`codedvideo.solvers.nonlocal_sc.finish`; None: none, the store's zeros) concurrently, then
    (last) every digest.

    A tile cut short before its digest does not match the digest on disk
    (none, or an old one of other contents), so it is never taken for done; a
    digest that matches vouches for exactly the bytes it was computed from.
    """
    tile_volume = np.ascontiguousarray(volume, dtype=np.float32)
    tile_stats = np.ascontiguousarray(stats, dtype=np.float64)
    tile_misfit = None if misfit is None else np.ascontiguousarray(misfit, dtype=np.float32)
    writes, digests = [], []
    for store, index, (y0, y1, x0, x1) in places:  # arrays opened here: never from inside zarr's event loop
        writes.append((store.array("volume").async_array, (slice(None), slice(y0, y1), slice(x0, x1)), tile_volume))
        writes.append((store.array("stats").async_array, (slice(index, index + 1), slice(None)), tile_stats[None]))
        if tile_misfit is not None:
            writes.append((store.array("misfit").async_array, (slice(y0, y1), slice(x0, x1)), tile_misfit))
        digests.append((store.array("digest").async_array, (slice(index, index + 1), slice(None)),
                        tile_digest(store.key, index, (y0, y1, x0, x1), tile_volume, tile_stats, tile_misfit)[None]))

    async def write():
        await asyncio.gather(*(arr.setitem(sel, value) for arr, sel, value in writes))
        await asyncio.gather(*(arr.setitem(sel, value) for arr, sel, value in digests))

    sync(write())


#: Working stores opened for tile access in this process (:meth:`WorkStore.opened`), the most recent last.
OPENED_KEPT = 64
_opened: "OrderedDict[tuple, WorkStore]" = OrderedDict()
_opened_lock = threading.Lock()


def _entry_ident(path: str | os.PathLike) -> tuple:
    """What tells one entry at ``path`` from another made later under the same name: its ``zarr.json``
    file (inode, size, modification time).  Raises OSError when there is none."""
    st = os.stat(Path(path) / "zarr.json")
    return str(path), st.st_ino, st.st_size, st.st_mtime_ns


def _remember(ident: tuple, store: "WorkStore") -> None:
    with _opened_lock:
        _opened[ident] = store
        _opened.move_to_end(ident)
        while len(_opened) > OPENED_KEPT:
            _opened.popitem(last=False)


class WorkStore:
    """The chunked working store of one reconstruction: one cache entry.

    Arrays: ``coded`` (H, W) float32, ``mask`` (N, H, W) uint8, ``still`` (H, W)
    uint8, ``volume`` (N, H, W) float32 and ``misfit`` (H, W) float32 (what the
    non-local method's projection took away; 0 elsewhere), all chunked by the
    same ``tile x tile`` grid, and ``stats`` (n_tiles, n_stats) float64 and
    ``digest`` (n_tiles, DIGEST_SIZE) uint8 with one chunk per tile.  A tile is
    done when its digest (written last) matches its volume core, statistics row
    and misfit core as read back (:meth:`read_verified`).
    """

    def __init__(self, path: str | os.PathLike, *, mode: str = "r+"):
        self.path = Path(path)
        self.group = zarr.open_group(str(self.path), mode=mode)
        self.key = str(self.group.attrs.get("key", ""))
        #: Made afresh by :meth:`create` (no tile of it is done), rather than opened or reused.
        self.created = False
        self._arrays: dict[str, zarr.Array] = {}

    def array(self, name: str) -> zarr.Array:
        """One of the store's arrays, its metadata read once for this store object."""
        arr = self._arrays.get(name)
        if arr is None:
            arr = self._arrays[name] = self.group[name]
        return arr

    @classmethod
    def opened(cls, path: str | os.PathLike) -> "WorkStore":
        """The store at ``path`` for tile access, opened once per process while it is the same entry.

        Every tile task of a job reads and writes its store; opening the
        group and its arrays reads four metadata files, several milliseconds
        a task.  An entry is the same while its ``zarr.json`` is the same
        file (inode, size, modification time): an entry rebuilt under the
        same name is opened afresh.
        """
        try:
            ident = _entry_ident(path)
        except OSError:  # no entry: let zarr name the problem
            return cls(path)
        with _opened_lock:
            store = _opened.get(ident)
            if store is not None:
                _opened.move_to_end(ident)
                return store
        store = cls(path)
        _remember(ident, store)
        return store

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
        still: np.ndarray | None = None,
    ) -> "WorkStore":
        """Reuse the entry at ``path`` when it is sound and holds these inputs; otherwise build it afresh.

        A reused entry must have this key, the current layout, every array
        (``zarr.json`` included) readable with the right shape, chunks and
        dtype, and inputs equal bit for bit to ``coded``, ``mask`` and ``still``
        (pixels whose patches take the still answer, :mod:`codedvideo.model.sequence`;
        None: none).
        Anything else -- a damaged or deleted ``zarr.json``, a damaged input
        chunk, an entry of an older layout -- is logged and replaced by a new
        entry, built under a temporary name and renamed into place, so no
        reader ever sees it half-made.  The caller holds :func:`entry_lock`.
        """
        target = Path(path)
        held_coded, held_mask, held_still = workstore_inputs(coded, mask, still)
        if os.path.lexists(target):
            problem = cls._problem(target, held_coded, held_mask, held_still, key=attrs.get("key"), tile=tile,
                                   n_stats=n_stats, n_tiles=n_tiles)
            if problem is None:
                return cls(target)
            log.warning("cache entry %s: %s; rebuilding it", target, problem)
        n, h, w = held_mask.shape
        tmp = temporary_name(target, keep_suffix=False)
        try:
            target.parent.mkdir(parents=True, exist_ok=True)
            remove_temporaries(target)  # left by killed runs (we hold the lock)
            layout = workstore_layout(n, h, w, tile=tile, n_stats=n_stats, n_tiles=n_tiles, mask=held_mask.dtype)
            inputs = dict(coded=held_coded, mask=held_mask, still=held_still)
            sync(_build_entry(tmp, layout, inputs, json.loads(json.dumps(dict(
                attrs, kind=WORKSTORE_KIND, format_version=WORKSTORE_FORMAT, tile=int(tile), n_tiles=int(n_tiles),
                inputs_digest=inputs_digest(held_coded, held_mask, held_still), complete_inputs=True)))))
            replace_dir(tmp, target)
        except OSError as exc:
            shutil.rmtree(tmp, ignore_errors=True)
            raise OutputError(f"working store {target}: cannot write ({exc.strerror or exc})") from exc
        store = cls(target)
        store.created = True
        _remember(_entry_ident(target), store)
        return store

    @staticmethod
    def _problem(path: Path, coded: np.ndarray, mask: np.ndarray, still: np.ndarray, *, key, tile: int,
                 n_stats: int, n_tiles: int) -> str | None:
        try:
            group = zarr.open_group(str(path), mode="r")
            problem = workstore_problem(group, key=key)
            if problem:
                return problem
            if group.attrs.get("tile") != tile or group.attrs.get("n_tiles") != n_tiles \
                    or group["stats"].shape[1] != n_stats or group["mask"].shape != mask.shape:
                return "tile size, statistics or shape differ from this run's"
            if not _same_bits(group["coded"][...], coded):
                return "its coded image differs from the input (damaged)"
            if not _same_bits(group["mask"][...], mask):
                return "its mask differs from the input (damaged)"
            if not _same_bits(group["still"][...], still):
                return "its still map differs from the input (damaged)"
        except Exception as exc:  # zarr raises its own types for damaged metadata and chunks
            return f"unreadable ({type(exc).__name__}: {exc})"
        return None

    # -- tile access, used inside tasks -------------------------------------------------
    def read_inputs(self, y0: int, y1: int, x0: int, x1: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The coded image, the mask and the still map (uint8) of a region, read concurrently."""
        region = (slice(y0, y1), slice(x0, x1))
        arrays = [self.array(name).async_array for name in ("coded", "mask", "still")]

        async def read():
            return await asyncio.gather(arrays[0].getitem(region), arrays[1].getitem((slice(None), *region)),
                                        arrays[2].getitem(region))

        return tuple(np.asarray(a) for a in sync(read()))

    # -- verified reads, used by the client -----------------------------------------------
    def tiles(self) -> list[_TileRef]:
        """The tiles of this store (index, core), in the order of :func:`codedvideo.engine.parallel.plan_tiles`."""
        h, w = self.group["coded"].shape
        t = int(self.group.attrs["tile"])
        return [_TileRef(i, (y0, min(y0 + t, h), x0, min(x0 + t, w)))
                for i, (y0, x0) in enumerate((y, x) for y in range(0, h, t) for x in range(0, w, t))]

    def _rows(self, name: str, fill) -> np.ndarray:
        """A per-tile array, whole; rows whose chunk cannot be decoded come back as ``fill``."""
        arr = self.array(name)
        try:
            return np.asarray(arr[...])
        except Exception:  # a damaged chunk: read row by row
            out = np.full(arr.shape, fill, dtype=arr.dtype)
            for i in range(arr.shape[0]):
                try:
                    out[i] = arr[i]
                except Exception:
                    pass
            return out

    def read_verified(self, tiles, volume: np.ndarray | None = None, *, assemble: bool = True,
                      misfit: np.ndarray | None = None):
        """Read tiles and check each against its digest.

        Parameters
        ----------
        tiles : sequence of objects with ``index`` and ``core``
        volume : ndarray (N, H, W) float32, optional
            Verified cores are copied into it.  None: a new array (the whole
            volume as read, when every tile is asked for; NaN elsewhere)
            whose cores that failed are NaN.
        assemble : bool
            False: only check the tiles, one core at a time (the returned
            volume and misfit are None), so that planning a job of many
            captures never holds their volumes.
        misfit : ndarray (H, W) float32, optional
            Verified misfit cores are copied into it (with ``volume``).
            None: a new array, as for ``volume``.

        Returns
        -------
        ok : bool array (n_tiles,)
            The tile was asked for and matches its digest.
        damaged : bool array (n_tiles,)
            The tile has a digest but it does not match, or its chunk cannot be decoded, or it was
            written (its statistics row holds numbers) but has no digest.
        volume : ndarray (N, H, W) float32
        stats : ndarray (n_tiles, n_stats) float64
            The statistics rows as read (valid where ``ok``).
        misfit : ndarray (H, W) float32
            The misfit map (:func:`write_tiles`) of the verified cores, 0 elsewhere (None when not assembled).
        """
        wanted = list(tiles)
        assembled = volume
        digests = self._rows("digest", 0)
        stats = self._rows("stats", np.nan)
        n_tiles = digests.shape[0]
        ok = np.zeros(n_tiles, bool)
        damaged = np.zeros(n_tiles, bool)
        varr, marr = self.array("volume"), self.array("misfit")
        claimed = [t for t in wanted if digests[t.index].any()]
        bulk, misfits = None, None
        if not assemble:
            assembled = None
        elif claimed and 2 * len(claimed) > n_tiles:  # most of the volume: one read, chunks fetched concurrently
            try:
                bulk = np.asarray(varr[...])
            except Exception:  # some chunk cannot be decoded: tile by tile below
                bulk = None
        if claimed and 2 * len(claimed) > n_tiles:
            try:
                misfits = np.asarray(marr[...])
            except Exception:
                misfits = None
        found = misfit if misfit is not None or not assemble else np.zeros(marr.shape, np.float32)
        adopt = assemble and assembled is None and bulk is not None and len(wanted) == n_tiles
        if assemble and assembled is None:
            assembled = bulk if adopt else np.full(varr.shape, np.nan, np.float32)
        for t in claimed:
            y0, y1, x0, x1 = t.core
            try:
                core = bulk[:, y0:y1, x0:x1] if bulk is not None else np.asarray(varr[:, y0:y1, x0:x1])
                taken = misfits[y0:y1, x0:x1] if misfits is not None else np.asarray(marr[y0:y1, x0:x1])
            except Exception:
                damaged[t.index] = True
                continue
            if tile_digest(self.key, t.index, t.core, core, stats[t.index], taken).tobytes() \
                    == digests[t.index].tobytes():
                ok[t.index] = True
                if assemble and not adopt:
                    assembled[:, y0:y1, x0:x1] = core
                if found is not None:
                    found[y0:y1, x0:x1] = taken
            else:
                damaged[t.index] = True
        for t in wanted:  # written (its statistics row is there) but its digest gone: deleted, or cut short
            if not digests[t.index].any() and np.isfinite(stats[t.index]).any():
                damaged[t.index] = True
        if adopt:  # never hand out a core that failed
            for t in wanted:
                if not ok[t.index]:
                    y0, y1, x0, x1 = t.core
                    assembled[:, y0:y1, x0:x1] = np.nan
        return ok, damaged, assembled, stats, found

    def read_tile(self, index: int, core: tuple[int, int, int, int]) -> tuple[np.ndarray, np.ndarray]:
        """One finished tile's volume core and statistics row, checked against its digest (used inside tasks:
        another job's tiles as a first estimate); a tile not done or that fails raises a one-line error."""
        y0, y1, x0, x1 = core
        arrays = [self.array(name).async_array for name in ("volume", "stats", "digest", "misfit")]

        async def read():
            return await asyncio.gather(arrays[0].getitem((slice(None), slice(y0, y1), slice(x0, x1))),
                                        arrays[1].getitem((slice(index, index + 1), slice(None))),
                                        arrays[2].getitem((slice(index, index + 1), slice(None))),
                                        arrays[3].getitem((slice(y0, y1), slice(x0, x1))))

        try:
            volume, stats, digest, misfit = (np.asarray(a) for a in sync(read()))
        except Exception as exc:  # zarr raises its own types for a damaged chunk
            raise RuntimeError(f"working store {self.path}: tile {index} cannot be read ({exc})") from exc
        if tile_digest(self.key, index, core, volume, stats[0], misfit).tobytes() != digest[0].tobytes():
            raise RuntimeError(f"working store {self.path}: tile {index} is not finished or fails its checksum")
        return volume, stats[0]

    def stats(self) -> np.ndarray:
        """The statistics rows as stored (unverified; see :meth:`read_verified`)."""
        return np.asarray(self.group["stats"][:])

    def volume(self) -> np.ndarray:
        """The volume as stored (unverified; see :meth:`read_verified`)."""
        return np.asarray(self.group["volume"][:])


@contextlib.contextmanager
def array_writer(path: str | os.PathLike, shape: tuple, dtype, *, chunks=None, attrs: dict | None = None):
    """Write one Zarr array part by part: yields the array (assign its parts), renamed into place at the end.

    The array is made under a temporary name; only when the block ends
    without an error do its attributes (with the format version) go in and
    the store appear under ``path``, so a reader never sees it half-written.
    """
    target = Path(path)
    with atomic_output(target) as tmp:
        try:
            arr = zarr.create_array(str(tmp), shape=tuple(shape), chunks=chunks or tuple(shape), dtype=dtype)
            yield arr
            if attrs:
                arr.update_attributes(json.loads(json.dumps(dict(attrs, format_version=FORMAT_VERSION))))
        except OSError as exc:
            raise OutputError(f"{target}: cannot write Zarr array ({exc.strerror or exc})") from exc


def load_array(path: str | os.PathLike) -> np.ndarray:
    """Read a Zarr array (or the ``volume`` array of a working store)."""
    source = Path(path)
    if not source.exists():
        raise InputError(f"{source}: no such file or directory")
    try:
        node = zarr.open(str(source), mode="r")
        if isinstance(node, zarr.Group):
            node = node["volume"]
        return np.asarray(node[...])
    except Exception as exc:
        raise InputError(f"{source}: not a readable Zarr array ({type(exc).__name__}: {exc})") from exc
