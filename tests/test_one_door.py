"""One door: the command line and the Python API take the same arrays to the same bits, refuse the same inputs
with the same one-line message (the API's with an exception class of the package's, naming its arguments), and
simulate with one sensor model."""
import json
import re
import warnings

import numpy as np
import pytest

import codedvideo as cv
from codedvideo.app.cli import main

N, SIZE = 8, 48
SMALL = 16  # the side of the captures that need no more


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


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_simulate_refuses_a_video_with_nan_or_inf_through_both_doors(tmp_path, capsys, bad):
    video = cv.synthetic_scene("default", frames=N, size=(SMALL, SMALL))
    video[3, 4, 5] = bad
    mask = cv.make_code("hitomi", (SMALL, SMALL), frames=N, bump=2)
    with pytest.raises(cv.InputError) as raised:
        cv.simulate(video, mask)
    api = str(raised.value)
    assert "\n" not in api and "video" in api and "contains NaN or Inf" in api, api
    np.save(tmp_path / "video.npy", video)
    capsys.readouterr()
    rc = main(["-q", "simulate", str(tmp_path / "video.npy"), "--frames", str(N), "--output", str(tmp_path / "cap")])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and len(err.splitlines()) == 1, err
    assert "video.npy" in err and "contains NaN or Inf" in err, err
    assert not (tmp_path / "cap").exists()


@pytest.mark.parametrize("call, said", [
    (lambda: cv.simulate(np.ones((N, SMALL, SMALL)), cv.make_code("global", (SMALL, SMALL), frames=N), seed=-1),
     "option seed -1"),
    (lambda: cv.make_code("bernoulli", (SMALL, SMALL), frames=N, seed=-1), "option seed -1"),
    (lambda: cv.make_code("bernoulli", (SMALL, SMALL), frames=N, seed=1.5), "option seed 1.5"),
    (lambda: cv.make_code("hitomi", (SMALL, SMALL), frames=N, bump=2, p=0.3), "p: code 'hitomi' does not use it"),
    (lambda: cv.make_code("bernoulli", (SMALL, SMALL), frames=N, bump=3), "bump: code 'bernoulli' does not use it"),
])
def test_the_apis_seed_and_code_options_are_checked_as_the_command_lines_are(call, said):
    """A bad seed raised numpy's own error, and a code option the code does not use was taken silently; the command
    line refuses both with one line naming the option."""
    with pytest.raises(cv.ConfigError, match=re.escape(said)):
        call()


@pytest.mark.parametrize("factor", [1 / 255, 257.0])
def test_a_truth_in_other_units_than_the_capture_is_said_before_work_through_both_doors(tmp_path, factor):
    """`reconstruct --truth` with the truth in [0, 1] (or 16-bit) against an 8-bit capture: every PSNR would mean
    nothing (19 dB, -29 dB), so both doors warn, as `evaluate` does; a truth in the capture's units is not warned."""
    video = cv.synthetic_scene("default", frames=N, size=(32, 32))
    mask = cv.make_code("hitomi", (32, 32), frames=N, bump=2, seed=0)
    coded = cv.simulate(video, mask)
    with pytest.warns(UserWarning, match="truth peaks at .* are they in the same units"):
        cv.reconstruct(coded, mask, truth=video * np.float32(factor), full_output=True)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        cv.reconstruct(coded, mask, truth=video, full_output=True)
    for name, array in (("coded", coded), ("mask", mask), ("truth", video * np.float32(factor)), ("good", video)):
        np.save(tmp_path / f"{name}.npy", array)
    for truth, warned in (("truth", True), ("good", False)):
        with warnings.catch_warnings(record=True) as said:
            warnings.simplefilter("always")
            rc = main(["-q", "reconstruct", "--coded", str(tmp_path / "coded.npy"), "--mask",
                       str(tmp_path / "mask.npy"), "--truth", str(tmp_path / f"{truth}.npy"), "--output",
                       str(tmp_path / f"{truth}-out.npy")])
        messages = [str(w.message) for w in said]
        assert rc == 0 and any("are they in the same units" in m for m in messages) == warned, messages


def test_a_black_truth_is_not_warned_of_as_other_units():
    """A truth black throughout says nothing of its units: reconstruct warned 'truth peaks at 0 ... same units?'."""
    mask = cv.make_code("hitomi", (SMALL, SMALL), frames=N, bump=2, seed=0)
    video = cv.synthetic_scene("default", frames=N, size=(SMALL, SMALL))
    with warnings.catch_warnings(record=True) as said:
        warnings.simplefilter("always")
        cv.reconstruct(cv.simulate(video, mask), mask, truth=np.zeros_like(video), full_output=True)
    assert not any("same units" in str(w.message) for w in said), [str(w.message) for w in said]


@pytest.fixture()
def capture_files(tmp_path):
    video = cv.synthetic_scene("default", frames=N, size=(SMALL, SMALL))
    mask = cv.make_code("hitomi", (SMALL, SMALL), frames=N, bump=2, seed=0)
    np.save(tmp_path / "coded.npy", cv.simulate(video, mask))
    np.save(tmp_path / "mask.npy", mask)
    return ["--coded", str(tmp_path / "coded.npy"), "--mask", str(tmp_path / "mask.npy")]


@pytest.mark.parametrize("extra, said", [
    (["--trust-saturated"], "--trust-saturated: keeps the pixels --white-level or --bits marks saturated"),
    (["--fps", "24"], "--fps 24 with --output"),
])
def test_reconstruct_refuses_a_flag_it_would_ignore_before_any_work(tmp_path, capsys, capture_files, extra, said):
    """`--trust-saturated` without a white level or bit depth, and `--fps` with an array output, changed
    nothing and were taken silently; refused as any ignored value is (docs/guarantees.md)."""
    capsys.readouterr()
    rc = main(["-q", "reconstruct", *capture_files, "--output", str(tmp_path / "out.npy"), *extra])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and len(err.splitlines()) == 1 and said in err, err
    assert not (tmp_path / "out.npy").exists()
    assert main(["-q", "reconstruct", *capture_files, "--output", str(tmp_path / "out.mp4"), "--fps", "24"]) == 0


def test_the_api_refuses_trust_saturated_without_a_white_level_in_its_own_terms(capture_files):
    coded, mask = np.load(capture_files[1]), np.load(capture_files[3])
    with pytest.raises(cv.ConfigError, match="option trust_saturated: keeps the pixels white_level or bits"):
        cv.reconstruct(coded, mask, trust_saturated=True)


def test_the_api_takes_bad_pixels_as_an_array_and_gives_the_files_bits(tmp_path, capture_files):
    """`bad_pixels=[[1, 1]]` raised a bare TypeError; an array of (y, x) rows (or a map) is now taken as the file
    of the same rows is, through both doors; a row outside the image is the file's one-line error."""
    coded, mask = np.load(capture_files[1]), np.load(capture_files[3])
    rows = np.array([[1, 1], [5, 9]])
    np.save(tmp_path / "bad.npy", rows)
    from_array = cv.reconstruct(coded, mask, bad_pixels=rows.tolist(), full_output=True)
    json.dumps(from_array.record, default=str)
    np.testing.assert_array_equal(from_array.frames, cv.reconstruct(coded, mask, bad_pixels=str(tmp_path / "bad.npy")))
    bad_map = np.zeros(coded.shape, bool)
    bad_map[1, 1] = bad_map[5, 9] = True
    np.testing.assert_array_equal(from_array.frames, cv.reconstruct(coded, mask, bad_pixels=bad_map))
    assert main(["-q", "reconstruct", *capture_files, "--bad-pixels", str(tmp_path / "bad.npy"),
                 "--output", str(tmp_path / "r.npy")]) == 0
    np.testing.assert_array_equal(np.load(tmp_path / "r.npy"), from_array.frames)
    with pytest.raises(cv.InputError, match="bad_pixels"):
        cv.reconstruct(coded, mask, bad_pixels=[[1, 99]])


@pytest.mark.parametrize("frames", [1, 4])
def test_a_code_that_opens_every_pixel_alike_needs_no_dictionary_through_both_doors(tmp_path, capsys, frames):
    """A global shutter (N = 1, or every pixel open in all 4 sub-frames) is solved by the static estimate,
    coded / N (docs/guarantees.md), yet asked for a dictionary of N that is not shipped; it no longer does, and a
    code that moves at that N still does."""
    video = cv.synthetic_scene("default", frames=frames, size=(SMALL, SMALL))
    mask = np.ones((frames, SMALL, SMALL), np.uint8)
    coded = cv.simulate(video, mask)
    frames_out = cv.reconstruct(coded, mask)
    np.testing.assert_allclose(frames_out, np.broadcast_to(coded / frames, frames_out.shape), rtol=1e-6)
    np.save(tmp_path / "coded.npy", coded)
    np.save(tmp_path / "mask.npy", mask)
    assert main(["-q", "reconstruct", "--coded", str(tmp_path / "coded.npy"), "--mask", str(tmp_path / "mask.npy"),
                 "--output", str(tmp_path / "out.npy")]) == 0
    np.testing.assert_array_equal(np.load(tmp_path / "out.npy"), frames_out)
    if frames > 1:
        moving = cv.make_code("hitomi", (SMALL, SMALL), frames=frames, bump=2, seed=0)
        with pytest.raises(cv.InputError, match=f"no dictionary is shipped for N = {frames}"):
            cv.reconstruct(cv.simulate(video, moving), moving)


def test_one_mask_as_a_stack_of_one_is_shared_by_a_stream_through_both_doors(tmp_path):
    """The command line shares a (1, N, H, W) mask among T captures; the API refused it ('6 coded images, 1
    masks'); both now share it, with the same bits as the (N, H, W) mask."""
    import dask.array as da

    mask = cv.make_code("hitomi", (SMALL, SMALL), frames=N, bump=2, seed=0)
    video = cv.synthetic_scene("default", frames=3 * N, size=(SMALL, SMALL))
    coded = cv.simulate(video, mask[None].repeat(3, 0))
    want = cv.reconstruct(coded, mask)
    np.testing.assert_array_equal(cv.reconstruct(coded, mask[None]), want)
    np.testing.assert_array_equal(cv.reconstruct(da.from_array(coded, chunks=(1, SMALL, SMALL)), mask[None]).compute(),
                                  want)
    np.save(tmp_path / "coded.npy", coded)
    np.save(tmp_path / "mask.npy", mask[None])
    assert main(["-q", "reconstruct", "--coded", str(tmp_path / "coded.npy"), "--mask", str(tmp_path / "mask.npy"),
                 "--output", str(tmp_path / "r.npy")]) == 0
    np.testing.assert_array_equal(np.load(tmp_path / "r.npy"), want)


def test_a_data_range_far_above_the_captures_is_said_through_both_doors(tmp_path):
    """camera.md's own `--data-range 4095`, given for 8-bit frames: no word, a PSNR of 51.1 dB that is 27.0 at 255,
    and a tolerance 16 times too loose.  Both doors now warn before any work; the range that fits does not."""
    video = cv.synthetic_scene("default", frames=8, size=(32, 32))
    mask = cv.make_code("hitomi", (32, 32), frames=8, bump=2, seed=0)
    coded = cv.simulate(video, mask)
    for given, warned in ((4095.0, True), (255.0, False)):
        with warnings.catch_warnings(record=True) as said:
            warnings.simplefilter("always")
            cv.reconstruct(coded, mask, data_range=given)
        messages = [str(w.message) for w in said if "under 1/16 of the data range" in str(w.message)]
        assert bool(messages) == warned, (given, [str(w.message) for w in said])
        if warned:
            assert "data range 4095 given (data_range)" in messages[0], messages
    np.save(tmp_path / "coded.npy", coded)
    np.save(tmp_path / "mask.npy", mask)
    with warnings.catch_warnings(record=True) as said:
        warnings.simplefilter("always")
        assert main(["-q", "reconstruct", "--coded", str(tmp_path / "coded.npy"), "--mask", str(tmp_path / "mask.npy"),
                     "--data-range", "4095", "--output", str(tmp_path / "r.npy")]) == 0
    said = [str(w.message) for w in said]
    assert any("coded.npy" in m and "data range 4095 given (--data-range)" in m for m in said), said


def test_a_nan_in_a_stream_names_its_capture_through_both_doors(tmp_path, capsys):
    """The command line said `capture 3` of a stream's NaN; the API, numpy and dask alike, named none."""
    da = pytest.importorskip("dask.array")
    video = cv.synthetic_scene("default", frames=8, size=(32, 32))
    mask = cv.make_code("hitomi", (32, 32), frames=8, bump=2, seed=0)
    coded = np.stack([cv.simulate(video, mask)] * 3)
    coded[2, 3, 3] = np.nan
    for given in (coded, da.from_array(coded, chunks=(1, 32, 32))):
        with pytest.raises(cv.InputError, match=r"contains NaN or Inf \(capture 3 of 3\)"):
            out = cv.reconstruct(given, mask)
            getattr(out, "compute", lambda: out)()
    with pytest.raises(cv.InputError, match=r"truth: contains NaN or Inf \(frame 9 of 24\)"):
        truth = np.concatenate([video] * 3)
        truth[8, 0, 0] = np.inf
        cv.reconstruct(np.nan_to_num(coded), mask, truth=truth)
