import inspect

import numpy as np

import codedvideo as cv

from codedvideo.solvers.dictionaries import dct_dictionary, training_patches
from codedvideo.solvers.ksvd import ksvd
from conftest import random_dictionary


def test_ksvd_recovers_a_planted_dictionary_up_to_sign_and_order(rng):
    f, K, n, k = 20, 30, 1500, 3
    D_true = random_dictionary(rng, f, K)
    X = np.zeros((n, K), np.float32)
    for i in range(n):
        X[i, rng.choice(K, k, replace=False)] = rng.normal(size=k) + np.sign(rng.normal(size=k))
    Y = X @ D_true.T
    D0 = random_dictionary(rng, f, K)
    D, hist = ksvd(Y, D0, sparsity=k, iterations=40, rng=0)
    match = np.abs(D_true.T @ D).max(1)
    assert (match > 0.99).mean() >= 0.9, match
    assert hist.rmse[-1] < 0.2 * hist.rmse[0]


def test_ksvd_replaces_degenerate_atoms(rng):
    Y = rng.normal(size=(400, 16)).astype(np.float32)
    D0 = random_dictionary(rng, 16, 24)
    D0[:, 3] = 0.0
    D0[:, 5] = D0[:, 4]
    D, _ = ksvd(Y, D0, sparsity=3, iterations=3, rng=1)
    assert np.isfinite(D).all()
    np.testing.assert_allclose(np.linalg.norm(D, axis=0), 1.0, rtol=1e-4)
    G = np.abs(D.T @ D) - np.eye(24)
    assert G.max() < 0.995


def test_ksvd_keeps_the_atoms_no_sample_uses_when_asked_and_replaces_them_otherwise(rng):
    """Samples on 4 atoms of a basis of 16: with replace_unused=False the 12 others come out as they went in
    (normalised: to float32 rounding; a basis keeps its span); by default they become badly represented samples."""
    f = 16
    D0 = np.linalg.qr(rng.normal(size=(f, f)))[0].astype(np.float32)
    Y = (rng.normal(size=(300, 4)) @ D0[:, :4].T).astype(np.float32) + 0.01 * rng.normal(size=(300, f)).astype(
        np.float32)
    kept, _ = ksvd(Y, D0, sparsity=2, iterations=2, rng=0, replace_unused=False)
    replaced, hist = ksvd(Y, D0, sparsity=2, iterations=2, rng=0)
    np.testing.assert_allclose(kept[:, 4:], D0[:, 4:], atol=1e-6)
    assert sum(hist.replaced) >= 12 and not np.allclose(replaced[:, 4:], D0[:, 4:], atol=1e-3)
    assert np.abs(np.abs(np.sum(kept[:, :4] * D0[:, :4], 0)) - 1).max() < 0.05  # the used atoms still updated


def test_dct_dictionary_is_orthonormal_and_overcomplete_variant_unit_norm():
    D = dct_dictionary(4)
    assert D.shape == (196, 196)
    np.testing.assert_allclose(D.T @ D, np.eye(196), atol=1e-5)
    Do = dct_dictionary(4, redundancy=2.0)
    assert Do.shape[1] > 196
    np.testing.assert_allclose(np.linalg.norm(Do, axis=0), 1.0, rtol=1e-5)


def test_training_patches_augment_and_are_seeded(rng):
    v = rng.random((10, 20, 20)).astype(np.float32)
    a = training_patches([v], frames=4, samples=200, rng=3)
    b = training_patches([v], frames=4, samples=200, rng=3)
    assert a.shape == (200, 4 * 49)
    np.testing.assert_array_equal(a, b)
    # augmentation: a time-reversed copy of a raw patch appears when playback is random;
    # at least the set of patches is not identical to unaugmented sampling
    c = training_patches([v], frames=4, samples=200, rng=3, augment=False)
    assert not np.array_equal(a, c)


def test_the_k_svd_defaults_are_one_set_through_the_api_the_config_and_the_solver():
    from codedvideo.engine.config import DictionaryConfig
    from codedvideo.solvers.dictionaries import KsvdSettings, learn_dictionary

    api = inspect.signature(cv.train).parameters
    solver = inspect.signature(learn_dictionary).parameters["settings"].default
    assert solver == KsvdSettings()
    for key in ("atoms", "samples", "iterations", "sparsity"):
        config = DictionaryConfig.model_fields[key].default
        assert api[key].default == getattr(solver, key) == config, (key, api[key].default, getattr(solver, key), config)
