"""Forward model and patch operators: brute force and dot tests."""
import tracemalloc

import numpy as np

from codedvideo.model import patches as P
from codedvideo.model import physics
from codedvideo.model.codes import make_code
from codedvideo.model.physics import adjoint, forward, simulate, static_estimate


def test_forward_matches_brute_force_loop(rng):
    n, h, w = 5, 9, 11
    video = rng.random((n, h, w)).astype(np.float32) * 255
    mask = (rng.random((n, h, w)) < 0.5).astype(np.uint8)
    expected = np.zeros((h, w))
    for t in range(n):
        for y in range(h):
            for x in range(w):
                expected[y, x] += mask[t, y, x] * video[t, y, x]
    np.testing.assert_allclose(forward(video, mask), expected, rtol=1e-5, atol=1e-3)


def test_forward_copies_the_mask_a_band_at_a_time(rng, monkeypatch):
    """Issue 29: a uint8 mask is not copied whole to float32 (at 4K N = 18 a second 600 MB volume at the end of every
    capture); bands of any height give the same bits as one band."""
    n, h, w = 18, 300, 400
    video = (rng.random((n, h, w)) * 255).astype(np.float32)
    mask = (rng.random((n, h, w)) < 0.5).astype(np.uint8)
    whole = np.einsum("thw,thw->hw", video, mask.astype(np.float32), dtype=np.float32)
    for rows in (1, 7, 64, h):
        monkeypatch.setattr(physics, "_BAND_ELEMENTS", rows * n * w)
        assert np.array_equal(forward(video, mask), whole)
        assert np.array_equal(forward(video.astype(np.float64), mask.astype(bool)), whole)
    monkeypatch.setattr(physics, "_BAND_ELEMENTS", 16 * n * w)
    tracemalloc.start()
    try:
        forward(video, mask)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert peak < video.nbytes / 4  # a band's copy and the coded image, not a float32 copy of the whole mask


def test_sum_convention_pixel_open_k_subframes_records_k_times_value():
    mask = make_code("hitomi", (14, 14), frames=8, bump=3)
    video = np.full((8, 14, 14), 10.0, np.float32)
    np.testing.assert_allclose(forward(video, mask), 30.0)
    np.testing.assert_allclose(static_estimate(forward(video, mask), mask), 10.0)


def test_dot_test_coded_exposure(rng):
    mask = (rng.random((6, 13, 17)) < 0.4).astype(np.uint8)
    u = rng.normal(size=mask.shape)
    v = rng.normal(size=mask.shape[1:])
    lhs = float(np.sum(forward(u, mask).astype(np.float64) * v))
    rhs = float(np.sum(u * adjoint(v, mask).astype(np.float64)))
    assert abs(lhs - rhs) <= 1e-4 * max(abs(lhs), 1.0)


def test_dot_test_patch_extraction(rng):
    vol = rng.normal(size=(3, 12, 15)).astype(np.float32)
    pt = rng.normal(size=((12 - 6) * (15 - 6), 3, 49)).astype(np.float32)
    lhs = float(np.sum(P.extract(vol).astype(np.float64) * pt))
    rhs = float(np.sum(vol.astype(np.float64) * P.fold(pt, (12, 15))))
    assert abs(lhs - rhs) <= 1e-4 * max(abs(lhs), 1.0)


def test_coverage_is_exact_count_of_patches(rng):
    for shape in [(7, 7), (8, 20), (30, 9), (13, 13)]:
        ones = np.ones((P.grid_shape(shape)[0] * P.grid_shape(shape)[1], 1, 49), np.float32)
        counted = P.fold(ones, shape)[0]
        np.testing.assert_array_equal(counted, P.coverage(shape))
        assert P.coverage(shape).min() >= 1
    assert P.coverage((30, 30)).max() == 49


def test_extract_layout_is_t_dy_dx():
    vol = np.arange(2 * 8 * 9, dtype=np.float32).reshape(2, 8, 9)
    pt = P.extract(vol)
    # patch with top-left (1, 2): entry (t=1, dy=3, dx=4) is vol[1, 4, 6]
    p = 1 * (9 - 6) + 2
    assert pt[p, 1, 3 * 7 + 4] == vol[1, 4, 6]


def test_noise_is_seeded_and_has_the_requested_sigma():
    video = np.zeros((4, 64, 64), np.float32)
    mask = np.ones_like(video, dtype=np.uint8)
    a = simulate(video, mask, sigma=4.0, rng=3)
    b = simulate(video, mask, sigma=4.0, rng=3)
    np.testing.assert_array_equal(a, b)
    assert 3.8 < a.std() < 4.2
