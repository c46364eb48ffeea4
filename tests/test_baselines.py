"""Baselines on the same forward model: shapes, exactness where it is known, and against the trivial estimate."""
import json
import subprocess
import sys
import time

import numpy as np
import pytest

from codedvideo.solvers.baselines import gap_tv, interp, normalized_fill, thinout
from codedvideo.engine.captures import reconstruct_method
from codedvideo.engine.windows import Execution
from codedvideo.model.codes import CodeSpec, make_code
from codedvideo.model.errors import InputError
from codedvideo.model.metrics import evaluate
from codedvideo.model.physics import forward, static_estimate
from codedvideo.data.scenes import load_video
from codedvideo.engine.simulation import simulate_capture


@pytest.fixture(scope="module")
def scene():
    """A moving test scene (disc crossing a drifting photograph), 48x48, N = 8."""
    return load_video("synth:default", frames=8, size=(48, 48))


def smooth_moving(n=8, size=(40, 40)):
    """A smooth pattern translating one pixel per sub-frame."""
    yy, xx = np.mgrid[0 : size[0], 0 : size[1]].astype(np.float32)
    return np.stack([128 + 80 * np.sin(2 * np.pi * (xx - t) / 23.0) * np.cos(2 * np.pi * yy / 31.0)
                     for t in range(n)]).astype(np.float32)


@pytest.mark.parametrize("code", ["thinout", "grid", "hitomi", "bernoulli"])
@pytest.mark.parametrize("fn", [thinout, interp, gap_tv])
def test_shape_and_finite(scene, fn, code):
    cap = simulate_capture(scene, code=CodeSpec(code, bump=2), sigma=2.0, seed=1)
    out = fn(cap["coded"], cap["mask"])
    assert out.shape == scene.shape and out.dtype == np.float32
    assert np.isfinite(out).all()


def test_normalized_fill_is_linear_interpolation_on_a_lattice():
    x = np.arange(20, dtype=np.float32)
    values = 3.0 * x + 1.0
    weights = (x % 4 == 0).astype(np.float32)
    out = normalized_fill(values * weights, weights, (4,))
    inside = x <= 16  # beyond the last sample the fill is constant, not extrapolated
    np.testing.assert_allclose(out[inside], values[inside], rtol=1e-5)
    np.testing.assert_allclose(out[17:], values[16])


def test_normalized_fill_fills_holes_wider_than_the_kernel():
    values = np.zeros((30, 30), np.float32)
    weights = np.zeros_like(values)
    values[0, 0], weights[0, 0] = 7.0, 1.0
    out = normalized_fill(values, weights, (2, 2))
    np.testing.assert_allclose(out, 7.0)


def test_thinout_keeps_read_rows_and_interpolates_linearly_between_them():
    n = 4
    truth = np.broadcast_to(np.arange(24, dtype=np.float32)[None, :, None] * 5.0, (n, 24, 6)).copy()
    mask = make_code("thinout", (24, 6), frames=n)
    out = thinout(forward(truth, mask), mask)
    # a linear ramp in y is reproduced exactly between the first and last rows read in each sub-frame
    for t in range(n):  # sub-frame t reads rows t, t + 4, ..., t + 20
        np.testing.assert_allclose(out[t, t : t + 21], truth[t, t : t + 21], rtol=1e-5)
        np.testing.assert_allclose(out[t, :t], np.broadcast_to(truth[t, t], (t, 6)))  # constant before the first row read


def test_interp_beats_trivial_on_a_smooth_moving_scene_with_the_grid_code():
    truth = smooth_moving()
    cap = simulate_capture(truth, code=CodeSpec("grid", bump=1), sigma=0.0, seed=0)
    trivial = evaluate(static_estimate(cap["coded"], cap["mask"]), truth, data_range=255.0)["psnr"]
    got = evaluate(interp(cap["coded"], cap["mask"]), truth, data_range=255.0)["psnr"]
    assert got > trivial + 3.0


def test_thinout_beats_trivial_on_a_smooth_moving_scene():
    truth = smooth_moving()
    cap = simulate_capture(truth, code=CodeSpec("thinout", bump=1), sigma=0.0, seed=0)
    trivial = evaluate(static_estimate(cap["coded"], cap["mask"]), truth, data_range=255.0)["psnr"]
    assert evaluate(thinout(cap["coded"], cap["mask"]), truth, data_range=255.0)["psnr"] > trivial + 1.0


@pytest.mark.parametrize("code,bump", [("hitomi", 2), ("hitomi", 3), ("bernoulli", 1)])
def test_gaptv_beats_the_trivial_estimate(scene, code, bump):
    cap = simulate_capture(scene, code=CodeSpec(code, bump=bump), sigma=0.0, seed=0)
    trivial = evaluate(static_estimate(cap["coded"], cap["mask"]), scene, data_range=255.0)["psnr"]
    got = gap_tv(cap["coded"], cap["mask"])
    assert evaluate(got, scene, data_range=255.0)["psnr"] > trivial + 1.0
    # the measurement is (nearly) met
    assert np.sqrt(np.mean((forward(got, cap["mask"]) - cap["coded"]) ** 2)) < 5.0


def test_reconstruct_method_dispatch(scene, tmp_path):
    cap = simulate_capture(scene, code=CodeSpec("hitomi", bump=2), sigma=0.0, seed=0)
    trivial = evaluate(static_estimate(cap["coded"], cap["mask"]), scene, data_range=255.0)["psnr"]
    for method in ("dct", "thinout", "interp", "gaptv"):
        start = time.perf_counter()
        vol, info = reconstruct_method(method, cap["coded"], cap["mask"], run=Execution(tile=32, cache=str(tmp_path)))
        wall = time.perf_counter() - start
        assert vol.shape == scene.shape and np.isfinite(vol).all()
        assert info["method"] == method
        assert 0 < info["seconds"]["reconstruct"] <= wall  # the call's own time, not a placeholder
        if method in ("dct", "gaptv"):
            assert evaluate(vol, scene, data_range=255.0)["psnr"] > trivial
    for method in ("omp", "nonlocal"):
        with pytest.raises(InputError, match=f"method {method}: needs a dictionary"):
            reconstruct_method(method, cap["coded"], cap["mask"])
    with pytest.raises(InputError, match="unknown"):
        reconstruct_method("nope", cap["coded"], cap["mask"])


def test_cli_reconstruct_method_without_dictionary(tmp_path, scene):
    cap = simulate_capture(scene, code=CodeSpec("grid", bump=1), sigma=0.0, seed=0)
    for name in ("coded", "mask", "truth"):
        np.save(tmp_path / f"{name}.npy", cap[name])
    cli = [sys.executable, "-m", "codedvideo.app.cli", "-q", "reconstruct", "--coded", str(tmp_path / "coded.npy"),
           "--mask", str(tmp_path / "mask.npy"), "--truth", str(tmp_path / "truth.npy"), "--cache", str(tmp_path / "c")]
    for method in ("interp", "dct"):
        out = tmp_path / f"{method}.npy"
        proc = subprocess.run([*cli, "--method", method, "--output", str(out)], capture_output=True, text=True,
                              timeout=300)
        assert proc.returncode == 0, proc.stderr
        metrics = json.loads((tmp_path / f"{method}.metrics.json").read_text())
        assert metrics["settings"]["method"] == method
        assert np.load(out).shape == scene.shape
    # omp without --dictionary: the dictionary shipped for the mask's N (tests/test_shipped.py), else an error
    proc = subprocess.run([*cli, "--output", str(tmp_path / "omp.npy")], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    assert json.loads((tmp_path / "omp.metrics.json").read_text())["inputs"]["dictionary"].endswith("dict-N8.zip")
