"""A mask folder missing one image reads as a code of fewer sub-frames: every door says to look at the mask
(before: with a truth the error blamed the truth's shape, without one it said to train an N = 7 dictionary, and
`codes check` called the mask fine)."""
import json
import warnings

import numpy as np
import pytest
from skimage import io

import codedvideo as cv
from codedvideo.app.cli import main

SIZE, N = 32, 8
MISSING = "missing from the mask"


@pytest.fixture()
def seven(tmp_path):
    """A capture of N = 8 sub-frames, its truth, and its mask as a folder of PNGs with the last one lost."""
    video = cv.synthetic_scene("default", frames=N, size=(SIZE, SIZE))
    mask = cv.make_code("hitomi", (SIZE, SIZE), frames=N, seed=0)
    np.save(tmp_path / "coded.npy", cv.simulate(video, mask))
    np.save(tmp_path / "truth.npy", video)
    (tmp_path / "mask").mkdir()
    for k in range(N - 1):
        io.imsave(tmp_path / "mask" / f"sub_{k:02d}.png", (mask[k] * 255).astype(np.uint8), check_contrast=False)
    return tmp_path, video, mask[: N - 1]


def _error(capsys, *args) -> str:
    assert main(["-q", *map(str, args)]) == 2
    return capsys.readouterr().err


def test_with_a_truth_the_command_line_and_the_api_point_at_the_mask(seven, capsys):
    tmp, video, mask = seven
    said = _error(capsys, "reconstruct", "--coded", tmp / "coded.npy", "--mask", tmp / "mask",
                  "--truth", tmp / "truth.npy", "--output", tmp / "r.npy")
    assert MISSING in said and f"mask {tmp / 'mask'} has 7 sub-frames" in said
    with pytest.raises(cv.InputError, match=MISSING):
        cv.reconstruct(np.load(tmp / "coded.npy"), mask, truth=video)
    assert not (tmp / "r.npy").exists()


def test_without_a_truth_the_advice_is_the_mask_before_a_dictionary_of_seven(seven, capsys):
    tmp, _, mask = seven
    said = _error(capsys, "reconstruct", "--coded", tmp / "coded.npy", "--mask", tmp / "mask", "--output", tmp / "r.npy")
    assert MISSING in said and said.index(MISSING) < said.index("train")
    with pytest.raises(cv.InputError, match=MISSING):
        cv.reconstruct(np.load(tmp / "coded.npy"), mask)


def test_a_dictionary_of_eight_names_the_mask_too(seven, capsys):
    tmp, _, _ = seven
    from codedvideo.data import shipped

    said = _error(capsys, "reconstruct", "--coded", tmp / "coded.npy", "--mask", tmp / "mask", "--output",
                  tmp / "r.npy", "--dictionary", shipped.path_for(N))
    assert "built for N = 8" in said and MISSING in said


def test_codes_check_prints_n_and_says_no_dictionary_is_shipped_for_it(seven, capsys):
    tmp, _, _ = seven
    with pytest.warns(UserWarning, match=f"N = 7 sub-frames.*{MISSING}"):
        assert main(["codes", "check", str(tmp / "mask")]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["frames"] == 7 and report["dictionary_shipped"] is False
    np.save(tmp / "eight.npy", cv.make_code("hitomi", (SIZE, SIZE), frames=N, seed=0))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert main(["codes", "check", str(tmp / "eight.npy")]) == 0
    assert json.loads(capsys.readouterr().out)["dictionary_shipped"] is True
