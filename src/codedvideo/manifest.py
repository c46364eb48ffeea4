"""``data_manifest``: every dataset codedvideo uses, with its checksum, split and licence.

A tab-separated file (UTF-8) whose first line is the header::

    id  path_or_generator  frames  split  sha256  source  licence

- ``path_or_generator``: ``skimage:FILE`` (a photograph inside the installed scikit-image's
  ``skimage/data`` folder), ``synth:NAME`` (a scene of :mod:`codedvideo.synth`, or
  ``synth:train``, its training set), or a file path (relative to the manifest's folder).
- ``frames``: a positive integer (1 for a photograph), or ``any`` (or blank) for a generator.
- ``split``: ``train`` or ``test``. A photograph is in one split only; a generated scene is
  in the split of the photographs it is made from.
- ``sha256``: 64 lowercase hex digits: of the file's bytes; for a generator, of the
  little-endian float32 C-order bytes of the array it generates with the reference settings
  (:data:`REFERENCE`: ``make_scene(NAME, frames=8, size=(256, 256), seed=0)``;
  :data:`TRAIN_REFERENCE` for ``synth:train``: the 16 clips of
  ``training_videos(frames=8, count=16, size=(64, 64), seed=0)`` stacked), so that a change
  of the generator or of scipy/numpy that alters the data is detected.

Blank lines and lines starting with ``#`` are ignored. Every problem is an
:class:`~codedvideo.errors.InputError` naming the manifest, the line and the id, e.g.
``data_manifest line 12 (camera): sha256 mismatch for /.../camera.png: expected ab12..., got cd34...``.
``write_manifest()`` regenerates the file after a deliberate change (``python -m
codedvideo.manifest [PATH]``).
"""

from __future__ import annotations

import functools
import hashlib
import os
import re
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable

import numpy as np

from .errors import InputError

HEADER: tuple[str, ...] = ("id", "path_or_generator", "frames", "split", "sha256", "source", "licence")
SPLITS: tuple[str, ...] = ("train", "test")

#: the repository's manifest (next to ``src/``).
DEFAULT_PATH: Path = Path(__file__).resolve().parents[2] / "data_manifest"

#: settings of the generated arrays whose sha256 the ``synth:NAME`` rows record.
REFERENCE = {"frames": 8, "size": (256, 256), "seed": 0}
TRAIN_REFERENCE = {"frames": 8, "count": 16, "size": (64, 64), "seed": 0}

SOURCE_SKIMAGE = "scikit-image data (skimage/data)"

#: short licence of each photograph, from the docstrings of skimage.data (scikit-image 0.26);
#: skimage/data/README.txt states none.
PHOTO_LICENCES: dict[str, str] = {
    "astronaut": "public domain (NASA; no known copyright restrictions)",
    "chelsea": "CC0 (Stefan van der Walt)",
    "coffee": "CC0 (Rachel Michetti)",
    "rocket": "public domain (SpaceX)",
    "brick": "CC0 (CC0Textures Bricks25)",
    "grass": "CC0 (linolafett, DeviantArt)",
    "gravel": "CC0 (CC0Textures Gravel04)",
    "motorcycle_left": "not stated: Middlebury 2014 stereo (Scharstein et al., GCPR 2014); see skimage.data.stereo_motorcycle",
    "hubble_deep_field": "public domain (NASA)",
    "retina": "CC0 1.0 (Mikael Haggstrom, Wikimedia Commons)",
    "camera": "CC0 (Lav Varshney)",
    "coins": "no known copyright restrictions (Brooklyn Museum)",
    "moon": "not stated; see skimage.data.moon",
    "text": "public domain (Wikipedia File:Corner.png)",
    "page": "not stated; see skimage.data.page",
    "cell": "CC0 (qpformat example data)",
}

_SHA = re.compile(r"[0-9a-f]{64}")
_ID = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.+-]*")


@dataclass(frozen=True)
class Entry:
    """One row of the manifest (the columns as written), with where it was read from."""

    id: str
    path_or_generator: str
    frames: str
    split: str
    sha256: str
    source: str
    licence: str
    line: int = 0
    manifest: str = "data_manifest"

    @property
    def kind(self) -> str:
        """``skimage``, ``synth`` or ``file``."""
        if self.path_or_generator.startswith("skimage:"):
            return "skimage"
        if self.path_or_generator.startswith("synth:"):
            return "synth"
        return "file"

    @property
    def name(self) -> str:
        """The part after ``skimage:`` / ``synth:`` (the path for a file row)."""
        return self.path_or_generator.split(":", 1)[1] if self.kind != "file" else self.path_or_generator

    @property
    def photo(self) -> str | None:
        """For a ``skimage:`` row, the photograph's name (the file name without its suffix)."""
        return Path(self.name).stem if self.kind == "skimage" else None

    def where(self) -> str:
        return f"{self.manifest} line {self.line} ({self.id})"


def _scene_photos() -> dict[str, tuple[str, ...]]:
    from . import synth

    names = ("train", *synth.NAMED_SCENES, *synth.TEST_SCENES)
    return {n: synth.scene_photos(n) for n in names}


#: photographs each named synthetic scene (and ``train``) is made of.
SCENE_PHOTOS: dict[str, tuple[str, ...]] = _scene_photos()


# ----------------------------------------------------------------------------- reading
def _locate(path: str | Path) -> Path:
    p = Path(path)
    if not p.exists() and not p.is_absolute() and (DEFAULT_PATH.parent / p).exists():
        return DEFAULT_PATH.parent / p  # "data_manifest" from outside the repository root
    return p


def load_manifest(path: str | Path = "data_manifest") -> list[Entry]:
    """Read and validate a manifest: the header, every row, unique ids, disjoint splits."""
    p = _locate(path)
    label = str(path)
    try:
        text = p.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise InputError(f"{label}: manifest not found") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"{label}: cannot be read as UTF-8 text ({exc.__class__.__name__})") from None
    lines = text.splitlines()
    if not lines:
        raise InputError(f"{label} line 1: empty manifest, expected the header {' '.join(HEADER)}")
    header = tuple(c.strip() for c in lines[0].split("\t"))
    if header != HEADER:
        missing = [c for c in HEADER if c not in header]
        extra = [c for c in header if c not in HEADER]
        detail = "; ".join(x for x in (
            f"missing column(s) {', '.join(missing)}" if missing else "",
            f"unknown column(s) {', '.join(extra)}" if extra else "",
            "columns out of order" if not missing and not extra else "") if x)
        raise InputError(f"{label} line 1: header must be the tab-separated columns {' '.join(HEADER)} ({detail})")
    entries: list[Entry] = []
    first_line: dict[str, int] = {}
    for n, raw in enumerate(lines[1:], start=2):
        if not raw.strip() or raw.lstrip().startswith("#"):
            continue
        cols = [c.strip() for c in raw.split("\t")]
        if len(cols) != len(HEADER):
            raise InputError(f"{label} line {n}: expected {len(HEADER)} tab-separated columns, got {len(cols)}")
        e = Entry(*cols, line=n, manifest=label)
        _check_row(e)
        if e.id in first_line:
            raise InputError(f"{label} line {n}: duplicate id {e.id!r} (first on line {first_line[e.id]})")
        first_line[e.id] = n
        entries.append(e)
    check_splits(entries)
    return entries


def _check_row(e: Entry) -> None:
    where = e.where()
    if not _ID.fullmatch(e.id):
        raise InputError(f"{e.manifest} line {e.line}: malformed id {e.id!r} (letters, digits, _ . + -)")
    if e.split not in SPLITS:
        raise InputError(f"{where}: unknown split {e.split!r} (expected train or test)")
    if not _SHA.fullmatch(e.sha256):
        raise InputError(f"{where}: malformed sha256 {e.sha256!r} (expected 64 lowercase hex digits)")
    if not e.path_or_generator:
        raise InputError(f"{where}: empty path_or_generator")
    if e.kind == "skimage":
        if not e.name or "/" in e.name or "\\" in e.name or e.name.startswith("."):
            raise InputError(f"{where}: {e.path_or_generator!r} must name a file directly inside skimage/data")
    if e.kind == "synth" and not e.name:
        raise InputError(f"{where}: {e.path_or_generator!r} names no generator")
    if e.kind == "synth":
        if e.frames not in ("", "any") and not e.frames.isdigit():
            raise InputError(f"{where}: frames must be a positive integer or 'any', got {e.frames!r}")
    elif not (e.frames.isdigit() and int(e.frames) >= 1):
        raise InputError(f"{where}: frames must be a positive integer, got {e.frames!r}")


# ----------------------------------------------------------------------------- checksums
def file_sha256(path: str | Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def array_sha256(a: np.ndarray) -> str:
    """sha256 of an array's little-endian float32 C-order bytes."""
    return hashlib.sha256(np.ascontiguousarray(a, dtype="<f4").tobytes()).hexdigest()


def generate(name: str) -> np.ndarray:
    """The reference array of generator ``name`` (``synth:NAME``) whose sha256 the manifest records."""
    from . import synth

    if name == "train":
        r = TRAIN_REFERENCE
        return np.stack(synth.training_videos(frames=r["frames"], count=r["count"], size=r["size"], seed=r["seed"]))
    return synth.make_scene(name, frames=REFERENCE["frames"], size=REFERENCE["size"], seed=REFERENCE["seed"])


def _reference_label(name: str) -> str:
    if name == "train":
        r = TRAIN_REFERENCE
        return f"synth:train (count={r['count']}, frames={r['frames']}, {r['size'][0]}x{r['size'][1]}, seed {r['seed']})"
    r = REFERENCE
    return f"synth:{name} (frames={r['frames']}, {r['size'][0]}x{r['size'][1]}, seed {r['seed']})"


def resolve(entry: str | Entry, path: str | Path = "data_manifest") -> Path | str:
    """What an entry (or the id of one in the manifest at ``path``) refers to: the file's
    path, or the generator spec ``synth:NAME``."""
    e = lookup(entry, path) if isinstance(entry, str) else entry
    if e.kind == "skimage":
        from .synth import data_dir

        return data_dir() / e.name
    if e.kind == "synth":
        return e.path_or_generator
    p = Path(e.name)
    return p if p.is_absolute() else _locate(e.manifest).parent / p


def verify(entry: Entry) -> Path | None:
    """Check an entry's sha256; return its file (None for a generator). InputError on a
    missing file, an unknown generator or a mismatch."""
    target = resolve(entry)
    if isinstance(target, str):
        from . import synth

        if entry.name != "train":
            synth.scene_photos(entry.name)  # unknown scene -> InputError
        try:
            got = array_sha256(generate(entry.name))
        except InputError as exc:
            raise InputError(f"{entry.where()}: {exc}") from None
        label = _reference_label(entry.name)
    else:
        if not target.is_file():
            raise InputError(f"{entry.where()}: file {target} is missing")
        got = file_sha256(target)
        label = str(target)
    if got != entry.sha256:
        raise InputError(f"{entry.where()}: sha256 mismatch for {label}: expected {entry.sha256}, got {got}")
    return None if isinstance(target, str) else target


def verify_all(path: str | Path = "data_manifest") -> list[Entry]:
    """Load, check and verify every entry of a manifest."""
    entries = load_manifest(path)
    for e in entries:
        verify(e)
    return entries


def lookup(id_: str, path: str | Path = "data_manifest") -> Entry:
    """The entry ``id_`` of the manifest at ``path``."""
    for e in load_manifest(path):
        if e.id == id_:
            return e
    raise InputError(f"{path}: no entry with id {id_!r}")


@functools.lru_cache(maxsize=None)
def _verified(path: str, mtime_ns: int, ids: tuple[str, ...]) -> None:
    by_id = {e.id: e for e in load_manifest(path)}
    for i in ids:
        if i not in by_id:
            raise InputError(f"{path}: no entry with id {i!r}")
        verify(by_id[i])


def verify_ids(ids: Iterable[str], path: str | Path = "data_manifest") -> None:
    """Verify the entries ``ids`` (e.g. the photographs a scene uses), once per process for an
    unchanged manifest."""
    p = _locate(path)
    try:
        mtime = p.stat().st_mtime_ns
    except OSError:
        raise InputError(f"{path}: manifest not found") from None
    _verified(str(p), mtime, tuple(sorted(set(ids))))


# ----------------------------------------------------------------------------- splits
def check_splits(entries: list[Entry]) -> None:
    """Training and test data never overlap: a photograph (by id or by file) is in one split
    only, it is in the split :mod:`codedvideo.synth` uses it for, and a generated scene is in
    the split of every photograph it is made from."""
    from . import synth

    photo_split: dict[str, tuple[str, Entry]] = {}
    for e in entries:
        if e.kind != "skimage":
            continue
        for key in {e.id, e.photo}:
            prev = photo_split.setdefault(key, (e.split, e))
            if prev[0] != e.split:
                raise InputError(f"{e.where()}: photo {key!r} is in both the train and the test split "
                                 f"(line {prev[1].line} has it in {prev[0]})")
        want = "train" if e.photo in synth.TRAIN_PHOTOS else "test" if e.photo in synth.TEST_PHOTOS else None
        if want and want != e.split:
            raise InputError(f"{e.where()}: photo {e.photo!r} is marked {e.split} but codedvideo.synth "
                             f"uses it for {want}")
    for e in entries:
        if e.kind != "synth":
            continue
        try:
            used = synth.scene_photos(e.name)
        except InputError as exc:
            raise InputError(f"{e.where()}: {exc}") from None
        for name in used:
            split = photo_split[name][0] if name in photo_split else (
                "train" if name in synth.TRAIN_PHOTOS else "test")
            if split != e.split:
                raise InputError(f"{e.where()}: scene {e.path_or_generator} is marked {e.split} but uses "
                                 f"{split} photo {name!r}")


# ----------------------------------------------------------------------------- writing
def manifest_rows() -> list[list[str]]:
    """The rows of the manifest of the embedded data, checksums computed now."""
    from . import synth

    rows: list[list[str]] = []
    for split, photos in (("train", synth.TRAIN_PHOTOS), ("test", synth.TEST_PHOTOS)):
        for name in photos:
            p = synth.photo_path(name)
            rows.append([name, f"skimage:{p.name}", "1", split, file_sha256(p), SOURCE_SKIMAGE,
                         PHOTO_LICENCES.get(name, "see skimage/data/README.txt")])
    for scene in ("train", *synth.NAMED_SCENES, *synth.TEST_SCENES):
        photos = synth.scene_photos(scene)
        split = "train" if scene == "train" else "test"
        ref = TRAIN_REFERENCE if scene == "train" else REFERENCE
        source = (f"codedvideo.synth from scikit-image photos {', '.join(photos) if scene != 'train' else 'TRAIN_PHOTOS'}"
                  f"; sha256 of float32 frames={ref['frames']} {ref['size'][0]}x{ref['size'][1]} seed={ref['seed']}"
                  + (f" count={ref['count']}" if scene == "train" else ""))
        rows.append([f"synth-{scene}", f"synth:{scene}", "any", split, array_sha256(generate(scene)), source,
                     "derived from its photographs (see their rows)"])
    return rows


def write_manifest(path: str | Path = DEFAULT_PATH) -> Path:
    """(Re)write the manifest of the embedded data; a developer runs this after a deliberate
    change of the photographs or of the generator."""
    path = Path(path)
    text = "\n".join("\t".join(r) for r in [list(HEADER), *manifest_rows()]) + "\n"
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", dir=path.parent or ".")
    try:
        with os.fdopen(fd, "w", encoding="utf-8", newline="\n") as fh:
            fh.write(text)
        os.chmod(tmp, 0o644)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    _verified.cache_clear()
    return path


if __name__ == "__main__":  # pragma: no cover
    print(write_manifest(sys.argv[1] if len(sys.argv) > 1 else DEFAULT_PATH))
