"""Batch-OMP (K-SVD's coding step) against the numpy OMP, and the compiled K-SVD update against numpy."""

import numpy as np
import pytest

from codedvideo.solvers.ksvd import ksvd
from codedvideo.solvers.omp import PlainOperator, omp
from codedvideo.solvers.ksvd_kernel import row_energy, subtract_codes, update_atoms
from codedvideo.solvers.omp_kernel import batch_omp
from conftest import random_dictionary


def _planted(rng, P_, K, k):
    X = np.zeros((P_, K), np.float32)
    for p in range(P_):
        X[p, rng.choice(K, k, replace=False)] = rng.normal(size=k) + 2 * np.sign(rng.normal(size=k))
    return X


def _assert_same_pursuit(res, ref, K):
    np.testing.assert_array_equal(res.count, ref.count)
    used = np.arange(res.index.shape[1])[None, :] < res.count[:, None]
    np.testing.assert_array_equal(np.where(used, res.index, -1), np.where(used, ref.index, -1))
    np.testing.assert_array_equal(res.dependent, ref.dependent)
    scale = np.abs(ref.coef).max()
    np.testing.assert_allclose(res.dense(K), ref.dense(K), atol=2e-4 * scale)


@pytest.mark.parametrize("stop", ["sparsity", "tolerance"])
@pytest.mark.parametrize("scale", [1.0, 100.0])
def test_batch_omp_equals_numpy_omp_on_random_problems(rng, stop, scale):
    """Not planted: noisy signals over a redundant dictionary, same atoms in the same order and same coefficients."""
    m, K, P = 64, 200, 400
    D = random_dictionary(rng, m, K)
    D[:, ::7] *= 3.0  # atoms of other norms: selection is by normalised correlation
    Y = (rng.normal(size=(P, m)) * scale).astype(np.float32)
    tol = 0.0 if stop == "sparsity" else 0.5 * (Y.astype(np.float64) ** 2).sum(1)
    ref = omp(Y, PlainOperator(D), max_atoms=8, tol=tol)
    res = batch_omp(Y, D, max_atoms=8, tol=tol)
    _assert_same_pursuit(res, ref, K)
    if stop == "sparsity":
        assert (res.count == 8).all()
    else:
        assert (res.count < 8).any() and (res.residual <= tol).mean() > 0.5
    fit = Y - res.dense(K) @ D.T
    np.testing.assert_allclose(res.residual, (fit.astype(np.float64) ** 2).sum(1), rtol=1e-3)


def test_batch_omp_chunks_and_precision_do_not_change_the_answer(rng):
    D = random_dictionary(rng, 49, 120)
    Y = rng.normal(size=(300, 49)).astype(np.float32)
    whole = batch_omp(Y, D, max_atoms=6, tol=0.2 * (Y**2).sum(1))
    for kw in (dict(chunk=37), dict(precision=np.float64)):
        _assert_same_pursuit(batch_omp(Y, D, max_atoms=6, tol=0.2 * (Y**2).sum(1), **kw), whole, 120)


def test_batch_omp_recovers_planted_sparse_codes(rng):
    D = random_dictionary(rng, 100, 300)
    X = _planted(rng, 64, 300, 5)
    res = batch_omp(X @ D.T, D, max_atoms=10, tol=1e-6)
    assert (res.count == 5).all() and not res.dependent.any()
    np.testing.assert_allclose(res.dense(300), X, atol=2e-4)
    assert (res.residual < 1e-6).all()


def test_batch_omp_zero_signals_and_degenerate_atoms_stay_finite(rng):
    D = random_dictionary(rng, 49, 60)
    D[:, 1] = D[:, 0] + 1e-7 * rng.normal(size=49).astype(np.float32)  # Gram cond >> 1e8
    D[:, 1] /= np.linalg.norm(D[:, 1])
    D[:, 2] = 0.0
    Y = rng.normal(size=(50, 49)).astype(np.float32)
    Y[:5] = 0.0
    res = batch_omp(Y, D, max_atoms=49, tol=0.0)
    assert np.isfinite(res.coef).all() and np.isfinite(res.residual).all() and (res.residual >= 0).all()
    assert (res.count[:5] == 0).all() and (res.coef[:5] == 0).all() and not res.dependent[:5].any()
    used = np.arange(res.index.shape[1])[None, :] < res.count[:, None]
    assert not (used & (res.index == 2)).any()  # a zero atom is never chosen
    for p in range(5, 50):  # atoms 0 and 1 never both: once one is chosen the other has no correlation left
        chosen = set(res.index[p, : res.count[p]].tolist())
        assert len(chosen) == res.count[p] and not {0, 1} <= chosen
    ref = omp(Y, PlainOperator(D), max_atoms=49, tol=0.0)
    np.testing.assert_array_equal(res.count, ref.count)
    fit = Y - res.dense(60) @ D.T
    np.testing.assert_allclose(res.residual, (fit.astype(np.float64) ** 2).sum(1), atol=1e-3)


def test_batch_omp_stops_on_linear_dependence_as_numpy_omp_does(rng):
    """Atoms spanning only 3 dimensions: after 3 atoms every further one is dependent, a counted stop, never a NaN."""
    basis = np.linalg.qr(rng.normal(size=(49, 3)))[0]
    D = (basis @ rng.normal(size=(3, 20))).astype(np.float32)
    D /= np.linalg.norm(D, axis=0)
    Y = rng.normal(size=(40, 49)).astype(np.float32)
    res = batch_omp(Y, D, max_atoms=8, tol=0.0)
    ref = omp(Y, PlainOperator(D), max_atoms=8, tol=0.0)
    assert (res.count == 3).all() and res.dependent.all()
    _assert_same_pursuit(res, ref, 20)
    outside = Y.astype(np.float64) - (Y @ basis) @ basis.T
    np.testing.assert_allclose(res.residual, (outside**2).sum(1), rtol=1e-4)


def _update_reference(E, D, coef, index, count, atoms, steps):
    """The numpy K-SVD atom update (rank-1 by power iteration), one atom after the other."""
    E, D, coef = E.astype(np.float64), D.astype(np.float64), coef.astype(np.float64)
    for k in atoms:
        users, slot = np.nonzero((index == k) & (np.arange(index.shape[1])[None, :] < count[:, None]))
        Ek = E[users] + coef[users, slot, None] * D[:, k][None, :]
        d = D[:, k]
        for _ in range(steps):
            d = Ek.T @ (Ek @ d)
            d /= np.linalg.norm(d)
        x = Ek @ d
        D[:, k], coef[users, slot] = d, x
        E[users] = Ek - x[:, None] * d[None, :]
    return E, D, coef


def test_compiled_ksvd_update_equals_the_numpy_update(rng):
    f, K, P = 30, 40, 500
    D = random_dictionary(rng, f, K)
    X = rng.normal(size=(P, f)).astype(np.float32) * 10
    codes = batch_omp(X, D, max_atoms=4, tol=0.0)
    coef = codes.coef.copy()
    E = np.empty_like(X)
    err = np.empty(P)
    subtract_codes(X, codes.index, coef, codes.count, np.ascontiguousarray(D.T), E, err)
    np.testing.assert_allclose(E, X - codes.dense(K) @ D.T, atol=1e-4)
    np.testing.assert_allclose(err, row_energy(E), rtol=1e-6)
    S = codes.index.shape[1]
    flat = np.where(np.arange(S)[None, :] < codes.count[:, None], codes.index, -1).ravel()
    order = np.argsort(flat, kind="stable")
    bounds = np.searchsorted(flat[order], np.arange(K + 1))
    atoms = np.array([a for a in rng.permutation(K) if bounds[a + 1] > bounds[a]])
    E_ref, D_ref, coef_ref = _update_reference(E, D, coef, codes.index, codes.count, atoms, 3)
    Dt = np.ascontiguousarray(D.T)
    update_atoms(E, err, Dt, coef, atoms, order, bounds, 3)
    np.testing.assert_allclose(Dt.T, D_ref, atol=1e-4)
    np.testing.assert_allclose(coef, coef_ref, atol=1e-3)
    np.testing.assert_allclose(E, E_ref, atol=1e-3)
    np.testing.assert_allclose(err, (E.astype(np.float64) ** 2).sum(1), rtol=1e-5)
    np.testing.assert_allclose(np.linalg.norm(Dt, axis=1)[atoms], 1.0, rtol=1e-5)
    # the update lowers the residual (each atom's rank-1 fit is at least as good as the old one)
    before = X.astype(np.float64) - codes.dense(K) @ D.T.astype(np.float64)
    assert err.sum() < 0.99 * (before**2).sum()


def test_ksvd_with_batch_omp_reduces_the_error_on_patches(rng):
    # smooth random 8x8 "patches" (sums of a few low-frequency cosines) with noise
    f, n = 64, 3000
    t = np.arange(8)
    basis = np.stack([np.outer(np.cos(np.pi * a * (t + 0.5) / 8), np.cos(np.pi * b * (t + 0.5) / 8)).ravel()
                      for a in range(4) for b in range(4)], 1)
    X = (rng.normal(size=(n, 16)) * np.linspace(3, 0.3, 16)) @ basis.T + 0.05 * rng.normal(size=(n, f))
    D0 = random_dictionary(rng, f, 48)
    seen = []
    D, hist = ksvd(X.astype(np.float32), D0, sparsity=3, iterations=8, rng=0, progress=lambda it, r: seen.append(r))
    assert seen == hist.rmse and len(hist.rmse) == 8
    # 16-dimensional signals, 3 atoms each: the error falls by a third, and at every iteration
    # (no atom is replaced here; numpy OMP gave the same history to 4 digits: 2.7585 ... 1.6589)
    assert hist.rmse[-1] < 0.65 * hist.rmse[0] and sum(hist.replaced) == 0
    assert all(b < a for a, b in zip(hist.rmse, hist.rmse[1:]))
    assert D.shape == (f, 48) and D.dtype == np.float32 and D.flags.c_contiguous
    np.testing.assert_allclose(np.linalg.norm(D, axis=0), 1.0, rtol=1e-4)
    # the history's error is the error of coding with the returned dictionary's last state (up to the
    # coefficients the update refitted), so coding again cannot be much worse
    again = batch_omp(X.astype(np.float32), D, max_atoms=3)
    assert np.sqrt(again.residual.mean() / f) <= hist.rmse[-1] * 1.05
