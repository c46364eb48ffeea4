"""The sensor and noise model: shot noise, read noise, quantisation, saturation."""
import json

import warnings

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

import codedvideo as cv
from conftest import capture_settings
from codedvideo.app.cli import main
from codedvideo.model.codes import CodeSpec, check_code, make_code
from codedvideo.model.errors import InputError
from codedvideo.model.physics import (
    SensorModel,
    add_read_noise,
    add_shot_noise,
    forward,
    measure,
    quantise,
    saturated_as_missing,
    simulate,
)

N, SIZE = 8, 16


@pytest.fixture
def scene(rng):
    video = rng.uniform(0, 255, size=(8, 24, 20)).astype(np.float32)
    mask = make_code("hitomi", (24, 20), frames=8, bump=2, rng=1)
    return video, mask


# ----------------------------------------------------------------------------- read noise, unchanged
def test_plain_read_noise_is_bit_identical_to_before(scene):
    video, mask = scene
    clean = forward(video, mask)
    expected = (clean + np.random.default_rng(3).normal(0.0, 4.0, size=clean.shape)).astype(np.float32)
    assert np.array_equal(simulate(video, mask, sigma=4.0, rng=3), expected)
    assert np.array_equal(measure(clean, SensorModel(read_sigma=4.0), 3), expected)
    assert np.array_equal(simulate(video, mask, rng=3, sensor=SensorModel(read_sigma=4.0)), expected)
    assert np.array_equal(measure(clean, SensorModel(), 3), clean)  # the default model is the identity


def test_default_capture_is_bit_identical_to_before():
    from codedvideo.engine.config import NoiseConfig
    from codedvideo.engine.simulation import sensor_model, simulate_capture

    video = np.random.default_rng(0).uniform(0, 255, (8, 16, 16)).astype(np.float32)
    cap = simulate_capture(video, code=CodeSpec("hitomi", bump=2), sigma=2.0, seed=5)
    code_rng, noise_rng = (np.random.default_rng(s) for s in np.random.SeedSequence(5).spawn(2))
    mask = make_code("hitomi", (16, 16), frames=8, bump=2, rng=code_rng)
    assert np.array_equal(cap["mask"], mask)
    assert np.array_equal(cap["coded"], add_read_noise(forward(video, mask), 2.0, noise_rng))
    assert sensor_model(NoiseConfig(sigma=2.0)) is None


def test_sigma_and_sensor_together_is_an_error(scene):
    with pytest.raises(InputError, match="read_sigma"):
        simulate(*scene, sigma=1.0, sensor=SensorModel(shot_noise=True))


# ----------------------------------------------------------------------------- shot noise
@pytest.mark.parametrize("level,gain", [(5.0, 1.0), (100.0, 4.0), (400.0, 0.5)])
def test_shot_noise_has_poisson_statistics(level, gain):
    n = 200 * 200
    flat = np.full((200, 200), level, np.float32)
    noisy = measure(flat, SensorModel(shot_noise=True, gain=gain, full_well=1e9), rng=7).astype(np.float64)
    electrons = noisy * gain
    np.testing.assert_allclose(electrons, np.rint(electrons), atol=1e-5 * electrons.max())  # whole electrons
    var = level / gain  # Poisson in electrons: variance = mean, in grey levels / gain**2
    assert abs(noisy.mean() - level) < 5 * np.sqrt(var / n)
    assert abs(noisy.var() / var - 1) < 5 * np.sqrt(2 / n)


def test_shot_noise_saturates_at_the_full_well():
    flat = np.full((50, 50), 1000.0, np.float32)
    out = add_shot_noise(flat, gain=10.0, full_well=5000.0, rng=0)
    assert (out == 500.0).all()
    out = add_shot_noise(np.full((4, 4), -3.0), gain=2.0, full_well=10.0, rng=0)
    assert (out == 0).all()  # negative light is no light


def test_noise_streams_are_seeded_and_independent(rng):
    clean = rng.uniform(50, 200, (100, 100)).astype(np.float32)
    both = SensorModel(shot_noise=True, gain=2.0, read_sigma=3.0)
    a = measure(clean, both, 11)
    assert np.array_equal(a, measure(clean, both, 11))
    assert not np.array_equal(a, measure(clean, both, 12))
    shot_only = measure(clean, SensorModel(shot_noise=True, gain=2.0), 11)
    read_part = a.astype(np.float64) - shot_only
    # the read noise is the plain read-noise draw of the same seed ...
    np.testing.assert_allclose(read_part, add_read_noise(np.zeros_like(clean), 3.0, 11), atol=1e-3)
    # ... and uncorrelated with the shot noise
    shot_part = shot_only.astype(np.float64) - clean
    assert abs(np.corrcoef(read_part.ravel(), shot_part.ravel())[0, 1]) < 0.05


def test_noise_sigma_adds_the_variances():
    m = SensorModel(shot_noise=True, gain=4.0, read_sigma=3.0, bits=8, white_level=255.0)
    assert m.noise_sigma(64.0) == pytest.approx(np.sqrt(9 + 16 + 1 / 12))
    assert SensorModel(read_sigma=2.5).noise_sigma(1000.0) == 2.5


# ----------------------------------------------------------------------------- the sensor's output
@settings(max_examples=30, deadline=None)
@given(bits=st.integers(1, 12), white=st.floats(1.0, 5000.0), seed=st.integers(0, 2**31))
def test_quantisation_levels(bits, white, seed):
    x = np.random.default_rng(seed).uniform(-0.2 * white, 1.2 * white, 500).astype(np.float32)
    q = quantise(x, bits=bits, full_scale=white)
    step = white / (2**bits - 1)
    levels = q.astype(np.float64) / step
    assert q.dtype == np.float32
    np.testing.assert_allclose(levels, np.rint(levels), atol=1e-3)
    assert len(np.unique(q)) <= 2**bits
    assert q.min() >= 0 and q.max() <= np.float32(white)
    inside = (x >= 0) & (x <= white)
    assert (np.abs(q[inside] - x[inside]) <= step / 2 * (1 + 1e-4) + 1e-3).all()
    assert (q[x > white] == np.float32(white)).all() and (q[x < 0] == 0).all()


def test_bits_alone_give_integer_grey_levels():
    clean = np.linspace(-10, 300, 1000, dtype=np.float32).reshape(10, 100)
    out = measure(clean, SensorModel(bits=8), 0)
    assert np.array_equal(out, np.clip(np.rint(clean), 0, 255))


def test_white_level_clips_and_leaves_the_rest():
    clean = np.linspace(0, 400, 1000, dtype=np.float32).reshape(10, 100)
    out = measure(clean, SensorModel(white_level=300.0), 0)
    assert out.max() == np.float32(300.0)
    below = clean < 300
    assert np.array_equal(out[below], clean[below]) and (out[~below] == 300).all()
    # with quantisation the top level is exactly the white level too
    out = measure(clean, SensorModel(bits=10, white_level=333.3, read_sigma=2.0), 1)
    top = out == np.float32(333.3)
    assert out.max() == np.float32(333.3)
    assert top[clean > 333.3 + 10].all() and not top[clean < 333.3 - 10].any()


@pytest.mark.parametrize("kw,match", [
    (dict(gain=0.0), "gain"), (dict(full_well=-1.0), "full_well"), (dict(read_sigma=np.nan), "read_sigma"),
    (dict(bits=0), "bits"), (dict(bits=2.5), "bits"), (dict(white_level=0.0), "white_level"),
])
def test_sensor_model_rejects_bad_values(kw, match):
    with pytest.raises(InputError, match=match):
        SensorModel(**kw)


# ----------------------------------------------------------------------------- saturation as missing
def test_saturated_as_missing(scene):
    video, mask = scene
    coded = measure(forward(video, mask), SensorModel(white_level=300.0), 0)
    n_sat = int((coded >= np.float32(300.0)).sum())
    assert 0 < n_sat < coded.size
    before = mask.copy()
    out, count = saturated_as_missing(coded, mask, 300.0)
    assert count == n_sat
    assert np.array_equal(mask, before), "the input mask is not modified"
    assert out.dtype == mask.dtype and out.shape == mask.shape
    sat = coded >= 300.0
    assert not out[:, sat].any()
    assert np.array_equal(out[:, ~sat], mask[:, ~sat])
    assert check_code(out).never_open_pixels == n_sat
    with pytest.raises(InputError, match="does not match"):
        saturated_as_missing(coded[:5], mask, 300.0)
    with pytest.raises(InputError, match="white level"):
        saturated_as_missing(coded, mask, 0.0)


# ----------------------------------------------------------------------------- command line and pipeline
def _cli(*args):
    from codedvideo.app.cli import main

    return main(["-q", *map(str, args)])


def test_cli_simulate_rowwise_and_shot_noise(tmp_path, capsys):
    assert _cli("simulate", "synth:default", "--frames", 8, "--bump", 2, "--code", "rowwise", "--seed", 2,
                "--size", 32, 40, "--output", tmp_path / "row") == 0
    paths = json.loads(capsys.readouterr().out)
    coded, mask, truth = (np.load(tmp_path / "row" / f"{k}.npy") for k in ("coded", "mask", "truth"))
    assert set(paths) == {"coded", "mask", "truth", "coded_tif"} and (tmp_path / "row" / "coded.tif").stat().st_size
    assert coded.shape == (32, 40) and coded.dtype == np.float32
    assert mask.shape == (8, 32, 40) and mask.dtype == np.uint8 and truth.shape == (8, 32, 40)
    assert (mask == mask[:, :, :1]).all()
    rep = check_code(mask)
    assert rep.single_bump and rep.bump_length == 2 and rep.window_coverage
    np.testing.assert_allclose(coded, (mask * truth).sum(0), rtol=1e-5, atol=1e-3)

    assert _cli("simulate", "synth:default", "--frames", 8, "--bump", 2, "--code", "rowwise", "--seed", 2,
                "--size", 32, 40, "--shot-noise", "--gain", 2, "--bits", 12, "--white-level", 400,
                "--output", tmp_path / "shot") == 0
    noisy = np.load(tmp_path / "shot" / "coded.npy")
    assert np.array_equal(np.load(tmp_path / "shot" / "mask.npy"), mask), "noise does not change the code"
    clean = (mask * truth).sum(0)
    step = 400 / 4095
    assert noisy.max() <= np.float32(400) and np.allclose(noisy / step, np.rint(noisy / step), atol=1e-2)
    ok = clean < 350
    z = (noisy[ok] - clean[ok]) / np.sqrt(np.maximum(clean[ok], 1) / 2)
    assert 0.6 < z.std() < 1.4 and abs(z.mean()) < 0.3


def test_cli_simulate_code_file_and_errors(tmp_path, capsys):
    mask = make_code("grid", (24, 24), frames=4)
    np.save(tmp_path / "grid.npy", mask)
    assert _cli("simulate", "synth:default", "--frames", 4, "--code-file", tmp_path / "grid.npy",
                "--size", 24, 24, "--output", tmp_path / "f") == 0
    assert np.array_equal(np.load(tmp_path / "f" / "mask.npy"), mask)
    capsys.readouterr()
    assert _cli("simulate", "synth:default", "--frames", 8, "--code-file", tmp_path / "grid.npy",
                "--size", 24, 24, "--output", tmp_path / "g") == 2
    err = capsys.readouterr().err.strip()
    assert "grid.npy" in err and "N = 4" in err and len(err.splitlines()) == 1
    assert _cli("simulate", "synth:default", "--frames", 4, "--code", "file", "--size", 24, 24,
                "--output", tmp_path / "h") == 2
    assert _cli("simulate", "synth:default", "--frames", 4, "--shot-noise", "--gain", 0, "--size", 24, 24,
                "--output", tmp_path / "i") == 2
    assert "gain" in capsys.readouterr().err
    assert not (tmp_path / "g").exists() and not (tmp_path / "i").exists()


def test_cli_simulate_a_code_file_of_one_code_per_capture(tmp_path, capsys):
    """A calibrated code that changes per capture (K, N, H, W): capture t takes code t mod K, in memory and from a
    video file alike, and mask.npy holds the code of every capture (a (T, N, H, W) code file was refused)."""
    from codedvideo.formats import io as cio
    from codedvideo.data.synth import make_scene

    codes = np.stack([make_code("hitomi", (24, 24), frames=4, bump=2, rng=k) for k in range(2)])
    codes = codes.astype(np.float32) * 0.9 + 0.05  # calibrated: leakage and a response below 1
    np.save(tmp_path / "codes.npy", codes)
    assert _cli("simulate", "synth:default", "--frames", 4, "--code-file", tmp_path / "codes.npy", "--captures", 3,
                "--size", 24, 24, "--output", tmp_path / "mem") == 0
    mask = np.load(tmp_path / "mem" / "mask.npy")
    assert mask.shape == (3, 4, 24, 24)
    for t in range(3):
        np.testing.assert_array_equal(mask[t], codes[t % 2])
    coded, truth = np.load(tmp_path / "mem" / "coded.npy"), np.load(tmp_path / "mem" / "truth.npy")
    np.testing.assert_allclose(coded[2], (codes[0] * truth[8:12]).sum(0), rtol=1e-5, atol=1e-3)
    cio.write_video(tmp_path / "clip.mkv", make_scene("default", frames=12, size=(24, 24)), fps=30)
    assert _cli("simulate", tmp_path / "clip.mkv", "--frames", 4, "--code-file", tmp_path / "codes.npy",
                "--captures", "all", "--output", tmp_path / "file") == 0
    np.testing.assert_array_equal(np.load(tmp_path / "file" / "mask.npy"), mask)
    capsys.readouterr()
    assert _cli("simulate", "synth:default", "--frames", 4, "--code-file", tmp_path / "codes.npy", "--captures", 3,
                "--new-code-per-capture", "--size", 24, 24, "--output", tmp_path / "new") == 2
    err = capsys.readouterr().err.strip()
    assert "codes.npy" in err and "--new-code-per-capture" in err and len(err.splitlines()) == 1
    assert not (tmp_path / "new").exists()


def test_cli_reconstruct_keeps_saturated_pixels_as_lower_bounds(tmp_path, capsys):
    W = 80.0
    assert _cli("simulate", "synth:default", "--frames", 4, "--bump", 2, "--white-level", W, "--size", 24, 24,
                "--output", tmp_path / "cap") == 0
    assert _cli("train", "--frames", 4, "--kind", "dct", "--output", tmp_path / "d.zarr", "--cache", tmp_path / "c") == 0
    coded = np.load(tmp_path / "cap" / "coded.npy")
    n_sat = int((coded >= W).sum())
    assert n_sat > 0
    common = ["--coded", tmp_path / "cap" / "coded.npy", "--mask", tmp_path / "cap" / "mask.npy",
              "--dictionary", tmp_path / "d.zarr", "--tile", 24, "--cache", tmp_path / "c"]
    assert _cli("reconstruct", *common, "--output", tmp_path / "r1.npy", "--white-level", W) == 0
    m1 = json.loads((tmp_path / "r1.metrics.json").read_text())
    assert m1["reconstruction"]["saturated_pixels"] == n_sat
    assert m1["reconstruction"]["never_open_pixels"] == 0  # kept as measurements, not left out
    r1 = np.load(tmp_path / "r1.npy")
    mask = np.load(tmp_path / "cap" / "mask.npy")
    assert np.isfinite(r1).all() and ((mask * r1).sum(0)[coded >= W] >= W - 1e-2).all()
    assert _cli("reconstruct", *common, "--output", tmp_path / "r2.npy", "--white-level", W, "--trust-saturated") == 0
    assert json.loads((tmp_path / "r2.metrics.json").read_text())["reconstruction"]["saturated_pixels"] == 0


@pytest.mark.parametrize("code", ["hitomi", "bernoulli"])
def test_saturated_pixels_are_kept_and_record_at_least_the_white_level(tmp_path, code):
    """A saturated pixel's value is a lower bound: it stays a measurement at its clipped value, and after the
    reconstruction its frames are raised (along its own shutter weights) wherever they record less than the
    white level.  That is never below taking the clipped values as exact, and above leaving the pixels out (as
    the white level did before: 5 % of a held-out scene clipped cost 0.3 to 9 dB)."""
    import warnings

    from codedvideo.solvers.dictionaries import dct_dictionary
    from codedvideo.model.metrics import evaluate
    from codedvideo.model.physics import saturated_as_missing
    from codedvideo.solvers.region import OmpSettings
    from codedvideo.engine.captures import reconstruct_capture
    from codedvideo.data.synth import make_scene
    from codedvideo.model.units import infer_data_range

    video = make_scene("default", frames=8, size=(48, 48))
    mask = make_code(code, (48, 48), frames=8, bump=2, rng=1)
    W = 380.0
    coded = np.minimum(simulate(video, mask), W).astype(np.float32)
    common = dict(data_range=infer_data_range(255.0), settings=OmpSettings(max_atoms=8, tol_rms=2.0),
                  dictionary=dct_dictionary(8), tile=48, progress=False)
    saturated = coded >= W
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)  # (the never-open notice)
        vol, info = reconstruct_capture(capture_settings("omp", white_level=W, cache=tmp_path / "a", **common),
                                        coded, mask)
        exact, _ = reconstruct_capture(capture_settings("omp", cache=tmp_path / "b", **common), coded, mask)
        dropped, _ = saturated_as_missing(coded, mask, W)
        left_out, _ = reconstruct_capture(capture_settings("omp", cache=tmp_path / "c", **common),
                                          np.where(saturated, 0, coded).astype(np.float32), dropped)
    assert saturated.mean() > 0.01 and info["saturated_raised"] > 0 and info["saturated_pixels"] == saturated.sum()
    assert ((mask * vol).sum(0)[saturated] >= W - 1e-2).all()
    np.testing.assert_array_equal(vol[:, ~saturated], exact[:, ~saturated])
    q = {name: evaluate(v, video, data_range=255.0)["psnr"] for name, v in dict(kept=vol, exact=exact, left_out=left_out).items()}
    assert q["kept"] >= q["exact"] and q["kept"] > q["left_out"], q


def test_pipeline_white_level_and_shot_noise(tmp_path):
    from codedvideo.engine.config import PipelineConfig
    from codedvideo.api import run_pipeline

    cfg = PipelineConfig.model_validate(dict(
        frames=4, cache=str(tmp_path / "c"), stages=["simulate", "reconstruct"],
        scene=dict(size=[24, 24]), code=dict(name="rowwise"),
        noise=dict(shot_noise=True, gain=4.0, bits=10, white_level=80.0),
        dictionary=dict(kind="dct"), reconstruct=dict(tile=24), output=dict(dir=str(tmp_path / "o"), frames="none"),
    ))
    with warnings.catch_warnings(record=True) as said:
        warnings.simplefilter("always")
        report = run_pipeline(cfg, progress=False)
    assert not [w for w in said if "never open" in str(w.message)]  # saturated pixels are kept as measurements
    coded = np.load(tmp_path / "o" / "capture" / "coded.npy")
    n_sat = int((coded >= np.float32(80.0)).sum())
    assert n_sat > 0 and report["reconstruction"]["saturated_pixels"] == n_sat
    written = json.loads((tmp_path / "o" / "recon.metrics.json").read_text())
    assert written["reconstruction"]["saturated_pixels"] == n_sat
    assert written["config"]["noise"]["bits"] == 10


def test_shot_noise_far_past_the_full_well_saturates_instead_of_failing():
    """numpy's Poisson sampler refuses means past ~1e19 (gain 1e17, or values near 1e30): it was a traceback."""
    out = add_shot_noise(np.array([[1.0, 128.0], [1e30, 0.0]], np.float32), gain=1e17, full_well=20000.0, rng=0)
    np.testing.assert_array_equal(out, np.float32(20000.0 / 1e17) * np.array([[1, 1], [1, 0]], np.float32))


def test_a_capture_at_the_sensors_ceiling_everywhere_is_warned(tmp_path, capsys):
    """A 16-bit video through the default sensor (ceiling 2000 grey levels) came out one flat value, silently."""
    y, x = np.mgrid[0:32, 0:32]
    video = np.stack([128 + 100 * np.sin((x + 2 * t) / 6) * np.cos(y / 9) for t in range(8)]) * 128
    np.save(tmp_path / "v16.npy", video.astype(np.uint16))
    np.save(tmp_path / "v8.npy", (video / 128).astype(np.float32))
    with pytest.warns(UserWarning, match="100% of the pixels of capture 1 are at the sensor's ceiling"):
        assert _cli("simulate", tmp_path / "v16.npy", "--frames", 8, "--shot-noise", "--output", tmp_path / "a") == 0
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the same sensor on the 8-bit video: nothing to say
        assert _cli("simulate", tmp_path / "v8.npy", "--frames", 8, "--shot-noise", "--output", tmp_path / "b") == 0


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


def test_simulate_refuses_a_new_code_per_capture_for_one_capture(tmp_path, capsys):
    capsys.readouterr()
    rc = main(["-q", "simulate", "synth:default", "--frames", str(N), "--size", "16", "16", "--new-code-per-capture",
               "--output", str(tmp_path / "cap")])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and "--new-code-per-capture: one capture is made" in err and len(err.splitlines()) == 1, err
    assert not (tmp_path / "cap").exists()


def test_simulate_refuses_a_black_level_with_a_cacti_file(tmp_path, capsys):
    """`--black-level 64 --cacti-out F.mat` wrote a meas 64 above the plain sum CACTI files hold, silently (17.9 dB
    read back against 32.1); refused before any work."""
    capsys.readouterr()
    rc = main(["-q", "simulate", "synth:default", "--frames", str(N), "--size", "16", "16", "--black-level", "64",
               "--output", str(tmp_path / "cap"), "--cacti-out", str(tmp_path / "c.mat")])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and "--black-level 64" in err and "plain sum" in err and len(err.splitlines()) == 1, err
    assert not (tmp_path / "cap").exists() and not (tmp_path / "c.mat").exists()
