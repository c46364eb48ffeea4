"""Raw sensor data: black level, bit depth / white level and defective pixels, each brings the answer closer.

Every correction is measured the same way: the same raw capture reconstructed without the correction and with
it (through the pipeline's reconstruct_volume, which fills missing pixels), PSNR against the truth.
"""
import warnings

import numpy as np
import pytest

from codedvideo.model import physics
from codedvideo.model import sensor
from codedvideo.model.codes import make_code
from codedvideo.solvers.dictionaries import dct_dictionary
from codedvideo.model.errors import InputError
from codedvideo.model.metrics import evaluate
from codedvideo.engine.windows import Execution, reconstruct_volume
from codedvideo.solvers.region import OmpSettings
from codedvideo.data.synth import make_scene

N, H, W = 8, 64, 64
SETTINGS = OmpSettings(max_atoms=8, tol_rms=2.0)


@pytest.fixture(scope="module")
def video():
    return make_scene("default", frames=N, size=(H, W))


@pytest.fixture(scope="module")
def mask():
    return make_code("hitomi", (H, W), frames=N, bump=2, rng=1)


@pytest.fixture(scope="module")
def D():
    return dct_dictionary(N, redundancy=2.0)


def recon_psnr(coded, mask, truth, D, tmp_path, *, data_range=255.0):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)  # "pixels are never open": the missing ones, filled
        vol, info = reconstruct_volume(np.asarray(coded, np.float32), mask, D, settings=SETTINGS,
                                       run=Execution(tile=64, cache=tmp_path, workers=1, progress=False))
    assert np.isfinite(vol).all()
    return evaluate(vol, truth, data_range=data_range)["psnr"]


def corrupt(coded, rng, count=60):
    """Stuck-high, warm (dark-current offset) and dead pixels at random places; returns the frame and the rows."""
    idx = rng.choice(coded.size, 3 * count, replace=False)
    ys, xs = np.unravel_index(idx, coded.shape)
    out = np.array(coded, np.float32, copy=True)
    out[ys[:count], xs[:count]] = 2 * 255.0
    out[ys[count:2 * count], xs[count:2 * count]] += 80.0
    out[ys[2 * count:], xs[2 * count:]] = 0.0
    return out, np.stack([ys, xs], 1)


# ----------------------------------------------------------------------------- black level
def test_sensor_model_adds_the_black_level_once_per_readout(video, mask):
    clean = physics.forward(video, mask)
    raw = physics.simulate(video, mask, rng=0, sensor=physics.SensorModel(black_level=16.0))
    np.testing.assert_array_equal(raw, clean + np.float32(16.0))
    q = physics.SensorModel(bits=10, black_level=64.0)
    raw = physics.simulate(video, mask, rng=0, sensor=q)
    np.testing.assert_array_equal(raw, physics.quantise(clean + np.float32(64), bits=10, full_scale=1023.0))
    # no black level: the output of before, bit for bit
    plain = physics.SensorModel(bits=8, read_sigma=2.0)
    np.testing.assert_array_equal(physics.measure(clean, plain, 3), physics.measure(clean, physics.SensorModel(
        bits=8, read_sigma=2.0, black_level=0.0), 3))
    for bad in (-1.0, float("nan"), 1023.0):
        with pytest.raises(InputError, match="black_level"):
            physics.SensorModel(bits=10, black_level=bad)


def test_black_level_correction_brings_the_answer_closer(video, mask, D, tmp_path):
    model = physics.SensorModel(bits=12, read_sigma=1.0, black_level=64.0)
    raw = physics.simulate(video, mask, rng=0, sensor=model)
    fixed = sensor.correct_raw(raw, mask, levels=sensor.RawLevels(black_level=64.0, bits=12))
    clean = physics.forward(video, mask)
    assert abs(float(np.mean(fixed.coded - clean))) < 0.2  # offset gone (once, not once per open sub-frame)
    assert fixed.saturated_pixels == 0 and fixed.black_level == 64.0 and fixed.white_level == 4095.0
    without = recon_psnr(raw, mask, video, D, tmp_path / "raw")
    with_ = recon_psnr(fixed.coded, fixed.mask, video, D, tmp_path / "fixed")
    assert with_ > without + 3.0, (without, with_)


def test_black_level_below_the_signal_clips_at_zero_and_a_dark_frame_works(mask):
    raw = np.full((H, W), 10.0, np.float32)
    dark = np.full((H, W), 8.0, np.float32)
    dark[0, :5] = 12.0  # above the raw value: clipped
    fixed = sensor.correct_raw(raw, mask, levels=sensor.RawLevels(black_level=dark))
    assert fixed.clipped_pixels == 5 and (fixed.coded[0, :5] == 0).all() and (fixed.coded[1] == 2.0).all()
    assert fixed.black_level is None
    kept = sensor.correct_raw(raw, mask, levels=sensor.RawLevels(black_level=dark), clip_negative=False)
    assert (kept.coded[0, :5] == -2.0).all()


# ----------------------------------------------------------------------------- bit depth and white level
def test_white_level_of_the_bit_depth_marks_pixels_at_full_scale_missing(video, mask, D, tmp_path):
    """A 10-bit sensor with hot pixels stuck at full scale (1023): knowing the depth drops them."""
    model = physics.SensorModel(bits=10, read_sigma=1.0, black_level=32.0)
    raw = physics.simulate(video, mask, rng=0, sensor=model)
    assert raw.max() < 1023  # the scene itself does not saturate
    rows = np.stack(np.unravel_index(np.random.default_rng(2).choice(H * W, 80, replace=False), (H, W)), 1)
    raw[rows[:, 0], rows[:, 1]] = 1023.0
    fixed = sensor.correct_raw(raw, mask, levels=sensor.RawLevels(black_level=32.0, bits=10))
    assert fixed.saturated_pixels == 80 and fixed.white_level == 1023.0
    assert not fixed.mask[:, rows[:, 0], rows[:, 1]].any() and (fixed.coded[rows[:, 0], rows[:, 1]] == 0).all()
    # the black level only: full-scale pixels trusted
    naive = sensor.correct_raw(raw, mask, levels=sensor.RawLevels(black_level=32.0))
    assert naive.saturated_pixels == 0 and naive.white_level is None
    without = recon_psnr(naive.coded, naive.mask, video, D, tmp_path / "naive")
    with_ = recon_psnr(fixed.coded, fixed.mask, video, D, tmp_path / "fixed")
    assert with_ > without + 1.0, (without, with_)
    trusted = sensor.correct_raw(raw, mask, levels=sensor.RawLevels(black_level=32.0, bits=10), trust_saturated=True)
    assert trusted.saturated_pixels == 80 and trusted.missing_pixels == 0
    np.testing.assert_array_equal(trusted.coded, naive.coded)
    # an explicit white level below the ADC's top (a full well that saturates first)
    lower = sensor.correct_raw(raw, mask, levels=sensor.RawLevels(black_level=32.0, bits=10, white_level=400.0))
    assert lower.saturated_pixels == int((raw >= 400).sum()) > 80


def test_raw_values_that_no_adc_of_that_depth_gives_are_errors(mask):
    raw = np.full((H, W), 100.0, np.float32)
    raw[3, 4] = 5000.0
    with pytest.raises(InputError, match=r"coded image: value 5000 is above 4095, the largest 12-bit value"):
        sensor.correct_raw(raw, mask, levels=sensor.RawLevels(bits=12))
    with pytest.raises(InputError, match="black level 300 is not below the white level 255"):
        sensor.correct_raw(np.full((H, W), 10.0, np.float32), mask, levels=sensor.RawLevels(bits=8, black_level=300.0))
    with pytest.raises(InputError, match="every pixel is saturated"):
        sensor.correct_raw(np.full((H, W), 255.0, np.float32), mask, levels=sensor.RawLevels(bits=8))
    with pytest.raises(InputError, match="bits must be an integer"):
        sensor.correct_raw(raw, mask, levels=sensor.RawLevels(bits=0))


# ----------------------------------------------------------------------------- defective pixels
def test_bad_pixels_from_a_list_bring_the_answer_closer(video, mask, D, tmp_path):
    clean = physics.simulate(video, mask, sigma=1.0, rng=0)
    raw, rows = corrupt(clean, np.random.default_rng(3))
    listing = tmp_path / "bad.txt"
    listing.write_text("# y x\n" + "\n".join(f"{y} {x}" for y, x in rows) + "\n\n")
    read = sensor.read_bad_pixels(listing, (H, W))
    np.testing.assert_array_equal(read, rows)
    np.save(tmp_path / "bad.npy", rows.astype(np.int32))
    np.testing.assert_array_equal(sensor.read_bad_pixels(tmp_path / "bad.npy", (H, W)), rows)
    fixed = sensor.correct_raw(raw, mask, bad_pixels=read)
    assert fixed.bad_pixels == len(rows) and fixed.missing_pixels == len(rows)
    without = recon_psnr(raw, mask, video, D, tmp_path / "raw")
    with_ = recon_psnr(fixed.coded, fixed.mask, video, D, tmp_path / "fixed")
    assert with_ > without + 1.0, (without, with_)
    fixed = sensor.correct_raw(raw, mask, bad_pixels=read, clip_negative=False)
    coded2, mask2, count = sensor.drop_pixels(raw, mask, read)
    np.testing.assert_array_equal(coded2, fixed.coded)
    np.testing.assert_array_equal(mask2, fixed.mask)
    assert count == len(rows)


def test_detected_bad_pixels_bring_the_answer_closer(video, mask, D, tmp_path):
    clean = physics.simulate(video, mask, sigma=1.0, rng=0)
    raw, rows = corrupt(clean, np.random.default_rng(3))
    truth = sensor.bad_pixel_map(rows, (H, W))
    found = sensor.detect_bad_pixels(raw, mask)
    stuck = truth & (raw == 2 * 255.0)
    assert (found & stuck).sum() >= 0.8 * stuck.sum()
    assert (found & ~truth).sum() <= 0.01 * H * W  # false alarms: a few
    coded, mask_used, count = sensor.drop_pixels(raw, mask, found)
    without = recon_psnr(raw, mask, video, D, tmp_path / "raw")
    with_ = recon_psnr(coded, mask_used, video, D, tmp_path / "detected")
    assert with_ > without + 1.0, (without, with_)


def test_a_stack_of_captures_keeps_the_defects_and_drops_the_false_alarms(mask):
    long = make_scene("default", frames=3 * N, size=(H, W))
    rng = np.random.default_rng(7)
    idx = rng.choice(H * W, 40, replace=False)
    ys, xs = np.unravel_index(idx, (H, W))
    stack = []
    for k in range(3):  # three captures of the moving scene, the same defects in each
        coded = physics.simulate(long[k * N:(k + 1) * N], mask, sigma=1.0, rng=k)
        coded[ys[:20], xs[:20]] = 4 * 255.0
        coded[ys[20:], xs[20:]] = 0.0  # dead: found where the scene is not dark
        stack.append(coded)
    stack = np.stack(stack)
    truth = sensor.bad_pixel_map(np.stack([ys, xs], 1), (H, W))
    single = sensor.detect_bad_pixels(stack[0], mask)
    several = sensor.detect_bad_pixels(stack, mask)
    assert several[ys[:20], xs[:20]].all() and (several & truth).sum() >= 0.5 * truth.sum()
    assert (several & ~truth).sum() <= min(2, (single & ~truth).sum())  # measured: 0 against 15
    assert np.array_equal(several, sensor.detect_bad_pixels(stack, np.stack([mask] * 3)))  # a mask per capture


def test_detection_on_a_float_mask_and_never_open_pixels(video, mask):
    measured = physics.blur_shift_mask(mask)
    measured[:, 10, 10] = 0  # never open: not an outlier, not a false contrast for its neighbours
    coded = physics.forward(video, measured)
    coded[20, 30] = 4 * 255.0
    found = sensor.detect_bad_pixels(coded, measured)
    assert found[20, 30] and not found[10, 10] and found.sum() <= 0.01 * H * W


@pytest.mark.parametrize("text,problem", [
    ("1 2\n3 4\n70 5\n", r"line 3 \(y=70, x=5\) is outside the 64x64 image"),
    ("# comment\n-1 2\n", r"line 2 \(y=-1, x=2\) is outside the 64x64 image"),
    ("1 2\n3 64\n", r"line 2 \(y=3, x=64\) is outside"),
    ("1 2\n3\n", r"line 2 \('3'\) is not two integers 'y x'"),
    ("1 2.5\n", r"line 1 \('1 2.5'\) is not two integers"),
])
def test_a_bad_pixel_list_out_of_range_is_a_one_line_error_naming_the_file(tmp_path, text, problem):
    path = tmp_path / "bad.txt"
    path.write_text(text)
    with pytest.raises(InputError, match=f"bad-pixel list {path}: {problem}") as err:
        sensor.read_bad_pixels(path, (H, W))
    assert "\n" not in str(err.value)


def test_bad_pixel_npy_lists_and_missing_files(tmp_path):
    np.save(tmp_path / "out.npy", np.array([[1, 2], [5, 99]]))
    with pytest.raises(InputError, match=rf"bad-pixel list {tmp_path / 'out.npy'}: row 2 \(y=5, x=99\) is outside"):
        sensor.read_bad_pixels(tmp_path / "out.npy", (H, W))
    np.save(tmp_path / "shape.npy", np.full((3, 3), 7, np.int64))
    with pytest.raises(InputError, match=r"shape.npy: expected an array of shape \(K, 2\)"):
        sensor.read_bad_pixels(tmp_path / "shape.npy", (H, W))
    np.save(tmp_path / "small-map.npy", np.zeros((32, 32), bool))  # a map of the wrong size says so
    with pytest.raises(InputError, match=r"small-map.npy: a map of 32x32 pixels, the image has 64x64"):
        sensor.read_bad_pixels(tmp_path / "small-map.npy", (H, W))
    ones = np.zeros((H, W), np.uint8)  # a map of 0 and 1 (uint8, as image tools save it), and a list with a BOM
    ones[3, 5] = 1
    np.save(tmp_path / "map-u8.npy", ones)
    np.testing.assert_array_equal(sensor.read_bad_pixels(tmp_path / "map-u8.npy", (H, W)), [[3, 5]])
    (tmp_path / "bom.txt").write_text("\ufeff3 5\n", encoding="utf-8")
    np.testing.assert_array_equal(sensor.read_bad_pixels(tmp_path / "bom.txt", (H, W)), [[3, 5]])
    np.save(tmp_path / "frac.npy", np.array([[1.5, 2.0]]))
    with pytest.raises(InputError, match=r"frac.npy: row 1 \(1.5 2\) is not two integers"):
        sensor.read_bad_pixels(tmp_path / "frac.npy", (H, W))
    with pytest.raises(InputError, match=rf"bad-pixel list {tmp_path / 'none.txt'}: no such file"):
        sensor.read_bad_pixels(tmp_path / "none.txt", (H, W))
    (tmp_path / "empty.txt").write_text("# nothing\n")
    assert sensor.read_bad_pixels(tmp_path / "empty.txt", (H, W)).shape == (0, 2)
    np.save(tmp_path / "empty.npy", np.zeros((0, 2), np.int64))
    assert sensor.read_bad_pixels(tmp_path / "empty.npy", (H, W)).shape == (0, 2)
    flags = np.zeros((H, W), bool)
    flags[3, 5] = flags[60, 1] = True
    np.save(tmp_path / "map.npy", flags)
    np.testing.assert_array_equal(sensor.read_bad_pixels(tmp_path / "map.npy", (H, W)), [[3, 5], [60, 1]])
    np.save(tmp_path / "float_ok.npy", np.array([[1.0, 2.0]]))
    np.testing.assert_array_equal(sensor.read_bad_pixels(tmp_path / "float_ok.npy", (H, W)), [[1, 2]])
