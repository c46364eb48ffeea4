"""Strict JSON: metrics never print Infinity or NaN (json_safe turns them into null)."""
import json
import math
import warnings

import numpy as np
import pytest

import codedvideo as cv
from codedvideo.app.cli import main
from codedvideo.model.metrics import PSNR_CEILING, evaluate, json_safe

N, SIZE = 8, 16


def test_psnr_of_identical_volumes_is_strict_json():
    v = np.full((3, 16, 16), 100.0, np.float32)
    metrics = evaluate(v, v, data_range=255.0)
    assert math.isinf(metrics["psnr_per_frame"][0])  # a frame's own PSNR stays +inf
    assert metrics["psnr"] == PSNR_CEILING  # (the mean counts each frame at most at the ceiling)
    with pytest.raises(ValueError):
        json.dumps(metrics, allow_nan=False)
    text = json.dumps(json_safe(metrics), allow_nan=False)
    back = json.loads(text)
    assert back["psnr"] == PSNR_CEILING and back["psnr_per_frame"] == [None, None, None]
    assert back["ssim"] == metrics["ssim"] and back["data_range"] == 255.0
    assert "Infinity" not in text and "NaN" not in text


def test_nested_python_and_numpy_values():
    x = {
        "a": float("inf"),
        "b": float("-inf"),
        "c": float("nan"),
        "d": [1.5, np.float32("nan"), np.float64(2.25), np.float16("inf"), {"e": (np.float32(0.5), float("nan"))}],
        "f": np.array([[1.0, np.nan], [np.inf, -3.0]], np.float32),
        "g": np.int64(7),
        "h": np.bool_(True),
        "i": "text",
        "j": None,
        "k": 3,
        "l": True,
        "m": np.float64(-0.0),
        "n": np.array(4.5),
        "o": np.arange(3, dtype=np.int32),
    }
    out = json_safe(x)
    assert json.loads(json.dumps(out, allow_nan=False)) == out  # strict, and round-trips exactly
    assert out["a"] is None and out["b"] is None and out["c"] is None
    assert out["d"] == [1.5, None, 2.25, None, {"e": [0.5, None]}]
    assert out["f"] == [[1.0, None], [None, -3.0]]
    assert out["g"] == 7 and type(out["g"]) is int
    assert out["h"] is True and out["l"] is True and out["k"] == 3 and type(out["k"]) is int
    assert out["i"] == "text" and out["j"] is None
    assert out["m"] == 0.0 and out["n"] == 4.5 and out["o"] == [0, 1, 2]


def test_finite_values_are_preserved_exactly_and_the_input_is_not_changed():
    rng = np.random.default_rng(0)
    vals = rng.normal(size=50) * 10.0 ** rng.integers(-300, 300, 50)
    vals32 = (rng.normal(size=50) * 10.0 ** rng.integers(-30, 30, 50)).astype(np.float32)
    x = {"v": [float(v) for v in vals], "w": vals32, "nested": {"inf": float("inf")}}
    out = json_safe(x)
    assert out["v"] == [float(v) for v in vals]  # bit for bit
    assert out["w"] == [float(v) for v in vals32]
    assert json.loads(json.dumps(out, allow_nan=False))["v"] == out["v"]
    assert x["nested"]["inf"] == float("inf") and isinstance(x["w"], np.ndarray)  # a copy, the input untouched
    assert out is not x and out["nested"] is not x["nested"]
    json.dumps(out, allow_nan=False)


def test_evaluate_of_a_real_reconstruction_is_unchanged():
    rng = np.random.default_rng(1)
    truth = (rng.random((2, 12, 12)) * 255).astype(np.float32)
    metrics = evaluate(truth + rng.normal(0, 3, truth.shape).astype(np.float32), truth, data_range=255.0)
    assert json_safe(metrics) == metrics


def test_an_exact_frame_counts_at_the_ceiling_in_the_mean_psnr():
    """Reported: one still, exactly reconstructed frame made a capture's PSNR (and the run's) null; then, left
    out of the mean, it counted at 66 dB once written as 8-bit video and 114 dB as 16-bit frames."""
    rng = np.random.default_rng(0)
    truth = rng.uniform(0, 255, (3, 16, 16))
    recon = truth.copy()
    recon[1] += rng.normal(0, 4, (16, 16))
    recon[2] += rng.normal(0, 8, (16, 16))
    m = evaluate(recon, truth, data_range=255.0)
    assert m["exact_frames"] == 1 and np.isinf(m["psnr_per_frame"][0])
    assert m["psnr"] == pytest.approx(np.mean([PSNR_CEILING, *m["psnr_per_frame"][1:]]))
    assert evaluate(truth, truth, data_range=255.0)["psnr"] == PSNR_CEILING  # every frame exact: the ceiling, not null


def test_the_mean_psnr_does_not_change_with_the_outputs_quantisation():
    """The same reconstruction, a still frame exact and two in error, scored as floats, rounded to 16 bits and
    rounded to 8 bits (an 8-bit video): the means agree (before: 33.3, 73.9 and 49.7 dB on a still stream)."""
    rng = np.random.default_rng(1)
    truth = rng.uniform(0, 255, (3, 32, 32))
    recon = truth.copy()
    recon[1:] += rng.normal(0, 6, (2, 32, 32))
    recon = np.clip(recon, 0, 255)
    as_float = evaluate(recon, truth, data_range=255.0)["psnr"]
    as_16_bit = evaluate(np.round(recon / 255 * 65535) * 255 / 65535, truth, data_range=255.0)["psnr"]
    as_8_bit = evaluate(np.round(recon), truth, data_range=255.0)["psnr"]
    assert as_16_bit == pytest.approx(as_float, abs=0.01)
    assert as_8_bit == pytest.approx(as_float, abs=0.1)


def test_a_rerun_from_the_cache_reports_no_patches_solved(tmp_path, capsys):
    """Reported: a stream reconstructed again from its cached tiles claimed 0.9 to 1.3 M patches a second."""
    from codedvideo.app.cli import main
    from codedvideo.engine.simulation import simulate_capture
    from codedvideo.model.codes import CodeSpec
    from codedvideo.data.synth import make_scene

    cap = simulate_capture(make_scene("default", frames=12, size=(32, 32)), code=CodeSpec("hitomi", bump=2), sigma=0,
                           seed=0, captures=3)
    for name in ("coded", "mask"):
        np.save(tmp_path / f"{name}.npy", cap[name])
    rates = []
    for out in ("a.npy", "b.npy"):
        assert main(["-q", "reconstruct", "--coded", str(tmp_path / "coded.npy"), "--mask", str(tmp_path / "mask.npy"),
                     "--method", "dct", "--independent-captures", "--output", str(tmp_path / out),
                     "--cache", str(tmp_path / "cache")]) == 0
        rates.append(json.loads((tmp_path / out).with_suffix(".metrics.json").read_text())
                     ["reconstruction"]["patches_per_second"])
    assert rates[0] > 0 and rates[1] == 0


def test_the_metrics_say_the_quality_is_the_volumes_and_when_the_file_is_lossy(tmp_path, capsys):
    from codedvideo.app.cli import main
    from codedvideo.engine.simulation import simulate_capture
    from codedvideo.model.codes import CodeSpec
    from codedvideo.data.synth import make_scene

    video = make_scene("default", frames=4, size=(24, 24))
    cap = simulate_capture(video, code=CodeSpec("hitomi", bump=2), sigma=0, seed=0)
    for name in ("coded", "mask", "truth"):
        np.save(tmp_path / f"{name}.npy", cap[name])
    said = {}
    for out in ("r.npy", "r.mp4"):
        assert main(["-q", "reconstruct", "--coded", str(tmp_path / "coded.npy"), "--mask", str(tmp_path / "mask.npy"),
                     "--truth", str(tmp_path / "truth.npy"), "--method", "dct", "--output", str(tmp_path / out),
                     "--cache", str(tmp_path / "cache"), "--overwrite"]) == 0
        said[out] = json.loads((tmp_path / "r.metrics.json").read_text())["quality"]["measured_on"]
    assert said["r.npy"] == "volume before encoding" and "lossy (H.264)" in said["r.mp4"]


def _evaluate(capsys, recon, truth):
    from codedvideo.app.cli import main

    capsys.readouterr()
    assert main(["-q", "evaluate", "--recon", str(recon), "--truth", str(truth)]) == 0
    return json.loads(capsys.readouterr().out)


def test_a_colour_truth_scores_alike_in_any_container(tmp_path, capsys):
    """Reported: a colour truth in a video, frame folder or TIFF was read as luma: the score depended on the
    container (26.98 dB over 24 frames against a .npy truth, 26.77 over 8 against the same truth in a .mkv)."""
    from codedvideo.data.synth import make_scene
    from codedvideo.formats.volumes import write_volume

    t = np.rint(make_scene("default", frames=4, size=(32, 32))).astype(np.float32)
    r = np.clip(t + np.random.default_rng(0).normal(0, 6, t.shape), 0, 255).astype(np.float32)
    colour = lambda v: np.stack([v, 0.9 * v, 0.7 * v]).round().astype(np.float32)  # noqa: E731
    np.save(tmp_path / "rc.npy", colour(r))
    np.save(tmp_path / "tc.npy", colour(t))
    write_volume(colour(t), tmp_path / "tc.mkv")
    write_volume(colour(t), tmp_path / "tcframes")
    scores = [_evaluate(capsys, tmp_path / "rc.npy", tmp_path / truth)
              for truth in ("tc.npy", "tc.mkv", "tcframes")]
    assert [len(s["psnr_per_frame"]) for s in scores] == [12, 12, 12]
    assert max(s["psnr"] for s in scores) - min(s["psnr"] for s in scores) < 0.05


def test_a_reconstruction_in_other_units_than_its_truth_is_warned(tmp_path, capsys):
    rng = np.random.default_rng(0)
    t = rng.uniform(0, 255, (4, 16, 16)).astype(np.float32)
    np.save(tmp_path / "t.npy", t)
    np.save(tmp_path / "r01.npy", t / 255)
    with pytest.warns(UserWarning, match="same units"):
        _evaluate(capsys, tmp_path / "r01.npy", tmp_path / "t.npy")


def test_a_dark_scene_in_the_same_units_as_its_truth_is_not_warned(tmp_path, capsys, recwarn):
    """Reported: the reconstruction's peak was compared with the truth's data range, so any dark scene (truth
    and reconstruction at 0.04 of 8-bit, peaks near 10) was asked whether it was in the same units."""
    rng = np.random.default_rng(0)
    t = rng.uniform(0, 255, (4, 16, 16)).astype(np.float32) * np.float32(0.04)
    np.save(tmp_path / "t.npy", t)
    np.save(tmp_path / "r.npy", t * np.float32(1.14))  # (peaks 10.2 and 11.6)
    result = _evaluate(capsys, tmp_path / "r.npy", tmp_path / "t.npy")
    assert result["data_range_source"].startswith("values")  # (range 255 found from the truth's peak)
    assert not [w for w in recwarn if "same units" in str(w.message)], [str(w.message) for w in recwarn]
    np.save(tmp_path / "r01.npy", t / 255)  # the dark scene in [0, 1] against its 8-bit truth: still warned
    with pytest.warns(UserWarning, match="same units"):
        _evaluate(capsys, tmp_path / "r01.npy", tmp_path / "t.npy")


def test_an_output_sharing_a_stem_with_another_says_it_replaces_its_record(tmp_path, capsys):
    """Reported: rec.npy and rec.mp4 share rec.metrics.json; the second run replaced the first's figures in
    silence."""
    from codedvideo.app.cli import main
    from codedvideo.engine.simulation import simulate_capture
    from codedvideo.model.codes import CodeSpec
    from codedvideo.data.synth import make_scene

    cap = simulate_capture(make_scene("default", frames=4, size=(24, 24)), code=CodeSpec("hitomi", bump=2), sigma=0,
                           seed=0)
    for name in ("coded", "mask"):
        np.save(tmp_path / f"{name}.npy", cap[name])
    args = ["-q", "reconstruct", "--coded", str(tmp_path / "coded.npy"), "--mask", str(tmp_path / "mask.npy"),
            "--method", "dct", "--cache", str(tmp_path / "cache")]
    assert main([*args, "--output", str(tmp_path / "rec.npy")]) == 0
    with pytest.warns(UserWarning, match="held the record of .*rec.npy"):
        assert main([*args, "--output", str(tmp_path / "rec.mp4")]) == 0


def test_the_same_output_named_relative_then_absolute_is_not_said_to_replace_another(tmp_path, capsys, monkeypatch,
                                                                                    recwarn):
    """Reported: rec.npy, then /abs/rec.npy, warned that the metrics file held the record of another output."""
    from codedvideo.app.cli import main
    from codedvideo.engine.simulation import simulate_capture
    from codedvideo.model.codes import CodeSpec
    from codedvideo.data.synth import make_scene

    cap = simulate_capture(make_scene("default", frames=4, size=(24, 24)), code=CodeSpec("hitomi", bump=2), sigma=0,
                           seed=0)
    for name in ("coded", "mask"):
        np.save(tmp_path / f"{name}.npy", cap[name])
    monkeypatch.chdir(tmp_path)
    args = ["-q", "reconstruct", "--coded", "coded.npy", "--mask", "mask.npy", "--method", "dct", "--cache", "cache"]
    assert main([*args, "--output", "rec.npy"]) == 0
    assert main([*args, "--output", str(tmp_path / "rec.npy"), "--overwrite"]) == 0
    assert not [w for w in recwarn if "held the record" in str(w.message)], [str(w.message) for w in recwarn]
    assert json.loads((tmp_path / "rec.metrics.json").read_text())["output"] == str(tmp_path / "rec.npy")


def test_evaluate_scores_colour_volumes_alike_through_both_doors(tmp_path, capsys):
    """`codedvideo evaluate` scored (3, N, H, W) colour volumes (every channel's frames) where `cv.evaluate` refused
    them; colour against grey is scored as luma, with a warning, through both."""
    rng = np.random.default_rng(0)
    truth = rng.uniform(0, 255, (3, N, SIZE, SIZE)).astype(np.float32)
    recon = np.clip(truth + rng.normal(0, 4, truth.shape), 0, 255).astype(np.float32)
    np.save(tmp_path / "t.npy", truth)
    np.save(tmp_path / "r.npy", recon)
    api = cv.evaluate(recon, truth)
    assert api["psnr"] == pytest.approx(cv.evaluate(recon.reshape(-1, SIZE, SIZE), truth.reshape(-1, SIZE, SIZE))["psnr"])
    capsys.readouterr()
    assert main(["-q", "evaluate", "--recon", str(tmp_path / "r.npy"), "--truth", str(tmp_path / "t.npy")]) == 0
    assert json.loads(capsys.readouterr().out)["psnr"] == pytest.approx(api["psnr"])
    grey = np.tensordot(np.array([0.299, 0.587, 0.114], np.float32), truth, axes=([0], [0]))
    with pytest.warns(UserWarning, match="is colour and .* grey; compared as luma"):
        luma = cv.evaluate(recon, grey)
    np.save(tmp_path / "g.npy", grey)
    with pytest.warns(UserWarning, match="compared as luma"):
        assert main(["-q", "evaluate", "--recon", str(tmp_path / "r.npy"), "--truth", str(tmp_path / "g.npy")]) == 0
    assert json.loads(capsys.readouterr().out)["psnr"] == pytest.approx(luma["psnr"])


def test_evaluate_says_only_the_nan_and_checks_its_data_range_as_the_command_line():
    """A NaN reconstruction was warned of as 'peaks at nan ... same units?' before its error; a data range of 0
    raised InputError where reconstruct raises ConfigError."""
    truth = np.linspace(0, 255, N * SIZE * SIZE, dtype=np.float32).reshape(N, SIZE, SIZE)
    bad = truth.copy()
    bad[0, 0, 0] = np.nan
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(cv.InputError, match="NaN"):
            cv.evaluate(bad, truth)
    with pytest.raises(cv.ConfigError, match="option data_range 0"):
        cv.evaluate(truth, truth, data_range=0)
