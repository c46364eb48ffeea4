"""The record and the printed line carry the PSNR of the file written, beside the reconstruction's own."""
import json

import numpy as np
import pytest

import codedvideo as cv
from codedvideo.app.cli import main

SIZE, N = 48, 8


@pytest.fixture()
def capture(tmp_path):
    video = cv.synthetic_scene("default", frames=N, size=(SIZE, SIZE))
    mask = cv.make_code("hitomi", (SIZE, SIZE), frames=N, seed=0)
    for name, value in dict(coded=cv.simulate(video, mask), mask=mask, truth=video).items():
        np.save(tmp_path / f"{name}.npy", value)
    return ["--coded", str(tmp_path / "coded.npy"), "--mask", str(tmp_path / "mask.npy"),
            "--truth", str(tmp_path / "truth.npy")]


@pytest.mark.parametrize("name", ["rec.mp4", "rec.mkv", "frames"])
def test_a_quantised_output_is_scored_as_written(tmp_path, capsys, capture, name):
    out = tmp_path / name
    assert main(["-q", "reconstruct", *capture, "--output", str(out), "--cache", str(tmp_path / "c")]) == 0
    printed = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert main(["-q", "evaluate", "--recon", str(out), "--truth", str(tmp_path / "truth.npy")]) == 0
    evaluated = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert printed["output_file_psnr"] == pytest.approx(evaluated["psnr"], abs=0.01)
    record = json.loads((tmp_path / (out.stem + ".metrics.json")).read_text())
    assert record["quality"]["output_file"]["psnr"] == pytest.approx(evaluated["psnr"], abs=1e-6)
    if name == "rec.mp4":  # H.264 loses what the reconstruction held: the two figures differ, both said
        assert printed["output_file_psnr"] < printed["psnr"]


def test_a_float_output_is_the_reconstruction_and_gets_no_second_figure(tmp_path, capsys, capture):
    assert main(["-q", "reconstruct", *capture, "--output", str(tmp_path / "rec.npy")]) == 0
    printed = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert "psnr" in printed and "output_file_psnr" not in printed


@pytest.mark.parametrize("video", ["recon.mp4", "recon.mkv"])
def test_run_scores_the_video_it_wrote(tmp_path, capsys, video):
    """Reported: `codedvideo run`'s record gave the reconstruction's PSNR only, not its lossy video's."""
    out = tmp_path / "out"
    config = tmp_path / "p.yaml"
    config.write_text(f"frames: 4\ncache: {tmp_path / 'cache'}\nscene: {{video: synth:default, size: [32, 32]}}\n"
                      f"dictionary: {{kind: dct}}\noutput: {{dir: {out}, video: {video}}}\n")
    assert main(["-q", "run", str(config)]) == 0
    printed = capsys.readouterr().out
    record = json.loads((out / "recon.metrics.json").read_text())
    quality = record["quality"]
    assert main(["-q", "evaluate", "--recon", str(out / video), "--truth", str(out / "capture" / "truth.npy")]) == 0
    evaluated = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert quality["output_file"]["psnr"] == pytest.approx(evaluated["psnr"], abs=1e-6)
    if video == "recon.mp4":  # H.264 loses what the reconstruction held: the two figures differ, both said
        assert quality["output_file"]["psnr"] < quality["psnr"]
    assert f"PSNR of {out / video} as written: {quality['output_file']['psnr']:.2f} dB" in printed
