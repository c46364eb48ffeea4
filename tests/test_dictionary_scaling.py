"""Dictionary scaling: atoms of any nonzero norm give the same answer; zero atoms are dropped or refused.

Reconstruction goes through :func:`codedvideo.solvers.dictionaries.prepare_dictionary`
(:func:`codedvideo.engine.captures.reconstruct_method`), and the OMP kernels' own
floors are relative, so a globally scaled dictionary works even without it.
"""
import warnings

import numpy as np
import pytest

from codedvideo.model import patches as P
from codedvideo.data import synth
from codedvideo.engine.captures import reconstruct_method
from codedvideo.model.codes import make_code
from codedvideo.solvers.dictionaries import (UNIT_NORM_TOL, KsvdSettings, dct_dictionary, learn_dictionary,
                                             prepare_dictionary)
from codedvideo.model.errors import InputError
from codedvideo.model.metrics import evaluate
from codedvideo.solvers.omp import MaskedOperator, omp
from codedvideo.model.physics import simulate, static_estimate
from codedvideo.engine.windows import Execution, reconstruct_volume
from codedvideo.solvers.region import OmpSettings
from codedvideo.data.synth import make_scene

H, W, N = 32, 40, 8
SETTINGS = OmpSettings(max_atoms=8, tol_rms=2.0)
#: The promise: PSNR within this of the unit-norm dictionary's (dB).
PSNR_TOL = 0.01


@pytest.fixture(scope="module")
def scene():
    video = make_scene("default", frames=N, size=(H, W))
    mask = make_code("hitomi", (H, W), frames=N, bump=2, rng=1)
    return video, mask, simulate(video, mask)


@pytest.fixture(scope="module")
def dictionary():
    """A small learned (K-SVD) dictionary: unit-norm float32 atoms, not orthogonal (about 2 s)."""
    videos = synth.training_videos(frames=N, count=12, seed=0)
    D, _ = learn_dictionary(videos, frames=N, settings=KsvdSettings(atoms=128, samples=2000, iterations=2), seed=0)
    assert D.dtype == np.float32 and np.abs(np.linalg.norm(D.astype(np.float64), axis=0) - 1).max() < 1e-6
    return D


def _recon(scene, D, cache, **kw):
    video, mask, coded = scene
    with warnings.catch_warnings():
        warnings.simplefilter("error", UserWarning)  # no "stopped early", no overflow: a clean run
        vol, info = reconstruct_method("omp", coded, mask, dictionary=D, settings=SETTINGS,
                                       run=Execution(tile=16, cache=cache), **kw)
    return vol, info, evaluate(vol, video, data_range=255.0)["psnr"]


@pytest.fixture(scope="module")
def reference(scene, dictionary, tmp_path_factory):
    vol, info, psnr = _recon(scene, dictionary, tmp_path_factory.mktemp("ref"))
    video, mask, coded = scene
    assert psnr > evaluate(static_estimate(coded, mask), video, data_range=255.0)["psnr"] + 2  # a meaningful reconstruction
    return vol, info, psnr


def _per_atom_scales(k, seed=0):
    return np.exp(np.random.default_rng(seed).uniform(np.log(1e-6), np.log(1e6), k)).astype(np.float32)


@pytest.mark.parametrize("scale", ["1e-12", "1e30", "per-atom 1e-6..1e6"])
def test_atom_scale_does_not_change_the_answer(scene, dictionary, reference, scale, tmp_path):
    ref, ref_info, ref_psnr = reference
    factor = _per_atom_scales(dictionary.shape[1])[None, :] if scale.startswith("per-atom") else np.float32(scale)
    D = dictionary * factor
    assert np.isfinite(D).all() and D.dtype == np.float32
    vol, info, psnr = _recon(scene, D, tmp_path)
    assert abs(psnr - ref_psnr) < PSNR_TOL, (psnr, ref_psnr)
    assert np.abs(vol - ref).max() < 0.05  # grey levels: float32 roundoff of the rescaled atoms
    assert info["dictionary_atoms"] == dictionary.shape[1]


@pytest.mark.parametrize("code", ["hitomi", "hitomi-tiled", "bernoulli"])
@pytest.mark.parametrize("scale", [1e-12, 1e15])
def test_omp_floors_are_relative_without_prepare(dictionary, code, scale, tmp_path):
    """reconstruct_volume itself (no prepare_dictionary): compiled kernel, grouped and table paths, any global scale

    within float32's range of squares gives the unit dictionary's answer (before: 1e-12 fell under an absolute floor,
    8 to 18 dB).
    """
    video = make_scene("default", frames=N, size=(H, W))
    mask = make_code(code, (H, W), frames=N, bump=2, rng=1)
    coded = simulate(video, mask)
    D = dictionary
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)  # never-open pixels of the Bernoulli mask
        ref, _ = reconstruct_volume(coded, mask, D, settings=SETTINGS,
                                    run=Execution(tile=16, cache=tmp_path / "a", progress=False))
        vol, info = reconstruct_volume(coded, mask, D * np.float32(scale), settings=SETTINGS,
                                       run=Execution(tile=16, cache=tmp_path / "b", progress=False))
    assert info["dependent_stops"] == 0
    assert abs(evaluate(vol, video, data_range=255.0)["psnr"] - evaluate(ref, video, data_range=255.0)["psnr"]) < PSNR_TOL


def test_batched_omp_selects_the_same_atoms_at_any_global_scale(rng):
    """The numpy OMP (MaskedOperator) picks the same atoms for D, D * 1e-12 and D * 1e15."""
    D = dct_dictionary(4, redundancy=2.0)
    S = P.extract((rng.random((4, 12, 14)) < 0.5).astype(np.uint8))
    Y = (rng.normal(size=(S.shape[0], 49)) * 50).astype(np.float32)
    tol = 0.05 * (Y**2).sum(1)
    ref = omp(Y, MaskedOperator(S, D), max_atoms=6, tol=tol)
    for scale in (1e-12, 1e15):
        res = omp(Y, MaskedOperator(S, D * np.float32(scale)), max_atoms=6, tol=tol)
        np.testing.assert_array_equal(res.count, ref.count)
        used = np.arange(6)[None] < ref.count[:, None]
        np.testing.assert_array_equal(res.index[used], ref.index[used])
        np.testing.assert_allclose(res.coef[used] * np.float32(scale), ref.coef[used], rtol=1e-3, atol=1e-3)


def test_zero_and_nan_atoms_are_dropped_with_a_warning(scene, dictionary, reference, tmp_path):
    """Zero atoms anywhere (and NaN ones) are dropped, counted in a warning, and change nothing else."""
    ref, ref_info, _ = reference
    k = dictionary.shape[1]
    rng = np.random.default_rng(3)
    D = dictionary.copy()
    at = np.sort(rng.choice(k + 6, 6, replace=False))
    D = np.insert(D, at - np.arange(6), 0.0, axis=1)  # 6 zero atoms at random places
    assert D.shape[1] == k + 6 and (np.linalg.norm(D, axis=0) == 0).sum() == 6
    video, mask, coded = scene
    with pytest.warns(UserWarning, match=f"dropped 6 all-zero .*of its {k + 6} atoms"):
        vol, info = reconstruct_method("omp", coded, mask, dictionary=D, settings=SETTINGS,
                                       run=Execution(tile=16, cache=tmp_path))
    assert info["dictionary_atoms"] == k
    np.testing.assert_array_equal(vol, ref)  # the kept atoms are the clean dictionary, bit for bit
    D[:, 0] = np.nan
    with pytest.warns(UserWarning, match="dropped 6 all-zero and 1 non-finite"):
        prepared = prepare_dictionary(D, "test.zarr")
    assert prepared.shape[1] == k - 1 and np.isfinite(prepared).all()


def test_all_zero_dictionary_is_a_one_line_error(scene, tmp_path):
    video, mask, coded = scene
    D = np.zeros((N * 49, 64), np.float32)
    with pytest.raises(InputError, match="every atom is zero") as exc:
        reconstruct_method("omp", coded, mask, dictionary=D, settings=SETTINGS,
                           run=Execution(tile=16, cache=tmp_path / "cache"))
    assert "\n" not in str(exc.value) and str(exc.value).startswith("dictionary ")
    assert not (tmp_path / "cache").exists()  # refused before any work
    with pytest.raises(InputError, match=r"^dictionary runs/d\.zarr: every atom is zero"):
        prepare_dictionary(D, "runs/d.zarr")
    D[:, :3] = np.nan  # zero or NaN: still nothing to reconstruct with
    with pytest.raises(InputError, match="every atom is zero or not finite"):
        prepare_dictionary(D, "runs/d.zarr")


def test_unit_norm_dictionaries_are_used_bit_for_bit(dictionary):
    """Within UNIT_NORM_TOL of unit norm (every learned or DCT dictionary) nothing is rescaled: same bits, same keys."""
    assert prepare_dictionary(dictionary, "x") is dictionary
    nearly = dictionary * np.float32(1 + 0.5 * UNIT_NORM_TOL)
    np.testing.assert_array_equal(prepare_dictionary(nearly, "x"), nearly)
    np.testing.assert_array_equal(prepare_dictionary(dictionary.astype(np.float64), "x"), dictionary)


@pytest.mark.parametrize("dtype,scale", [(np.float32, 1e-25), (np.float32, 1e30), (np.float64, 1e-300), (np.float64, 1e300)])
def test_rescaled_atoms_have_unit_norm_without_overflow(dictionary, dtype, scale):
    D = dictionary.astype(dtype) * _per_atom_scales(dictionary.shape[1]).astype(dtype)[None, :] * dtype(scale)
    assert np.isfinite(D).all()
    out = prepare_dictionary(D, "x")
    assert out.dtype == np.float32 and out.flags.c_contiguous
    np.testing.assert_allclose(np.linalg.norm(out.astype(np.float64), axis=0), 1.0, rtol=1e-6)
    np.testing.assert_allclose(out, dictionary, atol=1e-6)


@pytest.mark.parametrize("bad", [np.zeros(49), np.zeros((49, 0)), np.zeros((2, 49, 3))])
def test_malformed_dictionaries_are_refused(bad):
    with pytest.raises(InputError, match="^dictionary x: "):
        prepare_dictionary(bad, "x")


def test_dct_method_goes_through_the_same_preparation(scene, tmp_path):
    """--method dct: its DCT is already unit-norm, used as built."""
    video, mask, coded = scene
    vol, info = reconstruct_method("dct", coded, mask, settings=SETTINGS, run=Execution(tile=16, cache=tmp_path))
    assert info["dictionary_atoms"] == N * 49 and np.isfinite(vol).all()
