"""Adversarial-probe findings not covered elsewhere: a NaN/Inf video refused by simulate through both doors, the
K-SVD defaults read from one place, and --adapt free of any quantity in data units (tests/test_one_door.py holds
the empty code shapes and the NaN/Inf captures and masks; tests/test_owned_folders.py the in-place edits)."""
import inspect

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
    from codedvideo.solvers.dictionaries import learn_dictionary

    api = inspect.signature(cv.train).parameters
    solver = inspect.signature(learn_dictionary).parameters
    for key in ("atoms", "samples", "iterations", "sparsity"):
        config = DictionaryConfig.model_fields[key].default
        assert api[key].default == solver[key].default == config, (key, api[key].default, solver[key].default, config)


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
