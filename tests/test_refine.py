"""The refinement under the measurement (``--refine``, ``--preset best``): GAP iterations with a weighted-nuclear-
norm prior on groups of similar patches followed across sub-frames (codedvideo.solvers.refine)."""
import numba
import numpy as np
import pytest

from conftest import capture_settings
from codedvideo.data.scenes import load_video
from codedvideo.model.metrics import evaluate
from codedvideo.model.physics import forward
from codedvideo.engine.simulation import simulate_capture
from codedvideo.model.codes import CodeSpec
from codedvideo.solvers import refine as R
from codedvideo.solvers.refine_kernel import match_frame_patches, shrink_frame_groups


@pytest.fixture(scope="module")
def carphone():
    """A 64x64 crop of real footage no dictionary was trained on (a clip the refinement's recipe was chosen on),
    hitomi L = 2, and the default's result from it."""
    import codedvideo as cv

    video = load_video("footage:carphone", frames=8, size=(64, 64))
    cap = simulate_capture(video, code=CodeSpec("hitomi", bump=2), sigma=0.0, seed=0)
    start = cv.reconstruct(cap["coded"], cap["mask"], data_range=255.0)
    return video, cap, start


def test_the_compiled_shrinkage_is_the_numpy_rule():
    """``shrink_frame_groups`` (gather, Gram, eigendecomposition, shrinkage, synthesis in one kernel) gives what
    :func:`refine.shrinkage` gives written out in numpy, at three noise levels (none, some, all shrunk)."""
    rng = np.random.default_rng(0)
    n, h, w, side = 4, 20, 22, R.SIDE
    base = rng.normal(100, 20, (n, h, w)).astype(np.float32)
    x = (base + rng.normal(0, 3, base.shape)).astype(np.float32)
    refs = R.reference_grid(n, h, w, step=3)
    groups = np.empty((refs.size, 6), np.int64)
    match_frame_patches(x, refs, side, 4, 1, 6, groups)
    assert (groups[:, 0] == refs).all()  # the reference first
    assert (np.abs(groups // (h * w) - refs[:, None] // (h * w)) <= 1).all()  # members one sub-frame away at most
    d = side * side
    t, r, c = groups // (h * w), groups % (h * w) // w, groups % w
    members = np.stack([x[a, b:b + side, e:e + side].reshape(-1) for a, b, e in zip(t.ravel(), r.ravel(), c.ravel())])
    members = members.reshape(groups.shape + (d,)).astype(np.float64)
    mean = members.mean(1, keepdims=True)
    centred = members - mean
    for sigma in (0.0, 3.0, 1e4):
        est = np.empty((groups.size, d), np.float32)
        shrink_frame_groups(x, groups, side, sigma * sigma, R.SHRINK, est)
        P = R.shrinkage(np.einsum("gid,gjd->gij", centred, centred), d, sigma)
        expected = mean + np.einsum("gij,gjd->gid", P, centred)
        np.testing.assert_allclose(est, expected.reshape(est.shape), rtol=0, atol=2e-3)
        if sigma == 0.0:  # nothing shrunk: every member as it was
            np.testing.assert_allclose(est, members.reshape(est.shape), rtol=0, atol=2e-3)
        if sigma == 1e4:  # everything shrunk: every member its group's mean
            np.testing.assert_allclose(est, np.broadcast_to(mean, members.shape).reshape(est.shape), atol=2e-3)


def test_a_group_follows_the_motion_into_the_next_sub_frames():
    """A texture moving one pixel right per sub-frame: a reference's group holds, in each sub-frame up to
    ``FRAMES`` away, the patch it moved to (an exact match), and the sub-frames' reference grids differ."""
    rng = np.random.default_rng(3)
    n, h, w = 8, 40, 48
    texture = rng.uniform(0, 255, (h, w + n)).astype(np.float32)
    video = np.stack([texture[:, n - t:n - t + w] for t in range(n)])  # frame t: the texture t pixels right
    refs = R.reference_grid(n, h, w)
    per_frame = [set((refs[refs // (h * w) == t] % (h * w)).tolist()) for t in range(n)]
    assert per_frame[0] != per_frame[1] and all(0 in f for f in per_frame)  # (the first patch always a reference)
    ref = 3 * h * w + 12 * w + 20  # sub-frame 3, corner (12, 20)
    groups = np.empty((1, R.GROUP), np.int64)
    match_frame_patches(video, np.array([ref]), R.SIDE, R.WINDOW, R.FRAMES, R.GROUP, groups)
    found = set(groups[0].tolist())
    for dt in range(-R.FRAMES, R.FRAMES + 1):
        assert (3 + dt) * h * w + 12 * w + 20 + dt in found, dt  # where the patch moved to in sub-frame 3 + dt
    assert groups[0, 0] == ref


def test_refining_keeps_the_measurements_and_improves_held_out_footage(carphone):
    video, cap, start = carphone
    refined, info = R.refine(cap["coded"], cap["mask"], start, iterations=12)
    assert refined.dtype == np.float32 and np.isfinite(refined).all()
    residual = forward(refined, cap["mask"]) - cap["coded"]
    start_residual = forward(start, cap["mask"]) - cap["coded"]
    # the mean of two estimates that reproduce the measurements (the start to its own residual)
    assert np.sqrt(np.mean(residual ** 2)) <= 0.5 * np.sqrt(np.mean(start_residual ** 2)) + 0.01
    gain = evaluate(refined, video, data_range=255.0)["psnr"] - evaluate(start, video, data_range=255.0)["psnr"]
    assert gain > 0.3, gain  # measured +0.9 dB here (from the default's result)
    matched = [R.reference_grid(8, 64, 64, matching=m).size for m in range(-(-12 // R.REGROUP))]
    assert info["iterations"] == 12 and info["groups"] == round(np.mean(matched))  # groups shrunk an iteration


def test_each_matching_puts_the_references_on_a_shifted_grid():
    """The grids of successive matchings are shifted within the ``STEP x STEP`` cell (the first matching's
    unshifted), spread so that a few matchings put references on many more places than one does; each grid
    keeps the first and last patch of every row and column."""
    assert R.grid_shift(0) == (0, 0)
    shifts = [R.grid_shift(m) for m in range(8)]
    assert len(set(shifts)) == 8 and all(0 <= a < R.STEP and 0 <= b < R.STEP for a, b in shifts)
    assert len({a for a, _ in shifts}) >= 4 and len({b for _, b in shifts}) >= 4  # (spread along both axes)
    n, h, w = 8, 64, 80
    grids = [R.reference_grid(n, h, w, matching=m) for m in range(8)]
    np.testing.assert_array_equal(grids[0], R.reference_grid(n, h, w))
    assert len(set(np.concatenate(grids).tolist())) > 3 * grids[0].size
    for g in grids:
        corner = g % (h * w)
        rows, cols = corner // w, corner % w
        assert {0, h - R.SIDE} <= set(rows.tolist()) and {0, w - R.SIDE} <= set(cols.tolist())


def test_the_result_does_not_depend_on_the_threads_or_the_chunks(carphone, monkeypatch):
    _, cap, start = carphone
    ref, _ = R.refine(cap["coded"], cap["mask"], start, iterations=5)
    threads = numba.get_num_threads()
    try:
        numba.set_num_threads(1)
        one, _ = R.refine(cap["coded"], cap["mask"], start, iterations=5)
    finally:
        numba.set_num_threads(threads)
    np.testing.assert_array_equal(one, ref)
    monkeypatch.setattr(R, "CHUNK", 7)  # groups solved and added seven at a time
    np.testing.assert_array_equal(R.refine(cap["coded"], cap["mask"], start, iterations=5)[0], ref)


def test_one_block_is_the_kernels_matching_on_the_whole_video(carphone):
    """A grey capture (one block, the default): the references and the groups the kernel matches on the whole
    video, as before blocks existed, and the same refinement as ``blocks=1`` bit for bit."""
    _, cap, start = carphone
    x = np.ascontiguousarray(start, np.float32)
    refs = R.reference_grid(8, 64, 64)
    np.testing.assert_array_equal(refs, R.reference_grid(8, 64, 64, blocks=1))
    direct = np.empty((refs.size, R.GROUP), np.int64)
    match_frame_patches(x, refs, R.SIDE, R.WINDOW, R.FRAMES, R.GROUP, direct)
    np.testing.assert_array_equal(np.concatenate([part for part, *_ in R.match(x, refs)]), direct)
    one, info = R.refine(cap["coded"], cap["mask"], start, iterations=3)
    np.testing.assert_array_equal(one, R.refine(cap["coded"], cap["mask"], start, iterations=3, blocks=1)[0])
    assert "blocks" not in info


def test_a_stack_of_blocks_is_grouped_and_denoised_each_block_as_a_video_alone():
    """Three videos of 4 sub-frames stacked (a colour video's channels): every group's members lie in its
    reference's block, even where the next block's first sub-frame repeats this one's last exactly (one block:
    the groups cross there), and the stack is denoised block by block as each video alone is, bit for bit."""
    rng = np.random.default_rng(5)
    blocks, n, h, w = 3, 4, 30, 34
    x = rng.normal(120, 25, (blocks * n, h, w)).astype(np.float32)
    x[n] = x[n - 1]  # block 1's first sub-frame: block 0's last
    x[2 * n] = x[2 * n - 1] + 0.5
    refs = R.reference_grid(blocks * n, h, w, blocks=blocks)
    alone = R.reference_grid(n, h, w)
    np.testing.assert_array_equal(refs, np.concatenate([alone + b * n * h * w for b in range(blocks)]))
    chunks = R.match(x, refs, blocks=blocks)
    groups = np.concatenate([part for part, *_ in chunks])
    assert (groups // (n * h * w) == refs[:, None] // (n * h * w)).all()
    crossing = np.concatenate([part for part, *_ in R.match(x, refs)])
    assert (crossing // (n * h * w) != refs[:, None] // (n * h * w)).any()  # (the test can see a crossing)
    stacked = R.denoise(x, chunks, 4.0)
    for b in range(blocks):
        video = np.ascontiguousarray(x[b * n:(b + 1) * n])
        np.testing.assert_array_equal(stacked[b * n:(b + 1) * n], R.denoise(video, R.match(video, alone), 4.0))
    with pytest.raises(ValueError, match="not 5 equal blocks"):
        R.reference_grid(blocks * n, h, w, blocks=5)


@pytest.mark.parametrize("value", [0.0, 255.0])
def test_flat_scenes_stay_exactly_flat(value):
    """All dark, all white: nothing to shrink, every group its mean; the measurements hold the same value."""
    mask = np.random.default_rng(1).random((8, 24, 24)) < 0.5
    video = np.full((8, 24, 24), value, np.float32)
    coded = forward(video, mask)
    refined, _ = R.refine(coded, mask, video, iterations=4)
    np.testing.assert_allclose(refined, value, atol=1e-3 * max(value, 1.0))


def test_images_smaller_than_a_patch_and_no_iterations_return_the_start():
    start = np.arange(8 * 5 * 9, dtype=np.float32).reshape(8, 5, 9)
    mask = np.ones((8, 5, 9), np.uint8)
    out, info = R.refine(forward(start, mask), mask, start, iterations=10)
    np.testing.assert_array_equal(out, start)
    assert info["iterations"] == 0
    out, info = R.refine(np.zeros((9, 9), np.float32), np.ones((8, 9, 9)), np.zeros((8, 9, 9)), iterations=0)
    assert info["iterations"] == 0 and not out.any()


def test_a_pixel_never_open_is_not_held_to_a_measurement():
    """Its ``Phi Phi^T`` is 0: no step to the measurements (no division by it), and the prior may only move it
    towards its neighbours (from the 40 it was filled with towards their 50)."""
    rng = np.random.default_rng(2)
    video = np.full((4, 16, 16), 50.0, np.float32)
    mask = (rng.random(video.shape) < 0.5).astype(np.uint8)
    mask[:, 8, 8] = 0
    coded = forward(video, mask)
    start = video.copy()
    start[:, 8, 8] = 40.0
    refined, _ = R.refine(coded, mask, start, iterations=6)
    assert np.isfinite(refined).all()
    assert 40.0 - 1e-3 <= refined[:, 8, 8].min() and refined[:, 8, 8].max() <= 50.0 + 1e-3
    np.testing.assert_allclose(np.delete(refined.reshape(4, -1), 8 * 16 + 8, axis=1), 50.0, atol=0.1)


def test_a_capture_in_other_units_is_refined_to_the_same_video_times_the_scale(carphone):
    """The refinement runs in working units (its noise levels are grey levels of an 8-bit capture): the capture
    as [0, 1] floats gives the 8-bit capture's video / 255."""
    import codedvideo as cv

    _, cap, _ = carphone
    eight = cv.reconstruct(cap["coded"], cap["mask"], refine=6, data_range=255.0, full_output=True)
    unit = cv.reconstruct(cap["coded"] / np.float32(255), cap["mask"], refine=6, data_range=1.0)
    assert eight.info[0]["refine"]["iterations"] == 6
    np.testing.assert_allclose(unit * 255, eight.frames, rtol=0, atol=0.05)
    plain = cv.reconstruct(cap["coded"], cap["mask"], data_range=255.0)
    assert np.abs(eight.frames - plain).max() > 1.0  # (refined: not the plain result)


def test_the_step_to_the_measurements_in_bands_is_the_whole_step(monkeypatch):
    rng = np.random.default_rng(4)
    x = rng.normal(100, 30, (6, 40, 30)).astype(np.float32)
    mask = (rng.random(x.shape) < 0.5).astype(np.uint8)
    coded = forward(rng.normal(100, 30, x.shape).astype(np.float32), mask)
    open2 = forward(mask, mask)
    inv = np.divide(1.0, open2, out=np.zeros_like(open2), where=open2 > 0)
    whole = x.copy()
    R.to_measurements(whole, mask, coded, inv)
    np.testing.assert_allclose(forward(whole, mask)[open2 > 0], coded[open2 > 0], rtol=1e-5, atol=1e-3)
    monkeypatch.setattr(R, "BAND", 6 * 30 * 7)  # seven rows at a time
    banded = x.copy()
    R.to_measurements(banded, mask, coded, inv)
    np.testing.assert_array_equal(banded, whole)


def test_in_a_stream_the_pixels_only_still_patches_cover_keep_their_still_answer(tmp_path, capsys):
    """70 % of the frame still across 3 captures: the refinement leaves the pixels only still patches cover as
    they were (bit for bit), and changes the moving part."""
    from codedvideo.app.cli import main

    def run(*args):
        capsys.readouterr()
        assert main(["-q", *map(str, args)]) == 0, capsys.readouterr().err

    cap = tmp_path / "cap"
    run("simulate", "synth:default-static70", "--frames", 8, "--size", 64, 96, "--captures", 3, "--output", cap)
    common = ["reconstruct", "--coded", cap / "coded.npy", "--mask", cap / "mask.npy", "--method", "dct", "--cache",
              tmp_path / "cache"]
    run(*common, "--output", tmp_path / "plain.npy")
    run(*common, "--refine", 4, "--output", tmp_path / "refined.npy")
    plain, refined = np.load(tmp_path / "plain.npy"), np.load(tmp_path / "refined.npy")
    same = (refined == plain).all(0)  # (H, W): every sub-frame of every capture unchanged
    assert same.mean() > 0.4
    assert np.abs(refined - plain)[:, ~same].max() > 0.5


def test_saturated_pixels_are_not_held_to_their_clipped_values_and_still_record_the_white_level(carphone, tmp_path):
    """With --white-level the clipped pixels are left out of the refinement's measurements (never pulled down to
    the clipped value) and afterwards still record at least the white level; the rest keeps its measurements."""
    from codedvideo.engine.config import PipelineConfig, omp_settings
    from codedvideo.engine.captures import reconstruct_capture
    from codedvideo.model.units import infer_data_range
    from codedvideo.solvers.dictionaries import dct_dictionary

    video, cap, _ = carphone
    white = float(np.quantile(cap["coded"], 0.9))
    coded = np.minimum(cap["coded"], np.float32(white))
    saturated = coded >= np.float32(white)
    runs = {}
    for refine in (0, 6):
        runs[refine] = reconstruct_capture(capture_settings("omp", refine=refine, white_level=white,
                                                           dictionary=dct_dictionary(8),
                                                           data_range=infer_data_range(255.0, given=255.0), tile=32,
                                                           progress=False, cache=tmp_path,
                                                           settings=omp_settings(PipelineConfig().reconstruct, 0.0)),
                                           coded, cap["mask"])
    vol, info = runs[6]
    assert np.isfinite(vol).all() and info["refine"]["iterations"] == 6 and saturated.sum() > 100
    recorded = forward(vol, cap["mask"])
    assert (recorded[saturated] >= white - 1e-3).all()
    rms = lambda v: float(np.sqrt(np.mean((forward(v, cap["mask"]) - coded)[~saturated] ** 2)))  # noqa: E731
    # the mean of the start (to its tolerance) and an estimate that reproduces the measurements: half the misfit
    assert rms(vol) <= 0.55 * rms(runs[0][0])


def test_with_read_noise_the_relaxed_steps_beat_holding_the_noisy_measurements_exactly():
    """``noise_sigma``: plain GAP with relaxed steps; on a noisy capture (sigma 8) it ends closer to the truth than
    the exact steps, which hold the measurements' noise (measured +0.36 dB here)."""
    import codedvideo as cv

    video = load_video("footage:carphone", frames=8, size=(64, 64))
    cap = simulate_capture(video, code=CodeSpec("hitomi", bump=2), sigma=8.0, seed=0)
    start = cv.reconstruct(cap["coded"], cap["mask"], data_range=255.0, noise_sigma=8.0)
    exact, _ = R.refine(cap["coded"], cap["mask"], start, iterations=12)
    relaxed, info = R.refine(cap["coded"], cap["mask"], start, iterations=12, noise_sigma=8.0)
    assert info["noise_sigma"] == 8.0 and np.isfinite(relaxed).all()
    assert evaluate(relaxed, video, data_range=255.0)["psnr"] > evaluate(exact, video, data_range=255.0)["psnr"] + 0.15
    # the exact steps reproduce the noisy measurements, the relaxed ones do not (they leave some of the noise)
    misfit = lambda v: float(np.sqrt(np.mean((forward(v, cap["mask"]) - cap["coded"]) ** 2)))  # noqa: E731
    assert misfit(relaxed) > misfit(exact) + 0.5


@pytest.mark.parametrize("scale", [1.0, 255.0])
def test_the_command_line_read_noise_reaches_the_refinement_in_working_units(tmp_path, capsys, scale):
    """``--noise-sigma`` in the capture's units: the refinement gets it in working units (4 grey levels of an 8-bit
    capture from both the 8-bit capture and the [0, 1] one)."""
    import json

    from codedvideo.app.cli import main

    video = load_video("footage:carphone", frames=8, size=(32, 32))
    cap = simulate_capture(video, code=CodeSpec("hitomi", bump=2), sigma=4.0, seed=0)
    np.save(tmp_path / "coded.npy", (cap["coded"] / np.float32(scale)).astype(np.float32))
    np.save(tmp_path / "mask.npy", cap["mask"])
    rc = main(["-q", "reconstruct", "--coded", str(tmp_path / "coded.npy"), "--mask", str(tmp_path / "mask.npy"),
               "--noise-sigma", f"{4.0 / scale!r}", "--refine", "3", "--cache", str(tmp_path / "cache"),
               *(["--data-range", "1"] if scale != 1.0 else []), "--output", str(tmp_path / "out.npy")])
    assert rc == 0, capsys.readouterr().err
    record = json.loads((tmp_path / "out.metrics.json").read_text())["reconstruction"]["refine"]
    assert record["iterations"] == 3 and record["noise_sigma"] == pytest.approx(4.0, rel=1e-5)


@pytest.mark.parametrize("kind", ["flat", "ramp"])
def test_on_equal_patches_every_sub_frame_is_covered_alike(kind):
    """Where many patches are equal (a flat or a smooth region) the ties keep a group in and near its own
    sub-frame: no matching leaves a sub-frame mostly outside every group (with ties to the earliest sub-frame the
    last one was 23 % uncovered on a flat scene, at every matching), and the shifted grids of a run's matchings
    together cover every voxel."""
    n, h, w = 8, 64, 64
    if kind == "flat":
        video = np.full((n, h, w), 100.0, np.float32)
    else:
        video = np.tile(np.linspace(0, 255, w, dtype=np.float32), (n, h, 1))
    union = np.zeros((n, h, w), bool)
    for matching in range(32 // R.REGROUP):
        covered = np.zeros((n, h, w), bool)
        for _, where, _, _ in R.match(video, R.reference_grid(n, h, w, matching=matching)):
            for p in where:
                t, r, c = p // (h * w), p % (h * w) // w, p % w
                covered[t, r:r + R.SIDE, c:c + R.SIDE] = True
        uncovered = 1 - covered.reshape(n, -1).mean(1)
        assert uncovered.max() < 0.25, (matching, uncovered)
        union |= covered
    assert union.all()


def test_with_a_truth_the_record_gives_the_psnr_along_the_refinements_iterations():
    """Error against time inside a run: the estimate before the refinement and every WATCH_EVERY iterations,
    scored against the truth, with the seconds to each; the last point is the result's own PSNR, and watching
    changes no bit of the result."""
    import codedvideo as cv
    from codedvideo.solvers.refine import WATCH_EVERY

    video = cv.synthetic_scene("default", frames=8, size=(48, 48)) / 255
    mask = cv.make_code("hitomi", (48, 48), frames=8, bump=2, seed=0)
    coded = cv.simulate(video, mask, noise_sigma=0.01, seed=1)
    iterations = 2 * WATCH_EVERY + 3
    scored = cv.reconstruct(coded, mask, refine=iterations, noise_sigma=0.01, truth=video, full_output=True)
    plain = cv.reconstruct(coded, mask, refine=iterations, noise_sigma=0.01)
    assert np.array_equal(scored.frames, plain)
    trace = scored.record["reconstruction"]["refine_trace"]
    assert [p["iterations"] for p in trace if "iterations" in p] == [0, WATCH_EVERY, 2 * WATCH_EVERY, iterations]
    # (a last point, the result, where a step after the refinement moved it: here its still regions)
    assert all("iterations" in p for p in trace[:-1]) and trace[-1].get("stage", "result") == "result"
    seconds = [p["seconds"] for p in trace]
    assert seconds == sorted(seconds) and seconds[0] >= 0
    assert abs(trace[-1]["psnr"] - scored.record["quality"]["psnr"]) < 1e-9
    assert trace[-1]["psnr"] > trace[0]["psnr"]  # the refinement gains on this scene
    assert "refine_trace" not in cv.reconstruct(coded, mask, noise_sigma=0.01, truth=video,
                                                full_output=True).record["reconstruction"]



def test_with_a_truth_best_records_the_psnr_after_each_pass_before_its_refinement():
    """``--preset best`` with a truth: ``stage_trace`` holds the PSNR after each pass of its adaptation (two
    rounds: passes 1 and 2) at the capture's seconds to it, before ``refine_trace``'s first point (the third
    pass's result); the last pass's PSNR is that first point's, and scoring changes no bit."""
    import codedvideo as cv

    video = load_video("footage:carphone", frames=8, size=(48, 48))
    mask = cv.make_code("hitomi", (48, 48), frames=8, bump=2, seed=0)
    coded = cv.simulate(video, mask)
    scored = cv.reconstruct(coded, mask, preset="best", refine=8, data_range=255.0, truth=video, full_output=True)
    assert np.array_equal(scored.frames, cv.reconstruct(coded, mask, preset="best", refine=8, data_range=255.0))
    record = scored.record["reconstruction"]
    stages, trace = record["stage_trace"], record["refine_trace"]
    assert [p["stage"] for p in stages] == ["pass 1", "pass 2"]
    seconds = [p["seconds"] for p in stages] + [p["seconds"] for p in trace]
    assert seconds == sorted(seconds) and seconds[0] > 0
    assert all(np.isfinite(p["psnr"]) and p["psnr"] > 20 for p in stages)
    assert stages[0]["psnr"] < trace[0]["psnr"] < trace[-1]["psnr"], (stages, trace)
    assert "stage_trace" not in cv.reconstruct(coded, mask, method="nonlocal", refine=4, data_range=255.0,
                                               truth=video, full_output=True).record["reconstruction"]

@pytest.mark.parametrize("kind", ["spread", "clustered", "low-rank"])
def test_the_kept_eigenpairs_are_lapacks(kind):
    """``kept_eigenpairs`` (the shrinkage's selective eigensolver) gives the eigenvalues above the cut and an
    orthonormal basis of their eigenvectors that LAPACK's whole decomposition gives: on spread spectra, on
    clusters of equal eigenvalues and on Gram matrices of fewer members than their size; more than
    ``SELECT_MAX`` above the cut: -1 (the caller decomposes whole)."""
    from codedvideo.solvers.refine_kernel import SELECT_MAX, kept_eigenpairs

    rng = np.random.default_rng({"spread": 0, "clustered": 1, "low-rank": 2}[kind])
    k = R.GROUP
    for trial in range(40):
        if kind == "spread":
            A = rng.normal(0, 1, (k, 64)) * np.geomspace(50, 0.1, 64)
            C = A @ A.T
        elif kind == "clustered":  # three eigenvalues equal, two more equal, the rest small
            Q, _ = np.linalg.qr(rng.normal(size=(k, k)))
            C = (Q * np.r_[[900.0] * 3, [400.0] * 2, rng.uniform(0, 10, k - 5)]) @ Q.T
        else:
            A = rng.normal(0, 1, (k, 3)) @ rng.normal(0, 5, (3, 64))
            C = A @ A.T
        lam_ref, U_ref = np.linalg.eigh(C)
        kept = 1 + trial % SELECT_MAX
        cut = 0.5 * (lam_ref[k - kept] + lam_ref[k - kept - 1])
        if not lam_ref[k - kept] - lam_ref[k - kept - 1] > 1e-6 * lam_ref[-1]:
            continue  # (a cut inside a cluster: which side is a matter of rounding)
        lam, U = np.empty(k), np.empty((k, k))
        m = kept_eigenpairs(C, cut, lam, U, np.empty((2 * k + 11, k)))
        assert m == kept
        np.testing.assert_allclose(lam[:m], lam_ref[::-1][:m], rtol=0, atol=1e-9 * lam_ref[-1])
        np.testing.assert_allclose(U[:, :m].T @ U[:, :m], np.eye(m), atol=1e-8)
        # the same invariant subspace (the projector onto it), whatever basis a cluster is given
        np.testing.assert_allclose(U[:, :m] @ U[:, :m].T, U_ref[:, k - m:] @ U_ref[:, k - m:].T, atol=1e-6)
    many = np.diag(np.arange(1.0, k + 1))
    work = np.empty((2 * k + 11, k))
    assert kept_eigenpairs(many, 0.5, np.empty(k), np.empty((k, k)), work) == -1
    assert kept_eigenpairs(many, k + 1.0, np.empty(k), np.empty((k, k)), work) == 0


def test_known_pixels_are_left_out_of_the_groups(carphone):
    """``known`` (a stream's still answers, kept by the caller): no group is referenced where a patch holds only
    known pixels, so a capture known everywhere costs no group, and one known on its left half costs the groups
    of its right half, with the same answer there as when every reference is solved (within 0.05 dB)."""
    video, cap, start = carphone
    n, h, w = start.shape
    refs = R.reference_grid(n, h, w)
    everywhere = np.ones((h, w), bool)
    assert R.moving_references(refs, everywhere, start.shape).size == 0
    out, info = R.refine(cap["coded"], cap["mask"], start, iterations=4, known=everywhere)
    assert info["groups"] == 0 and np.isfinite(out).all()
    left = np.zeros((h, w), bool)
    left[:, :32] = True
    kept = R.moving_references(refs, left, start.shape)
    cols = kept % w
    assert (cols + R.SIDE > 32).all() and 0 < kept.size < refs.size  # every patch kept reaches the right half
    assert ((refs % w) + R.SIDE > 32).sum() == kept.size
    whole, _ = R.refine(cap["coded"], cap["mask"], start, iterations=8)
    half, info = R.refine(cap["coded"], cap["mask"], start, iterations=8, known=left)
    matched = [R.moving_references(R.reference_grid(n, h, w, matching=m), left, start.shape).size
               for m in range(-(-8 // R.REGROUP))]
    assert info["groups"] == round(np.mean(matched)) and matched[0] == kept.size
    right = np.s_[:, :, 40:]  # (beyond the reach of the left half's groups)
    gap = evaluate(half[right], video[right], data_range=255.0)["psnr"] - evaluate(whole[right], video[right], data_range=255.0)["psnr"]
    assert abs(gap) < 0.05, gap


def test_a_large_volume_is_refined_in_bands_with_the_same_quality(carphone, monkeypatch):
    """Above ``BAND_VOXELS`` the refinement goes a band of rows at a time, each with ``HALO`` rows beyond it:
    bands cover every row once, and the result keeps the measurements and the whole image's PSNR (within
    0.05 dB; measured 0.004 dB on a 512x512 capture in 4 bands)."""
    video, cap, start = carphone
    n, h, w = start.shape
    assert R.bands((n, h, w)) == [(0, h)]
    whole, _ = R.refine(cap["coded"], cap["mask"], start, iterations=8)
    monkeypatch.setattr(R, "HALO", 4)
    monkeypatch.setattr(R, "BAND_VOXELS", n * w * 24)  # bands of 16 rows
    parts = R.bands((n, h, w))
    assert len(parts) == 4 and parts[0][0] == 0 and parts[-1][1] == h
    assert all(a[1] == b[0] for a, b in zip(parts, parts[1:]))
    seen = []
    banded, info = R.refine(cap["coded"], cap["mask"], start, iterations=8, run=R.RefineRun(
        watch=lambda i, v, seconds, rows: seen.append((i, rows.start, rows.stop, v.shape[1]))))
    assert info["bands"] == 4 and not np.array_equal(banded, whole)
    assert sorted(seen) == sorted((i, a, b, b - a) for i in (8,) for a, b in parts)  # each band's rows, once
    residual = forward(banded, cap["mask"]) - cap["coded"]
    start_residual = forward(start, cap["mask"]) - cap["coded"]
    assert np.sqrt(np.mean(residual ** 2)) <= 0.5 * np.sqrt(np.mean(start_residual ** 2)) + 0.01
    gap = evaluate(banded, video, data_range=255.0)["psnr"] - evaluate(whole, video, data_range=255.0)["psnr"]
    assert abs(gap) < 0.05, gap
    # in place (the memory of one band beside the start): the same bits, written into the start itself
    own = start.astype(np.float32).copy()
    inplace, _ = R.refine(cap["coded"], cap["mask"], own, iterations=8, run=R.RefineRun(overwrite=True))
    assert inplace is own
    np.testing.assert_array_equal(inplace, banded)


def test_the_error_against_time_of_a_banded_refinement_adds_up_its_bands(monkeypatch):
    """``refine_trace`` of a refinement in bands: each point scores every row (the bands' squared errors added),
    the last point is the result's PSNR, and the seconds to each point add up the bands'."""
    import codedvideo as cv

    video = load_video("footage:carphone", frames=8, size=(64, 64))
    mask = cv.make_code("hitomi", (64, 64), frames=8, bump=2, seed=0)
    coded = cv.simulate(video, mask)
    monkeypatch.setattr(R, "HALO", 4)
    monkeypatch.setattr(R, "BAND_VOXELS", 8 * 64 * 24)  # bands of 16 rows
    got = cv.reconstruct(coded, mask, data_range=255.0, refine=16, truth=video, full_output=True)
    trace = got.record["reconstruction"]["refine_trace"]
    assert [p["iterations"] for p in trace] == [0, 8, 16]
    assert got.record["reconstruction"]["refine"]["bands"] == 4
    assert trace[-1]["psnr"] == pytest.approx(got.record["quality"]["psnr"], abs=1e-9)
    assert trace[0]["seconds"] < trace[1]["seconds"] < trace[2]["seconds"]
    assert trace[2]["psnr"] > trace[0]["psnr"]
