"""Option ranges, to the ends of float: every numeric option of every command gives a finite answer or one
line (exit 2) naming the option, the value and the allowed range; never a traceback, a leaked numpy warning
or a non-finite value written.  And the PSNR a user reads does not depend on the units of the files."""
import argparse
import json
import warnings

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from codedvideo.app import cli
from codedvideo.app.cli import main
from codedvideo.model.codes import make_code
from codedvideo.model.physics import simulate
from codedvideo.data.synth import make_scene

N, H, W = 4, 32, 32


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    d = tmp_path_factory.mktemp("capture")
    video = make_scene("default", frames=N, size=(H, W))
    mask = make_code("hitomi", (H, W), frames=N, bump=2, rng=1)
    np.save(d / "coded.npy", simulate(video, mask))
    np.save(d / "mask.npy", mask)
    np.save(d / "truth.npy", video)
    return d


def _run(args, capsys):
    """``main(args)``: its exit status, stderr, and the warnings raised on the way."""
    capsys.readouterr()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        rc = main(["-q", *map(str, args)])
    return rc, capsys.readouterr().err, caught


def _one_line_error(rc, err, caught, *words):
    assert rc == 2, err
    assert len(err.strip().splitlines()) == 1 and err.startswith("codedvideo: error: "), err
    assert "Traceback" not in err
    assert not [w for w in caught if not issubclass(w.category, UserWarning)], [str(w.message) for w in caught]
    for word in words:
        assert word in err, err


# ------------------------------------------------------------------------------------------- the reported cases
def _reconstruct(capture, tmp_path, *extra):
    return ["reconstruct", "--coded", capture / "coded.npy", "--mask", capture / "mask.npy", "--method", "dct",
            "--cache", tmp_path / "cache", "--output", tmp_path / "v.npy", *extra]


@pytest.mark.parametrize("option,value,words", [
    ("--noise-sigma", "1e300", ["[0, 1e+12]"]),  # OverflowError in units.tolerance_warning
    ("--data-range", "1e300", ["[1e-06, 1e+12]"]),  # ZeroDivisionError in stages
    ("--data-range", "1e-300", ["[1e-06, 1e+12]"]),
    ("--white-level", "1e300", ["(0, 1e+12]"]),  # an overflow warning leaked
    ("--black-level", "1e300", ["[0, 1e+12]"]),  # an overflow warning, then "must be finite" for a finite value
    ("--tol-rms", "-inf", ["[0, 1e+12]"]),  # argparse's "expected one argument"
    ("--tol-rms", "nan", ["[0, 1e+12]"]),
    ("--max-atoms", "-3", ["[1, 49]"]),
    ("--noise-sigma", "-1e3", ["[0, 1e+12]"]),
    ("--white-level", "-2", ["(0, 1e+12]"]),
    ("--black-level", "-0.5", ["[0, 1e+12]"]),
    ("--cache-budget", "-5M", []),
])
def test_reconstruct_refuses_a_value_at_the_ends_of_float_in_one_line(capture, tmp_path, capsys, option, value, words):
    rc, err, caught = _run(_reconstruct(capture, tmp_path, option, value), capsys)
    _one_line_error(rc, err, caught, f"option {option}", *words)
    assert not (tmp_path / "v.npy").exists()


def test_a_setting_a_million_data_ranges_high_is_refused_once_the_range_is_known(capture, tmp_path, capsys):
    rc, err, caught = _run(_reconstruct(capture, tmp_path, "--noise-sigma", "1e10", "--data-range", "255"), capsys)
    _one_line_error(rc, err, caught, "option --noise-sigma 1e+10", "data range 255", "[0, 2.55e+08]")
    rc, err, caught = _run(_reconstruct(capture, tmp_path, "--data-range", "1e-5"), capsys)
    _one_line_error(rc, err, caught, "data range 1e-05")


@pytest.mark.parametrize("value", ["1e300", "1e-300", "-1", "inf"])
def test_evaluate_refuses_a_data_range_out_of_bounds(capture, capsys, value):
    """1e300 gave an OverflowError traceback; 1e-300 reported every frame "exact" for a poor reconstruction."""
    recon = capture / "coded.npy"  # (any volume of the truth's shape would do: the range is refused first)
    np.save(capture / "poor.npy", np.load(capture / "truth.npy") * 0.5)
    rc, err, caught = _run(["evaluate", "--recon", capture / "poor.npy", "--truth", capture / "truth.npy",
                            "--data-range", value], capsys)
    _one_line_error(rc, err, caught, "option --data-range", "[1e-06, 1e+12]")
    del recon


@pytest.mark.parametrize("option,value", [("--noise-sigma", "1e300"), ("--black-level", "1e300"),
                                          ("--white-level", "1e300"), ("--noise-sigma", "-inf"),
                                          ("--gain", "1e-300"), ("--full-well", "1e300")])
def test_simulate_refuses_a_value_that_would_write_non_finite_values(tmp_path, capsys, option, value):
    extra = ["--shot-noise"] if option in ("--gain", "--full-well") else []
    rc, err, caught = _run(["simulate", "synth:default", "--frames", N, "--size", H, W, "--output", tmp_path / "s",
                            option, value, *extra], capsys)
    _one_line_error(rc, err, caught, f"option {option}")
    assert not (tmp_path / "s" / "coded.npy").exists()


def test_simulate_refuses_a_start_frame_a_synthetic_scene_ignores(tmp_path, capsys):
    """--start 50 of synth:default was accepted, and the truth was byte-identical to --start 0."""
    rc, err, caught = _run(["simulate", "synth:default", "--frames", N, "--size", H, W, "--start", 50,
                            "--output", tmp_path / "s"], capsys)
    _one_line_error(rc, err, caught, "--start 50", "synth:default")


def test_pipeline_yaml_names_the_key_and_the_allowed_range(tmp_path, capsys):
    path = tmp_path / "p.yaml"
    path.write_text("stages: [simulate]\nnoise:\n  sigma: 1.0e+300\n")
    rc, err, caught = _run(["run", path], capsys)
    _one_line_error(rc, err, caught, "noise.sigma", "[0, 1e+12]")
    path.write_text("stages: [simulate]\nscene:\n  start: 50\n")
    rc, err, caught = _run(["run", path], capsys)
    _one_line_error(rc, err, caught, "start 50")


# ----------------------------------------------------------------------- every numeric option, the float range
def _numeric_options() -> list[tuple[str, str, int]]:
    """``(command, option, nargs)`` of every option whose value is a number, read from the parser itself (a
    new option cannot escape the test): typed int or float, or a size (--cache-budget), or a count (--captures)."""
    found = []

    def walk(parser, command):
        for action in parser._actions:
            if isinstance(action, argparse._SubParsersAction):
                for name, sub in action.choices.items():
                    walk(sub, f"{command} {name}".strip())
            elif action.option_strings and (action.type in (int, float) or action.dest in ("cache_budget", "captures")):
                found.append((command, action.option_strings[0], action.nargs or 1))

    walk(cli._parser(), "")
    return found


NUMERIC_OPTIONS = _numeric_options()
#: Values at the ends of float, and the kinds of numbers in between.
HOSTILE = ["nan", "-nan", "inf", "-inf", "1e300", "-1e300", "1e-300", "-1e-300", "5e-324", "1.7976931348623157e308",
           "0", "-0", "-1", "0.5", "2", "3", str(2**63), str(-2**63), str(10**30), "1e12", "1e-6"]


def test_the_option_list_is_whole():
    """The commands whose options the property test draws, and the options the issue named, are all found."""
    named = {option for _, option, _ in NUMERIC_OPTIONS}
    assert {c for c, _, _ in NUMERIC_OPTIONS} == {"train", "simulate", "reconstruct", "evaluate"}
    assert {"--noise-sigma", "--data-range", "--tol-rms", "--white-level", "--black-level", "--max-atoms",
            "--cache-budget", "--start", "--size", "--full-well", "--gain", "--p", "--fps"} <= named


def _base(command: str, option: str, capture, tmp):
    if command == "train":
        return ["train", "--frames", N, "--output", tmp / "d.zarr", "--cache", tmp / "cache"]
    if command == "simulate":
        extra = ["--shot-noise"] if option in ("--full-well", "--gain") else []
        extra += ["--code", "bernoulli"] if option == "--p" else []
        extra += [] if option == "--frames" else ["--frames", N]
        extra += [] if option == "--size" else ["--size", H, W]
        return ["simulate", "synth:default", "--output", tmp / "s", *extra]
    if command == "reconstruct":
        return ["reconstruct", "--coded", capture / "coded.npy", "--mask", capture / "mask.npy", "--method", "dct",
                "--truth", capture / "truth.npy", "--cache", tmp / "cache", "--output", tmp / "v.npy"]
    return ["evaluate", "--recon", capture / "truth.npy", "--truth", capture / "truth.npy", "--output", tmp / "e.json"]


@settings(max_examples=80, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(which=st.sampled_from(NUMERIC_OPTIONS),
       value=st.one_of(st.sampled_from(HOSTILE), st.floats(allow_nan=True, allow_infinity=True).map(repr)))
def test_every_numeric_option_gives_a_finite_answer_or_one_line(capture, tmp_path_factory, capsys, monkeypatch, which,
                                                                value):
    command, option, nargs = which
    tmp = tmp_path_factory.mktemp("opt")
    if command == "train":  # K-SVD itself is not run (a valid --samples 10000000 would take minutes): the options'
        from codedvideo.engine import training  # checks all come before it

        trained = []
        monkeypatch.setattr(training, "train_dictionary", lambda cfg, **kw: trained.append(cfg) or (
            kw["output"], dict(atoms=1, frames=N, reused=False, seconds=0.0)))
    rc, err, caught = _run([*_base(command, option, capture, tmp), f"{option}={value}" if nargs == 1 else option,
                            *([value] * nargs if nargs != 1 else [])], capsys)
    leaked = [str(w.message) for w in caught if not issubclass(w.category, UserWarning)]
    assert not leaked, (which, value, leaked)
    assert "Traceback" not in err
    if rc == 2:
        assert len(err.strip().splitlines()) == 1 and err.startswith("codedvideo: error: "), (which, value, err)
        assert option in err or option.lstrip("-").replace("-", "_") in err, (which, value, err)
        return
    assert rc == 0, (which, value, err)
    for path in [*tmp.rglob("*.npy"), *tmp.rglob("*.json")]:
        if path.suffix == ".npy":
            data = np.load(path)
            assert np.isfinite(data).all(), (which, value, path)
        else:
            json.loads(path.read_text(), parse_constant=lambda c: pytest.fail(f"{path} holds {c}"))


# ----------------------------------------------------------------------------------- units of the reported figures
def test_the_psnr_does_not_depend_on_the_units_of_the_files(tmp_path, capsys):
    """The same capture and truth x1000 (float32) reported 29.02 dB where 8-bit and [0, 1] gave 28.79: the data
    range found was 262143 (the next 2**b - 1), not 255000."""
    video = make_scene("default", frames=N, size=(H, W))  # peaks at 248, not 255: a range found, not the peak
    mask = make_code("hitomi", (H, W), frames=N, bump=2, rng=1)
    coded = simulate(np.rint(video), mask)
    versions = {"u8": (np.rint(video).astype(np.uint8), coded.astype(np.uint16), 255.0),
                "f01": ((np.rint(video) / 255).astype(np.float32), (coded / 255).astype(np.float32), 1.0),
                "x1000": ((np.rint(video) * 1000).astype(np.float32), (coded * 1000).astype(np.float32), 255000.0)}
    psnr = {}
    for name, (truth, stored, peak) in versions.items():
        d = tmp_path / name
        d.mkdir()
        np.save(d / "truth.npy", truth)
        np.save(d / "coded.npy", stored)
        np.save(d / "mask.npy", mask)
        rc, err, _ = _run(["reconstruct", "--coded", d / "coded.npy", "--mask", d / "mask.npy", "--truth",
                           d / "truth.npy", "--method", "dct", "--cache", tmp_path / "cache", "--output",
                           d / "v.npy"], capsys)
        assert rc == 0, err
        metrics = json.loads((d / "v.metrics.json").read_text())
        assert metrics["quality"]["data_range"] == peak  # the peak PSNR was taken against, recorded
        assert metrics["quality"]["psnr_peak"]["value"] == peak and metrics["quality"]["psnr_peak"]["source"]
        psnr[name] = metrics["quality"]["psnr"]
        rc, err, _ = _run(["evaluate", "--recon", d / "v.npy", "--truth", d / "truth.npy"], capsys)
        assert rc == 0, err
    assert psnr["u8"] > 20
    assert abs(psnr["f01"] - psnr["u8"]) < 0.05 and abs(psnr["x1000"] - psnr["u8"]) < 0.05, psnr


def test_evaluate_takes_the_same_peak_in_any_scale(tmp_path, capsys):
    truth = make_scene("default", frames=N, size=(H, W))
    recon = truth + np.random.default_rng(0).normal(0, 4, truth.shape).astype(np.float32)
    scores = []
    for scale in (1.0, 1 / 255, 1000.0):
        np.save(tmp_path / "t.npy", truth * np.float32(scale))
        np.save(tmp_path / "r.npy", recon * np.float32(scale))
        capsys.readouterr()
        assert main(["evaluate", "--recon", str(tmp_path / "r.npy"), "--truth", str(tmp_path / "t.npy")]) == 0
        result = json.loads(capsys.readouterr().out)
        assert result["psnr_peak"]["value"] == pytest.approx(255 * scale)
        scores.append(result["psnr"])
    assert max(scores) - min(scores) < 0.01, scores
