"""Tile level: chunked reconstruction equals the whole-image reconstruction."""
import numpy as np
import pytest

from codedvideo.model.codes import make_code
from codedvideo.solvers.dictionaries import dct_dictionary
from codedvideo.engine.parallel import plan_tiles
from codedvideo.model.physics import simulate
from codedvideo.engine.windows import Execution, reconstruct_volume
from codedvideo.solvers.region import OmpSettings, reconstruct_region


@pytest.fixture(scope="module")
def capture():
    rng = np.random.default_rng(7)
    n, h, w = 4, 37, 45
    yy, xx = np.mgrid[0:h, 0:w]
    video = np.stack([128 + 60 * np.sin((xx - 1.5 * t) / 4.0) * np.cos(yy / 6.0) for t in range(n)]).astype(np.float32)
    video += rng.normal(0, 2, video.shape).astype(np.float32)
    mask = make_code("hitomi", (h, w), frames=n, bump=2, rng=3)
    return simulate(video, mask, sigma=0.0), mask, video


def test_plan_covers_image_exactly_once():
    tiles = plan_tiles((37, 45), 16)
    hit = np.zeros((37, 45), int)
    for t in tiles:
        y0, y1, x0, x1 = t.core
        hit[y0:y1, x0:x1] += 1
        hy0, hy1, hx0, hx1 = t.halo
        assert hy0 == max(0, y0 - 6) and hy1 == min(37, y1 + 6)
    assert (hit == 1).all()


@pytest.mark.parametrize("tile", [8, 13, 32])
def test_chunked_equals_single_chunk(capture, tile, tmp_path):
    coded, mask, _ = capture
    D = dct_dictionary(4)
    s = OmpSettings(max_atoms=6, tol_rms=0.5, batch=97)
    whole, _ = reconstruct_region(coded, mask, D, s)
    vol, info = reconstruct_volume(coded, mask, D, settings=s,
                                   run=Execution(tile=tile, cache=tmp_path, workers=2, progress=False))
    assert info["tiles"] == len(plan_tiles(coded.shape, tile))
    np.testing.assert_allclose(vol, whole, rtol=1e-4, atol=1e-3)


def test_rerun_reuses_finished_tiles(capture, tmp_path):
    coded, mask, _ = capture
    D = dct_dictionary(4)
    s = OmpSettings(max_atoms=4, tol_rms=0.5)
    v1, i1 = reconstruct_volume(coded, mask, D, settings=s, run=Execution(tile=16, cache=tmp_path, progress=False))
    v2, i2 = reconstruct_volume(coded, mask, D, settings=s, run=Execution(tile=16, cache=tmp_path, progress=False))
    assert i1["tiles_computed"] == i1["tiles"] and i2["tiles_computed"] == 0
    np.testing.assert_array_equal(v1, v2)
    # other settings: a different key, computed afresh
    _, i3 = reconstruct_volume(coded, mask, D, settings=OmpSettings(max_atoms=3, tol_rms=0.5),
                               run=Execution(tile=16, cache=tmp_path, progress=False))
    assert i3["tiles_computed"] == i3["tiles"]


def test_reconstruction_beats_trivial_estimate(capture, tmp_path):
    from codedvideo.model.metrics import evaluate
    from codedvideo.model.physics import static_estimate

    coded, mask, video = capture
    vol, _ = reconstruct_volume(coded, mask, dct_dictionary(4), settings=OmpSettings(max_atoms=8, tol_rms=0.5),
                                run=Execution(tile=32, cache=tmp_path, progress=False))
    assert evaluate(vol, video, data_range=255.0)["psnr"] > evaluate(static_estimate(coded, mask), video, data_range=255.0)["psnr"] + 3


def test_still_patches_take_the_cheap_path_with_the_same_answer():
    """A still, smooth scene is accepted by the still-scene test and matches full OMP within the noise."""
    from codedvideo.solvers.region import STAT_NAMES

    n, h, w = 6, 30, 34
    yy, xx = np.mgrid[0:h, 0:w]
    still = (60 + 0.8 * xx + 0.5 * yy).astype(np.float32)  # gentle ramps
    video = np.repeat(still[None], n, axis=0)
    mask = make_code("hitomi", (h, w), frames=n, bump=2, rng=9)
    coded = simulate(video, mask, sigma=0.0)
    D = dct_dictionary(n)
    skip, st_skip = reconstruct_region(coded, mask, D, OmpSettings(max_atoms=8, tol_rms=0.5, static_atoms=4))
    full, st_full = reconstruct_region(coded, mask, D, OmpSettings(max_atoms=8, tol_rms=0.5, static_atoms=0))
    stats = dict(zip(STAT_NAMES, st_skip))
    assert stats["patches_static"] == stats["patches"]  # every patch took the cheap path
    assert dict(zip(STAT_NAMES, st_full))["patches_static"] == 0
    assert np.sqrt(np.mean((skip - full) ** 2)) < 0.5
    assert np.sqrt(np.mean((skip - video) ** 2)) < 0.5
    # a moving pattern is not taken for a still one
    moving = np.stack([128 + 60 * np.sin((xx - 2.0 * t) / 2.5) for t in range(n)]).astype(np.float32)
    _, st_mov = reconstruct_region(simulate(moving, mask), mask, D, OmpSettings(max_atoms=8, tol_rms=0.5, static_atoms=4))
    assert dict(zip(STAT_NAMES, st_mov))["patches_static"] < 0.05 * dict(zip(STAT_NAMES, st_mov))["patches"]


@pytest.mark.parametrize("code", ["hitomi", "bernoulli"])
def test_the_still_test_keeps_a_change_of_the_light_below_the_tolerance(code):
    """A flat region whose light flickers by less than the tolerance passes the still test; its temporal profile,
    fitted through each patch's code, keeps the flicker that the still image alone flattens, and under heavy
    noise the profile's ridge keeps the still image."""
    from codedvideo.solvers.region import region_patches, still_patches

    n, h, w = 8, 14, 15
    flicker = 1.5 * np.sin(np.arange(n) * 2 * np.pi / 5)  # grey levels: below the tolerance of 2
    video = np.broadcast_to((100 + flicker)[:, None, None], (n, h, w)).astype(np.float32)
    mask = make_code(code, (h, w), frames=n, bump=2, rng=3)
    patches = region_patches(simulate(video, mask).astype(np.float32), mask, True, 7)
    rows = np.arange(patches.y.shape[0])
    tol = patches.n_open * 2.0**2
    codes = (patches.codes, patches.corners(rows))
    ok, flat = still_patches(patches.y, patches.n_pix, tol, 8, frames=n)
    ok_p, kept = still_patches(patches.y, patches.n_pix, tol, 8, frames=n, codes=codes)
    ok_n, noisy = still_patches(patches.y, patches.n_pix, patches.n_open * 30.0**2, 8, frames=n, codes=codes,
                                ridge=(30.0 / 2.0) ** 2)
    assert ok.all() and ok_p.all() and ok_n.all()
    truth = np.broadcast_to((100 + flicker)[None, :, None], (rows.size, n, 49))

    def rms(a):
        return float(np.sqrt(np.mean(np.square(a, dtype=np.float64))))

    assert rms(flat.reshape(-1, n, 49) - truth) > 0.9  # the still image: the flicker is gone
    assert rms(kept.reshape(-1, n, 49) - truth) < 0.2 * rms(flat.reshape(-1, n, 49) - truth)
    assert rms(noisy - flat) < 0.1 * rms(kept - flat)  # a ridge of (30 / 2)**2: under a tenth of the profile


@pytest.mark.parametrize("code", ["hitomi", "hitomi-tiled", "bernoulli"])
def test_still_test_equals_omp_over_the_still_dictionary(code):
    """The closed-form still test (no dictionary search) agrees with OMP over the still atoms."""
    from codedvideo.model import patches as P
    from codedvideo.solvers.omp import MaskedOperator, omp
    from codedvideo.solvers.omp_kernel import synthesize
    from codedvideo.solvers.region import static_dictionary, still_patches

    rng = np.random.default_rng(11)
    n, h, w = 6, 24, 26
    yy, xx = np.mgrid[0:h, 0:w]
    still = 90 + 40 * np.cos(xx / 9.0) + 25 * np.sin(yy / 11.0) + rng.normal(0, 0.2, (h, w))
    video = np.repeat(still[None].astype(np.float32), n, axis=0)
    video[:, :, w // 2 :] = np.stack([128 + 60 * np.sin((xx[:, w // 2 :] - 2.0 * t) / 2.0) for t in range(n)])
    mask = make_code(code, (h, w), frames=n, bump=2, rng=5)
    y, S = P.extract(simulate(video, mask)), P.extract(mask)
    tol = (S.any(1)).sum(1).astype(np.float32) * 1.5**2
    ok, est = still_patches(y, S.sum(1), tol, 8, frames=n)
    assert 0 < ok.sum() < ok.size  # the still half passes, the moving half does not
    # every accepted estimate explains its measurement within the tolerance
    resid = y[ok] - (S[ok] * est.reshape(-1, n, 49)).sum(1)
    assert ((resid**2).sum(1) <= tol[ok] * (1 + 1e-4) + 1e-3).all()
    if code != "bernoulli":  # fixed bump: exactly OMP over the still dictionary
        Dst = static_dictionary(n)
        ref = omp(y, MaskedOperator(S, Dst), max_atoms=8, tol=tol)
        np.testing.assert_array_equal(ok, ref.residual <= tol)
        np.testing.assert_allclose(est, synthesize(ref.select(ok), Dst), atol=2e-2)


@pytest.mark.parametrize("side", [3, 10, 14, 30])
def test_never_open_regions_are_filled_from_neighbours_not_zeros(side, tmp_path):
    """Patches with no measured pixel are left out of the average; wider holes are filled and counted."""
    n, h, w = 6, 48, 52
    yy, xx = np.mgrid[0:h, 0:w]
    video = np.repeat((100 + 0.3 * xx + 0.2 * yy)[None].astype(np.float32), n, axis=0)
    mask = make_code("hitomi", (h, w), frames=n, bump=2, rng=1)
    mask[:, 10 : 10 + side, 12 : 12 + side] = 0
    with pytest.warns(UserWarning, match="never open"):
        vol, info = reconstruct_volume(simulate(video, mask), mask, dct_dictionary(n), settings=OmpSettings(),
                                       run=Execution(tile=16, cache=tmp_path, progress=False))
    hole = (slice(None), slice(10, 10 + side), slice(12, 12 + side))
    assert np.isfinite(vol).all()
    assert np.abs(vol[hole] - video[hole]).max() < 0.3 * side + 2  # a ramp filled by its nearest neighbours
    assert info["never_open_pixels"] == side * side
    assert info["filled_pixels"] == max(side - 12, 0) ** 2  # pixels farther than 6 from any measurement


def test_one_shutter_pattern_for_all_pixels_gives_the_static_estimate(capture, tmp_path):
    """A flutter code (one temporal sequence for every pixel) holds no per-pixel timing: no invented motion."""
    from codedvideo.model.physics import static_estimate

    _, mask, video = capture
    flutter = make_code("flutter", video.shape[1:], frames=video.shape[0], rng=3)
    coded = simulate(video, flutter)
    vol, info = reconstruct_volume(coded, flutter, dct_dictionary(video.shape[0]), settings=OmpSettings(),
                                   run=Execution(tile=16, cache=tmp_path, progress=False))
    assert info["method"] == "static"
    np.testing.assert_allclose(vol, static_estimate(coded, flutter), rtol=1e-6)
    assert 0 < flutter.sum(0).min() < video.shape[0]  # a real flutter sequence, not all open


@pytest.mark.parametrize("stride", [2, 3, 7])
def test_patch_stride_covers_every_pixel_and_chunking_does_not_matter(capture, stride, tmp_path):
    """A stride solves fewer patches, counted from the image's corner, so tiles agree with the whole image."""
    from codedvideo.solvers.region import STAT_NAMES

    coded, mask, video = capture
    D = dct_dictionary(4)
    s = OmpSettings(max_atoms=6, tol_rms=0.5, stride=stride, static_atoms=0)
    whole, st_whole = reconstruct_region(coded, mask, D, s)
    full, st_full = reconstruct_region(coded, mask, D, OmpSettings(max_atoms=6, tol_rms=0.5, static_atoms=0))
    assert np.isfinite(whole).all()  # every pixel covered
    solved = lambda st: dict(zip(STAT_NAMES, st))["atoms_total"]
    assert solved(st_whole) < solved(st_full) / (0.8 * stride**2 if stride < 7 else 10)
    # the patches counted are those taken: atoms per patch stay what they are (they read a quarter at stride 2)
    counted = lambda st: dict(zip(STAT_NAMES, st))["patches"]
    on_grid = len(range(0, coded.shape[0] - 6, stride)) * len(range(0, coded.shape[1] - 6, stride))
    assert counted(st_whole) <= on_grid + coded.shape[0] + coded.shape[1]  # (the last row and column are kept too)
    per_patch = lambda st: solved(st) / counted(st)
    assert per_patch(st_whole) > 0.5 * per_patch(st_full)
    for tile in (9, 16):
        vol, _ = reconstruct_volume(coded, mask, D, settings=s,
                                    run=Execution(tile=tile, cache=tmp_path / str(tile), progress=False))
        np.testing.assert_allclose(vol, whole, rtol=1e-4, atol=1e-3)


@pytest.mark.parametrize("scheduler", [None, "sync"])
def test_a_runner_chains_its_graphs_and_lets_go_of_those_done(scheduler):
    """Three graphs handed over one after another run to the end on one pool (sync: one at a time), each
    group waited for in order; a graph let go of holds no tasks and still answers; a task's error is raised
    by the wait for it, and the runner closes."""
    import threading

    import dask

    from codedvideo.engine.parallel import GraphRunner

    ran, lock = [], threading.Lock()

    def work(g, i):
        with lock:
            ran.append((g, i))
        if (g, i) == (2, 1):
            raise ValueError("tile 1 of graph 2")
        return g * 10 + i

    task = dask.delayed(work, pure=False)
    with GraphRunner(scheduler=scheduler, workers=2, progress=False) as runner:
        graphs = [runner.offer([task(g, i, dask_key_name=f"tile-{g}-{i}") for i in range(4)],
                               [[0, 1], [2, 3]], share=1 / 3) for g in range(3)]
        for g in graphs[:2]:
            for j in range(2):
                runner.wait(g, j)
            runner.forget(g)
            assert runner.graphs[g]["tasks"] == [] and runner.graphs[g]["finished"].all()
            runner.wait(g, 1)  # (answers at once)
        with pytest.raises(ValueError, match="tile 1 of graph 2"):
            runner.wait(graphs[2], 0)
    assert {(g, i) for g, i in ran} >= {(g, i) for g in range(2) for i in range(4)}
    assert not any(t.is_alive() for t in runner.threads)
