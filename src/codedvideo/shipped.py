"""The dictionaries shipped with codedvideo: reconstruct and `make run` work in seconds, with no training.

Each is the dictionary `codedvideo train --frames N` makes with its defaults
(K-SVD, 512 atoms, 80000 samples, 20 iterations, sparsity 6, 144 clips of
synthetic motion of the training photographs, seed 0), stored as a Zarr
dictionary store zipped into one file, ``codedvideo/data/dict-N{N}.zip``, and listed in
``data_manifest`` (id ``dict-n{N}``) with the sha256 of its atoms and the
command that made it.  `make train` regenerates them.

A shipped dictionary is used where training would give it: by
:func:`codedvideo.stages.train_dictionary` when the settings key matches
(so a pipeline.yaml with the default ``dictionary:`` section trains nothing),
and by ``reconstruct`` without ``--dictionary``.
"""

from __future__ import annotations

import json
from pathlib import Path

from . import manifest

DATA = Path(__file__).resolve().parent / "data"


def path_for(frames: int) -> Path:
    return DATA / f"dict-N{frames}.zip"


def manifest_id(frames: int) -> str:
    return f"dict-n{frames}"


def available() -> list[int]:
    """The N of every shipped dictionary (those listed in data_manifest whose store is present)."""
    ids = {e.id for e in manifest.load_manifest()}
    return sorted(int(p.name[6:-4]) for p in DATA.glob("dict-N*.zip") if manifest_id(int(p.name[6:-4])) in ids)


def train_command(frames: int) -> str:
    """The command that makes the dictionary for ``frames`` sub-frames with the defaults."""
    return f"codedvideo train --frames {frames} --output dict-N{frames}.zarr"


def settings_key(frames: int) -> str | None:
    """The training settings key recorded in the shipped store (None when there is none)."""
    import zipfile

    try:
        with zipfile.ZipFile(path_for(frames)) as z:
            return json.loads(z.read("zarr.json"))["attributes"].get("settings_key")
    except (OSError, ValueError, KeyError, zipfile.BadZipFile):
        return None


def verified(frames: int) -> Path | None:
    """The shipped dictionary for ``frames``, checked against data_manifest; None when none is shipped."""
    import hashlib

    from .errors import InputError
    from .store import load_dictionary

    if frames not in available():
        return None
    path, entry = path_for(frames), manifest.lookup(manifest_id(frames))
    D, _ = load_dictionary(path)  # its own recorded sha256 too
    if hashlib.sha256(D.tobytes()).hexdigest() != entry.sha256:
        raise InputError(f"shipped dictionary {path}: its atoms do not match {entry.where()} (reinstall codedvideo)")
    return path


def matching(frames: int, key: str) -> Path | None:
    """The shipped dictionary that training with settings ``key`` would make, if any (verified)."""
    if settings_key(frames) != key:
        return None
    return verified(frames)
