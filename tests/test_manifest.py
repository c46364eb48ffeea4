import pytest

from codedvideo import manifest, synth
from codedvideo.errors import InputError


def _rows(path=manifest.DEFAULT_PATH):
    return [line.split("\t") for line in path.read_text(encoding="utf-8").splitlines()]


def _write(path, rows):
    path.write_text("".join("\t".join(r) + "\n" for r in rows), encoding="utf-8")
    return path


def _row(rows, id_):
    return next(i for i, r in enumerate(rows) if r[0] == id_)


def test_repository_manifest_loads_and_verifies():
    entries = manifest.load_manifest()
    ids = {e.id for e in entries}
    assert set(synth.TRAIN_PHOTOS) | set(synth.TEST_PHOTOS) <= ids
    assert {"synth-default", "synth-default-static70", "synth-train"} <= ids
    for e in entries:
        path = manifest.verify(e)
        if e.kind == "skimage":
            assert path == synth.photo_path(e.id)
            assert e.frames == "1" and e.source == "scikit-image data (skimage/data)" and e.licence
        else:
            assert path is None and e.kind == "synth"
    manifest.check_splits(entries)
    manifest.verify_ids(["camera", "coins"])


def test_splits_are_disjoint_and_match_synth():
    entries = manifest.load_manifest("data_manifest")
    train = {e.id for e in entries if e.split == "train"}
    test = {e.id for e in entries if e.split == "test"}
    assert not train & test
    assert set(synth.TRAIN_PHOTOS) <= train and set(synth.TEST_PHOTOS) <= test
    for e in entries:
        if e.kind == "synth":
            want = {"train": set(synth.TRAIN_PHOTOS), "test": set(synth.TEST_PHOTOS)}[e.split]
            assert set(synth.scene_photos(e.name)) <= want, e.id


def test_resolve():
    assert manifest.resolve("camera") == synth.photo_path("camera")
    assert manifest.resolve("synth-default") == "synth:default"
    with pytest.raises(InputError, match="nosuch"):
        manifest.resolve("nosuch")


def test_tampered_checksums_are_detected(tmp_path):
    rows = _rows()
    for id_ in ("camera", "synth-default-static70"):
        bad = [list(r) for r in rows]
        i = _row(bad, id_)
        bad[i][4] = ("0" if bad[i][4][0] != "0" else "1") + bad[i][4][1:]
        entry = next(e for e in manifest.load_manifest(_write(tmp_path / "m", bad)) if e.id == id_)
        with pytest.raises(InputError, match=rf"line {i + 1} \({id_}\): sha256 mismatch") as err:
            manifest.verify(entry)
        assert "\n" not in str(err.value) and bad[i][4] in str(err.value)


def test_malformed_manifests_are_rejected(tmp_path):
    rows = _rows()
    header, cam = rows[0], rows[_row(rows, "camera")]
    cases = [
        ([header[:-1], cam[:-1]], "header.*missing column.*licence"),
        ([header, cam, cam], "line 3: duplicate id 'camera' .first on line 2"),
        ([header, cam[:4] + ["abc"] + cam[5:]], r"line 2 \(camera\): malformed sha256"),
        ([header, cam[:3] + ["validation"] + cam[4:]], r"line 2 \(camera\): unknown split 'validation'"),
        ([header, cam[:5]], "line 2: expected 7 tab-separated columns, got 5"),
        ([header, cam[:2] + ["0"] + cam[3:]], "frames"),
        ([header, cam[:1] + ["synth:nosuch", "any"] + cam[3:]], "unknown scene"),
    ]
    for rows_, message in cases:
        with pytest.raises(InputError, match=message):
            manifest.load_manifest(_write(tmp_path / "m", rows_))
    with pytest.raises(InputError, match="not found"):
        manifest.load_manifest(tmp_path / "absent")


def test_crossing_splits_are_rejected(tmp_path):
    rows = _rows()
    header, cam = rows[0], rows[_row(rows, "camera")]
    again = ["camera2"] + cam[1:3] + ["train"] + cam[4:]
    with pytest.raises(InputError, match="both the train and the test split"):
        manifest.load_manifest(_write(tmp_path / "m", [header, cam, again]))
    moved = cam[:3] + ["train"] + cam[4:]
    with pytest.raises(InputError, match="marked train"):
        manifest.load_manifest(_write(tmp_path / "m", [header, moved]))
    ast = rows[_row(rows, "astronaut")]
    leak = ["leak", "synth:astronaut-translate", "any", "test"] + cam[4:]
    with pytest.raises(InputError, match=r"leak.*marked test but uses train photo 'astronaut'"):
        manifest.load_manifest(_write(tmp_path / "m", [header, ast, leak]))


def test_missing_file_is_reported(tmp_path):
    row = ["clip", "clips/none.mp4", "8", "train", "a" * 64, "me", "CC0"]
    path = _write(tmp_path / "m", [list(manifest.HEADER), row])
    with pytest.raises(InputError, match=r"line 2 \(clip\): file .*none.mp4 is missing"):
        manifest.verify(manifest.load_manifest(path)[0])
    with pytest.raises(InputError, match="no entry"):
        manifest.verify_ids(["nosuch"], path)


def test_write_manifest_reproduces_the_repository_file(tmp_path):
    out = manifest.write_manifest(tmp_path / "data_manifest")
    assert out.read_text(encoding="utf-8") == manifest.DEFAULT_PATH.read_text(encoding="utf-8")
