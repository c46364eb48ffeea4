import shutil

import pytest

from codedvideo.data import manifest
from codedvideo.data import shipped
from codedvideo.data import synth
from codedvideo.model.errors import InputError


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


def test_the_packaged_manifest_holds_the_projects_rows():
    """The wheel carries codedvideo/data/manifest.tsv; the checkout's data_manifest lists the same datasets:
    the same ids, checksums and sources, and each path names the same file."""
    packaged = {e.id: e for e in manifest.load_manifest(manifest.DEFAULT_PATH)}
    project = {e.id: e for e in manifest.load_manifest(manifest.PROJECT_PATH)}
    assert manifest.DEFAULT_PATH.parent.name == "data" and manifest.DEFAULT_PATH.parent.parent.name == "codedvideo"
    assert packaged.keys() == project.keys()
    for id_, e in packaged.items():
        p = project[id_]
        assert (e.frames, e.split, e.sha256, e.source, e.licence) == (p.frames, p.split, p.sha256, p.source, p.licence)
        assert manifest.resolve(e) == manifest.resolve(p), id_


def test_shipped_rows_rebase_to_each_manifest(tmp_path):
    """write_manifest gives each manifest its own relative paths to the shipped dictionaries."""
    rows = shipped.shipped_rows(manifest.DEFAULT_PATH.parent)
    assert rows and all(r.split("\t")[1].startswith("dict-N") for r in rows)
    project_rows = shipped.shipped_rows(manifest.PROJECT_PATH.parent)
    assert all(r.split("\t")[1].startswith("src/codedvideo/data/dict-N") for r in project_rows)
    assert [r.split("\t")[4] for r in rows] == [r.split("\t")[4] for r in project_rows]
