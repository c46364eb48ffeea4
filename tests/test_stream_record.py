"""A stream's record: each capture's own seconds, on a first run and on a resume from the cache, and a
refinement's trace that ends at the capture's own PSNR."""
import json

import numpy as np
import pytest

from codedvideo.app.cli import main
from codedvideo.engine.simulation import simulate_capture
from codedvideo.model.codes import CodeSpec
from codedvideo.data.synth import make_scene

H = W = 48
N, T = 8, 3


@pytest.fixture()
def stream(tmp_path):
    video = make_scene("default", frames=N * T, size=(H, W))
    cap = simulate_capture(video, code=CodeSpec("hitomi", bump=2), sigma=0, seed=1, captures=T)
    for name in ("coded", "mask", "truth"):
        np.save(tmp_path / f"{name}.npy", cap[name])
    return ["--coded", str(tmp_path / "coded.npy"), "--mask", str(tmp_path / "mask.npy"),
            "--truth", str(tmp_path / "truth.npy"), "--cache", str(tmp_path / "cache"), "--overwrite"]


def _captures(tmp_path, capsys, stream, *extra):
    assert main(["-q", "reconstruct", *stream, "--output", str(tmp_path / "r.npy"), *extra]) == 0
    capsys.readouterr()
    return json.loads((tmp_path / "r.metrics.json").read_text())["captures"]


def test_each_capture_has_its_own_seconds_first_and_on_resume(tmp_path, capsys, stream):
    infos = [e["reconstruction"] for e in _captures(tmp_path, capsys, stream)]
    work = np.array([i["seconds_total"] for i in infos])
    spent = np.array([i["seconds"]["reconstruct"] for i in infos])
    assert (work > 0).all()
    # (before: the first capture of the window held the window's wait, 0.61 s, and the next 0.0003 s)
    np.testing.assert_allclose(spent / spent.sum(), work / work.sum(), rtol=1e-6)
    again = [e["reconstruction"] for e in _captures(tmp_path, capsys, stream)]
    assert all(i["tiles_computed"] == 0 for i in again)
    # nothing solved again: no seconds of tile work, no patches a second (before: the first run's figures)
    assert all(i["seconds_total"] == 0 and i["patches_per_second"] == 0 for i in again)


def test_the_refinement_trace_ends_at_the_captures_psnr(tmp_path, capsys, stream):
    for entry in _captures(tmp_path, capsys, stream, "--refine", "4"):
        trace = entry["reconstruction"]["refine_trace"]
        assert trace[-1]["psnr"] == pytest.approx(entry["quality"]["psnr"], abs=1e-9)
