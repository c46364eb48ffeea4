"""Check and clean a codedvideo cache folder (``--cache``, ``cache:`` in pipeline.yaml).

A cache holds entries of three kinds, each recognised by its name and its
contents; nothing else in the folder is ever reported or removed:

* ``dict-KEY.zarr`` -- a trained dictionary (checked: readable, its atoms
  match their recorded sha256, made for the settings ``KEY`` names);
* ``recon-KEY.zarr`` -- the working store of a reconstruction (checked: the
  current layout, its inputs match their recorded digest, every finished
  tile matches its blake2b digest);
* ``report/KEY.json`` (and ``report/KEY.npy`` beside it) -- an experiment record of
  ``codedvideo report`` (checked: the JSON parses and holds a record's fields, ``key`` its name's,
  the array loads).  A JSON that is not such a record is taken as a damaged one only when it names
  its own key or holds nothing (``{}``); a ``.npy`` without a record is not taken as ours.

Besides, ``.NAME.tmp-*`` temporaries that killed runs left behind, and
``dict-KEY.lock`` / ``recon-KEY.lock`` lock files.  Each entry is examined
and removed only while holding its lock (:func:`codedvideo.formats.store.entry_lock`);
an entry a running codedvideo holds is reported ``busy`` and left alone.

Statuses: ``ok``; ``partial`` (a reconstruction with tiles still to compute:
a rerun resumes it); ``broken`` (damaged, or a finished tile whose digest is gone: a rerun rebuilds or recomputes it);
``stale`` (written by another version of codedvideo: never reused);
``leftover`` (a temporary of a killed run); ``busy``.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import re
import time
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from codedvideo.model import doors
from codedvideo.engine.config import parse_size
from codedvideo.formats.atomic import discard, temporary_pattern
from codedvideo.model.errors import InputError
from codedvideo.model.patches import PATCH

if TYPE_CHECKING:
    from codedvideo.engine.config import PipelineConfig

__all__ = ["verify_cache", "clean_cache", "CacheBudget", "parse_size", "REMOVED_WHEN_BROKEN", "RECON_VERSION",
           "content_key", "dictionary_key", "recon_key", "recon_entry", "dictionary_entry"]

_ENTRY = re.compile(r"^(dict|recon)-([0-9a-f]{16})\.zarr$")
_TEMP = re.compile(temporary_pattern(r"(dict|recon)-[0-9a-f]{16}\.zarr"))
_LOCK = re.compile(r"^((dict|recon)-[0-9a-f]{16})\.lock$")
_REPORT = re.compile(r"^([0-9a-f]{16})\.(json|npy)$")
#: What a store of each kind may hold at its top level (a damaged one is still recognised by these).
_MEMBERS = {"dict": {"zarr.json", "atoms"}, "recon": {"zarr.json", "coded", "mask", "still", "volume", "stats", "digest"}}
_KINDS = {"dict": "dictionary", "recon": "reconstruction"}
#: Statuses that ``clean_cache(root, broken_only=True)`` removes.
REMOVED_WHEN_BROKEN = ("broken", "stale", "leftover")


# ----------------------------------------------------------------------------- keys
#: Part of every reconstruction cache key: bump it when the per-tile algorithm changes
#: its output, so that tiles computed by an older version are never reused.
RECON_VERSION = "recon-v14"  # v4: per-tile digests in the working store; v5: still patches across captures;
# v6: the non-local method in three stages (its estimates summed block by block: other roundings);
# v7: equal non-local tiles told apart by all their blocks read (v6 could share one answer between two);
# v8: a non-local group's support capped (nonlocal_sc.group_atoms: max_atoms over 12 gave other supports)
# v9: a patch estimate with more than twice its still answer's energy solved again with the coefficient prior
# v10: that energy from the coefficients (the estimate's own only where a pixel is never open)
# v11: a non-local result under read noise left unprojected (OmpSettings.exact)
# v12: the still test's patches with their temporal profiles (region.still_patches); a pixel never open keeps the
# non-local method's first estimate
# v13: only a pixel with no open pixel within half a patch keeps it (nonlocal_sc.finish)
# v14: the non-local tiles keep the misfit their projection took away beside them (working store layout 4)


def content_key(*parts) -> str:
    """A short sha256 over settings (JSON-able) and arrays."""
    h = hashlib.sha256()
    for part in parts:
        if isinstance(part, np.ndarray):
            h.update(str((part.shape, part.dtype.str)).encode())
            h.update(np.ascontiguousarray(part).tobytes())
        else:
            h.update(json.dumps(part, sort_keys=True, default=str).encode())
    return h.hexdigest()[:16]


def recon_key(coded: np.ndarray, mask: np.ndarray, dictionary_key: str, settings, tile: int, *,
              still: np.ndarray | None = None, first_key: str | None = None) -> str:
    """The key of a capture's working store: its inputs, its dictionary's key (:func:`content_key` of its atoms
    when it has none of its own), its settings (an :class:`~codedvideo.solvers.region.OmpSettings`) and tile,
    its still map, and the key of the store its groups are matched on (``first_key``), each only when given."""
    return content_key(RECON_VERSION, coded, mask, dictionary_key, settings.__dict__, tile,
                       *(() if still is None else (np.asarray(still, np.uint8),)),
                       *(() if first_key is None else (first_key,)))


def recon_entry(cache: str | os.PathLike, key: str) -> Path:
    """The working store of key ``key`` in the cache folder ``cache`` (absolute: a dask.distributed worker
    started in another folder opens it too)."""
    return Path(cache).absolute() / f"recon-{key}.zarr"


def dictionary_entry(cache: str | os.PathLike, key: str) -> Path:
    """The trained dictionary of settings key ``key`` (:func:`dictionary_key`) in the cache folder ``cache``."""
    return Path(cache) / f"dict-{key}.zarr"


def dictionary_key(cfg: PipelineConfig) -> str:
    """The key of the training settings of ``cfg`` (cache entries and shipped dictionaries carry it).

    The user's training videos count by what they hold, not by their names: a video replaced under
    the same name trains again, and the same file under another name or folder reuses the entry.
    """
    settings = dict(cfg.dictionary.model_dump(exclude={"path", "init", "augment"}), frames=cfg.frames, seed=cfg.seed,
                    patch=PATCH)
    if cfg.dictionary.init is not None:  # (only when given: every key made before they existed stays the same)
        settings["init"] = init_dictionary_digest(cfg.dictionary.init, cfg.frames)
    if not cfg.dictionary.augment:
        settings["augment"] = False
    # a user's video counted with how it is read: "working-units" since its values are scaled to its data range
    # (a [0, 1] video trained on its raw values before); the named sources, and so the shipped keys, unchanged
    settings["training"] = [digest if digest == spec else f"working-units:{digest}"
                            for spec, digest in ((s, _source_digest(s)) for s in cfg.dictionary.training)]
    return content_key("dictionary-v1", settings)


def init_dictionary_digest(init: str, frames: int) -> str:
    """The dictionary a K-SVD starts from, by its content (its sha256, checked on load)."""
    from codedvideo.data.shipped import init_dictionary

    return str(init_dictionary(init, frames)[1]["sha256"])


def _source_digest(spec: str) -> str:
    """A training source by its content: a video file's bytes, or a folder's or printf pattern's frames
    in order (their bytes).  Named sources (``synth:train``; ``manifest:ID``, checked against the
    sha256 its manifest lists) and paths that do not exist (training names them) stay as they are."""
    from codedvideo.formats import io as cio

    if spec.startswith(("synth:", "manifest:", "footage:", "skimage:")):
        return spec
    path = Path(spec)
    try:
        files = [path] if path.is_file() else cio.frame_files(path) or []
    except InputError:
        return spec
    h = hashlib.sha256()
    for file in files:
        try:
            with open(file, "rb") as fh:
                h.update(hashlib.file_digest(fh, "sha256").digest())
        except OSError:
            return spec  # unreadable: training says so
    return "sha256:" + h.hexdigest() if files else spec


def verify_cache(root: str | os.PathLike) -> list[dict]:
    """Check every entry of a cache folder.

    Returns
    -------
    list of dict
        One per entry: ``entry`` (its path), ``kind`` (``dictionary``,
        ``reconstruction``, ``report`` or ``temporary``), ``status`` (see the
        module docstring) and ``detail`` (what was found, in words).
    """
    return _scan(Path(root), remove=None)


def clean_cache(root: str | os.PathLike, *, broken_only: bool) -> list[Path]:
    """Remove cache entries: all of them, or (``broken_only``) those that are broken, stale or leftovers.

    Each entry is re-checked and removed while its lock is held, so an entry
    in use by a running codedvideo is never removed, and a run waiting for
    an entry being removed then builds it afresh.  Only codedvideo cache
    entries (see the module docstring) are ever removed; other files and
    folders in ``root`` are left as they are.

    Returns the removed paths.
    """
    statuses = REMOVED_WHEN_BROKEN if broken_only else ("ok", "partial") + REMOVED_WHEN_BROKEN
    removed: list[Path] = []
    _scan(Path(root), remove=(statuses, removed, not broken_only))
    return removed


def _folder_bytes(path: Path) -> int:
    """Bytes of the files under ``path`` (0 when it is gone)."""
    total = 0
    stack = [str(path)]
    while stack:
        try:
            with os.scandir(stack.pop()) as it:
                for e in it:
                    if e.is_dir(follow_symlinks=False):
                        stack.append(e.path)
                    elif e.is_file(follow_symlinks=False):
                        total += e.stat(follow_symlinks=False).st_size
        except OSError:
            continue
    return total


class CacheBudget:
    """Keep a cache's working stores (``recon-KEY.zarr``) within ``budget`` bytes while a job writes more.

    A long coded video makes a working store per capture (at 3840x2160,
    N = 18: about 550 MB each), so a minute of it would need about 1 TB of
    cache.  Each time the job is done with some of its stores
    (:meth:`finished`), the stores least recently used are removed until the
    working stores fit the budget again, each while holding its lock: an entry
    any run holds (this job's stores still in use included) is left alone, and
    dictionaries and report records are never touched.  A removed store costs
    a rerun its tiles (they are computed again, to the same bits), nothing else.
    The stores are sized once when the job starts and then as it finishes them.
    """

    def __init__(self, root: str | os.PathLike, budget: int):
        # absolute, as the job names its stores: a relative cache (the default, cache) is one place either way
        self.root, self.budget = Path(root).absolute(), int(budget)
        self.sizes: dict[Path, int] = {}
        self.used: dict[Path, float] = {}
        self.removed: list[Path] = []
        #: Stores never removed while in this set (what the job will read again; absolute paths).
        self.keep: set[Path] = set()
        if self.root.is_dir():
            for child in self.root.iterdir():
                m = _ENTRY.match(child.name)
                if m and m.group(1) == "recon" and _looks_like_entry(child, "recon"):
                    self.sizes[child] = _folder_bytes(child)
                    with contextlib.suppress(OSError):
                        self.used[child] = child.stat().st_mtime

    def total(self) -> int:
        """Bytes of the working stores as last sized."""
        return sum(self.sizes.values())

    def finished(self, entries, busy=()) -> list[Path]:
        """The job is done with ``entries`` (working stores, still locked by it or not): size them, mark them
        used now, and remove stores, least recently used first, until the rest fit the budget; never one in
        ``busy`` (the entries the job holds: on a file system whose locks are per process, NFS, asking for
        their lock again would not show them in use).  Returns the stores removed now."""
        from codedvideo.formats.store import entry_lock

        in_use = {Path(b).absolute() for b in busy}
        now = max(time.time(), max(self.used.values(), default=0.0))
        for entry in entries:
            entry = Path(entry).absolute()
            now += 1e-6  # (in the order given: the first done is the first to go)
            self.sizes[entry] = _folder_bytes(entry)
            self.used[entry] = now
        removed, total = [], self.total()
        for entry in sorted(self.sizes, key=lambda e: self.used.get(e, 0.0)):
            if total <= self.budget:
                break
            if entry in self.keep or entry in in_use:
                continue
            with entry_lock(entry, blocking=False) as held:
                if not held:  # in use (by this job or another run): kept
                    continue
                if os.path.lexists(entry) and _looks_like_entry(entry, "recon"):
                    _remove_entry(entry, removed)
            total -= self.sizes.pop(entry)
            self.used.pop(entry, None)
        self.removed += removed
        return removed


def working_store_bytes(frames: int, height: int, width: int) -> int:
    """About the bytes of one capture's working store: its volume (float32) and its inputs (coded float32,
    mask and still map uint8), before compression (which shrinks a volume by about a seventh)."""
    return frames * height * width * 5 + height * width * 5


def cache_room_problem(cache: str | os.PathLike, stores: int, frames: int, height: int, width: int,
                       budget: int | None, in_use: int = 3) -> str | None:
    """Why the disk under ``cache`` may not hold a job's ``stores`` working stores (None: it may), for a
    warning before any work: all of them (with a budget: at most the budget and the ``in_use`` stores a
    job holds at once beside it) against the disk's free bytes."""
    import shutil

    each = working_store_bytes(frames, height, width)
    need = stores * each if budget is None else min(stores * each, budget + in_use * each)
    place = Path(cache).absolute()
    while not place.exists() and place != place.parent:  # (the cache is made when the first entry is)
        place = place.parent
    try:
        free = shutil.disk_usage(place).free
    except OSError:
        return None
    if need <= free:
        return None
    option = doors.name("cache_budget")
    advice = (f"give {option} below the free space" if budget is None else f"give a smaller {option}")
    return (f"cache {cache}: this job's working stores may take about {_human(need)} ({stores} "
            f"{'store' if stores == 1 else 'stores'} of about {_human(each)}), and its disk has "
            f"{_human(free)} free; {advice}, or a cache on a larger disk")


def _human(size: float) -> str:
    """Bytes as a person reads them: ``"3.2 GiB"``, ``"15 KiB"``, ``"512 B"``."""
    value = size
    for unit in ("B", "KiB", "MiB", "GiB"):
        if value < 1024:
            return f"{value:.0f} {unit}" if unit == "B" or value >= 10 else f"{value:.1f} {unit}"
        value /= 1024
    return f"{value:.1f} TiB"


# ----------------------------------------------------------------------------- scanning
def _scan(root: Path, remove) -> list[dict]:
    from codedvideo.formats.store import entry_lock

    if not root.is_dir():
        raise InputError(f"cache {root}: {'not a folder' if root.exists() else 'no such folder'}")
    names: dict[str, dict] = {}  # "recon-KEY" -> {"entry": Path | None, "temps": [...], "lock": Path | None}
    for child in sorted(root.iterdir()):
        for pattern, slot in ((_ENTRY, "entry"), (_TEMP, "temps"), (_LOCK, "lock")):
            m = pattern.match(child.name)
            if not m:
                continue
            stem = m.group(1).removesuffix(".zarr") if slot != "entry" else f"{m.group(1)}-{m.group(2)}"
            rec = names.setdefault(stem, dict(entry=None, temps=[], lock=None))
            if slot == "temps":
                rec["temps"].append(child)
            else:
                rec[slot] = child
    records: list[dict] = []
    for stem, found in names.items():
        prefix = stem.split("-", 1)[0]
        entry = root / f"{stem}.zarr"
        if found["entry"] is not None and not _looks_like_entry(entry, prefix):
            found["entry"] = None  # a user's folder or file that happens to have the name: never touched
        if found["entry"] is None and not found["temps"] and (remove is None or found["lock"] is None):
            continue  # a bare lock file (removed by clean_cache below), or nothing of ours
        with entry_lock(entry, blocking=False) as held:
            if not held:
                if found["entry"] is not None:
                    records.append(_record(entry, _KINDS[prefix], "busy",
                                           "in use by a running codedvideo; not checked"))
                continue
            if found["entry"] is not None:
                status, detail = (_check_dictionary if prefix == "dict" else _check_reconstruction)(entry)
                records.append(_record(entry, _KINDS[prefix], status, detail))
                if remove is not None and status in remove[0]:
                    _remove_entry(entry, remove[1])
            for tmp in found["temps"]:
                records.append(_record(tmp, "temporary", "leftover",
                                       f"left by a run that was stopped while writing {entry.name}"))
                if remove is not None and "leftover" in remove[0]:
                    _remove_entry(tmp, remove[1], lock=False)
            if remove is not None and found["lock"] is not None and not os.path.lexists(entry):
                from codedvideo.formats.store import lock_path

                Path(lock_path(entry)).unlink(missing_ok=True)  # no entry left to lock
    records += _scan_report(root / "report", remove)
    return records


def _record(entry: Path, kind: str, status: str, detail: str) -> dict:
    return dict(entry=str(entry), kind=kind, status=status, detail=detail)


def _looks_like_entry(path: Path, prefix: str) -> bool:
    """A folder written by codedvideo: its kind says so, or (damaged metadata) it holds only the members of one."""
    if path.is_symlink() or not path.is_dir():
        return False
    try:
        meta = json.loads((path / "zarr.json").read_text())
    except (OSError, ValueError):
        meta = None  # none, or damaged: the members decide
    if isinstance(meta, dict):  # metadata that reads: its kind decides (a user's own store, or a file, is not ours)
        attrs = meta.get("attributes")
        return isinstance(attrs, dict) and attrs.get("kind") == {
            "dict": "codedvideo-dictionary", "recon": "codedvideo-reconstruction"}[prefix]
    # damaged or missing metadata: only the members of an entry, each a folder (an array), or nothing at all
    # (an entry emptied by hand)
    members = list(path.iterdir())
    return all(p.name in _MEMBERS[prefix] and (p.name == "zarr.json" or (p.is_dir() and not p.is_symlink()))
               for p in members)


def _remove_entry(path: Path, removed: list, *, lock: bool = True) -> None:
    from codedvideo.formats.store import remove_locked_entry

    if lock:
        remove_locked_entry(path)  # we hold its lock
    else:
        discard(path)
    removed.append(path)


# ----------------------------------------------------------------------------- checks
def _check_dictionary(path: Path) -> tuple[str, str]:
    from codedvideo.formats.store import load_dictionary

    try:
        D, meta = load_dictionary(path)
    except InputError as exc:
        return "broken", str(exc)
    key = _ENTRY.match(path.name).group(2)
    if meta.get("settings_key") != key:
        return "broken", f"made for settings {meta.get('settings_key')!r}, its name says {key}"
    return "ok", f"{D.shape[1]} atoms, checksum matches"


def _check_reconstruction(path: Path) -> tuple[str, str]:
    from codedvideo.formats.store import WORKSTORE_FORMAT, WORKSTORE_KIND, WorkStore, inputs_digest, workstore_problem

    try:
        store = WorkStore(path, mode="r")
        attrs = dict(store.group.attrs)
    except Exception as exc:  # zarr raises its own types for damaged metadata
        return "broken", f"unreadable ({type(exc).__name__}: {exc})"
    if attrs.get("kind") == WORKSTORE_KIND and (attrs.get("format_version") != WORKSTORE_FORMAT
                                               or attrs.get("version") != RECON_VERSION):
        return "stale", (f"written by another codedvideo (layout {attrs.get('format_version')!r}, "
                         f"{attrs.get('version') or 'recon-v3 or older'}); never reused")
    problem = workstore_problem(store.group)
    if problem:
        return "broken", problem
    if attrs.get("key") != _ENTRY.match(path.name).group(2):
        return "broken", f"holds the entry {attrs.get('key')!r}, its name says {_ENTRY.match(path.name).group(2)}"
    try:
        coded = np.asarray(store.group["coded"][...])
        mask = np.asarray(store.group["mask"][...])
        still = np.asarray(store.group["still"][...])
    except Exception as exc:
        return "broken", f"inputs unreadable ({type(exc).__name__}: {exc})"
    if inputs_digest(coded, mask, still) != attrs.get("inputs_digest"):
        return "broken", "inputs do not match their recorded digest"
    try:
        ok, damaged, *_ = store.read_verified(store.tiles())
        # of the damaged, a tile whose results are written but whose digest is gone (deleted, or a run killed
        # between the two writes) cannot be verified: said apart from one that fails its checksum
        unverifiable = damaged & ~store._rows("digest", 0).any(axis=1)
    except Exception as exc:
        return "broken", f"tiles unreadable ({type(exc).__name__}: {exc})"
    n = len(ok)
    if (damaged & ~unverifiable).any():
        bad = np.flatnonzero(damaged & ~unverifiable).tolist()
        return "broken", f"tiles {bad[:20]}{' ...' if len(bad) > 20 else ''} of {n} fail their checksum"
    if unverifiable.any():
        bad = np.flatnonzero(unverifiable).tolist()
        return "broken", (f"tiles {bad[:20]}{' ...' if len(bad) > 20 else ''} of {n} have results but no digest "
                          "(deleted), so they cannot be verified")
    if not ok.all():
        return "partial", f"{int(ok.sum())} of {n} tiles done and verified; a rerun computes the rest"
    return "ok", f"{n} tiles, every one matches its checksum"


#: Fields of every report record (its settings and scores: the report's tables and figures read them).
REPORT_FIELDS = ("key", "scene", "frames", "code", "bump", "sigma", "method", "psnr", "ssim", "seconds")


def report_record_problem(record, key: str) -> str | None:
    """What makes a parsed ``report/KEY.json`` record unusable (None: nothing)."""
    if not isinstance(record, dict):
        return "not a JSON object"
    missing = [name for name in REPORT_FIELDS if name not in record]
    if missing:
        return f"no {', '.join(missing)}"
    if record["key"] != key:
        return f"its key {record['key']!r} is not its file's"
    return None


def _report_json(path: Path, key: str) -> tuple[str, str] | None:
    """The status of ``report/KEY.json`` as codedvideo's record, or None when it is someone else's file.

    Ours: a record the check passes, or a damaged one that names its own key (``"key": KEY``, even cut short)
    or holds nothing (``{}``, an empty file: nothing to lose).  A user's JSON of that name was removed when
    it shared a field with a record (its scene and psnr, say)."""
    try:
        text = path.read_text()
    except (OSError, ValueError):
        return None  # unreadable: nothing says it is ours
    try:
        record = json.loads(text)
    except ValueError as exc:
        return ("broken", f"record does not parse ({exc})") if not text.strip() or f'"key": "{key}"' in text \
            else None
    problem = report_record_problem(record, key)
    if problem is None:
        return "ok", "record parses"
    if record == {} or (isinstance(record, dict) and record.get("key") == key):
        return "broken", f"record is not a report record ({problem})"
    return None


def _scan_report(folder: Path, remove) -> list[dict]:
    """``report/KEY.json`` records (and their ``KEY.npy`` volumes); written atomically, so no lock."""
    if not folder.is_dir():
        return []
    keys: dict[str, dict] = {}
    for child in sorted(folder.iterdir()):
        m = _REPORT.match(child.name)
        if m and child.is_file() and not child.is_symlink():
            keys.setdefault(m.group(1), {})[m.group(2)] = child
    records = []
    for key, files in keys.items():
        found = _report_json(files["json"], key) if "json" in files else None
        if found is None:
            continue  # someone else's JSON, or a .npy with no record of ours beside it: left alone
        status, detail = found
        if status == "ok" and "npy" in files:
            try:
                np.load(files["npy"], mmap_mode="r", allow_pickle=False)
                detail = "record parses, volume loads"
            except (OSError, ValueError) as exc:
                status, detail = "broken", f"volume does not load ({exc})"
        records.append(_record(files["json"], "report", status, detail))
        if remove is not None and status in remove[0]:
            for path in files.values():
                path.unlink(missing_ok=True)
                remove[1].append(path)
    return records
