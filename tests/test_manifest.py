import shutil

import pytest

from codedvideo import manifest, synth
from codedvideo.errors import InputError


def test_repository_manifest_loads_and_verifies():
    entries = manifest.load_manifest()
    assert {e.id for e in entries} >= set(synth.TRAIN_PHOTOS) | set(synth.TEST_PHOTOS) | {"synth-default"}
    for e in entries:
        manifest.verify(e)


def test_splits_are_disjoint():
    entries = manifest.load_manifest()
    train = {e.id for e in entries if e.split == "train"}
    test = {e.id for e in entries if e.split == "test"}
    assert not train & test
    assert set(synth.TRAIN_PHOTOS) <= train and set(synth.TEST_PHOTOS) <= test


def _copy(tmp_path):
    dst = tmp_path / "data_manifest"
    shutil.copy(manifest.DEFAULT_PATH, dst)
    return dst


def test_tampered_checksum_is_detected(tmp_path):
    path = _copy(tmp_path)
    lines = path.read_text().splitlines()
    cols = lines[1].split("\t")
    cols[4] = "0" * 64
    lines[1] = "\t".join(cols)
    path.write_text("\n".join(lines) + "\n")
    entry = manifest.load_manifest(path)[0]
    with pytest.raises(InputError, match=rf"{cols[0]}.*sha256 mismatch"):
        manifest.verify(entry)


def test_malformed_manifests_are_rejected(tmp_path):
    path = _copy(tmp_path)
    text = path.read_text().splitlines()
    path.write_text("\n".join([text[0], text[1], text[1]]) + "\n")
    with pytest.raises(InputError, match="duplicate id"):
        manifest.load_manifest(path)
    path.write_text("\n".join([text[0].replace("\tlicence", ""), text[1]]) + "\n")
    with pytest.raises(InputError, match="header"):
        manifest.load_manifest(path)
    camera = next(line for line in text if line.startswith("camera\t"))
    path.write_text("\n".join([text[0], camera, camera.replace("camera\t", "camera2\t", 1).replace("\ttest\t", "\ttrain\t")]) + "\n")
    with pytest.raises(InputError, match="both the train and the test split"):
        manifest.load_manifest(path)


def test_missing_file_is_reported(tmp_path):
    path = tmp_path / "data_manifest"
    path.write_text("\t".join(manifest.HEADER) + "\n" + "\t".join(["clip", "clips/none.mp4", "8", "train", "a" * 64, "me", "CC0"]) + "\n")
    with pytest.raises(InputError, match="clip.*missing"):
        manifest.verify(manifest.load_manifest(path)[0])
