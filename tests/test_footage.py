"""Held-out real footage: package clips listed in data_manifest, verified, cut into test scenes."""
import numpy as np
import pytest

from codedvideo.data import manifest
from codedvideo.model.errors import InputError
from codedvideo.data.footage import SCENES, footage_scene
from codedvideo.data.scenes import load_video


def test_package_clips_are_listed_as_test_data_and_verify():
    entries = {e.id: e for e in manifest.load_manifest()}
    for id_ in {s[0] for s in SCENES.values()}:
        assert entries[id_].split == "test"
        assert manifest.verify(entries[id_]).exists()


@pytest.mark.parametrize("name", sorted(SCENES))
def test_every_scene_is_256_square_real_motion(name):
    v = footage_scene(name, frames=8)
    assert v.shape == (8, 256, 256) and v.dtype == np.float32
    assert 0 <= v.min() and v.max() <= 255 and v.std() > 10
    assert np.abs(np.diff(v, axis=0)).mean() > 0.5  # the frames move


def test_load_video_crops_and_rejects_unknown_and_tampered(tmp_path):
    assert load_video("footage:bikes-b", frames=4, size=(64, 80)).shape == (4, 64, 80)
    with pytest.raises(InputError, match="unknown scene"):
        load_video("footage:nope", frames=4, size=None)
    # a manifest whose checksum does not match the file is refused, naming the entry
    bad = tmp_path / "manifest"
    text = manifest.DEFAULT_PATH.read_text().replace("91028f9d6c72", "000000000000")
    bad.write_text(text)
    entry = manifest.lookup("skv-bikes", bad)
    with pytest.raises(InputError, match="skv-bikes.*sha256 mismatch"):
        manifest.verify(entry)
