"""The dictionaries shipped with codedvideo: reconstruct and `make run` work in seconds, with no training.

Each is the dictionary `codedvideo train --frames N` makes with its defaults
(K-SVD, 512 atoms, 80000 samples, 20 iterations, sparsity 6, 144 clips of
synthetic motion of the training photographs, seed 0), stored as a Zarr
dictionary store zipped into one file, ``codedvideo/data/dict-N{N}.zip``, and listed in
``data_manifest`` (id ``dict-n{N}``) with the sha256 of its atoms and the
command that made it.  `make train` regenerates them.

A shipped dictionary is used where training would give it: by
:func:`codedvideo.engine.training.train_dictionary` when the settings key matches
(so a pipeline.yaml with the default ``dictionary:`` section trains nothing),
and by ``reconstruct`` without ``--dictionary``.
"""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path

import numpy as np

from codedvideo.data import manifest
from codedvideo.model.errors import ConfigError, InputError
from codedvideo.formats.atomic import atomic_output
from codedvideo.formats.store import check_dictionary, load_dictionary
from codedvideo.solvers.dictionaries import KSVD_ATOMS, KSVD_ITERATIONS, KSVD_SAMPLES, KSVD_SPARSITY

#: The folder of the shipped dictionaries (this package's own folder, installed as package data).
DATA = Path(__file__).resolve().parent


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
    if frames not in available():
        return None
    path, entry = path_for(frames), manifest.lookup(manifest_id(frames))
    D, _ = load_dictionary(path)  # its own recorded sha256 too
    if hashlib.sha256(D.tobytes()).hexdigest() != entry.sha256:
        raise InputError(f"shipped dictionary {path}: its atoms do not match {entry.where()} (reinstall codedvideo)")
    return path


def required(frames: int, where: str, how: str) -> Path:
    """The shipped dictionary for ``frames`` (verified), or an :class:`InputError` naming ``where`` the need
    arose, the N that are shipped and ``how`` to give a dictionary of one's own (besides training it)."""
    found = verified(frames)
    if found is None:
        have = ", ".join(map(str, available())) or "none"
        ask = missing_frame_question(frames)
        raise InputError(f"{where}: no dictionary is shipped for N = {frames} (shipped: N = {have}); "
                         + (f"{ask} Otherwise, train one" if ask else "train one") + f" with {how}")
    return found


def missing_frame_question(frames: int) -> str:
    """Where a dictionary is shipped for one or two sub-frames more than ``frames``, whether the mask lost some
    (a mask folder missing an image reads as a code of fewer sub-frames); empty otherwise."""
    from codedvideo.model.codes import short_of

    near = min((k for k in available() if 0 < k - frames <= 2), default=0)
    return f"the mask has {frames} sub-frames; if the code has {near}, {short_of(frames, near)}" if near else ""


def matching(frames: int, key: str) -> Path | None:
    """The shipped dictionary that training with settings ``key`` would make, if any (verified)."""
    if settings_key(frames) != key:
        return None
    return verified(frames)


def write_manifests() -> list[Path]:
    """Regenerate the package's manifest and, in a checkout, the project's ``data_manifest`` (same rows)."""
    return [write_manifest(p) for p in (manifest.DEFAULT_PATH, manifest.PROJECT_PATH) if p == manifest.DEFAULT_PATH or p.exists()]


def write_manifest(path: str | Path = manifest.DEFAULT_PATH) -> Path:
    """Regenerate the manifest of the embedded data (developers run this after a deliberate change)."""
    from codedvideo.data.synth import TEST_PHOTOS, TRAIN_PHOTOS, photo_path

    lines = ["\t".join(manifest.HEADER)]
    for split, photos in (("train", TRAIN_PHOTOS), ("test", TEST_PHOTOS)):
        for name in photos:
            p = photo_path(name)
            lines.append("\t".join([name, f"skimage:{p.name}", "1", split, manifest._file_digest(p),
                                    "scikit-image data (skimage/data)", manifest.PHOTO_LICENCES[name]]))
    for id_, (rel, frames, source, licence) in manifest.PACKAGE_CLIPS.items():
        digest = manifest._file_digest(manifest._package_file(rel))
        lines.append("\t".join([id_, f"pkg:{rel}", str(frames), "test", digest, source, licence]))
    for scene in manifest.SCENE_PHOTOS:
        lines.append("\t".join([f"synth-{scene}", f"synth:{scene}", "8", "test", manifest._synth_digest(scene, 8),
                                "codedvideo.data.synth from test photographs", "as its photographs"]))
    lines += shipped_rows(Path(path).parent)
    with atomic_output(path) as tmp:
        tmp.write_text("\n".join(lines) + "\n")
    return Path(path)


def shipped_rows(root: Path) -> list[str]:
    """data_manifest rows of the shipped dictionaries present under ``codedvideo/data``."""
    rows = []
    for store in sorted(DATA.glob("dict-N*.zip"), key=lambda p: int(p.name[6:-4])):
        frames = int(store.name[6:-4])
        D, _ = load_dictionary(store)
        rows.append("\t".join([manifest_id(frames), os.path.relpath(store, root), str(frames), "model",
                                hashlib.sha256(D.tobytes()).hexdigest(),
                                f"{train_command(frames)} (defaults: K-SVD {KSVD_ATOMS} atoms, {KSVD_SAMPLES} samples, "
                                f"{KSVD_ITERATIONS} iterations, sparsity {KSVD_SPARSITY}, 144 clips of synth:train, "
                                "max speed 4, seed 0)",
                                "as its training photographs (split train)"]))
    return rows


def init_dictionary(init: str, frames: int) -> tuple[np.ndarray, dict]:
    """The dictionary a K-SVD starts from (``dictionary.init``): ``shipped`` (the one shipped for N) or a
    store, checked against N."""
    path = verified(frames) if init == "shipped" else Path(init)
    if path is None:
        raise ConfigError(f"dictionary.init shipped (--init): no dictionary is shipped for N = {frames} "
                          f"(N = {', '.join(map(str, available()))} are)")
    D, meta = load_dictionary(path)
    check_dictionary(meta, frames, path, D, needs="training for")
    return D, meta
