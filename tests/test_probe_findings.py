"""Adversarial-probe findings not covered elsewhere: a NaN/Inf video refused by simulate through both doors, the
K-SVD defaults read from one place, and --adapt free of any quantity in data units (tests/test_one_door.py holds
the empty code shapes and the NaN/Inf captures and masks; tests/test_owned_folders.py the in-place edits)."""
import inspect
import json
import re
import warnings

import numpy as np
import pytest

import codedvideo as cv
from codedvideo.app.cli import main

N, SIZE = 8, 16


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_simulate_refuses_a_video_with_nan_or_inf_through_both_doors(tmp_path, capsys, bad):
    video = cv.synthetic_scene("default", frames=N, size=(SIZE, SIZE))
    video[3, 4, 5] = bad
    mask = cv.make_code("hitomi", (SIZE, SIZE), frames=N, bump=2)
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


def test_the_k_svd_defaults_are_one_set_through_the_api_the_config_and_the_solver():
    from codedvideo.engine.config import DictionaryConfig
    from codedvideo.solvers.dictionaries import KsvdSettings, learn_dictionary

    api = inspect.signature(cv.train).parameters
    solver = inspect.signature(learn_dictionary).parameters["settings"].default
    assert solver == KsvdSettings()
    for key in ("atoms", "samples", "iterations", "sparsity"):
        config = DictionaryConfig.model_fields[key].default
        assert api[key].default == getattr(solver, key) == config, (key, api[key].default, getattr(solver, key), config)


@pytest.fixture(scope="module")
def carphone():
    from codedvideo.data.scenes import load_video

    video = load_video("footage:carphone", frames=N, size=(48, 48))
    mask = cv.make_code("hitomi", (48, 48), frames=N, bump=2, seed=0)
    return video, mask, cv.simulate(video, mask)


@pytest.mark.parametrize("options", [dict(adapt=True, adapt_rounds=2, noise_sigma=2.0), dict(preset="best")])
def test_adapt_works_in_working_units_a_power_of_two_scale_gives_the_same_bits(carphone, options):
    """--adapt (K-SVD per capture, then --refine with best) holds no quantity in the capture's units: a capture
    scaled by a power of two, whose working units are then the same floats, gives the same bits scaled.  (Another
    scale's float32 roundoff can flip K-SVD's greedy choices: docs/formats.md, "Units".)"""
    _, mask, coded = carphone
    base = cv.reconstruct(coded, mask, data_range=255.0, **options)
    for scale in (1024.0, 1 / 1024):
        scaled = dict(options, noise_sigma=options["noise_sigma"] * scale) if "noise_sigma" in options else options
        got = cv.reconstruct(coded * np.float32(scale), mask, data_range=255.0 * scale, **scaled)
        np.testing.assert_array_equal(got / np.float32(scale), base)


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


@pytest.mark.parametrize("planes", [2, 4, 5])
def test_color_channels_refuses_an_npy_of_other_than_1_or_3_planes_before_any_work(tmp_path, capsys, planes):
    """`--color channels` on a (5, H, W) .npy (a stream of captures) took it for 5 colour channels, ran the whole
    reconstruction and failed only at the video writer; now it is refused first, naming the file."""
    video = cv.synthetic_scene("default", frames=N, size=(SIZE, SIZE))
    mask = cv.make_code("hitomi", (SIZE, SIZE), frames=N, bump=2, seed=0)
    coded = cv.simulate(video, mask)
    np.save(tmp_path / "coded.npy", np.stack([coded] * planes))
    np.save(tmp_path / "mask.npy", mask)
    cache = tmp_path / "cache"
    capsys.readouterr()
    rc = main(["-q", "reconstruct", "--coded", str(tmp_path / "coded.npy"), "--mask", str(tmp_path / "mask.npy"),
               "--color", "channels", "--cache", str(cache), "--output", str(tmp_path / "out.mp4")])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and len(err.splitlines()) == 1, err
    assert "coded.npy" in err and f"{planes} colour channels" in err, err
    assert not (tmp_path / "out.mp4").exists() and not (cache.exists() and any(cache.iterdir()))


def test_color_channels_refuses_a_stack_of_other_than_1_or_3_channels(tmp_path):
    from codedvideo.formats.io import read_stack

    np.save(tmp_path / "mask.npy", np.ones((5, N, SIZE, SIZE), np.float32))
    with pytest.raises(cv.InputError, match="mask.npy: 5 colour channels"):
        read_stack(tmp_path / "mask.npy", color="channels")
    np.save(tmp_path / "rgb.npy", np.ones((3, N, SIZE, SIZE), np.float32))
    assert read_stack(tmp_path / "rgb.npy", color="channels").shape == (3, N, SIZE, SIZE)


@pytest.mark.parametrize("call, said", [
    (lambda: cv.simulate(np.ones((N, SIZE, SIZE)), cv.make_code("global", (SIZE, SIZE), frames=N), seed=-1),
     "option seed -1"),
    (lambda: cv.make_code("bernoulli", (SIZE, SIZE), frames=N, seed=-1), "option seed -1"),
    (lambda: cv.make_code("bernoulli", (SIZE, SIZE), frames=N, seed=1.5), "option seed 1.5"),
    (lambda: cv.make_code("hitomi", (SIZE, SIZE), frames=N, bump=2, p=0.3), "p: code 'hitomi' does not use it"),
    (lambda: cv.make_code("bernoulli", (SIZE, SIZE), frames=N, bump=3), "bump: code 'bernoulli' does not use it"),
])
def test_the_apis_seed_and_code_options_are_checked_as_the_command_lines_are(call, said):
    """A bad seed raised numpy's own error, and a code option the code does not use was taken silently; the command
    line refuses both with one line naming the option."""
    with pytest.raises(cv.ConfigError, match=re.escape(said)):
        call()


def test_a_command_quoted_in_an_api_message_keeps_its_options():
    """The API's messages name its arguments, but a command they quote is run as written (`--frames`, not
    `frames`)."""
    mask = cv.make_code("hitomi", (SIZE, SIZE), frames=4, bump=2, seed=0)
    with pytest.raises(cv.InputError) as raised:
        cv.reconstruct(np.ones((SIZE, SIZE), np.float32), mask)
    assert "`codedvideo train --frames 4 --output dict-N4.zarr`" in str(raised.value), str(raised.value)


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


def test_simulate_bits_with_a_white_level_spans_it_in_the_videos_units_as_documented():
    """`bits=8, white_level=200`: the 256 levels of an ADC whose full scale is 200 grey levels (docs/api.md), so the
    values are multiples of 200 / 255, not raw counts; they reconstruct as grey levels (no `bits`)."""
    video = cv.synthetic_scene("default", frames=N, size=(SIZE, SIZE))
    mask = cv.make_code("hitomi", (SIZE, SIZE), frames=N, bump=2, seed=0)
    coded = cv.simulate(video, mask, sensor=dict(bits=8, white_level=200.0))
    levels = coded.astype(np.float64) / (200.0 / 255)
    assert coded.max() <= 200 and np.allclose(levels, np.round(levels), atol=1e-3)
    assert not np.allclose(coded, np.round(coded))  # not whole numbers: not raw counts
    assert np.isfinite(cv.reconstruct(coded, mask, white_level=200.0)).all()


@pytest.fixture()
def capture_files(tmp_path):
    video = cv.synthetic_scene("default", frames=N, size=(SIZE, SIZE))
    mask = cv.make_code("hitomi", (SIZE, SIZE), frames=N, bump=2, seed=0)
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


def test_simulate_refuses_a_new_code_per_capture_for_one_capture(tmp_path, capsys):
    capsys.readouterr()
    rc = main(["-q", "simulate", "synth:default", "--frames", str(N), "--size", "16", "16", "--new-code-per-capture",
               "--output", str(tmp_path / "cap")])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and "--new-code-per-capture: one capture is made" in err and len(err.splitlines()) == 1, err
    assert not (tmp_path / "cap").exists()


def test_cache_verify_of_a_file_says_it_is_not_a_folder(tmp_path, capsys):
    (tmp_path / "f").write_text("x")
    capsys.readouterr()
    assert main(["-q", "cache", "verify", str(tmp_path / "f")]) == 2
    assert "not a folder" in capsys.readouterr().err


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
    video = cv.synthetic_scene("default", frames=frames, size=(SIZE, SIZE))
    mask = np.ones((frames, SIZE, SIZE), np.uint8)
    coded = cv.simulate(video, mask)
    frames_out = cv.reconstruct(coded, mask)
    np.testing.assert_allclose(frames_out, np.broadcast_to(coded / frames, frames_out.shape), rtol=1e-6)
    np.save(tmp_path / "coded.npy", coded)
    np.save(tmp_path / "mask.npy", mask)
    assert main(["-q", "reconstruct", "--coded", str(tmp_path / "coded.npy"), "--mask", str(tmp_path / "mask.npy"),
                 "--output", str(tmp_path / "out.npy")]) == 0
    np.testing.assert_array_equal(np.load(tmp_path / "out.npy"), frames_out)
    if frames > 1:
        moving = cv.make_code("hitomi", (SIZE, SIZE), frames=frames, bump=2, seed=0)
        with pytest.raises(cv.InputError, match=f"no dictionary is shipped for N = {frames}"):
            cv.reconstruct(cv.simulate(video, moving), moving)


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


def test_a_coded_stream_read_from_a_lossy_video_is_warned_of(tmp_path):
    """An H.264 .mp4 was taken as the coded stream without a word, though its compression changes the values the
    sensor recorded (the docs ask for a lossless video); FFV1 in .mkv is read as it is, silently."""
    from codedvideo.formats.io import write_video
    from codedvideo.formats.volumes import read_coded_stack

    mask = cv.make_code("hitomi", (SIZE, SIZE), frames=N, bump=2, seed=0)
    video = cv.synthetic_scene("default", frames=3 * N, size=(SIZE, SIZE))
    coded = np.round(cv.simulate(video, np.stack([mask] * 3)) / 2).astype(np.float32)  # (3, H, W), within 8 bits
    write_video(tmp_path / "c.mp4", coded)
    write_video(tmp_path / "c.mkv", coded)
    with pytest.warns(UserWarning, match="c.mp4: a h264 video, whose compression changes the values"):
        read_coded_stack(tmp_path / "c.mp4")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        stack = read_coded_stack(tmp_path / "c.mkv")
    np.testing.assert_array_equal(np.stack([stack[i] for i in range(len(stack))]), coded)


def test_a_dask_mosaic_under_bayer_gives_the_numpy_paths_colour_frames(tmp_path):
    """`bayer=` with a dask mosaic gave a lazy (N, H, W) array whose computing failed ('coded (1, H, W); under
    bayer= it is one mosaic (H, W)'); it now gives the numpy path's (3, N, H, W) frames."""
    import dask.array as da

    cap = tmp_path / "cap"
    assert main(["-q", "simulate", "synth:color-default", "--frames", str(N), "--bump", "2", "--bayer", "rggb",
                 "--size", "32", "32", "--output", str(cap)]) == 0
    coded, mask = np.load(cap / "coded.npy"), np.load(cap / "mask.npy")
    want = cv.reconstruct(coded, mask, bayer="RGGB")
    lazy = cv.reconstruct(da.from_array(coded), mask, bayer="RGGB")
    assert lazy.shape == want.shape == (3, N, 32, 32)
    np.testing.assert_array_equal(lazy.compute(), want)


def test_one_mask_as_a_stack_of_one_is_shared_by_a_stream_through_both_doors(tmp_path):
    """The command line shares a (1, N, H, W) mask among T captures; the API refused it ('6 coded images, 1
    masks'); both now share it, with the same bits as the (N, H, W) mask."""
    import dask.array as da

    mask = cv.make_code("hitomi", (SIZE, SIZE), frames=N, bump=2, seed=0)
    video = cv.synthetic_scene("default", frames=3 * N, size=(SIZE, SIZE))
    coded = cv.simulate(video, mask[None].repeat(3, 0))
    want = cv.reconstruct(coded, mask)
    np.testing.assert_array_equal(cv.reconstruct(coded, mask[None]), want)
    np.testing.assert_array_equal(cv.reconstruct(da.from_array(coded, chunks=(1, SIZE, SIZE)), mask[None]).compute(),
                                  want)
    np.save(tmp_path / "coded.npy", coded)
    np.save(tmp_path / "mask.npy", mask[None])
    assert main(["-q", "reconstruct", "--coded", str(tmp_path / "coded.npy"), "--mask", str(tmp_path / "mask.npy"),
                 "--output", str(tmp_path / "r.npy")]) == 0
    np.testing.assert_array_equal(np.load(tmp_path / "r.npy"), want)


def test_a_dask_inputs_warnings_name_the_apis_arguments():
    """Warnings said while a dask input's graph is computed named the command line's options (--tol-rms)."""
    import dask.array as da

    mask = cv.make_code("hitomi", (SIZE, SIZE), frames=N, bump=2, seed=0)
    coded = cv.simulate(cv.synthetic_scene("default", frames=N, size=(SIZE, SIZE)), mask)
    with warnings.catch_warnings(record=True) as said:
        warnings.simplefilter("always")
        cv.reconstruct(da.from_array(coded), mask, data_range=65535).compute()
    messages = [str(w.message) for w in said]
    assert any("data_range" in m for m in messages), messages
    assert not any("--" in m for m in messages), messages


def test_a_black_truth_is_not_warned_of_as_other_units():
    """A truth black throughout says nothing of its units: reconstruct warned 'truth peaks at 0 ... same units?'."""
    mask = cv.make_code("hitomi", (SIZE, SIZE), frames=N, bump=2, seed=0)
    video = cv.synthetic_scene("default", frames=N, size=(SIZE, SIZE))
    with warnings.catch_warnings(record=True) as said:
        warnings.simplefilter("always")
        cv.reconstruct(cv.simulate(video, mask), mask, truth=np.zeros_like(video), full_output=True)
    assert not any("same units" in str(w.message) for w in said), [str(w.message) for w in said]


def test_dictionary_records_that_do_not_fit_are_named_plainly(tmp_path):
    """A store whose record says frames '8' (a string) was refused as 'built for N = 8, the mask has N = 8'; one
    whose atoms have the wrong rows was refused without its file; training's --init spoke of a mask."""
    from codedvideo.formats.store import check_dictionary

    with pytest.raises(cv.InputError, match=r"d.zarr: its record's frames '8' is not a whole number"):
        check_dictionary(dict(patch=7, frames="8"), 8, tmp_path / "d.zarr")
    with pytest.raises(cv.InputError, match=r"d.zarr: atoms of 300 rows; N = 8 needs N x 49 = 392"):
        check_dictionary(dict(patch=7, frames=8), 8, tmp_path / "d.zarr", np.zeros((300, 4), np.float32))
    with pytest.raises(cv.InputError, match=r"built for N = 16 sub-frames, training for N = 8"):
        check_dictionary(dict(patch=7, frames=16), 8, tmp_path / "d.zarr", needs="training for")


def test_a_bump_of_15_of_16_stays_within_the_data_range_through_both_doors(tmp_path):
    """A bump of 15 of 16 sub-frames leaves the motion nearly unobserved: OMP gave values from -578 to 1202 on
    8-bit frames (8.4 dB against the trivial estimate's 25.1), then a warning that they lay far outside the data
    range.  Under the guard (docs/guarantees.md) the default and the 3D DCT stay within a quarter of the range
    of it, and neither door has anything to warn of (a range that does not fit is still said:
    tests/test_units.py)."""
    video = cv.synthetic_scene("default", frames=16, size=(32, 32))
    mask = cv.make_code("hitomi", (32, 32), frames=16, bump=15, seed=0)
    coded = cv.simulate(video, mask)
    for method in ("omp", "dct"):
        with warnings.catch_warnings(record=True) as said:
            warnings.simplefilter("always")
            frames = cv.reconstruct(coded, mask, method=method)
        assert not [w for w in said if "far outside the data range" in str(w.message)], method
        assert -0.25 * 255 <= frames.min() and frames.max() <= 1.25 * 255, (method, frames.min(), frames.max())
    np.save(tmp_path / "coded.npy", coded)
    np.save(tmp_path / "mask.npy", mask)
    with warnings.catch_warnings(record=True) as said:
        warnings.simplefilter("always")
        assert main(["-q", "reconstruct", "--coded", str(tmp_path / "coded.npy"), "--mask", str(tmp_path / "mask.npy"),
                     "--output", str(tmp_path / "r.npy")]) == 0
    assert not any("far outside the data range" in str(w.message) for w in said)
    np.testing.assert_array_equal(np.load(tmp_path / "r.npy"), cv.reconstruct(coded, mask))


def test_simulate_refuses_a_black_level_with_a_cacti_file(tmp_path, capsys):
    """`--black-level 64 --cacti-out F.mat` wrote a meas 64 above the plain sum CACTI files hold, silently (17.9 dB
    read back against 32.1); refused before any work."""
    capsys.readouterr()
    rc = main(["-q", "simulate", "synth:default", "--frames", str(N), "--size", "16", "16", "--black-level", "64",
               "--output", str(tmp_path / "cap"), "--cacti-out", str(tmp_path / "c.mat")])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and "--black-level 64" in err and "plain sum" in err and len(err.splitlines()) == 1, err
    assert not (tmp_path / "cap").exists() and not (tmp_path / "c.mat").exists()


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


def test_a_tiff_of_separate_planes_read_as_one_capture_is_said(tmp_path):
    """tifffile stores a (3, H, W) array as planar RGB: a stack of three captures saved so was read as one capture,
    their luma, with no word.  It is now warned of; an interleaved colour TIFF is not."""
    tifffile = pytest.importorskip("tifffile")
    from codedvideo.formats import io as cio

    stack = np.arange(3 * 8 * 8, dtype=np.uint16).reshape(3, 8, 8)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)  # (tifffile's own, about this very layout)
        tifffile.imwrite(tmp_path / "planes.tif", stack)
    tifffile.imwrite(tmp_path / "rgb.tif", np.moveaxis(stack, 0, -1), photometric="rgb")
    for name, warned in (("planes.tif", True), ("rgb.tif", False)):
        with warnings.catch_warnings(record=True) as said:
            warnings.simplefilter("always")
            assert cio.read_image(tmp_path / name).shape == (8, 8)
        messages = [str(w.message) for w in said if "separate planes" in str(w.message)]
        assert bool(messages) == warned, name
        if warned:
            assert "planes.tif" in messages[0] and "3 channels" in messages[0], messages


def test_float_tiffs_read_back_without_optional_codecs(tmp_path):
    """The float TIFFs codedvideo writes used libtiff's floating-point predictor, which tifffile and scikit-image
    decode only with the optional imagecodecs package; they are now plain deflate, read by both as written."""
    tifffile = pytest.importorskip("tifffile")
    from codedvideo.formats import io as cio

    frames = np.random.default_rng(0).random((3, 8, 8)).astype(np.float32)
    cio.write_stack(tmp_path / "s.tif", frames)
    cio.write_image(tmp_path / "f.tif", frames[0])
    with tifffile.TiffFile(tmp_path / "s.tif") as tif:
        assert tif.pages[0].predictor == 1 and tif.pages[0].compression == 8  # none, deflate
    assert np.array_equal(tifffile.imread(tmp_path / "s.tif"), frames)
    assert np.array_equal(tifffile.imread(tmp_path / "f.tif"), frames[0])


def test_a_block_of_missing_pixels_stays_within_sensible_values_with_the_non_local_method(tmp_path):
    """An 8x8 square of bad pixels (or of saturated ones) ended `--preset best` and `nonlocal --adapt` with a
    RuntimeError traceback (the survey's grid patch inside it is no reference, and no group reached the pixels
    around it), and a 13x13 one gave values from -2031 to 2612 (groups' atoms fitted to the few measured pixels
    of a corner).  Patches that see too few measurements are now in no group, and pixels no group reaches keep
    the first estimate: every value within the default's spread, the rest of the frame better than the
    default's."""
    video = cv.synthetic_scene("default", frames=8, size=(64, 64))
    mask = cv.make_code("hitomi", (64, 64), frames=8, bump=2, seed=0)
    coded = cv.simulate(video, mask)
    for y0, side in ((20, 8), (15, 13)):
        bad = np.zeros((64, 64), bool)
        bad[y0:y0 + side, y0:y0 + side] = True  # (the first holds the survey's grid patch at 21..27)
        default = cv.reconstruct(coded, mask, bad_pixels=bad)
        frames = cv.reconstruct(coded, mask, method="nonlocal", adapt=True, bad_pixels=bad)
        assert np.isfinite(frames).all()
        spread = default.max() - default.min()
        assert default.min() - spread / 2 < frames.min() and frames.max() < default.max() + spread / 2, side
        far = np.ones((64, 64), bool)
        far[y0 - 6:y0 + side + 6, y0 - 6:y0 + side + 6] = False  # the square and the patches that reach into it
        error = {name: float(np.mean((f[:, far] - video[:, far]) ** 2)) for name, f in (("adapt", frames),
                                                                                     ("omp", default))}
        assert error["adapt"] < error["omp"], (side, error)


def test_a_folder_with_one_image_of_another_size_names_it(tmp_path, capsys):
    """A mask folder with one odd-sized image said `frames differ in shape [(32, 32), (64, 64)]`, naming no file."""
    from codedvideo.formats import io as cio

    (tmp_path / "m").mkdir()
    for i in range(3):
        cio.write_image(tmp_path / "m" / f"m{i}.png", np.full((16, 16) if i == 2 else (32, 32), 255, np.uint8))
    np.save(tmp_path / "coded.npy", np.ones((32, 32), np.float32))
    assert main(["reconstruct", "--coded", str(tmp_path / "coded.npy"), "--mask", str(tmp_path / "m"),
                 "--output", str(tmp_path / "r.npy")]) == 2
    assert "m2.png is (16, 16), m0.png (32, 32)" in capsys.readouterr().err
    assert not (tmp_path / "r.npy").exists()


def test_quiet_after_the_command_says_where_it_goes(capsys):
    """`codedvideo reconstruct -q ...` said only `unrecognized arguments: -q`."""
    assert main(["reconstruct", "-q", "--coded", "c.npy", "--mask", "m.npy", "--output", "r.npy"]) == 2
    assert "-q goes before the command" in capsys.readouterr().err


def test_the_fallback_of_the_non_local_method_says_the_dictionary_was_adapted():
    """A calibrated mask of many pixel patterns gives the per-patch OMP in place of the groups; with `--adapt` its
    dictionary is the adapted one, where the warning called it the default's answer."""
    video = cv.synthetic_scene("default", frames=8, size=(32, 32))
    mask = cv.make_code("hitomi", (32, 32), frames=8, bump=2, seed=0).astype(np.float32)
    mask = np.clip(mask * 0.9 + np.random.default_rng(0).random(mask.shape).astype(np.float32) * 0.1, 0, 1)
    coded = cv.simulate(video, mask)
    for adapt in (True, False):
        with warnings.catch_warnings(record=True) as said:
            warnings.simplefilter("always")
            cv.reconstruct(coded, mask, method="nonlocal", adapt=adapt)
        fallback = [str(w.message) for w in said if "distinct pixel shutter patterns" in str(w.message)]
        assert len(fallback) == 1 and ("with the adapted dictionary" in fallback[0]) == adapt, fallback


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


def test_a_raw_value_beyond_the_bits_in_a_folder_names_its_file(tmp_path, capsys):
    """`--bits 8` on a folder of 16-bit PNGs named the folder and the capture's number, not the file."""
    from codedvideo.formats import io as cio

    (tmp_path / "coded").mkdir()
    for i in range(3):
        cio.write_image(tmp_path / "coded" / f"c{i}.png", np.full((32, 32), 300 if i == 1 else 100, np.uint16),
                        dtype="uint16")
    np.save(tmp_path / "mask.npy", np.ones((8, 32, 32), np.uint8))
    assert main(["reconstruct", "--coded", str(tmp_path / "coded"), "--mask", str(tmp_path / "mask.npy"),
                 "--bits", "8", "--output", str(tmp_path / "r.npy")]) == 2
    assert "capture 2 of 3 (c1.png): value 300 is above 255" in capsys.readouterr().err
