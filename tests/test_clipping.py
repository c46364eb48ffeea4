"""Clipped captures: found without a flag in integer files, and used as what they are (lower bounds).

Before: an 8-bit single-bump capture whose brightest pixels sat at 255 was taken without a word (the clip test
compared open counts, which a single-bump code makes all equal), and ``--white-level 255`` left those pixels
out, 0.3 to 9 dB below taking them as exact on held-out scenes.
"""
import warnings

import numpy as np
import pytest

import codedvideo as cv
from codedvideo.app.cli import main


def _clipped(dtype, size=48):
    """synth:default coded with hitomi L = 2, scaled so that the brightest 5 % of coded pixels clip at the type's
    largest value: (coded, mask, truth in the same units)."""
    video = (cv.synthetic_scene("default", frames=8, size=(size, size)) / 255).astype(np.float32)
    mask = cv.make_code("hitomi", (size, size), frames=8, bump=2, seed=0)
    top = np.iinfo(dtype).max
    scale = top / np.percentile(cv.simulate(video, mask), 95)
    coded = np.clip(np.round(cv.simulate(video, mask) * scale), 0, top).astype(dtype)
    return coded, mask, video * scale, float(top)


def _psnr(frames, truth):
    return cv.evaluate(frames, truth, data_range=float(truth.max()))["psnr"]


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
def test_a_clipped_integer_capture_is_warned_of_without_a_flag(dtype):
    coded, mask, truth, top = _clipped(dtype)
    held = int((coded >= top).sum())
    with warnings.catch_warnings(record=True) as said:
        warnings.simplefilter("always")
        result = cv.reconstruct(coded, mask, data_range=float(truth.max()), full_output=True)
    messages = [str(w.message) for w in said if "clipped by the sensor" in str(w.message)]
    assert len(messages) == 1 and f"{held} of {coded.size}" in messages[0] and f"{top:g}" in messages[0], messages
    assert result.info[0]["saturated_pixels"] == held
    # every clipped pixel's frames record at least the level
    assert ((mask * result.frames).sum(0)[coded >= top] >= top - 1e-2 * top / 255).all()


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
def test_the_white_level_is_never_below_taking_every_value_as_exact(dtype):
    coded, mask, truth, top = _clipped(dtype)
    common = dict(data_range=float(truth.max()))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        told = _psnr(cv.reconstruct(coded, mask, white_level=top, **common), truth)
        unflagged = _psnr(cv.reconstruct(coded, mask, **common), truth)
        exact = _psnr(cv.reconstruct(coded, mask, white_level=top, trust_saturated=True, **common), truth)
    assert told >= exact - 0.1 and unflagged >= exact - 0.1, (told, unflagged, exact)


def test_an_unclipped_integer_capture_says_nothing(tmp_path):
    """The command line: a uint8 capture below 255 gets no clipping warning; one at 255 gets one, naming the file."""
    coded, mask, truth, top = _clipped(np.uint8)
    np.save(tmp_path / "mask.npy", mask)
    for name, values, said in (("low.npy", (coded // 2).astype(np.uint8), False), ("high.npy", coded, True)):
        np.save(tmp_path / name, values)
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            assert main(["-q", "reconstruct", "--coded", str(tmp_path / name), "--mask", str(tmp_path / "mask.npy"),
                         "--output", str(tmp_path / f"r-{name}")]) == 0
        messages = [str(w.message) for w in caught if "clipped by the sensor" in str(w.message)]
        assert bool(messages) == said and all(name in m and "--white-level" in m for m in messages), messages
