"""Temporal windows (solvers/temporal.py): a capture at N = 16 or 18 whose pixels each open briefly, seen as
overlapping captures of 8 sub-frames as well, on real footage the dictionaries never saw."""
import json

import numpy as np
import pytest

import codedvideo as cv
from codedvideo.data import shipped
from codedvideo.data.footage import footage_scene
from codedvideo.formats.store import load_dictionary
from codedvideo.model.metrics import evaluate
from codedvideo.solvers import guard, temporal
from codedvideo.solvers.baselines import gap_tv, static_estimate

SIZE = 64


def _score(frames, truth):
    return evaluate(np.clip(frames, 0, 1), truth, data_range=1.0)["psnr"]


@pytest.mark.parametrize("frames,first", [(16, [0, 2, 4, 6, 8]), (18, [0, 2, 4, 6, 8, 10]), (9, [0, 1])])
def test_the_windows_cover_every_sub_frame(frames, first):
    assert temporal.starts(frames) == first
    assert first[-1] + temporal.WINDOW == frames


def test_a_window_measures_the_pixels_whose_exposure_lies_inside_it():
    mask = cv.make_code("hitomi", (SIZE, SIZE), frames=16, seed=0, bump=2)
    coded = np.random.default_rng(0).random((SIZE, SIZE)).astype(np.float32) + 1
    opening = np.argmax(mask, axis=0)
    for s in temporal.starts(16):
        coded_w, mask_w = temporal.window_capture(coded, mask, s)
        inside = (opening >= s) & (opening + 2 <= s + temporal.WINDOW)
        assert mask_w.shape == (temporal.WINDOW, SIZE, SIZE)
        assert np.array_equal(mask_w.any(0), inside)
        assert np.array_equal(mask_w.sum(0)[inside], mask.sum(0)[inside])
        assert np.array_equal(coded_w[inside], coded[inside]) and not coded_w[~inside].any()


def test_the_windows_of_one_volume_combine_to_it():
    volume = np.random.default_rng(1).random((18, 5, 6)).astype(np.float32)
    first = temporal.starts(18)
    parts = [volume[s:s + temporal.WINDOW] for s in first]
    assert np.allclose(temporal.combined(parts, first, 18), volume, atol=1e-6)
    # each sub-frame leans on the windows whose centre is nearest
    weights = temporal.tent()
    assert weights.argmax() in (3, 4) and weights.min() >= 0.5


@pytest.mark.parametrize("frames,code,kw,expected", [
    (16, "hitomi", dict(bump=1), True),
    (16, "hitomi", dict(bump=2), True),
    (18, "hitomi", dict(bump=2), True),
    (16, "grid", {}, True),
    (18, "grid", {}, True),
    (16, "hitomi-tiled", dict(bump=2), True),
    (8, "hitomi", dict(bump=2), False),  # the paper's codes: one window is the capture
    (8, "grid", {}, False),
    (16, "hitomi", dict(bump=3), False),  # blended with GAP-TV by the guard
    (16, "bernoulli", dict(p=0.5), False),  # pixels open across the capture
    (16, "shifting", dict(p=0.5), False),
    (16, "rowwise", dict(bump=2), False),  # shared along rows: the guard halves its weight
])
def test_windows_apply_to_short_exposures_beyond_eight_sub_frames(frames, code, kw, expected):
    mask = cv.make_code(code, (SIZE, SIZE), frames=frames, seed=0, **kw)
    assert temporal.applies(mask, guard.sparse_weight(mask)[0]) is expected


def test_windows_leave_out_a_calibrated_mask_and_a_code_blind_to_a_sub_frame():
    mask = cv.make_code("hitomi", (SIZE, SIZE), frames=16, seed=0, bump=2).astype(np.float32)
    assert not temporal.applies(0.9 * mask, 1.0)
    blind = mask.copy()
    blind[5] = 0
    assert not temporal.applies(blind, 1.0)
    assert temporal.exposure_span(blind).max() <= 2


@pytest.mark.parametrize("frames,scene,corner,code,kw", [
    (16, "bikes-a", (192, 0), "hitomi", dict(bump=2)),
    (16, "bunny", (192, 0), "grid", {}),
])
def test_an_abrupt_change_at_sixteen_sub_frames_is_not_below_the_simple_answers(frames, scene, corner, code, kw):
    # held-out corners where the default without windows fell below GAP-TV: a bar sweeping through the second
    # half of bikes-a (-2.12 dB) and a corner of bunny under the grid code (-3.15 dB)
    y0, x0 = corner
    video = (footage_scene(scene, frames=frames)[:, y0:y0 + SIZE, x0:x0 + SIZE] / 255).astype(np.float32)
    mask = cv.make_code(code, (SIZE, SIZE), frames=frames, seed=0, **kw)
    coded = cv.simulate(video, mask, seed=1)
    floor = max(_score(static_estimate(coded, mask), video), _score(gap_tv(coded, mask, data_range=1.0), video))
    result = cv.reconstruct(coded, mask, data_range=1.0, progress=False, full_output=True)
    assert _score(result.frames, video) >= floor - 0.3
    record = result.info[0]["windows"]
    assert record["starts"] == temporal.starts(frames) and record["full_weight"] == temporal.FULL_WEIGHT
    assert result.info[0]["seconds"]["windows"] > 0


def test_a_dictionary_of_ones_own_is_not_windowed():
    video = (footage_scene("bunny", frames=16, size=(32, 32)) / 255).astype(np.float32)
    mask = cv.make_code("grid", (32, 32), frames=16, seed=0)
    coded = cv.simulate(video, mask, seed=1)
    D, _ = load_dictionary(shipped.path_for(16))  # the shipped atoms, given as the user's own array
    result = cv.reconstruct(coded, mask, data_range=1.0, progress=False, full_output=True, dictionary=D)
    assert "windows" not in result.info[0]
    assert "windows" in cv.reconstruct(coded, mask, data_range=1.0, progress=False, full_output=True).info[0]


def test_the_full_result_is_kept_where_it_holds_still_and_weighs_a_quarter_where_it_moves():
    rng = np.random.default_rng(3)
    full = np.repeat(rng.random((1, 20, 40), dtype=np.float32) * 255, 16, axis=0)
    full[:, :, 20:] += 40 * rng.standard_normal((16, 20, 20)).astype(np.float32)  # the right half moves
    windows = full + 7
    w = temporal.full_weights(full)
    assert np.all(w[:, :10] == 1) and np.allclose(w[:, 30:], temporal.FULL_WEIGHT)
    out = temporal.blended(full, windows)
    assert np.array_equal(out[:, :, :10], full[:, :, :10])
    assert np.allclose(out[:, :, 30:], full[:, :, 30:] + 7 * (1 - temporal.FULL_WEIGHT), atol=1e-3)


def test_the_command_line_windows_as_the_api_does(tmp_path):
    from codedvideo.app.cli import main

    video = (footage_scene("bikes-a", frames=16, size=(32, 32)) / 255).astype(np.float32)
    mask = cv.make_code("hitomi", (32, 32), frames=16, seed=0, bump=2)
    coded = cv.simulate(video, mask, seed=1)
    np.save(tmp_path / "coded.npy", coded)
    np.save(tmp_path / "mask.npy", mask)
    assert main(["-q", "reconstruct", "--coded", str(tmp_path / "coded.npy"), "--mask", str(tmp_path / "mask.npy"),
                 "--data-range", "1", "--output", str(tmp_path / "r.npy")]) == 0
    api = cv.reconstruct(coded, mask, data_range=1.0, progress=False, full_output=True)
    np.testing.assert_array_equal(np.load(tmp_path / "r.npy"), api.frames)
    record = json.loads((tmp_path / "r.metrics.json").read_text())["reconstruction"]
    assert record["windows"]["starts"] == api.info[0]["windows"]["starts"] == temporal.starts(16)
