import numpy as np
import pytest

from codedvideo.model import patches as P
from codedvideo.model.codes import make_code
from codedvideo.solvers.omp import MaskedOperator, PlainOperator, omp, omp_reference
from codedvideo.solvers.omp_kernel import synthesize
from conftest import random_dictionary


def _planted(rng, P_, K, k, scale=1.0):
    X = np.zeros((P_, K), np.float32)
    for p in range(P_):
        X[p, rng.choice(K, k, replace=False)] = (rng.normal(size=k) + 2 * np.sign(rng.normal(size=k))) * scale
    return X


def _explicit(S, D):
    n, m = S.shape
    return (S[:, :, None].astype(np.float64) * D.reshape(n, m, -1)).sum(0)


def test_plain_omp_recovers_planted_sparse_codes(rng):
    D = random_dictionary(rng, 100, 300)
    X = _planted(rng, 64, 300, 5)
    res = omp(X @ D.T, PlainOperator(D), max_atoms=10, tol=1e-8)
    np.testing.assert_allclose(res.dense(300), X, atol=2e-4)
    assert (res.count == 5).all()


@pytest.mark.parametrize("code", ["hitomi", "hitomi-tiled", "bernoulli"])
def test_masked_omp_recovers_planted_codes_and_matches_reference(rng, code):
    n, K, count = 8, 200, 40
    D = random_dictionary(rng, n * 49, K)
    S = P.extract(make_code(code, (7, 7 + count - 1), frames=n, bump=2, rng=2))
    X = _planted(rng, count, K, 3)
    A = [_explicit(S[p], D) for p in range(count)]
    Y = np.stack([A[p] @ X[p] for p in range(count)]).astype(np.float32)
    op = MaskedOperator(S, D)
    np.testing.assert_allclose(op.norms(np.arange(count)), np.stack([np.linalg.norm(a, axis=0) for a in A]), rtol=1e-4)
    res = omp(Y, op, max_atoms=8, tol=1e-6)
    np.testing.assert_allclose(res.dense(K), X, atol=1e-3)
    ref = np.stack([omp_reference(A[p], Y[p], max_atoms=8, tol=1e-6) for p in range(count)])
    np.testing.assert_allclose(res.dense(K), ref, atol=1e-3)


def test_fast_path_equals_reference_on_random_problems_with_tolerance(rng):
    """Not planted: noisy data, both stopping rules active; the chosen atoms and estimates agree."""
    n, K, count = 4, 120, 60
    D = random_dictionary(rng, n * 49, K)
    S = P.extract(make_code("hitomi", (7 + 5, 7 + 9), frames=n, bump=2, rng=4))[:count]
    Y = rng.normal(size=(count, 49)).astype(np.float32)
    tol = 0.6 * (Y**2).sum(1)
    res = omp(Y, MaskedOperator(S, D), max_atoms=6, tol=tol)
    for p in range(count):
        A = _explicit(S[p], D)
        ref = omp_reference(A, Y[p], max_atoms=6, tol=tol[p])
        np.testing.assert_allclose(A @ res.dense(K)[p], A @ ref, atol=2e-4)
        assert res.count[p] == np.count_nonzero(ref)


def test_stops_at_tolerance_and_counts_atoms(rng):
    D = random_dictionary(rng, 49, 100)
    X = _planted(rng, 20, 100, 2)
    Y = X @ D.T
    res = omp(Y, PlainOperator(D), max_atoms=20, tol=1e-6)
    assert (res.count == 2).all()
    zero = omp(np.zeros((3, 49), np.float32), PlainOperator(D), max_atoms=5, tol=0.0)
    assert (zero.count == 0).all() and (zero.coef == 0).all()


def test_duplicate_and_zero_atoms_stay_finite(rng):
    D = random_dictionary(rng, 49, 60)
    D[:, 1] = D[:, 0] + 1e-7 * rng.normal(size=49).astype(np.float32)  # Gram cond >> 1e8
    D[:, 1] /= np.linalg.norm(D[:, 1])
    D[:, 2] = 0.0
    Y = rng.normal(size=(50, 49)).astype(np.float32)
    res = omp(Y, PlainOperator(D), max_atoms=49, tol=0.0)
    assert np.isfinite(res.coef).all()
    used = np.arange(res.index.shape[1])[None, :] < res.count[:, None]
    assert used.any() and not (used & (res.index == 2)).any()  # a zero atom is never chosen, in any slot
    est = synthesize(res, D)
    assert np.isfinite(est).all()
    assert (res.index[:, :1] != 2).all()  # a zero atom is never chosen
    # the residual never grows beyond the signal
    assert (res.residual <= (Y**2).sum(1) * (1 + 1e-5)).all()


def test_grouped_operator_equals_masked_on_tiled_code(rng):
    from codedvideo.solvers.omp import GroupedOperator, masked_operator

    n, K = 6, 150
    D = random_dictionary(rng, n * 49, K)
    mask = make_code("hitomi-tiled", (30, 33), frames=n, bump=2, rng=5)
    S = P.extract(mask)
    Y = rng.normal(size=(S.shape[0], 49)).astype(np.float32) * 20
    grouped = masked_operator(S, D)
    assert isinstance(grouped, GroupedOperator) and grouped.A.shape[0] <= 49
    rows = np.arange(S.shape[0])
    np.testing.assert_allclose(grouped.norms(rows), MaskedOperator(S, D).norms(rows), rtol=1e-4)
    a = omp(Y, grouped, max_atoms=6, tol=49.0)
    b = omp(Y, MaskedOperator(S, D), max_atoms=6, tol=49.0)
    np.testing.assert_array_equal(a.count, b.count)
    np.testing.assert_allclose(synthesize(a, D), synthesize(b, D), atol=1e-2, rtol=1e-3)
    # the sliding code has (almost) as many codes as patches: no grouping
    assert isinstance(masked_operator(P.extract(make_code("hitomi", (30, 33), frames=n, bump=2)), D), MaskedOperator)
