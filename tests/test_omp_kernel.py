"""The compiled pattern-table OMP against the textbook reference and the numpy path."""

import numpy as np
import pytest

from codedvideo.model import patches as P
from codedvideo.model.codes import make_code
from codedvideo.solvers.omp import MaskedOperator, omp, omp_reference, pixel_patterns
from codedvideo.solvers.omp_kernel import synthesize
from codedvideo.solvers.omp_kernel import TableOMP, table_fits
from codedvideo.solvers.region import OmpSettings, reconstruct_region
from conftest import random_dictionary


def _explicit(S, D):
    n, m = S.shape
    return (S[:, :, None].astype(np.float64) * D.reshape(n, m, -1)).sum(0)


def _problem(rng, code, n, K, shape, bump=2):
    D = random_dictionary(rng, n * 49, K)
    mask = make_code(code, shape, frames=n, bump=bump, rng=3)
    patterns, which = pixel_patterns(mask)
    return D, mask, patterns, P.extract(which), P.extract(mask)


def test_pixel_patterns_rebuild_the_mask(rng):
    mask = make_code("bernoulli", (20, 23), frames=6, rng=1)
    patterns, which = pixel_patterns(mask)
    np.testing.assert_array_equal(patterns[which].transpose(2, 0, 1), mask)
    assert len(np.unique(patterns, axis=0)) == len(patterns)
    hitomi, _ = pixel_patterns(make_code("hitomi", (40, 40), frames=8, bump=3))
    assert len(hitomi) <= 8 - 3 + 1 and (hitomi.sum(1) == 3).all()  # one bump of L: N - L + 1 patterns


@pytest.mark.parametrize("code", ["hitomi", "bernoulli", "rowwise"])
def test_kernel_equals_textbook_omp_on_random_problems(rng, code):
    """Noisy data, both stopping rules active: same atoms, same fit as lstsq-based OMP."""
    n, K = 6, 150
    D, _, patterns, pat, S = _problem(rng, code, n, K, (7 + 5, 7 + 11))
    Y = rng.normal(size=(S.shape[0], 49)).astype(np.float32) * 30
    tol = 0.5 * (Y.astype(np.float64) ** 2).sum(1)
    res = TableOMP(patterns, D, 49).solve(Y, pat, max_atoms=6, tol=tol)
    dense = res.dense(K)
    for p in range(S.shape[0]):
        A = _explicit(S[p], D)
        ref = omp_reference(A, Y[p], max_atoms=6, tol=tol[p])
        assert res.count[p] == np.count_nonzero(ref)
        np.testing.assert_array_equal(np.flatnonzero(dense[p]), np.flatnonzero(ref))
        np.testing.assert_allclose(A @ dense[p], A @ ref, atol=2e-3 * np.abs(Y[p]).max())
        assert abs(res.residual[p] - ((A @ ref - Y[p]) ** 2).sum()) <= 1e-3 * (Y[p] ** 2).sum()


def test_kernel_recovers_planted_codes_and_matches_numpy_path(rng):
    n, K = 8, 200
    D, _, patterns, pat, S = _problem(rng, "hitomi", n, K, (7 + 3, 7 + 12))
    X = np.zeros((S.shape[0], K), np.float32)
    for p in range(S.shape[0]):
        X[p, rng.choice(K, 3, replace=False)] = rng.normal(size=3) + 2 * np.sign(rng.normal(size=3))
    Y = np.stack([_explicit(S[p], D) @ X[p] for p in range(S.shape[0])]).astype(np.float32)
    res = TableOMP(patterns, D, 49).solve(Y, pat, max_atoms=8, tol=1e-6)
    np.testing.assert_allclose(res.dense(K), X, atol=1e-3)
    ref = omp(Y, MaskedOperator(S, D), max_atoms=8, tol=1e-6)
    np.testing.assert_array_equal(res.count, ref.count)
    np.testing.assert_allclose(synthesize(res, D), synthesize(ref, D), atol=1e-3)


def test_sparse_synthesis_equals_the_dense_product(rng):
    D, _, patterns, pat, S = _problem(rng, "hitomi", 4, 90, (12, 12))
    Y = rng.normal(size=(S.shape[0], 49)).astype(np.float32)
    res = TableOMP(patterns, D, 49).solve(Y, pat, max_atoms=5, tol=0.0)
    np.testing.assert_allclose(synthesize(res, D), res.dense(90) @ D.T, atol=1e-5)


def test_kernel_edge_cases_stay_finite(rng):
    n, K = 4, 60
    D, _, patterns, pat, S = _problem(rng, "hitomi", n, K, (9, 9))
    D[:, 1] = D[:, 0]  # duplicate atoms: a dependent column ends the patch
    D[:, 2] = 0.0  # a zero atom is never chosen
    Y = rng.normal(size=(S.shape[0], 49)).astype(np.float32)
    Y[0] = 0.0  # nothing to explain: no atom
    res = TableOMP(patterns, D, 49).solve(Y, pat, max_atoms=49, tol=0.0)
    assert np.isfinite(res.coef).all() and np.isfinite(res.residual).all()
    assert res.count[0] == 0 and (res.coef[0] == 0).all()
    used = res.index[np.arange(res.index.shape[1])[None, :] < res.count[:, None]]
    assert (used != 2).all()
    assert (res.residual <= (Y.astype(np.float64) ** 2).sum(1) * (1 + 1e-5)).all()


def test_table_size_limit_falls_back_for_many_patterns():
    D = np.zeros((8 * 49, 512), np.float32)
    assert table_fits(8 - 2 + 1, D, 49)
    assert not table_fits(2**20, D, 49)


@pytest.mark.parametrize("code", ["hitomi", "bernoulli"])
def test_region_through_kernel_equals_numpy_operator(rng, code, monkeypatch):
    """reconstruct_region gives the same volume whichever exact OMP path runs."""
    from codedvideo.solvers import region as reconstruct

    n, K = 6, 120
    D = random_dictionary(rng, n * 49, K)
    mask = make_code(code, (26, 31), frames=n, bump=2, rng=7)
    video = rng.uniform(0, 255, size=(n, 26, 31)).astype(np.float32)
    coded = (mask * video).sum(0)
    s = OmpSettings(max_atoms=6, tol_rms=2.0, static_atoms=0, batch=256)
    fast, stats_fast = reconstruct_region(coded, mask, D, s)
    monkeypatch.setattr(reconstruct, "table_fits", lambda *a: False)
    slow, stats_slow = reconstruct_region(coded, mask, D, s)
    assert stats_fast[2] == stats_slow[2]  # the same number of atoms in all
    np.testing.assert_allclose(fast, slow, atol=2e-2 * 255 / 100)


def test_more_than_64_subframes_use_the_dense_path(rng, monkeypatch):
    """Patterns are 64-bit integers: beyond N = 64 the numpy operator (exact norms) takes over."""
    from codedvideo.solvers import omp as omp_module

    tables = []
    real_table = omp_module.pattern_table
    monkeypatch.setattr(omp_module, "pattern_table", lambda *a: tables.append(a[0].shape) or real_table(*a))
    for n, code in ((8, "hitomi"), (80, "bernoulli")):  # the table at N = 8 (the spy sees it), dense at N = 80
        D = random_dictionary(rng, n * 49, 60)
        mask = make_code(code, (12, 12), frames=n, bump=2, rng=1) if code == "hitomi" else \
            make_code(code, (12, 12), frames=n, rng=1)
        S = P.extract(mask)
        norms = MaskedOperator(S, D).norms(np.arange(S.shape[0]))
        for p in (0, 3, len(S) - 1):
            np.testing.assert_allclose(norms[p], np.linalg.norm(_explicit(S[p], D), axis=0), rtol=1e-4)
        assert len(tables) == 1 and tables[0][1] == 8, (n, tables)  # no pattern table beyond 64 sub-frames
    coded = (mask * rng.uniform(0, 255, (n, 12, 12))).sum(0).astype(np.float32)
    vol, stats = reconstruct_region(coded, mask, D, OmpSettings(max_atoms=4, tol_rms=2.0))
    assert np.isfinite(vol).all() and stats[2] > 0


# ----------------------------------------------------------------------------- codes with many patterns
def test_compiled_table_equals_the_numpy_pattern_table(rng):
    """build_table gives pattern_table's bits: binary codes with many patterns, and calibrated weights."""
    from codedvideo.solvers.omp import pattern_table
    from codedvideo.solvers.omp_kernel import build_table

    D = random_dictionary(rng, 8 * 49, 70) * np.float32(3.0)
    patterns, _ = pixel_patterns(make_code("bernoulli", (40, 40), frames=8, rng=2))
    assert len(patterns) > 200  # nearly all 256 patterns of N = 8
    assert np.array_equal(build_table(patterns, D, 49), pattern_table(patterns, D, 49))
    weights = (rng.uniform(0.1, 1.0, (30, 8)) * (rng.random((30, 8)) < 0.6)).astype(np.float32)
    weights[0] = 0.0  # a pixel never open: a zero row
    assert np.array_equal(build_table(weights, D, 49), pattern_table(weights, D, 49))


def test_shared_table_is_reused_only_for_the_same_patterns_and_dictionary(rng):
    from codedvideo.solvers.omp_kernel import build_table, shared_table

    D = random_dictionary(rng, 6 * 49, 40)
    patterns, _ = pixel_patterns(make_code("bernoulli", (20, 20), frames=6, rng=4))
    first = shared_table(patterns, D, 49)
    assert shared_table(patterns.copy(), D.copy(), 49) is first
    assert np.array_equal(first, build_table(patterns, D, 49))
    D2 = D.copy()
    D2[5, 7] += 1.0  # one entry of the dictionary changed: a new table
    other = shared_table(patterns, D2, 49)
    assert other is not first and np.array_equal(other, build_table(patterns, D2, 49))
    assert not np.array_equal(other, first)
    fewer = shared_table(patterns[:-1], D, 49)
    assert fewer.shape[1] == len(patterns) - 1 and np.array_equal(fewer, first[:, :-1])


def test_kernel_on_a_bernoulli_code_at_n8_matches_the_other_exact_paths(rng):
    """256 patterns: the table kernel gives the per-patch kernel's bits and the numpy operator's atoms."""
    from codedvideo.solvers.omp_kernel import WeightsOMP

    n, K = 8, 160
    D, mask, patterns, pat, S = _problem(rng, "bernoulli", n, K, (7 + 9, 7 + 13))
    assert len(patterns) > 100
    video = rng.uniform(0, 255, size=(n,) + mask.shape[1:]).astype(np.float32)
    Y = P.extract((mask * video).sum(0).astype(np.float32))
    tol = (S.sum(1) > 0).sum(1) * 4.0
    res = TableOMP(patterns, D, 49).solve(Y, pat, max_atoms=8, tol=tol)
    per_patch = WeightsOMP(D, 49).solve(Y, S.astype(np.float32), max_atoms=8, tol=tol)
    for f in ("index", "coef", "count", "residual", "dependent"):
        assert np.array_equal(getattr(res, f), getattr(per_patch, f)), f
    ref = omp(Y, MaskedOperator(S, D), max_atoms=8, tol=tol)
    np.testing.assert_array_equal(res.count, ref.count)
    np.testing.assert_array_equal(np.where(np.arange(8) < res.count[:, None], res.index, -1),
                                  np.where(np.arange(8) < ref.count[:, None], ref.index, -1))
    np.testing.assert_allclose(synthesize(res, D), synthesize(ref, D), atol=1e-2 * 255 / 100)


def test_kernel_column_norms_round_every_square(rng):
    """The norms are sums of the float32 squares B * B in pixel order, as the table of squares gave them:
    no fused multiply-add from the kernel's contraction flag (it changed atoms of a Bernoulli code)."""
    from codedvideo.solvers.omp_kernel import column_norms2

    B = rng.normal(size=(49, 3, 4096)).astype(np.float32) * rng.uniform(0.5, 5, (49, 3, 1)).astype(np.float32)
    pat = rng.integers(0, 3, 49).astype(np.int32)
    rows = B[np.arange(49), pat]
    want = np.zeros(B.shape[2], np.float32)
    fused = np.zeros(B.shape[2], np.float32)
    for i in range(49):
        want = want + rows[i] * rows[i]
        fused = (fused.astype(np.float64) + rows[i].astype(np.float64) ** 2).astype(np.float32)
    assert not np.array_equal(want, fused)  # the data tell the two apart
    assert np.array_equal(column_norms2(B, pat), want)
