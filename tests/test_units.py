"""Captures as users have them: the same capture in any units gives the same video, multiplied by the scale.

[0, 1] floats (scikit-image's img_as_float), 0..255 floats or uint8, 12-bit 0..4095, uint16 0..65535, or any
float scale with --data-range: the same PSNR within 0.01 dB, through `reconstruct` and through `--cacti`.
Volumes agree to float32 roundoff, which may flip a near-tie in OMP's selection on a few patches.
"""
import json

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings, strategies as st

import codedvideo as cv
from codedvideo.app.cli import main
from codedvideo.model.codes import make_code
from codedvideo.model.physics import simulate
from codedvideo.data.synth import make_scene
from codedvideo.model.units import infer_data_range, static_peak

N, H, W = 4, 32, 36


@pytest.fixture(scope="module")
def capture():
    truth = make_scene("default", frames=N, size=(H, W)).astype(np.float64)
    truth *= 250.0 / truth.max()  # 8-bit frames whose peak is known
    mask = make_code("hitomi", (H, W), frames=N, bump=2, rng=3)
    return truth, mask, simulate(truth.astype(np.float32), mask).astype(np.float64)


def _reconstruct(tmp_path, capsys, coded, truth, mask, method, extra=()):
    tmp_path.mkdir(parents=True, exist_ok=True)
    np.save(tmp_path / "coded.npy", coded)
    np.save(tmp_path / "truth.npy", truth)
    np.save(tmp_path / "mask.npy", mask)
    capsys.readouterr()
    rc = main(["-q", "reconstruct", "--coded", str(tmp_path / "coded.npy"), "--mask", str(tmp_path / "mask.npy"),
               "--truth", str(tmp_path / "truth.npy"), "--method", method, "--output", str(tmp_path / "r.npy"),
               "--cache", str(tmp_path / "cache"), "--overwrite", *extra])
    assert rc == 0, capsys.readouterr().err
    metrics = json.loads((tmp_path / "r.metrics.json").read_text())
    return np.load(tmp_path / "r.npy"), metrics


# the conventions users hold data in: (frame scale, dtype of the stored capture, inferred data range)
CONVENTIONS = [(1 / 255, np.float32, 1.0), (1.0, np.float32, 255.0), (1.0, np.float64, 255.0),
               (4095 / 255, np.float32, 4095.0), (4095 / 255, np.uint16, 4095.0), (65535 / 255, np.uint16, 65535.0),
               (65535 / 255, np.float32, 65535.0)]


@pytest.mark.parametrize("method", ["dct", "gaptv"])
@pytest.mark.parametrize("scale,dtype,expected", CONVENTIONS)
def test_every_common_convention_gives_the_8bit_answer_scaled(tmp_path, capsys, capture, method, scale, dtype,
                                                               expected):
    truth, mask, coded = capture
    stored = coded * scale
    if np.dtype(dtype).kind == "u":  # an integer file holds the coded sums in its range, as integers
        truth, stored = truth / 2, np.rint(stored / 2)
        assert stored.max() <= np.iinfo(dtype).max
    # the 8-bit answer, on the same values
    base, m0 = _reconstruct(tmp_path / "base", capsys, (stored / scale).astype(np.float32), truth.astype(np.float32),
                            mask, method)
    volume, m = _reconstruct(tmp_path / "scaled", capsys, stored.astype(dtype), (truth * scale).astype(np.float32), mask,
                             method)
    assert m["data_range"]["value"] == expected
    assert abs(m["quality"]["psnr"] - m0["quality"]["psnr"]) < 0.01
    # float32 roundoff in another scale may flip a near-tie in OMP's selection on a few patches
    assert np.mean(np.abs(volume / scale - base)) < 0.05 and np.mean(np.abs(volume / scale - base) > 0.5) < 0.02


def test_unit_floats_get_the_8bit_psnr_not_an_empty_video(tmp_path, capsys, capture):
    """The reported defect: img_as_float captures scored 2.5 to 9.7 dB with the defaults."""
    truth, mask, coded = capture
    _, m8 = _reconstruct(tmp_path / "a", capsys, coded.astype(np.float32), truth.astype(np.float32), mask, "dct")
    _, m1 = _reconstruct(tmp_path / "b", capsys, (coded / 255).astype(np.float32), (truth / 255).astype(np.float32),
                         mask, "dct")
    assert m8["quality"]["psnr"] > m8["trivial"]["psnr"] + 1
    assert abs(m1["quality"]["psnr"] - m8["quality"]["psnr"]) < 0.01
    assert m1["data_range"]["source"].startswith("values") and m1["data_range"]["value"] == 1.0


@settings(max_examples=8, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(scale=st.floats(1e-3, 1e4))
def test_any_float_scale_with_its_data_range(tmp_path_factory, capsys, capture, scale):
    truth, mask, coded = capture
    tmp = tmp_path_factory.mktemp("scale")
    base, m0 = _reconstruct(tmp / "base", capsys, coded.astype(np.float32), truth.astype(np.float32), mask, "dct")
    volume, m = _reconstruct(tmp / "s", capsys, (coded * scale).astype(np.float32), (truth * scale).astype(np.float32),
                             mask, "dct", ["--data-range", repr(255 * scale)])
    assert abs(m["quality"]["psnr"] - m0["quality"]["psnr"]) < 0.01
    # float32 roundoff in another scale may flip a near-tie in OMP's selection on a few patches
    assert np.mean(np.abs(volume / scale - base)) < 0.05 and np.mean(np.abs(volume / scale - base) > 0.5) < 0.02


@pytest.mark.parametrize("scale", [1 / 255, 4095 / 255])
def test_cacti_files_in_any_units(tmp_path, capsys, capture, scale):
    from codedvideo.formats.cacti import write_cacti

    truth, mask, coded = capture
    psnr = []
    for s in (1.0, scale):
        path = tmp_path / f"scene-{s:g}.mat"
        write_cacti(path, mask=mask, meas=(coded * s)[None], orig=(truth * s).astype(np.float64))
        capsys.readouterr()
        out = tmp_path / f"r-{s:g}.npy"
        assert main(["-q", "reconstruct", "--cacti", str(path), "--method", "dct", "--output", str(out),
                     "--cache", str(tmp_path / "cache")]) == 0
        psnr.append(json.loads(out.with_name(out.stem + ".metrics.json").read_text())["quality"]["psnr"])
    assert abs(psnr[0] - psnr[1]) < 0.01


def test_data_range_inference_rules():
    ones = np.ones((2, 4, 4), np.uint8)
    assert static_peak(np.full((4, 4), 3.0), ones) == 1.5  # coded / open count
    assert infer_data_range(0.93).value == 1.0
    assert infer_data_range(1.02).value == 1.0  # room for noise
    assert infer_data_range(200.0).value == 255.0
    assert infer_data_range(200.0, dtype=np.uint16).value == 255.0
    assert infer_data_range(0.5, dtype=np.uint16).value == 255.0  # integers are never [0, 1]
    assert infer_data_range(3000.0).value == 4095.0
    assert infer_data_range(268.0).value == 4095.0  # past 8 bits with 5 % room ...
    assert infer_data_range(268.0, noise=30.0).value == 255.0  # ... but within the known read noise's peaks
    assert infer_data_range(60000.0, dtype=np.uint16).value == 65535.0
    assert infer_data_range(3e5).value == 409500.0  # floats: a standard range times a power of ten (12-bit / 100)
    assert infer_data_range(248122.0).value == 255000.0  # thousandths of 8 bits (it was 262143: PSNR 0.23 dB high)
    assert infer_data_range(3e5, dtype=np.int32).value == 2 ** 19 - 1  # wide integers: the next 2**b - 1
    assert infer_data_range(3.0, dtype=np.uint8).value == 255.0
    got = infer_data_range(3.0, given=7.5)
    assert got.value == 7.5 and "given" in got.source and got.scale == 255 / 7.5


def test_a_tolerance_that_stops_omp_before_its_first_atom_is_warned(tmp_path, capsys, capture, caplog):
    truth, mask, coded = capture
    with pytest.warns(UserWarning, match="--tol-rms .* first atom .* still answer"):
        _reconstruct(tmp_path, capsys, coded.astype(np.float32), truth.astype(np.float32), mask, "dct",
                     ["--tol-rms", "1000"])


def test_a_video_written_from_unit_floats_evaluates_in_their_units(tmp_path, capsys):
    """A video holds 8-bit frames (the data range mapped to 255): evaluated against a [0, 1] truth, its
    frames are taken back to the units they were written in (the metrics JSON beside it), so the PSNR is
    the 8-bit run's, not a negative number."""
    import json

    from codedvideo.app.cli import main

    cap = tmp_path / "cap"
    assert main(["-q", "simulate", "synth:default", "--frames", "4", "--size", "32", "32", "--output", str(cap)]) == 0
    coded, truth = np.load(cap / "coded.npy"), np.load(cap / "truth.npy")
    np.save(tmp_path / "coded01.npy", coded / 255)
    np.save(tmp_path / "truth01.npy", truth / 255)
    psnr = {}
    for name, c, t in (("u8", cap / "coded.npy", cap / "truth.npy"), ("f01", tmp_path / "coded01.npy",
                                                                      tmp_path / "truth01.npy")):
        assert main(["-q", "reconstruct", "--coded", str(c), "--mask", str(cap / "mask.npy"), "--method", "dct",
                     "--output", str(tmp_path / f"{name}.mkv"), "--cache", str(tmp_path / "cache")]) == 0
        capsys.readouterr()
        assert main(["-q", "evaluate", "--recon", str(tmp_path / f"{name}.mkv"), "--truth", str(t)]) == 0
        psnr[name] = json.loads(capsys.readouterr().out)["psnr"]
    assert psnr["u8"] > 20
    assert abs(psnr["f01"] - psnr["u8"]) < 0.05


def test_a_metrics_file_that_another_output_of_the_stem_replaced_is_not_taken_for_the_video(tmp_path, capsys):
    """``v.mkv`` then ``v.npy`` both write ``v.metrics.json``: evaluating ``v.mkv`` must not take the
    second run's data range (255) for the range it was written with (1), and says why it leaves it out."""
    import json

    from codedvideo.app.cli import main

    cap = tmp_path / "cap"
    assert main(["-q", "simulate", "synth:default", "--frames", "4", "--size", "32", "32", "--output", str(cap)]) == 0
    np.save(tmp_path / "coded01.npy", np.load(cap / "coded.npy") / 255)
    np.save(tmp_path / "truth01.npy", np.load(cap / "truth.npy") / 255)
    common = ["--mask", str(cap / "mask.npy"), "--method", "dct", "--cache", str(tmp_path / "cache")]
    evaluate = ["-q", "evaluate", "--recon", str(tmp_path / "v.mkv"), "--truth", str(tmp_path / "truth01.npy")]
    assert main(["-q", "reconstruct", "--coded", str(tmp_path / "coded01.npy"), "--output", str(tmp_path / "v.mkv"),
                 *common]) == 0
    capsys.readouterr()
    assert main(evaluate) == 0
    alone = json.loads(capsys.readouterr().out)["psnr"]
    assert main(["-q", "reconstruct", "--coded", str(cap / "coded.npy"), "--output", str(tmp_path / "v.npy"),
                 *common]) == 0
    capsys.readouterr()
    with pytest.warns(UserWarning, match="v.metrics.json describes .*v.npy, not .*v.mkv"):
        assert main(evaluate) == 0
    assert alone > 20 and abs(json.loads(capsys.readouterr().out)["psnr"] - alone) < 0.05


def test_a_noisy_8_bit_capture_keeps_its_range_and_one_just_past_8_bits_is_warned(tmp_path, capsys):
    """Read noise sigma 30 lifts coded / open count to 268: with --noise-sigma the range stays 255 (it was
    taken as 4095, which scored the same result 24 dB higher); without, a warning says why it is 4095."""
    import json

    from codedvideo.app.cli import main

    cap = tmp_path / "cap"
    assert main(["-q", "simulate", "synth:default", "--frames", "8", "--size", "64", "64", "--noise-sigma", "40",
                 "--seed", "0", "--output", str(cap)]) == 0
    args = ["-q", "reconstruct", "--coded", str(cap / "coded.npy"), "--mask", str(cap / "mask.npy"), "--method",
            "dct", "--cache", str(tmp_path / "cache")]
    capsys.readouterr()
    assert main([*args, "--output", str(tmp_path / "a.npy"), "--noise-sigma", "40"]) == 0
    assert json.loads(capsys.readouterr().out)["data_range"] == 255.0
    with pytest.warns(UserWarning, match="data range 4095 found from a peak of .* just above 8-bit"):
        assert main([*args, "--output", str(tmp_path / "b.npy")]) == 0


def test_a_hot_pixel_in_a_unit_float_capture_keeps_its_range_and_is_warned(tmp_path, capsys, capture):
    """Reported: one pixel at 2.5 in a [0, 1] capture made it 8-bit (a black video, PSNR 71 dB, 15 dB true)."""
    truth, mask, coded = capture
    clean = (coded / 255).astype(np.float32)
    _, m0 = _reconstruct(tmp_path / "clean", capsys, clean, (truth / 255).astype(np.float32), mask, "dct")
    hot = clean.copy()
    hot[10, 20] = 2.5
    with pytest.warns(UserWarning, match=r"lie above the data range 1 .*clipped"):
        _, m = _reconstruct(tmp_path / "hot", capsys, hot, (truth / 255).astype(np.float32), mask, "dct")
    assert m["data_range"]["value"] == 1.0 and "outliers" in m["data_range"]["source"]
    # (one hot pixel spoils its 13x13 neighbourhood, an eighth of this small frame); before: +40 dB, unreal
    assert abs(m["quality"]["psnr"] - m0["quality"]["psnr"]) < 3.0


def test_data_range_outlier_rule_leaves_integers_and_8_bit_floats_alone():
    typical = lambda: 0.9  # noqa: E731
    assert infer_data_range(2.5, quantile=typical).value == 1.0
    assert infer_data_range(2.5, quantile=lambda: 1.2).value == 255.0  # more than 1 % above 1: not outliers
    assert infer_data_range(2.5, dtype=np.uint16, quantile=typical).value == 255.0  # integers are never [0, 1]
    assert infer_data_range(9.0, quantile=typical).value == 255.0  # far above: a dark 8-bit frame with a light
    assert infer_data_range(200.0, quantile=typical).value == 255.0
    asked = []
    infer_data_range(200.0, quantile=lambda: asked.append(1) or 0.9)
    assert not asked  # the quantile is computed only where the peak leaves a doubt


def test_a_data_range_given_below_the_values_is_warned(tmp_path, capsys, capture):
    truth, mask, coded = capture
    with pytest.warns(UserWarning, match=r"% of the pixels .* lie above the data range 1 \(given"):
        _reconstruct(tmp_path, capsys, coded.astype(np.float32), truth.astype(np.float32), mask, "dct",
                     extra=("--data-range", "1"))


def test_the_tolerance_warning_counts_the_patches_whose_coded_rms_is_within_the_tolerance():
    """A coded image that is dark except for a bright block: the share of 7x7 patches within the tolerance,
    counted patch by patch, decides whether the warning is given and the share it names."""
    from codedvideo.model.units import tolerance_warning

    rng = np.random.default_rng(3)
    coded = rng.uniform(0.0, 1.0, (40, 50))
    coded[:, 30:] = 200.0  # 20 bright columns: every patch that reaches them is far above the tolerance
    rms = np.array([[np.sqrt(np.mean(coded[y:y + 7, x:x + 7] ** 2)) for x in range(44)] for y in range(34)])
    share = float(np.mean(rms <= 2.0))
    assert 0.5 < share < 0.6  # the patches wholly left of column 30
    message = tolerance_warning(coded, 2.0)
    assert message is not None and f"on {share:.0%} of the patches" in message
    assert tolerance_warning(coded[:, :36], 2.0) is not None  # most patches dark: warned
    assert tolerance_warning(np.hstack([coded, np.full((40, 30), 200.0)]), 2.0) is None  # most bright: not
    assert tolerance_warning(coded, 0.0) is None and tolerance_warning(coded[:5, :5], 2.0) is None


@pytest.fixture(scope="module")
def carphone():
    from codedvideo.data.scenes import load_video

    video = load_video("footage:carphone", frames=8, size=(48, 48))
    mask = cv.make_code("hitomi", (48, 48), frames=8, bump=2, seed=0)
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
