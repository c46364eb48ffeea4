"""End to end through the command line, as a user runs it."""
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from codedvideo.app.cli import main

CLI = [sys.executable, "-m", "codedvideo.app.cli"]


def run(*args, cwd, check=True):
    proc = subprocess.run([*CLI, "-q", *map(str, args)], cwd=cwd, capture_output=True, text=True, timeout=600)
    if check and proc.returncode != 0:
        raise AssertionError(f"{args[0]} failed ({proc.returncode}): {proc.stderr}")
    return proc


@pytest.fixture(scope="module")
def workdir(tmp_path_factory):
    return tmp_path_factory.mktemp("cli")


@pytest.fixture(scope="module")
def dictionary(workdir):
    run("train", "--frames", 8, "--output", "dict.zarr", "--atoms", 256, "--iterations", 4, "--samples", 4000,
        "--seed", 1, "--cache", "cache", cwd=workdir)
    return workdir / "dict.zarr"


@pytest.fixture(scope="module")
def capture(workdir):
    run("simulate", "synth:default", "--frames", 8, "--bump", 2, "--noise-sigma", 0, "--seed", 3,
        "--size", 64, 64, "--output", "cap", cwd=workdir)
    return workdir / "cap"


def test_simulate_writes_the_contract_files(capture):
    coded = np.load(capture / "coded.npy")
    mask = np.load(capture / "mask.npy")
    truth = np.load(capture / "truth.npy")
    assert coded.shape == (64, 64) and coded.dtype == np.float32
    assert mask.shape == (8, 64, 64) and mask.dtype == np.uint8
    assert truth.shape == (8, 64, 64) and truth.dtype == np.float32
    np.testing.assert_allclose(coded, (mask * truth).sum(0), rtol=1e-5, atol=1e-3)
    assert (capture / "coded.tif").stat().st_size > 0


def test_reconstruct_beats_trivial_estimate_and_writes_metrics(workdir, dictionary, capture):
    out = workdir / "recon.npy"
    proc = run("reconstruct", "--coded", capture / "coded.npy", "--mask", capture / "mask.npy", "--dictionary", dictionary,
               "--output", out, "--truth", capture / "truth.npy", "--tile", 32, "--cache", "cache", cwd=workdir)
    summary = json.loads(proc.stdout.strip().splitlines()[-1])
    metrics = json.loads((workdir / "recon.metrics.json").read_text())
    vol = np.load(out)
    assert vol.shape == (8, 64, 64) and np.isfinite(vol).all()
    assert metrics["quality"]["psnr"] == pytest.approx(summary["psnr"], abs=0.01)
    assert metrics["quality"]["psnr"] > metrics["trivial"]["psnr"] + 3.0
    assert metrics["reconstruction"]["patches"] > 0 and metrics["reconstruction"]["patches_per_second"] > 0
    assert set(metrics["reconstruction"]["seconds"]) >= {"read", "reconstruct", "write", "total"}
    # evaluate agrees with the metrics written by reconstruct
    ev = json.loads(run("evaluate", "--recon", out, "--truth", capture / "truth.npy", cwd=workdir).stdout)
    assert ev["psnr"] == pytest.approx(metrics["quality"]["psnr"], abs=1e-6)
    assert len(ev["psnr_per_frame"]) == 8


def test_reconstruct_to_mp4_and_tiff_mask(workdir, dictionary, capture):
    from codedvideo.formats.io import read_video, write_multipage_tiff

    write_multipage_tiff(workdir / "mask.tif", np.load(capture / "mask.npy") * 255)  # 255: open
    run("reconstruct", "--coded", capture / "coded.tif", "--mask", workdir / "mask.tif", "--dictionary", dictionary,
        "--output", workdir / "recon.mp4", "--cache", "cache", cwd=workdir)
    frames = read_video(workdir / "recon.mp4")
    assert frames.shape[0] == 8 and frames.shape[1:] == (64, 64)
    ref = np.load(workdir / "recon.npy")
    assert np.abs(frames - np.clip(ref, 0, 255)).mean() < 4.0
    assert json.loads((workdir / "recon.metrics.json").read_text())["output"].endswith("recon.mp4")


def test_bad_inputs_give_one_line_errors(workdir, dictionary, capture):
    np.save(workdir / "wrong_mask.npy", np.ones((8, 10, 10), np.uint8))
    proc = run("reconstruct", "--coded", capture / "coded.npy", "--mask", workdir / "wrong_mask.npy", "--dictionary",
               dictionary, "--output", workdir / "x.npy", cwd=workdir, check=False)
    assert proc.returncode == 2
    assert "wrong_mask.npy" in proc.stderr and len(proc.stderr.strip().splitlines()) == 1
    assert not (workdir / "x.npy").exists()
    proc = run("reconstruct", "--coded", workdir / "missing.npy", "--mask", capture / "mask.npy", "--dictionary",
               dictionary, "--output", workdir / "x.npy", cwd=workdir, check=False)
    assert proc.returncode == 2 and "missing.npy" in proc.stderr


def test_run_pipeline_yaml(workdir):
    cfg = workdir / "p.yaml"
    cfg.write_text(
        "frames: 4\nscene: {video: synth:default, size: [48, 48]}\n"
        "dictionary: {kind: dct}\nreconstruct: {tile: 32}\noutput: {dir: runout, frames: none}\n"
    )
    proc = run("run", cfg, cwd=workdir)
    assert "runout/recon.mp4" in proc.stdout and "PSNR" in proc.stdout
    metrics = json.loads((workdir / "runout" / "recon.metrics.json").read_text())
    assert metrics["quality"]["psnr"] > metrics["trivial"]["psnr"]
    cfg.write_text("frames: 4\nreconstruct: {tiles: 32}\n")
    proc = run("run", cfg, cwd=workdir, check=False)
    assert proc.returncode == 2 and "reconstruct.tiles" in proc.stderr and "unknown key" in proc.stderr


def test_the_installed_command_keeps_its_exit_code_and_flushes_its_output(workdir, capture):
    """`codedvideo` leaves without finalising the interpreter (cli.console_main): its exit code and its
    last line of output must still arrive."""
    script = Path(sys.executable).with_name("codedvideo")
    if not script.exists():
        pytest.skip("the console script is not installed next to this interpreter")
    proc = subprocess.run([str(script), "codes", "check", str(capture / "mask.npy")], capture_output=True, text=True,
                          cwd=workdir, timeout=600)
    assert proc.returncode == 0, proc.stderr
    assert json.loads(proc.stdout)["frames"] == 8
    proc = subprocess.run([str(script), "codes", "check", str(workdir / "missing.npy")], capture_output=True,
                          text=True, cwd=workdir, timeout=600)
    assert proc.returncode == 2 and "missing.npy" in proc.stderr


@pytest.mark.parametrize("command", ["config", "evaluate"])
def test_a_reader_that_goes_away_ends_the_command_with_sigpipes_status_and_no_traceback(tmp_path, command):
    """`codedvideo config | head -1`: the reader closes its end before the command writes; the command ends with
    the shell's status for SIGPIPE (141) and says nothing (no BrokenPipeError traceback)."""
    video = np.linspace(0, 255, 8 * 16 * 16, dtype=np.float32).reshape(8, 16, 16)
    np.save(tmp_path / "v.npy", video)
    args = ["config"] if command == "config" else ["evaluate", "--recon", tmp_path / "v.npy", "--truth", tmp_path / "v.npy"]
    proc = subprocess.Popen([*CLI, *map(str, args)], stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    proc.stdout.close()  # before the interpreter has even started: every write meets a closed pipe
    err = proc.stderr.read().decode()
    assert proc.wait(timeout=120) == 141, err
    assert "Traceback" not in err and "BrokenPipeError" not in err, err


def test_quiet_after_the_command_says_where_it_goes(capsys):
    """`codedvideo reconstruct -q ...` said only `unrecognized arguments: -q`."""
    assert main(["reconstruct", "-q", "--coded", "c.npy", "--mask", "m.npy", "--output", "r.npy"]) == 2
    assert "-q goes before the command" in capsys.readouterr().err
