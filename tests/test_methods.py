"""The registry of methods (codedvideo.engine.methods) names the solvers and agrees with what the engine does."""
import pytest

from codedvideo.engine import methods
from codedvideo.engine.config import ReconstructConfig
from codedvideo.model.errors import InputError
from codedvideo.solvers import baselines


def test_the_registry_lists_every_method_and_each_baseline_is_a_solver_of_its_module():
    assert methods.METHOD_NAMES == ("omp", "nonlocal", "dct", "thinout", "interp", "gaptv")
    for name in methods.METHOD_NAMES:
        entry = methods.method(name)
        assert entry.sparse or callable(getattr(baselines, entry.solver))
    assert methods.SPARSE == ("omp", "nonlocal", "dct")
    assert methods.WITH_DICTIONARY == ("omp", "nonlocal")
    assert methods.ADAPTIVE == methods.SPARSE
    assert set(methods.REFINABLE) == set(methods.METHOD_NAMES)


def test_a_baseline_is_its_solver_and_an_unknown_name_is_refused_with_the_choices():
    assert methods.solver("gaptv") is baselines.gap_tv and methods.solver("thinout") is baselines.thinout
    assert methods.method("dct").solver == "omp" and methods.method("nonlocal").solver == "nonlocal"
    with pytest.raises(InputError, match="choose one of omp, nonlocal, dct, thinout, interp, gaptv"):
        methods.method("ksvd")
    with pytest.raises(ValueError, match="sparse-codes"):
        methods.solver("omp")


def test_pipeline_yaml_takes_the_methods_with_a_dictionary():
    for name in methods.WITH_DICTIONARY:
        assert ReconstructConfig(method=name).method == name
    with pytest.raises(ValueError):
        ReconstructConfig(method="gaptv")
