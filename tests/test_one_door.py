"""One door: the command line and the Python API take the same arrays to the same bits, refuse the same inputs
with the same one-line message (the API's with an exception class of the package's, naming its arguments), and
simulate with one sensor model.  Each probe finding here failed before the CLI became a shell over the API."""
import json
import warnings

import numpy as np
import pytest

import codedvideo as cv
from codedvideo.app.cli import main

N, SIZE = 8, 48


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    folder = tmp_path_factory.mktemp("door")
    video = cv.synthetic_scene("default", frames=N, size=(SIZE, SIZE))
    mask = cv.make_code("hitomi", (SIZE, SIZE), frames=N, bump=2, seed=1)
    coded = cv.simulate(video, mask)
    for name, arr in dict(coded=coded, mask=mask, truth=video).items():
        np.save(folder / f"{name}.npy", arr)
    return folder, video, mask, coded


def _cli(capsys, *args):
    capsys.readouterr()
    rc = main(["-q", *map(str, args)])
    out, err = capsys.readouterr()
    return rc, out, err.strip()


def _cli_reconstruct(capsys, folder, out, *extra, coded="coded.npy", mask="mask.npy"):
    return _cli(capsys, "reconstruct", "--coded", folder / coded, "--mask", folder / mask, "--output", out,
                "--cache", folder / "cache", "--overwrite", *extra)


@pytest.mark.parametrize("options,flags", [
    ({}, []),
    (dict(noise_sigma=4.0), ["--noise-sigma", "4"]),
    (dict(data_range=1000.0), ["--data-range", "1000"]),
    (dict(method="gaptv"), ["--method", "gaptv"]),
    (dict(white_level=300.0, stride=2), ["--white-level", "300", "--stride", "2"]),
])
def test_the_same_arrays_give_the_same_bits_through_both_doors(tmp_path, capsys, capture, options, flags):
    folder, _, mask, coded = capture
    rc, _, err = _cli_reconstruct(capsys, folder, tmp_path / "r.npy", *flags)
    assert rc == 0, err
    np.testing.assert_array_equal(np.load(tmp_path / "r.npy"), cv.reconstruct(coded, mask, **options))


def test_a_truth_scores_the_same_through_both_doors(tmp_path, capsys, capture):
    folder, video, mask, coded = capture
    rc, _, err = _cli_reconstruct(capsys, folder, tmp_path / "r.npy", "--truth", folder / "truth.npy")
    assert rc == 0, err
    record = json.loads((tmp_path / "r.metrics.json").read_text())
    got = cv.reconstruct(coded, mask, truth=video, full_output=True)
    assert got.record["quality"]["psnr"] == record["quality"]["psnr"]
    assert got.record["data_range"] == record["data_range"]


def _refused(capsys, tmp_path, folder, coded, mask, api_coded, api_mask, words, **options):
    """Both doors refuse: the CLI with exit 2 and one line, the API with an InputError; the same words in both."""
    np.save(folder / "bad_coded.npy", coded)
    np.save(folder / "bad_mask.npy", mask)
    rc, _, err = _cli_reconstruct(capsys, folder, tmp_path / "r.npy", coded="bad_coded.npy", mask="bad_mask.npy",
                                  *[x for k, v in options.items() for x in (f"--{k.replace('_', '-')}", v)])
    assert rc == 2 and len(err.splitlines()) == 1, err
    with pytest.raises(cv.InputError) as raised:
        cv.reconstruct(api_coded, api_mask, **options)
    assert "\n" not in str(raised.value)
    for word in words:
        assert word in err and word in str(raised.value), (err, str(raised.value))
    assert not (tmp_path / "r.npy").exists()


def test_a_0_255_mask_array_is_refused_by_both_doors(tmp_path, capsys, capture):
    folder, _, mask, coded = capture
    for scaled in (mask * np.uint8(255), mask.astype(np.uint16) * np.uint16(65535),
                   np.where(mask > 0, 1.5, 0).astype(np.float32)):
        _refused(capsys, tmp_path, folder, coded, scaled, coded, scaled, ["values outside [0, 1]"])


@pytest.mark.parametrize("where", ["coded", "mask"])
@pytest.mark.parametrize("bad", [np.nan, np.inf])
def test_nan_and_inf_are_refused_by_both_doors(tmp_path, capsys, capture, where, bad):
    folder, _, mask, coded = capture
    coded, mask = coded.copy(), mask.astype(np.float32)
    if where == "coded":
        coded[4, 5] = bad
    else:
        mask[3, 4, 5] = bad
    _refused(capsys, tmp_path, folder, coded, mask, coded, mask, ["contains NaN or Inf"], data_range=255.0)


def test_make_code_of_an_empty_shape_is_a_one_line_error():
    with pytest.raises(cv.InputError, match="at least 1 pixel"):
        cv.make_code("hitomi", (0, 64), frames=8)
    with pytest.raises(cv.InputError, match="at least 1"):
        cv.make_code("hitomi", (16, 16), frames=0)


def test_simulate_refuses_a_nan_video_and_a_mask_outside_0_1():
    mask = cv.make_code("hitomi", (16, 16), frames=4, bump=2)
    video = np.ones((4, 16, 16), np.float32)
    video[1, 2, 3] = np.nan
    with pytest.raises(cv.InputError, match="video: contains NaN or Inf"):
        cv.simulate(video, mask)
    with pytest.raises(cv.InputError, match=r"mask: values outside \[0, 1\]"):
        cv.simulate(np.ones((4, 16, 16)), mask * 255)


@pytest.mark.parametrize("flags,options", [
    (["--bits", "12"], dict(sensor=dict(bits=12))),
    (["--noise-sigma", "3"], dict(noise_sigma=3.0)),
    (["--shot-noise", "--gain", "4", "--white-level", "400"],
     dict(sensor=cv.SensorModel(shot_noise=True, gain=4.0, white_level=400.0))),
])
def test_simulate_has_one_sensor_model_through_both_doors(tmp_path, capsys, capture, flags, options):
    folder, _, mask, _ = capture
    rc, _, err = _cli(capsys, "simulate", "synth:default", "--frames", N, "--size", SIZE, SIZE, "--code", "file",
                      "--code-file", folder / "mask.npy", "--seed", 7, "--output", tmp_path / "cap", *flags)
    assert rc == 0, err
    truth = np.load(tmp_path / "cap" / "truth.npy")
    np.testing.assert_array_equal(np.load(tmp_path / "cap" / "coded.npy"), cv.simulate(truth, mask, seed=7, **options))


def test_api_warnings_name_its_arguments_at_the_callers_line(capture):
    _, video, mask, coded = capture
    dark = cv.simulate(video * np.float32(350 / video.max()), mask)  # just past 8 bits: a range of 4095, warned
    with warnings.catch_warnings(record=True) as said:
        warnings.simplefilter("always")
        cv.reconstruct(dark, mask, method="gaptv")
    texts = [str(w.message) for w in said]
    assert any("data_range 255" in t for t in texts), texts
    assert not any("--" in t for t in texts), texts
    assert all(w.filename == __file__ for w in said), [w.filename for w in said]


def test_simulate_takes_a_codes_unused_option_at_its_default_and_refuses_another_value(tmp_path, capsys):
    common = ["simulate", "synth:default", "--frames", N, "--size", 16, 16, "--code", "bernoulli"]
    rc, _, err = _cli(capsys, *common, "--bump", 2, "--output", tmp_path / "a")
    assert rc == 0, err  # 2 is the default: nothing is ignored
    rc, _, err = _cli(capsys, *common, "--bump", 3, "--output", tmp_path / "b")
    assert rc == 2 and "--bump 3" in err and "does not use it" in err, err


def test_a_presets_record_is_the_same_from_pipeline_yaml_and_the_command_line(tmp_path, capsys):
    """`preset: best` with `adapt: false` beside it: the run warns that the preset's adapt_rounds is left out,
    naming pipeline.yaml's key, and records what the command line records for `--preset best --no-adapt`."""
    folder = tmp_path
    rc, _, err = _cli(capsys, "simulate", "synth:default", "--frames", N, "--size", 32, 32, "--output", folder / "cap")
    assert rc == 0, err
    (folder / "p.yaml").write_text(
        f"frames: {N}\ncache: {folder / 'cache'}\nscene: {{video: synth:default, size: [32, 32]}}\n"
        f"reconstruct: {{preset: best, adapt: false, refine: 2, tile: 32}}\noutput: {{dir: {folder / 'out'}, frames: none}}\n")
    with pytest.warns(UserWarning, match=r"preset best: reconstruct\.adapt_rounds 2 is left out"):
        rc, _, err = _cli(capsys, "run", folder / "p.yaml")
    assert rc == 0, err
    yaml_record = json.loads((folder / "out" / "recon.metrics.json").read_text())["preset"]
    rc, _, err = _cli(capsys, "reconstruct", "--coded", folder / "cap" / "coded.npy", "--mask",
                      folder / "cap" / "mask.npy", "--preset", "best", "--no-adapt", "--refine", 2, "--tile", 32,
                      "--output", folder / "r.npy", "--cache", folder / "cache")
    assert rc == 0, err
    cli_record = json.loads((folder / "r.metrics.json").read_text())["preset"]
    assert {k: v for k, v in yaml_record.items() if k != "left_out"} == {k: v for k, v in cli_record.items()
                                                                         if k != "left_out"}
    assert yaml_record["given"] == ["adapt", "refine"] and list(yaml_record["left_out"]) == list(cli_record["left_out"])
    # each reason in its door's terms: pipeline.yaml's keys, the command line's options
    assert yaml_record["left_out"]["adapt_rounds"] == "applies with reconstruct.adapt only"
    assert cli_record["left_out"]["adapt_rounds"] == "applies with --adapt only"
