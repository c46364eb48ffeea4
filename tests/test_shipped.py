"""Shipped dictionaries: listed and verified in data_manifest, used without training, and reproducible."""
import json

import numpy as np
import pytest

from codedvideo.data import manifest
from codedvideo.data import shipped
from codedvideo.app.cli import main
from codedvideo.engine.config import PipelineConfig
from codedvideo.model.errors import InputError
from codedvideo.engine.cache import dictionary_key
from codedvideo.engine.simulation import simulate_capture
from codedvideo.model.codes import CodeSpec
from codedvideo.engine.training import train_dictionary
from codedvideo.formats.store import load_dictionary
from conftest import REGENERATE_TEST


def test_shipped_dictionaries_are_listed_verified_and_made_by_the_default_settings():
    assert 8 in shipped.available()
    for n in shipped.available():
        entry = manifest.lookup(shipped.manifest_id(n))
        assert entry.split == "model" and entry.frames == n and shipped.train_command(n) in entry.source
        manifest.verify(entry)
        assert shipped.settings_key(n) == dictionary_key(PipelineConfig(frames=n))


def test_default_training_uses_the_shipped_dictionary_and_trains_nothing(tmp_path):
    path, meta = train_dictionary(PipelineConfig(frames=8, cache=str(tmp_path / "cache")))
    assert path == shipped.path_for(8) and meta["shipped"] and meta["reused"]
    assert not (tmp_path / "cache").exists()
    other, meta = train_dictionary(PipelineConfig.model_validate(dict(frames=8, cache=str(tmp_path / "cache"),
                                                                      dictionary=dict(kind="dct"))))
    assert other != shipped.path_for(8) and not meta.get("shipped")


def test_a_damaged_shipped_dictionary_is_refused(tmp_path, monkeypatch):
    import shutil

    copy = tmp_path / "data"
    shutil.copytree(shipped.DATA, copy)
    chunk = copy / "dict-N8.zip"
    data = bytearray(chunk.read_bytes())
    data[len(data) // 2] ^= 0xFF
    chunk.write_bytes(bytes(data))
    monkeypatch.setattr(shipped, "DATA", copy)
    with pytest.raises(InputError, match="dict-N8"):
        shipped.verified(8)


def test_reconstruct_without_dictionary_uses_the_shipped_one_or_names_the_train_command(tmp_path, capsys):
    from codedvideo.data.synth import make_scene

    for n in (8, 5):
        cap = simulate_capture(make_scene("default", frames=n, size=(32, 32)), code=CodeSpec("hitomi", bump=2), sigma=0,
                               seed=0)
        np.save(tmp_path / f"coded{n}.npy", cap["coded"])
        np.save(tmp_path / f"mask{n}.npy", cap["mask"])
    capsys.readouterr()
    args = ["-q", "reconstruct", "--coded", str(tmp_path / "coded8.npy"), "--mask", str(tmp_path / "mask8.npy"),
            "--output", str(tmp_path / "r.npy"), "--cache", str(tmp_path / "cache")]
    assert main(args) == 0
    metrics = json.loads((tmp_path / "r.metrics.json").read_text())
    assert metrics["inputs"]["dictionary"].endswith("dict-N8.zip")
    args = [a.replace("coded8", "coded5").replace("mask8", "mask5") for a in args]
    assert main(args) == 2
    err = capsys.readouterr().err
    assert "N = 5" in err and "codedvideo train --frames 5" in err and len(err.strip().splitlines()) == 1


@pytest.mark.slow
def test_shipped_dictionary_regenerates_from_its_listed_settings(regenerated_dictionary):
    """Trained again with the listed settings (started at collection, see conftest), the N = 8 dictionary
    reconstructs the default scene within 0.05 dB of the shipped one."""
    assert REGENERATE_TEST == "test_shipped_dictionary_regenerates_from_its_listed_settings"
    from codedvideo.engine.config import omp_settings
    from codedvideo.model.metrics import evaluate
    from codedvideo.data.scenes import load_video
    from codedvideo.engine.windows import Execution, reconstruct_volume

    cfg = PipelineConfig()
    video = load_video(cfg.scene.video, frames=8, size=cfg.scene.size, seed=0)
    cap = simulate_capture(video, code=CodeSpec("hitomi", bump=2), sigma=0, seed=0)
    psnr = []
    for store in (shipped.path_for(8), regenerated_dictionary):
        D, _ = load_dictionary(store)
        vol, _ = reconstruct_volume(cap["coded"], cap["mask"], D, settings=omp_settings(cfg.reconstruct, 0.0),
                                    run=Execution(cache=regenerated_dictionary.parent / "recon", progress=False))
        psnr.append(evaluate(vol, cap["truth"], data_range=255.0)["psnr"])
    assert psnr[0] > 28 and abs(psnr[0] - psnr[1]) <= 0.05, psnr
