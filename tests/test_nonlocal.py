"""The non-local method (issue 16): grouping, the joint solve under different codes, stiff inputs."""

import warnings

import numpy as np
import pytest

import codedvideo as cv
from codedvideo.solvers.nonlocal_sc import joint_omp, match_groups, nonlocal_region
from codedvideo.solvers.region import OmpSettings, reconstruct_region

from conftest import capture_settings, random_dictionary

N = 4
PATCH = 7
M = PATCH * PATCH


def smooth_scene(rng, h=24, w=24, n=N):
    """A moving smooth pattern with texture, 0..255."""
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    frames = [128 + 60 * np.sin((xx + 1.5 * t) / 3.0) * np.cos(yy / 4.0) + 20 * np.sin((xx + yy) / 2.0)
              for t in range(n)]
    return np.stack(frames).astype(np.float32) + rng.normal(0, 1, (n, h, w)).astype(np.float32)


def capture(video, rng, sigma=0.0, p=0.5):
    mask = (rng.random(video.shape) < p).astype(np.float32)
    coded = (mask * video).sum(0) + rng.normal(0, sigma, video.shape[1:]).astype(np.float32) * (sigma > 0)
    return coded.astype(np.float32), mask


@pytest.fixture
def D(rng):
    return random_dictionary(rng, N * M, 64)


def test_grouping_is_deterministic_and_starts_with_the_patch_itself(rng):
    vol = rng.normal(size=(N, 20, 22)).astype(np.float32)
    vol[:, :, 11:] = vol[:, :, :11]  # exact duplicates: ties that must be broken the same way every time
    a, da = match_groups(vol, 6, 4)
    b, db = match_groups(vol.copy(), 6, 4)
    assert np.array_equal(a, b) and np.array_equal(da, db)
    assert np.array_equal(a[:, 0], np.arange(a.shape[0]))
    assert (np.diff(da, axis=1) >= 0).all()
    # a patch 11 columns away is identical but outside a window of 4; inside a window of 11 it comes second
    c, dc = match_groups(vol, 2, 11)
    wp = 22 - PATCH + 1
    assert c[0, 1] == 11 and dc[0, 1] == 0.0
    assert a[0, 1] != 11 and da[0, 1] > 0
    # every member lies within the window
    r, q = np.divmod(a, wp)
    r0, q0 = np.divmod(np.arange(a.shape[0]), wp)
    assert (np.abs(r - r0[:, None]) <= 4).all() and (np.abs(q - q0[:, None]) <= 4).all()


def test_identical_patches_under_different_codes_beat_any_member_alone(rng):
    """One 10-sparse patch seen by 8 codes: alone, OMP picks a wrong support for some members (49
    measurements, half of them closed); the group's shared support recovers every member."""
    D = random_dictionary(rng, N * M, 128)
    support = rng.choice(128, 10, replace=False)
    x = D[:, support] @ (rng.uniform(1, 2, 10) * rng.choice([-1, 1], 10)).astype(np.float32)
    k = 8
    S = (rng.random((k, N, M)) < 0.5).astype(np.float32)
    y = (S * x.reshape(N, M)).sum(1) + rng.normal(0, 0.02, (k, M)).astype(np.float32)
    tol = 1.5 * M * 0.02**2  # about the noise energy of a member
    alone = np.stack([joint_omp(y[i : i + 1], S[i : i + 1], D, max_atoms=12, tol=tol)[0] for i in range(k)])
    together = joint_omp(y, S, D, max_atoms=12, tol=tol)
    err_alone = np.linalg.norm(alone - x, axis=1) / np.linalg.norm(x)
    err_together = np.linalg.norm(together - x, axis=1) / np.linalg.norm(x)
    assert err_together.max() < 0.05  # every member recovered to the noise
    assert err_alone.max() > 0.3  # alone, some member is not
    assert err_together.mean() < 0.5 * err_alone.mean()
    assert (err_together <= err_alone * 1.1 + 1e-3).all()  # and no member is worse off in the group


@pytest.mark.parametrize("static_atoms", [0, 8])
def test_group_of_one_is_the_default_reconstruction(rng, D, static_atoms):
    video = smooth_scene(rng)
    coded, mask = capture(video, rng, sigma=2.0)
    s = OmpSettings(max_atoms=6, tol_rms=2.0, static_atoms=static_atoms)
    first, _ = reconstruct_region(coded, mask, D, s)
    vol, stats = nonlocal_region(coded, mask, D, first, s, group=1)
    assert np.array_equal(vol, first, equal_nan=True)
    # a real group changes the answer (the test above would pass for a method that ignores the group)
    vol8, _ = nonlocal_region(coded, mask, D, first, s, group=8, window=3)
    assert not np.allclose(vol8, first)


def _stiff_cases(rng):
    video = smooth_scene(rng)
    coded, mask = capture(video, rng)
    yield "all-zero coded", np.zeros_like(coded), mask
    yield "saturated constant", mask.sum(0) * 255.0, mask
    noisy = coded + rng.normal(0, 40, coded.shape).astype(np.float32)
    yield "sigma 40", noisy, mask
    closed = mask.copy()
    closed[:, 5:9, 5:9] = 0  # never-open pixels, a whole patch among them
    closed[:, 14:21, 0:7] = 0
    yield "never open", (closed * video).sum(0), closed


@pytest.mark.parametrize("case", range(4))
def test_output_is_finite_on_stiff_inputs(rng, D, case):
    name, coded, mask = list(_stiff_cases(rng))[case]
    tol = 40.0 if name == "sigma 40" else 1.0
    s = OmpSettings(max_atoms=8, tol_rms=tol)
    first, _ = reconstruct_region(coded, mask, D, s)
    vol, stats = nonlocal_region(coded, mask, D, first, s, group=8, window=4, iterations=2)
    assert vol.shape == first.shape and vol.dtype == np.float32
    covered = np.isfinite(first)
    assert np.isfinite(vol[covered]).all(), name
    assert np.isfinite(stats).all()
    if name == "all-zero coded":
        assert np.abs(vol[covered]).max() == 0.0


def test_near_duplicate_atoms_stay_finite(rng):
    D = random_dictionary(rng, N * M, 48)
    D[:, 1::2] = D[:, 0::2] + 1e-7 * rng.normal(size=(N * M, 24)).astype(np.float32)  # pairs of near twins
    D /= np.linalg.norm(D, axis=0)
    video = smooth_scene(rng)
    coded, mask = capture(video, rng)
    s = OmpSettings(max_atoms=12, tol_rms=0.0, static_atoms=0)
    first, _ = reconstruct_region(coded, mask, D, s)
    vol, _ = nonlocal_region(coded, mask, D, first, s, group=8, window=4)
    assert np.isfinite(vol).all()
    assert np.abs(vol).max() < 1e4  # no blow-up from nearly dependent columns


def test_a_tile_with_a_halo_gives_the_whole_image_answer(rng, D):
    """Region in, region out: a tile with a halo of ``patch - 1 + 2 * window`` keeps the whole image's pixels."""
    video = smooth_scene(rng, 40, 44)
    coded, mask = capture(video, rng, sigma=1.0)
    s = OmpSettings(max_atoms=6, tol_rms=1.0)
    first, _ = reconstruct_region(coded, mask, D, s)
    window, group = 2, 4
    whole, _ = nonlocal_region(coded, mask, D, first, s, group=group, window=window)
    halo = PATCH - 1 + 2 * window
    y0, y1, x0, x1 = 3, 37, 5, 40  # a region with the kept part [y0 + halo, y1 - halo) x [x0 + halo, x1 - halo)
    tile, _ = nonlocal_region(coded[y0:y1, x0:x1], mask[:, y0:y1, x0:x1], D, first[:, y0:y1, x0:x1], s,
                              group=group, window=window, origin=(y0, x0), image_shape=coded.shape)
    keep = (slice(None), slice(halo, y1 - y0 - halo), slice(halo, x1 - x0 - halo))
    assert tile[keep].size > 0
    np.testing.assert_allclose(tile[keep], whole[:, y0:y1, x0:x1][keep], rtol=0, atol=1e-3)


def test_passes_over_boxes_of_references_add_up_to_the_whole_pass(rng, D):
    """``refs=`` boxes that partition the corners, ``sums=True``: their sums add up to the whole pass's,
    and :func:`finish` of the total is the whole region's answer."""
    from codedvideo.solvers.nonlocal_sc import finish

    video = smooth_scene(rng, 40, 44)
    coded, mask = capture(video, rng, sigma=1.0)
    s = OmpSettings(max_atoms=6, tol_rms=1.0)
    first, _ = reconstruct_region(coded, mask, D, s)
    whole, _ = nonlocal_region(coded, mask, D, first, s, group=4, window=2)
    total_s, total_w, _ = nonlocal_region(coded, mask, D, first, s, group=4, window=2, sums=True)
    hp, wp = 40 - PATCH + 1, 44 - PATCH + 1
    parts = [nonlocal_region(coded, mask, D, first, s, group=4, window=2, sums=True, refs=(y0, y1, x0, x1))
             for y0, y1 in ((0, 13), (13, hp)) for x0, x1 in ((0, 20), (20, wp))]
    assert all(p[0].any() for p in parts)  # every box holds references of its own
    np.testing.assert_allclose(sum(p[0] for p in parts), total_s, rtol=1e-5, atol=1e-3)
    np.testing.assert_array_equal(sum(p[1] for p in parts), total_w)
    np.testing.assert_allclose(finish(sum(p[0] for p in parts), sum(p[1] for p in parts), coded, mask, first=first), whole,
                               rtol=0, atol=1e-3)
    assert not np.allclose(parts[0][0], total_s)  # a box alone is not the whole pass
    with pytest.raises(ValueError, match="one pass"):
        nonlocal_region(coded, mask, D, first, s, iterations=2, sums=True)


def test_the_method_through_the_tiled_graph_equals_one_whole_tile(tmp_path):
    """--method nonlocal runs on the Dask tile graph like the default: tiles with the non-local halo
    (reconstruct.tile_halo) give the whole image's answer."""
    import dataclasses

    from codedvideo.model.codes import make_code
    from codedvideo.solvers.dictionaries import dct_dictionary
    from codedvideo.model.physics import simulate
    from codedvideo.solvers.region import tile_halo
    from codedvideo.engine.windows import Execution, reconstruct_volume
    from codedvideo.data.synth import make_scene

    video = make_scene("default", frames=4, size=(72, 88))
    mask = make_code("hitomi", video.shape[1:], frames=4, bump=2, rng=2)
    coded = simulate(video, mask)
    s = dataclasses.replace(OmpSettings(max_atoms=6, tol_rms=1.0), method="nonlocal")
    assert tile_halo(s) > tile_halo(OmpSettings())
    D = dct_dictionary(4)
    whole, _ = reconstruct_volume(coded, mask, D, settings=s,
                                  run=Execution(tile=128, cache=tmp_path / "a", progress=False))
    tiled, info = reconstruct_volume(coded, mask, D, settings=s,
                                     run=Execution(tile=24, cache=tmp_path / "b", progress=False))
    assert info["tiles"] == 12
    np.testing.assert_allclose(tiled, whole, atol=1e-3)
    per_patch, _ = reconstruct_volume(coded, mask, D, settings=OmpSettings(max_atoms=6, tol_rms=1.0),
                                      run=Execution(tile=128, cache=tmp_path / "c", progress=False))
    err = lambda v: float(np.sqrt(np.mean((v - video) ** 2)))  # noqa: E731
    assert err(whole) < err(per_patch)  # groups under different codes beat each patch alone


def test_the_method_runs_from_pipeline_yaml(tmp_path):
    import yaml

    from codedvideo.app.cli import main

    cfg = dict(frames=8, cache=str(tmp_path / "cache"), stages=["reconstruct", "evaluate"],
               scene=dict(video="synth:default", size=[48, 48]), reconstruct=dict(method="nonlocal"),
               output=dict(dir=str(tmp_path / "out"), video="recon.mp4", frames="none"))
    (tmp_path / "p.yaml").write_text(yaml.safe_dump(cfg))
    assert main(["-q", "run", str(tmp_path / "p.yaml")]) == 0
    import json

    metrics = json.loads((tmp_path / "out" / "recon.metrics.json").read_text())
    assert metrics["config"]["reconstruct"]["method"] == "nonlocal"
    assert metrics["quality"]["psnr"] > metrics["trivial"]["psnr"]


def _periodic_capture(rng, period=20, reps=6, n=N):
    """A scene and code that repeat every ``period`` pixels: tiles of that size have equal inputs."""
    block = rng.uniform(20, 230, (n, period, period)).astype(np.float32)
    code = (rng.random((n, period, period)) < 0.5).astype(np.uint8)
    video = np.tile(block, (1, reps, reps))
    mask = np.tile(code, (1, reps, reps))
    return (mask * video).sum(0).astype(np.float32), mask, video


def test_the_three_stages_give_the_same_bits_on_one_thread_and_on_two(tmp_path, rng):
    """Blocks' sums are added in block order, whatever order the tasks finish in."""
    import dataclasses

    from codedvideo.solvers.dictionaries import dct_dictionary
    from codedvideo.engine.windows import Execution, reconstruct_volume

    coded, mask, _ = _periodic_capture(rng, period=23, reps=3)
    s = dataclasses.replace(OmpSettings(max_atoms=6, tol_rms=1.0), method="nonlocal")
    D = dct_dictionary(N)
    runs = [reconstruct_volume(coded, mask, D, settings=s,
                               run=Execution(tile=24, cache=tmp_path / name, scheduler=scheduler, progress=False))[0]
            for name, scheduler in (("sync", "sync"), ("threads", "threads"))]
    assert np.isfinite(runs[0]).all()
    assert np.array_equal(runs[0], runs[1])


def test_tiles_of_equal_inputs_share_an_answer_only_where_the_reference_grid_agrees(tmp_path, rng):
    """The non-local reference patches lie every third pixel from the image's corner: tiles of equal
    inputs 20 pixels apart are solved apart (and come out as the whole image), while the default,
    which has no grid, solves them once."""
    import dataclasses

    from codedvideo.solvers.dictionaries import dct_dictionary
    from codedvideo.engine.windows import Execution, reconstruct_volume

    coded, mask, _ = _periodic_capture(rng)
    D = dct_dictionary(N)
    per_patch = OmpSettings(max_atoms=6, tol_rms=1.0)
    s = dataclasses.replace(per_patch, method="nonlocal")
    _, omp_info = reconstruct_volume(coded, mask, D, settings=per_patch,
                                     run=Execution(tile=20, cache=tmp_path / "o", progress=False))
    tiled, info = reconstruct_volume(coded, mask, D, settings=s,
                                     run=Execution(tile=20, cache=tmp_path / "t", progress=False))
    whole, _ = reconstruct_volume(coded, mask, D, settings=s,
                                  run=Execution(tile=120, cache=tmp_path / "w", progress=False))
    assert omp_info["tile_tasks"] < 36  # equal tiles shared by the default
    assert info["tile_tasks"] > omp_info["tile_tasks"]
    np.testing.assert_allclose(tiled, whole, atol=1e-3)


def test_the_progress_bar_counts_the_stages_and_ends_full(tmp_path, rng, monkeypatch):
    """A non-local job's bar moves with its first estimates and blocks, not only with its last tasks."""
    import dataclasses

    import tqdm.auto

    from codedvideo.solvers.dictionaries import dct_dictionary
    from codedvideo.engine.windows import Execution, reconstruct_volume

    bars = []

    class Recording(tqdm.auto.tqdm):
        def close(self):
            if not self.disable:
                bars.append((self.total, self.n))
            super().close()

    monkeypatch.setattr(tqdm.auto, "tqdm", Recording)
    coded, mask, _ = _periodic_capture(rng, period=23, reps=2)  # 46 x 46: 3 x 3 tiles of 16, 6 x 6 blocks of 8
    s = OmpSettings(max_atoms=6, tol_rms=1.0)
    for settings in (s, dataclasses.replace(s, method="nonlocal")):
        _, info = reconstruct_volume(coded, mask, dct_dictionary(N), settings=settings,
                                     run=Execution(tile=16, cache=tmp_path / settings.method, progress=True))
    (omp_total, omp_n), (nl_total, nl_n) = bars
    assert omp_total == omp_n == 9  # the default: one task a tile
    assert nl_total == nl_n == 9 + 9 + 36  # tiles, their first estimates and blocks of half a tile


def test_a_tile_is_keyed_by_everything_its_blocks_read(rng):
    """Two non-local tiles are the same work only when all their blocks' regions (and the first estimate's
    patch around them) hold the same inputs: the blocks' distances are running sums from each region's
    corner, so pixels beyond the tile's halo still decide, in the last bits, which of two equally similar
    patches joins a group. A pixel beyond what the blocks read leaves the key alone (still regions far
    away keep being shared)."""
    from codedvideo.engine.parallel import nonlocal_blocks, nonlocal_reach, plan_tiles, tile_content
    from codedvideo.solvers.region import tile_halo

    shape, size = (96, 96), 32
    settings = OmpSettings(method="nonlocal")
    tiles = plan_tiles(shape, size, halo=tile_halo(settings))
    blocks = nonlocal_blocks(shape, size, 7)
    tile = tiles[4]  # the middle one: core rows and columns 32:64
    reach = nonlocal_reach(tile, blocks, shape, 7)
    read = [b.halo for b in blocks if b.halo[0] < 64 and 32 < b.halo[1] and b.halo[2] < 64 and 32 < b.halo[3]]
    assert reach == (max(0, min(r[0] for r in read) - 6), min(96, max(r[1] for r in read) + 6),
                     max(0, min(r[2] for r in read) - 6), min(96, max(r[3] for r in read) + 6))
    assert reach[0] < tile.halo[0] and reach[1] > tile.halo[1]  # wider than the halo
    coded = rng.uniform(0, 255, shape).astype(np.float32)
    mask = (rng.random((N, *shape)) < 0.5).astype(np.uint8)
    still = np.zeros(shape, np.uint8)

    def key(c):
        return tile_content(c, mask, still, tile, stride=3, reach=reach)

    inside, outside = coded.copy(), coded.copy()
    inside[reach[0], 48] += 1  # beyond the halo, read by a block
    outside[reach[0] - 1, 48] += 1  # read by none
    assert key(inside) != key(coded)
    assert key(outside) == key(coded)


def test_captures_of_one_job_come_out_as_each_alone(tmp_path, rng):
    """Non-local tiles shared between two captures (equal where their blocks read, different beyond)
    give each capture exactly what it gets alone."""
    import dataclasses

    from codedvideo.solvers.dictionaries import dct_dictionary
    from codedvideo.engine.windows import Execution, reconstruct_volume, sparse_volumes

    video = 100 + np.tile(rng.uniform(0, 3, (N, 4, 4)).astype(np.float32), (1, 24, 24))
    mask = np.tile((rng.random((N, 8, 8)) < 0.5).astype(np.uint8), (1, 12, 12))
    mask[0] = 1  # every pixel open once
    other = video.copy()
    other[:, :8] = rng.uniform(20, 230, (N, 8, 96))
    codeds = [(mask * v).sum(0).astype(np.float32) for v in (video, other)]
    s = dataclasses.replace(OmpSettings(max_atoms=6, tol_rms=0.5), method="nonlocal")
    D = dct_dictionary(N)
    job = list(sparse_volumes(2, lambda i: (codeds[i], mask, None), D, settings=s,
                              run=Execution(tile=32, cache=tmp_path / "j", progress=False)))
    assert job[0][2]["tile_tasks"] < 2 * 9  # the lower tiles are shared
    for i, volume, _ in job:
        alone, _ = reconstruct_volume(codeds[i], mask, D, settings=s,
                                      run=Execution(tile=32, cache=tmp_path / f"a{i}", progress=False))
        assert np.array_equal(volume, alone)


def test_patches_still_across_captures_take_the_still_answer_and_join_no_group(rng):
    """The still map of a sequence: wholly still patches are neither solved nor members of a group, and the
    pixels that only they cover keep coded / open count exactly, as the default's tiles do."""
    from codedvideo.solvers.region import _still_answer

    video = smooth_scene(rng, h=30, w=30)
    coded, mask = capture(video, rng)
    s = OmpSettings(max_atoms=6, tol_rms=1.0)
    D = random_dictionary(rng, N * 49, 96)
    first, _ = reconstruct_region(coded, mask, D, s)
    answer = _still_answer(coded, mask, True)
    volume, stats = nonlocal_region(coded, mask, D, first, s, still=np.ones(coded.shape, bool))
    assert np.array_equal(volume, np.broadcast_to(answer, volume.shape))
    assert stats[1] == 0  # no group solved
    still = np.zeros(coded.shape, bool)
    still[:, :14] = True  # patches with corners in columns 0..7 are still; pixels 0..6 only they cover
    part, part_stats = nonlocal_region(coded, mask, D, first, s, still=still)
    moving, moving_stats = nonlocal_region(coded, mask, D, first, s)
    assert np.array_equal(part[:, :, :7], np.broadcast_to(answer[:, :7], (N, 30, 7)))
    assert not np.array_equal(moving[:, :, :7], part[:, :, :7])
    assert 0 < part_stats[1] < moving_stats[1]
    assert np.isfinite(part).all()


def test_still_tiles_of_a_sequence_are_shared_and_come_out_as_each_capture_alone(tmp_path, rng):
    """Two captures whose left part is still (a still map on it) and whose right part moves: the tiles
    that only still patches reach are solved once for both (their answer is the still answer, which
    their halo decides), and each capture equals its reconstruction alone with the same still map."""
    import dataclasses

    from codedvideo.solvers.dictionaries import dct_dictionary
    from codedvideo.solvers.region import _still_answer
    from codedvideo.engine.windows import Execution, reconstruct_volume, sparse_volumes

    mask = (rng.random((N, 64, 96)) < 0.5).astype(np.uint8)
    mask[0] = 1
    videos = [smooth_scene(rng, h=64, w=96) for _ in range(2)]
    videos[1][:, :, :48] = videos[0][:, :, :48]
    codeds = [(mask * v).sum(0).astype(np.float32) for v in videos]
    still = np.zeros((64, 96), bool)
    still[:, :44] = True
    s = dataclasses.replace(OmpSettings(max_atoms=6, tol_rms=1.0), method="nonlocal")
    D = dct_dictionary(N)
    job = list(sparse_volumes(2, lambda i: (codeds[i], mask, still), D, settings=s,
                              run=Execution(tile=32, cache=tmp_path / "j", progress=False)))
    assert job[0][2]["tile_tasks"] == 2 * 6 - 2  # the two left tiles (columns 0:32) solved once
    for i, volume, _ in job:
        assert np.array_equal(volume[:, :, :32], np.broadcast_to(_still_answer(codeds[i], mask, True)[:, :32],
                                                                 (N, 64, 32)))
        alone = next(sparse_volumes(1, lambda _: (codeds[i], mask, still), D, settings=s,
                                    run=Execution(tile=32, cache=tmp_path / f"a{i}", progress=False)))[1]
        assert np.array_equal(volume, alone)
    moving, _ = reconstruct_volume(codeds[0], mask, D, settings=s,
                                   run=Execution(tile=32, cache=tmp_path / "m", progress=False))
    assert not np.array_equal(moving[:, :, :32], job[0][1][:, :, :32])


@pytest.mark.parametrize("max_atoms", [32, 49])
def test_a_large_atom_budget_does_not_make_the_members_fit_their_codes(max_atoms):
    """Every member fits its own 49 measurements: a group support as large as them fitted the noise and the
    code (max_atoms 49, tolerance 0: values -220..496 for 0..255, 21 dB against the default's 30.6)."""
    from codedvideo.data import shipped
    from codedvideo.model.metrics import evaluate
    from codedvideo.solvers.nonlocal_sc import group_atoms
    from codedvideo.engine.simulation import simulate_capture
    from codedvideo.model.codes import CodeSpec
    from codedvideo.formats.store import load_dictionary
    from codedvideo.data.synth import make_scene

    assert group_atoms(8) == 16 and group_atoms(16) == 24 and group_atoms(32) == 32 and group_atoms(49) == 39
    D, _ = load_dictionary(shipped.verified(8))
    video = make_scene("default", frames=8, size=(48, 48))
    cap = simulate_capture(video, code=CodeSpec("hitomi", bump=2), sigma=0.0, seed=0)
    s = OmpSettings(max_atoms=max_atoms, tol_rms=0.0)
    first, _ = reconstruct_region(cap["coded"], cap["mask"], D, s)
    vol, _ = nonlocal_region(cap["coded"], cap["mask"], D, first, s)
    assert np.isfinite(vol).all() and -64 < vol.min() and vol.max() < 320
    assert evaluate(vol, video, data_range=255.0)["psnr"] > evaluate(first, video, data_range=255.0)["psnr"] - 0.5


def test_a_code_with_too_many_patterns_for_the_method_says_so(tmp_path):
    """N = 16 Bernoulli: more pixel patterns than the groups' table holds; the tiles give the default's answer,
    and the metrics and a warning say so (it was silent, with method: nonlocal)."""
    from codedvideo.engine.captures import reconstruct_capture
    from codedvideo.model.units import infer_data_range

    rng = np.random.default_rng(3)
    mask = (rng.random((16, 40, 40)) < 0.5).astype(np.uint8)
    video = smooth_scene(rng, 40, 40, 16)
    coded = (mask * video).sum(0).astype(np.float32)
    D = random_dictionary(rng, 16 * M, 512)
    s = OmpSettings(max_atoms=6, tol_rms=1.0)
    common = dict(data_range=infer_data_range(255.0), settings=s, dictionary=D, tile=16, progress=False)
    plain, _ = reconstruct_capture(capture_settings("omp", cache=tmp_path / "a", **common), coded, mask)
    with pytest.warns(UserWarning, match="--method nonlocal .* distinct pixel shutter patterns"):
        vol, info = reconstruct_capture(capture_settings("nonlocal", cache=tmp_path / "b", **common), coded, mask)
    assert info["method"] == "omp" and "patterns" in info["nonlocal_unavailable"]
    np.testing.assert_array_equal(vol, plain)


def test_a_noisy_stream_whose_blocks_have_no_still_reference_runs(tmp_path, capsys):
    """Reported: a 2-capture noisy stack at tile 32 ended in a traceback ("cannot reshape array of size 0 into
    shape (0, newaxis)"): a block without a calm reference asked for the still answers of no patch."""
    from codedvideo.app.cli import main
    from codedvideo.solvers.region import still_answers
    from codedvideo.engine.simulation import simulate_capture
    from codedvideo.model.codes import CodeSpec
    from codedvideo.data.synth import make_scene

    assert still_answers(np.zeros((0, 49), np.float32), np.ones((0, 49), np.float32), 8).shape == (0, 8 * 49)
    video = make_scene("default", frames=16, size=(256, 256))[:, 96:160, 96:160]
    cap = simulate_capture(video, code=CodeSpec("hitomi", bump=2), sigma=2.0, seed=0, captures=2)
    for name in ("coded", "mask", "truth"):
        np.save(tmp_path / f"{name}.npy", cap[name])
    assert main(["-q", "reconstruct", "--coded", str(tmp_path / "coded.npy"), "--mask", str(tmp_path / "mask.npy"),
                 "--truth", str(tmp_path / "truth.npy"), "--noise-sigma", "2", "--method", "nonlocal", "--tile", "32",
                 "--output", str(tmp_path / "r.npy"), "--cache", str(tmp_path / "cache")]) == 0
    assert np.isfinite(np.load(tmp_path / "r.npy")).all()


def test_only_pixels_far_from_any_measurement_keep_the_first_estimate():
    """finish: a pixel never open with no open pixel within half a patch takes the first estimate; scattered
    pixels that are never open (a sparse code) keep the groups' estimate, which fills them from their measured
    neighbours (taking the first estimate there too cost best up to 1.6 dB under Bernoulli p = 0.1)."""
    from codedvideo.solvers.nonlocal_sc import finish

    n, h, w = 4, 30, 30
    mask = np.ones((n, h, w), np.uint8)
    mask[:, 5, 5] = 0  # a scattered pixel never open
    mask[:, 12:25, 12:25] = 0  # a 13x13 block of them
    summed, weight = np.full((n, h, w), 7.0, np.float32), np.ones((h, w), np.float32)
    first = np.zeros((n, h, w), np.float32)
    out = finish(summed, weight, np.zeros((h, w), np.float32), mask, project=False, first=first)
    deep = np.zeros((h, w), bool)
    deep[15:22, 15:22] = True  # three or more pixels inside the block
    assert (out[:, deep] == 0).all() and (out[:, ~deep] == 7).all()


def test_a_block_of_missing_pixels_stays_within_sensible_values_with_the_non_local_method(tmp_path):
    """An 8x8 square of bad pixels (or of saturated ones) ended `--preset best` and `nonlocal --adapt` with a
    RuntimeError traceback (the survey's grid patch inside it is no reference, and no group reached the pixels
    around it), and a 13x13 one gave values from -2031 to 2612 (groups' atoms fitted to the few measured pixels
    of a corner).  Patches that see too few measurements are now in no group, and pixels no group reaches keep
    the first estimate: every value within the default's spread, the rest of the frame better than the
    default's."""
    video = cv.synthetic_scene("default", frames=8, size=(64, 64))
    mask = cv.make_code("hitomi", (64, 64), frames=8, bump=2, seed=0)
    coded = cv.simulate(video, mask)
    for y0, side in ((20, 8), (15, 13)):
        bad = np.zeros((64, 64), bool)
        bad[y0:y0 + side, y0:y0 + side] = True  # (the first holds the survey's grid patch at 21..27)
        default = cv.reconstruct(coded, mask, bad_pixels=bad)
        frames = cv.reconstruct(coded, mask, method="nonlocal", adapt=True, bad_pixels=bad)
        assert np.isfinite(frames).all()
        spread = default.max() - default.min()
        assert default.min() - spread / 2 < frames.min() and frames.max() < default.max() + spread / 2, side
        far = np.ones((64, 64), bool)
        far[y0 - 6:y0 + side + 6, y0 - 6:y0 + side + 6] = False  # the square and the patches that reach into it
        error = {name: float(np.mean((f[:, far] - video[:, far]) ** 2)) for name, f in (("adapt", frames),
                                                                                     ("omp", default))}
        assert error["adapt"] < error["omp"], (side, error)


def test_the_fallback_of_the_non_local_method_says_the_dictionary_was_adapted():
    """A calibrated mask of many pixel patterns gives the per-patch OMP in place of the groups; with `--adapt` its
    dictionary is the adapted one, where the warning called it the default's answer."""
    video = cv.synthetic_scene("default", frames=8, size=(32, 32))
    mask = cv.make_code("hitomi", (32, 32), frames=8, bump=2, seed=0).astype(np.float32)
    mask = np.clip(mask * 0.9 + np.random.default_rng(0).random(mask.shape).astype(np.float32) * 0.1, 0, 1)
    coded = cv.simulate(video, mask)
    for adapt in (True, False):
        with warnings.catch_warnings(record=True) as said:
            warnings.simplefilter("always")
            cv.reconstruct(coded, mask, method="nonlocal", adapt=adapt)
        fallback = [str(w.message) for w in said if "distinct pixel shutter patterns" in str(w.message)]
        assert len(fallback) == 1 and ("with the adapted dictionary" in fallback[0]) == adapt, fallback


def _smooth_noisy_capture(sigma: float):
    """A slowly drifting smooth pattern (48x48, N = 8, [0, 1]) under hitomi L = 2 with read noise ``sigma``
    grey levels of 255."""
    yy, xx = np.mgrid[0:48, 0:48]
    still = 0.45 + 0.05 * np.sin(xx / 6.0) * np.cos(yy / 9.0)
    video = np.stack([np.roll(still, t, axis=1) for t in range(8)]).astype(np.float32)
    mask = cv.make_code("hitomi", (48, 48), frames=8, seed=0, bump=2)
    return video, mask, cv.simulate(video, mask, noise_sigma=sigma / 255, seed=1)


def test_under_read_noise_the_non_local_result_keeps_the_noise_out():
    """Measured (issue 48): projected onto noisy measurements, the non-local result took their noise back and
    fell 3.9 dB below the default on a smooth scene at read noise 15, and `best` 0.5 dB below it."""
    video, mask, coded = _smooth_noisy_capture(15.0)
    psnr = {}
    for name, options in (("default", {}), ("nonlocal", dict(method="nonlocal")), ("best", dict(preset="best"))):
        out = cv.reconstruct(coded, mask, data_range=1.0, noise_sigma=15 / 255, progress=False, **options)
        psnr[name] = cv.evaluate(np.clip(out, 0, 1), video, data_range=1.0)["psnr"]
    assert psnr["nonlocal"] > psnr["default"] - 1.0, psnr
    assert psnr["best"] > psnr["default"], psnr


def test_the_non_local_result_reproduces_exact_measurements_only():
    """Without read noise the non-local result reproduces the coded image (projected onto it); with read noise
    it is left as the groups' average, whose misfit is the noise's size, not zero."""
    from codedvideo.model.physics import forward

    for sigma in (0.0, 15.0):
        video, mask, coded = _smooth_noisy_capture(sigma)
        out = cv.reconstruct(coded, mask, data_range=1.0, noise_sigma=sigma / 255, progress=False, method="nonlocal")
        misfit = np.sqrt(np.mean((forward(out, mask) - coded) ** 2)) * 255
        if sigma == 0:
            assert misfit < 0.01
        else:
            assert 0.2 * sigma < misfit < 2 * sigma, misfit
