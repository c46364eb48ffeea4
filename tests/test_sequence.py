"""Coded video: a stream of captures through simulate and reconstruct as one job, streamed to its output."""
import json
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from codedvideo.app.cli import main
from codedvideo.engine.windows import Execution
from conftest import capture_settings, partly_still_capture

N, H, W, T = 4, 40, 44, 3
CLI = [sys.executable, "-m", "codedvideo.app.cli", "-q"]


def _run(capsys, *args):
    capsys.readouterr()
    rc = main(["-q", *map(str, args)])
    assert rc == 0, capsys.readouterr().err


@pytest.fixture(scope="module")
def sequence(tmp_path_factory):
    d = tmp_path_factory.mktemp("seq")
    assert main(["-q", "simulate", "synth:default", "--frames", str(N), "--size", str(H), str(W), "--captures", str(T),
                 "--output", str(d / "cap")]) == 0
    assert main(["-q", "simulate", "synth:default", "--frames", str(N), "--size", str(H), str(W), "--captures", str(T),
                 "--new-code-per-capture", "--output", str(d / "cap2")]) == 0
    return d


def test_simulate_writes_a_stream_of_captures(sequence):
    cap = sequence / "cap"
    assert np.load(cap / "coded.npy").shape == (T, H, W)
    assert np.load(cap / "mask.npy").shape == (N, H, W)
    assert np.load(cap / "truth.npy").shape == (T * N, H, W)
    masks = np.load(sequence / "cap2" / "mask.npy")
    assert masks.shape == (T, N, H, W) and not (masks[0] == masks[1]).all()
    # the first capture is the single capture of the same seed
    from codedvideo.data.scenes import load_video
    from codedvideo.engine.simulation import simulate_capture
    from codedvideo.model.codes import CodeSpec

    one = simulate_capture(load_video("synth:default", frames=N, size=(H, W)), code=CodeSpec("hitomi", bump=2), sigma=0,
                           seed=0)
    np.testing.assert_array_equal(np.load(cap / "coded.npy")[0], one["coded"])


@pytest.mark.parametrize("which", ["cap", "cap2"])
def test_a_sequence_equals_its_captures_reconstructed_one_by_one(sequence, tmp_path, capsys, which):
    cap = sequence / which
    coded, masks = np.load(cap / "coded.npy"), np.load(cap / "mask.npy")
    common = ["--method", "dct", "--cache", tmp_path / "cache"]
    _run(capsys, "reconstruct", "--coded", cap / "coded.npy", "--mask", cap / "mask.npy", "--truth",
         cap / "truth.npy", "--output", tmp_path / "all.npy", "--independent-captures", *common)
    whole = np.load(tmp_path / "all.npy")
    assert whole.shape == (T * N, H, W)
    for t in range(T):
        np.save(tmp_path / "c.npy", coded[t])
        np.save(tmp_path / "m.npy", masks[t] if masks.ndim == 4 else masks)
        _run(capsys, "reconstruct", "--coded", tmp_path / "c.npy", "--mask", tmp_path / "m.npy", "--output",
             tmp_path / f"one{t}.npy", *common)
        np.testing.assert_array_equal(whole[t * N : (t + 1) * N], np.load(tmp_path / f"one{t}.npy"))
    metrics = json.loads((tmp_path / "all.metrics.json").read_text())
    assert [e["capture"] for e in metrics["captures"]] == [1, 2, 3]
    assert len(metrics["quality"]["psnr_per_frame"]) == T * N and len(metrics["quality"]["psnr_per_capture"]) == T
    assert len(metrics["quality"]["boundaries"]["pairs"]) == T - 1


STREAMED = ("s.tif", "s.mkv", "s.zarr", "s_frames", "s.mat")  # besides .npy: every grey output, capture by capture


def test_streamed_output_equals_the_output_written_at_once(sequence, tmp_path, capsys):
    from codedvideo.formats.volumes import read_volume, write_volume

    cap = sequence / "cap"
    for out in ("s.npy", *STREAMED):
        _run(capsys, "reconstruct", "--coded", cap / "coded.npy", "--mask", cap / "mask.npy", "--method", "dct",
             "--cache", tmp_path / "cache", "--output", tmp_path / out)
    volume = np.load(tmp_path / "s.npy")
    assert volume.shape == (T * N, H, W)
    for out in STREAMED:
        whole = tmp_path / f"whole-{out}"
        write_volume(volume, whole)
        np.testing.assert_array_equal(read_volume(tmp_path / out), read_volume(whole), err_msg=out)
    np.testing.assert_array_equal(read_volume(tmp_path / "s.tif"), volume)  # float32 pages: exact
    np.testing.assert_array_equal(read_volume(tmp_path / "s.mat"), volume)  # single precision: exact
    np.testing.assert_array_equal(read_volume(tmp_path / "s.zarr"), volume)
    import zarr

    assert zarr.open_array(str(tmp_path / "s.zarr"), mode="r").chunks[0] == N  # a capture per chunk


@pytest.mark.parametrize("out", ["s.npy", *STREAMED])
def test_a_stream_cut_short_leaves_no_output(tmp_path, out):
    from codedvideo.formats.volumes import volume_writer

    parts = np.random.default_rng(0).uniform(0, 255, (2, N, H, W)).astype(np.float32)
    with pytest.raises(RuntimeError, match="capture 2 failed"):
        with volume_writer(tmp_path / out, (3 * N, H, W), part=N) as put:
            for i, part in enumerate(parts):
                put(slice(i * N, (i + 1) * N), part)
            raise RuntimeError("capture 2 failed")
    assert os.listdir(tmp_path) == []  # neither the output nor a temporary


@pytest.mark.parametrize("out", [*STREAMED])
def test_a_streamed_output_never_gathers_the_whole_volume(tmp_path, out, monkeypatch):
    """Every grey output is written part by part: the write-at-once path is never taken."""
    from codedvideo.formats import volumes

    def whole(*args, **kwargs):
        raise AssertionError("the whole volume was gathered")

    monkeypatch.setattr(volumes, "write_volume", whole)
    parts = np.random.default_rng(0).uniform(0, 255, (3, N, H, W)).astype(np.float32)
    with volumes.volume_writer(tmp_path / out, (3 * N, H, W), part=N) as put:
        for i, part in enumerate(parts):
            put(slice(i * N, (i + 1) * N), part)
    assert (tmp_path / out).exists()


def test_mask_per_capture_must_match_the_number_of_captures(sequence, tmp_path, capsys):
    masks = np.load(sequence / "cap2" / "mask.npy")
    np.save(tmp_path / "m.npy", masks[:2])
    capsys.readouterr()
    assert main(["-q", "reconstruct", "--coded", str(sequence / "cap" / "coded.npy"), "--mask", str(tmp_path / "m.npy"),
                 "--method", "dct", "--output", str(tmp_path / "r.npy"), "--cache", str(tmp_path / "c")]) == 2
    assert "2 masks" in capsys.readouterr().err and not (tmp_path / "r.npy").exists()


def test_the_boundary_step_is_no_worse_than_a_step_inside_a_capture(tmp_path, capsys):
    """Through the command line: captures joined (the default) against reconstructed on their own."""
    _run(capsys, "simulate", "synth:default", "--frames", "8", "--size", "96", "96", "--captures", "4", "--seed", "1",
         "--output", tmp_path / "cap")
    cap, ratio, psnr = tmp_path / "cap", {}, {}
    for name, flag in (("joined", []), ("alone", ["--independent-captures"])):
        _run(capsys, "reconstruct", "--coded", cap / "coded.npy", "--mask", cap / "mask.npy", "--truth",
             cap / "truth.npy", "--output", tmp_path / f"{name}.npy", "--cache", tmp_path / "cache", *flag)
        quality = json.loads((tmp_path / f"{name}.metrics.json").read_text())["quality"]
        ratio[name], psnr[name] = quality["boundaries"]["boundary_to_inside"], quality["psnr"]
    assert ratio["alone"] > 1.1  # the flicker the join removes
    assert ratio["joined"] <= 1.0
    assert psnr["joined"] >= psnr["alone"] - 0.05


@pytest.mark.slow
def test_sigkill_mid_sequence_then_rerun_equals_a_clean_run(tmp_path):
    cap = tmp_path / "cap"
    subprocess.run([*CLI, "simulate", "synth:default", "--frames", "8", "--size", "160", "160", "--captures", "4",
                    "--output", str(cap)], check=True)
    args = ["reconstruct", "--coded", str(cap / "coded.npy"), "--mask", str(cap / "mask.npy"), "--tile", "32",
            "--output", str(tmp_path / "out" / "r.npy")]
    proc = subprocess.Popen([*CLI, *args, "--cache", str(tmp_path / "cache")])

    def finished_tiles() -> int:  # a tile's digest is written last: a digest chunk on disk is a finished tile
        return sum(1 for p in (tmp_path / "cache").glob("recon-*.zarr/digest/c/**/*") if p.is_file())

    deadline = time.time() + 120
    while time.time() < deadline and finished_tiles() < 40:
        time.sleep(0.02)  # one graph over (capture, tile): killed with 40 or so of the 100 tiles done
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    done = finished_tiles()
    assert 40 <= done < 100 and not (tmp_path / "out" / "r.npy").exists()
    subprocess.run([*CLI, *args, "--cache", str(tmp_path / "cache")], check=True)
    subprocess.run([*CLI, *args[:-1], str(tmp_path / "clean.npy"), "--cache", str(tmp_path / "cache2")], check=True)
    np.testing.assert_array_equal(np.load(tmp_path / "out" / "r.npy"), np.load(tmp_path / "clean.npy"))
    metrics = json.loads((tmp_path / "out" / "r.metrics.json").read_text())
    reused = [c["reconstruction"]["tiles_reused"] for c in metrics["captures"]]
    assert sum(reused) >= done - 2  # every tile finished before the kill is reused (two might have been mid-write)
    assert sorted(p.name for p in (tmp_path / "out").iterdir() if ".tmp-" in p.name) == []


@pytest.mark.parametrize("new_code", [False, True])
def test_the_still_path_is_exact_for_a_still_scene(tmp_path, capsys, new_code):
    """Nothing moves (a tripod on a still scene): every frame is coded / open count, exactly, with no sparse coding."""
    from codedvideo.engine.simulation import simulate_capture
    from codedvideo.model.codes import CodeSpec
    from codedvideo.data.synth import make_scene

    still = np.repeat(make_scene("default", frames=1, size=(H, W)), T * N, axis=0)
    cap = simulate_capture(still, code=CodeSpec("hitomi", bump=2), new_code_per_capture=new_code, sigma=0, seed=1,
                           captures=T)
    for name in ("coded", "mask", "truth"):
        np.save(tmp_path / f"{name}.npy", cap[name])
    _run(capsys, "reconstruct", "--coded", tmp_path / "coded.npy", "--mask", tmp_path / "mask.npy", "--output",
         tmp_path / "r.npy", "--cache", tmp_path / "cache", "--method", "dct", "--truth", tmp_path / "truth.npy")
    np.testing.assert_allclose(np.load(tmp_path / "r.npy"), still, atol=1e-3)

    def strict(name):
        raise AssertionError(f"{name} is not JSON")

    printed = json.loads(capsys.readouterr().out, parse_constant=strict)  # exact frames: null, not Infinity
    assert printed["psnr"] > 49.9  # (every frame near exact: each counted at the 50 dB ceiling or just under)
    metrics = json.loads((tmp_path / "r.metrics.json").read_text())
    assert all(e["reconstruction"]["still_pixels"] == H * W for e in metrics["captures"])
    assert all(e["reconstruction"]["patches"] == 0 for e in metrics["captures"])


def test_a_partly_still_sequence_leaves_the_still_part_out_and_gains(tmp_path, capsys):
    """70 % of the frame still: those pixels skip the dictionary search and are better than sparse coding them."""
    cap = tmp_path / "cap"
    _run(capsys, "simulate", "synth:default-static70", "--frames", N, "--size", 64, 96, "--captures", T, "--output", cap)
    psnr, still = {}, {}
    for flag in ([], ["--independent-captures"]):
        out = tmp_path / f"r{len(flag)}.npy"
        _run(capsys, "reconstruct", "--coded", cap / "coded.npy", "--mask", cap / "mask.npy", "--truth",
             cap / "truth.npy", "--method", "dct", "--output", out, "--cache", tmp_path / "cache", *flag)
        metrics = json.loads(out.with_name(out.stem + ".metrics.json").read_text())
        psnr[len(flag)] = metrics["quality"]["psnr"]
        still[len(flag)] = sum(e["reconstruction"]["still_pixels"] for e in metrics["captures"])
    assert still[1] == 0 and still[0] > 0.4 * T * 64 * 96
    assert psnr[0] > psnr[1]



def test_the_refinement_of_a_partly_still_sequence_works_on_what_moved(tmp_path, capsys):
    """``--refine`` on a stream: no group of the refinement is referenced where a patch holds only still pixels
    (their still answers are kept), so the 70 %-still scene's captures solve far fewer groups than the whole
    grid's, and the still pixels keep their still answers."""
    from codedvideo.solvers.refine import reference_grid

    cap = tmp_path / "cap"
    _run(capsys, "simulate", "synth:default-static70", "--frames", N, "--size", 64, 96, "--captures", T, "--output", cap)
    out = tmp_path / "r.npy"
    _run(capsys, "reconstruct", "--coded", cap / "coded.npy", "--mask", cap / "mask.npy", "--truth", cap / "truth.npy",
         "--method", "dct", "--refine", 4, "--output", out, "--cache", tmp_path / "cache")
    metrics = json.loads(out.with_name(out.stem + ".metrics.json").read_text())
    whole = reference_grid(N, 64, 96).size
    groups = [e["reconstruction"]["refine"]["groups"] for e in metrics["captures"]]
    assert all(0 < g < 0.6 * whole for g in groups), (groups, whole)

def test_a_tile_equal_to_one_already_solved_reuses_its_result(tmp_path):
    """Captures that differ in one corner only: the unchanged tiles are solved once for all captures (one task per
    distinct tile content), and every capture equals its reconstruction on its own, bit for bit."""
    from codedvideo.model.codes import make_code
    from codedvideo.solvers.dictionaries import dct_dictionary
    from codedvideo.model.physics import simulate
    from codedvideo.solvers.region import OmpSettings
    from codedvideo.engine.windows import reconstruct_volume, sparse_volumes
    from codedvideo.data.synth import make_scene

    frames = make_scene("default", frames=4, size=(48, 48))
    mask = make_code("hitomi", frames.shape[1:], frames=4, bump=2, rng=3)
    moved = frames.copy()
    moved[:, 40:, 40:] = np.roll(frames[:, 40:, 40:], 2, axis=0)  # something changes in the corner tile only
    codeds = [simulate(frames, mask), simulate(moved, mask), simulate(frames, mask) + np.float32(0)]
    D, s = dct_dictionary(4), OmpSettings(max_atoms=6, tol_rms=1.0)
    results = list(sparse_volumes(3, lambda i: (codeds[i], mask, None), D, settings=s,
                                  run=Execution(tile=16, cache=tmp_path / "job", progress=False)))
    tasks = results[0][2]["tile_tasks"]
    assert tasks < 2 * 9  # 9 tiles a capture; capture 1 shares all but the tiles near the corner, capture 2 all
    assert tasks > 9  # the changed corner was solved again
    for i, volume, info in results:
        alone, _ = reconstruct_volume(codeds[i], mask, D, settings=s,
                                      run=Execution(tile=16, cache=tmp_path / f"alone{i}", progress=False))
        np.testing.assert_array_equal(volume, alone)


def test_captures_are_handed_out_in_order_while_later_ones_still_compute(tmp_path):
    """One graph over (capture, tile), streamed: the first capture arrives before the last capture's tiles are done."""
    from codedvideo.model.codes import make_code
    from codedvideo.solvers.dictionaries import dct_dictionary
    from codedvideo.model.physics import simulate
    from codedvideo.solvers.region import OmpSettings
    from codedvideo.engine.windows import sparse_volumes
    from codedvideo.data.synth import make_scene

    video = make_scene("default", frames=4 * 6, size=(48, 48))
    mask = make_code("hitomi", video.shape[1:], frames=4, bump=2, rng=1)
    codeds = [simulate(video[4 * t : 4 * t + 4], mask, sigma=1.0, rng=t) for t in range(6)]

    def finished_tiles() -> int:  # digests are written last
        return sum(1 for p in (tmp_path / "c").glob("recon-*.zarr/digest/c/**/*") if p.is_file())

    seen = []
    for i, volume, _ in sparse_volumes(6, lambda i: (codeds[i], mask, None), dct_dictionary(4),
                                       settings=OmpSettings(max_atoms=6, tol_rms=0.5),
                                       run=Execution(tile=16, cache=tmp_path / "c", workers=1, progress=False)):
        seen.append((i, finished_tiles()))
    assert [i for i, _ in seen] == list(range(6))
    assert seen[0][1] < 6 * 9 // 2  # the first capture came out with most of the job still to compute


def test_a_stream_is_read_capture_by_capture_and_checked_before_any_work(sequence, tmp_path, capsys):
    """A (T, H, W) .npy is read one capture at a time (never whole); a NaN in any capture is a one-line error naming
    the file and the capture, before anything is written."""
    from codedvideo.formats.volumes import NpyStack, read_coded_stack

    coded = np.load(sequence / "cap" / "coded.npy")
    stack = read_coded_stack(sequence / "cap" / "coded.npy")
    assert isinstance(stack, NpyStack) and stack.shape == coded.shape and len(stack) == T
    for t in range(T):
        np.testing.assert_array_equal(stack[t], coded[t])
    bad = coded.copy()
    bad[2, 5, 7] = np.nan
    np.save(tmp_path / "bad.npy", bad)
    capsys.readouterr()
    assert main(["-q", "reconstruct", "--coded", str(tmp_path / "bad.npy"), "--mask", str(sequence / "cap" / "mask.npy"),
                 "--method", "dct", "--output", str(tmp_path / "r.npy"), "--cache", str(tmp_path / "c")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "bad.npy" in err and "capture 3" in err and "NaN" in err
    assert not (tmp_path / "r.npy").exists() and not (tmp_path / "c").exists()


def test_still_patches_give_the_same_bits_at_every_tile_size(tmp_path):
    """Patches wholly inside the still map take coded / open count; the pixels only they cover are that value
    exactly, whether their tile is wholly still (answered without patches) or not: tile sizes agree bit for bit."""
    from codedvideo.model.sequence import erode_to_patches, normalised
    from codedvideo.engine.windows import sparse_volumes

    coded, mask, still, D, s = partly_still_capture((64, 72), 40, seed=5)
    runs = {}
    for tile in (16, 24, 128):
        (_, volume, info), = sparse_volumes(1, lambda i: (coded, mask, still), D, settings=s,
                                            run=Execution(tile=tile, cache=tmp_path / f"t{tile}", progress=False))
        runs[tile] = volume
        assert info["patches_static"] >= 58 * 34  # every patch inside the still columns
    np.testing.assert_array_equal(runs[16], runs[128])
    np.testing.assert_array_equal(runs[24], runs[128])
    inner = erode_to_patches(still)
    q = normalised(coded, mask)[0]
    assert inner.sum() > 0
    np.testing.assert_array_equal(runs[128][:, inner], np.broadcast_to(q[inner], (4, int(inner.sum()))))


def test_a_streams_truth_is_read_capture_by_capture_with_the_same_figures(sequence, tmp_path, capsys):
    """A (T*N, H, W) .npy truth is read N frames at a time: the same figures as the same truth read whole (a
    multi-page TIFF); a NaN in it is a one-line error naming the file and the frame, before any work."""
    from codedvideo.formats.io import write_stack
    from codedvideo.formats.volumes import NpyStack, read_truth_stack

    cap = sequence / "cap"
    truth = np.load(cap / "truth.npy")
    stack = read_truth_stack(cap / "truth.npy", N)
    assert isinstance(stack, NpyStack)
    np.testing.assert_array_equal(stack[N : 2 * N], truth[N : 2 * N])
    write_stack(tmp_path / "truth.tif", truth)
    figures = []
    for name, path in (("a", cap / "truth.npy"), ("b", tmp_path / "truth.tif")):
        _run(capsys, "reconstruct", "--coded", cap / "coded.npy", "--mask", cap / "mask.npy", "--method", "dct",
             "--cache", tmp_path / "cache", "--truth", path, "--output", tmp_path / f"{name}.npy")
        quality = json.loads((tmp_path / f"{name}.metrics.json").read_text())["quality"]
        figures.append((quality["psnr_per_frame"], quality["boundaries"]["pairs"]))
    assert figures[0] == figures[1] and len(figures[0][0]) == T * N
    bad = truth.copy()
    bad[N + 1, 3, 3] = np.inf
    np.save(tmp_path / "bad.npy", bad)
    capsys.readouterr()
    assert main(["-q", "reconstruct", "--coded", str(cap / "coded.npy"), "--mask", str(cap / "mask.npy"), "--truth",
                 str(tmp_path / "bad.npy"), "--method", "dct", "--output", str(tmp_path / "r.npy"), "--cache",
                 str(tmp_path / "c")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "bad.npy" in err and f"frame {N + 2}" in err
    assert not (tmp_path / "r.npy").exists()


def test_a_folder_or_tiff_of_coded_images_is_read_capture_by_capture(sequence, tmp_path, capsys):
    """A camera's stream as a folder of float TIFF files (one capture each), or as one multi-page TIFF, is read
    one capture at a time and gives the video of the same stack as one .npy; a file of another size is a one-line
    error naming it, before any work."""
    from codedvideo.formats.io import write_image, write_stack
    from codedvideo.formats.volumes import ImageStack, read_coded_stack

    cap = sequence / "cap"
    coded = np.load(cap / "coded.npy")
    (tmp_path / "stream").mkdir()
    for t in range(T):
        write_image(tmp_path / "stream" / f"coded_{t + 1}.tif", coded[t])
    stack = read_coded_stack(tmp_path / "stream")
    assert isinstance(stack, ImageStack) and stack.shape == coded.shape
    np.testing.assert_array_equal(stack[T - 1], coded[T - 1])
    write_stack(tmp_path / "stream.tif", coded)  # a multi-page TIFF: a page a capture, read page by page
    pages = read_coded_stack(tmp_path / "stream.tif")
    assert isinstance(pages, ImageStack) and pages.shape == coded.shape
    np.testing.assert_array_equal(pages[1], coded[1])
    for name, source in (("folder", tmp_path / "stream"), ("pattern", tmp_path / "stream" / "coded_%d.tif"),
                         ("pages", tmp_path / "stream.tif"), ("npy", cap / "coded.npy")):
        _run(capsys, "reconstruct", "--coded", source, "--mask", cap / "mask.npy", "--method", "dct", "--cache",
             tmp_path / "cache", "--output", tmp_path / f"{name}.npy")
    np.testing.assert_array_equal(np.load(tmp_path / "folder.npy"), np.load(tmp_path / "npy.npy"))
    np.testing.assert_array_equal(np.load(tmp_path / "pattern.npy"), np.load(tmp_path / "npy.npy"))
    np.testing.assert_array_equal(np.load(tmp_path / "pages.npy"), np.load(tmp_path / "npy.npy"))
    write_image(tmp_path / "stream" / "coded_2.tif", coded[1, :-2])
    capsys.readouterr()
    assert main(["-q", "reconstruct", "--coded", str(tmp_path / "stream"), "--mask", str(cap / "mask.npy"),
                 "--method", "dct", "--output", str(tmp_path / "r.npy"), "--cache", str(tmp_path / "c")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "coded_2.tif" in err and f"{H - 2}x{W}" in err
    assert not (tmp_path / "r.npy").exists()


def test_a_lossless_video_of_coded_images_is_decoded_capture_by_capture(sequence, tmp_path, capsys):
    """A coded camera's FFV1 stream (a frame a capture) is decoded on demand, in any order a job asks for its
    captures, and gives the video of the same stack as a .npy."""
    from codedvideo.formats.io import write_video
    from codedvideo.formats.volumes import VideoStack, read_coded_stack

    cap = sequence / "cap"
    coded = np.rint(np.load(cap / "coded.npy") / 4).astype(np.float32)  # 8-bit frames: the FFV1 stream is exact
    np.save(tmp_path / "coded.npy", coded)
    write_video(tmp_path / "coded.mkv", coded, data_range=255.0)
    stack = read_coded_stack(tmp_path / "coded.mkv")
    assert isinstance(stack, VideoStack) and stack.shape == coded.shape
    stack.KEEP = 1  # only the last frame kept: every step back decodes afresh
    for i in (2, 0, 1, 2, 2, 1, 0):
        np.testing.assert_array_equal(stack[i], coded[i])
    for name in ("mkv", "npy"):
        _run(capsys, "reconstruct", "--coded", tmp_path / f"coded.{name}", "--mask", cap / "mask.npy", "--method",
             "dct", "--cache", tmp_path / "cache", "--data-range", 255, "--output", tmp_path / f"{name}.npy")
    np.testing.assert_array_equal(np.load(tmp_path / "mkv.npy"), np.load(tmp_path / "npy.npy"))


def test_evaluate_reads_long_videos_a_block_of_frames_at_a_time(tmp_path, capsys):
    """`codedvideo evaluate` on (T*N, H, W) .npy videos longer than a block compares them block by block: the same
    figures as the arrays in memory; a NaN in frame k of the reconstruction names the file and the frame."""
    from codedvideo.model.metrics import EVALUATE_BLOCK, evaluate
    from codedvideo.formats.volumes import NpyStack, read_truth_stack

    rng = np.random.default_rng(5)
    truth = rng.uniform(0, 255, (2 * EVALUATE_BLOCK + 3, 24, 20)).astype(np.float32)
    recon = (truth + rng.normal(0, 6, truth.shape)).astype(np.float32)
    np.save(tmp_path / "truth.npy", truth)
    np.save(tmp_path / "recon.npy", recon)
    lazy = read_truth_stack(tmp_path / "recon.npy", EVALUATE_BLOCK, what="reconstruction")
    assert isinstance(lazy, NpyStack)
    whole = evaluate(recon, truth, data_range=255.0)
    assert evaluate(lazy, read_truth_stack(tmp_path / "truth.npy", EVALUATE_BLOCK), data_range=255.0) == whole
    capsys.readouterr()
    assert main(["-q", "evaluate", "--recon", str(tmp_path / "recon.npy"), "--truth", str(tmp_path / "truth.npy"),
                 "--data-range", "255"]) == 0
    printed = json.loads(capsys.readouterr().out)
    assert printed["psnr_per_frame"] == whole["psnr_per_frame"] and printed["psnr"] == whole["psnr"]
    recon[EVALUATE_BLOCK + 1, 2, 2] = np.nan
    np.save(tmp_path / "recon.npy", recon)
    assert main(["-q", "evaluate", "--recon", str(tmp_path / "recon.npy"), "--truth", str(tmp_path / "truth.npy")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "recon.npy" in err and f"frame {EVALUATE_BLOCK + 2}" in err


@pytest.mark.parametrize("source", ["video.mkv", "frames"])
@pytest.mark.parametrize("new_code", [False, True])
def test_simulate_streams_a_video_file_capture_by_capture_with_the_same_files(tmp_path, capsys, source, new_code):
    """`simulate VIDEO --captures T` reads, codes and writes a video file (or a frame folder) capture by capture:
    the files equal a simulation of the whole clip at once, bit for bit."""
    from codedvideo.formats.io import write_frames, write_video
    from codedvideo.data.scenes import read_clip
    from codedvideo.engine.simulation import simulate_capture
    from codedvideo.model.codes import CodeSpec
    from codedvideo.data.synth import make_scene
    from codedvideo.formats.volumes import read_volume

    frames = np.rint(make_scene("default", frames=4 * N, size=(H + 4, W + 6)))
    write_video(tmp_path / "video.mkv", frames) if source == "video.mkv" else write_frames(tmp_path / "frames", frames)
    flags = ["--new-code-per-capture"] if new_code else []
    with pytest.warns(UserWarning, match=rf"make 3 captures of N = {N}; its last {N - 2} frames are left out"):
        _run(capsys, "simulate", tmp_path / source, "--frames", N, "--captures", "all", "--start", 2, "--size", H, W,
             "--noise-sigma", 2, "--seed", 7, *flags, "--output", tmp_path / "cap")
    whole = simulate_capture(read_clip(str(tmp_path / source), frames=3 * N, size=(H, W), start=2),
                             code=CodeSpec("hitomi", bump=2), new_code_per_capture=new_code, sigma=2.0, seed=7,
                             captures=3)
    for name in ("coded", "mask", "truth"):
        np.testing.assert_array_equal(np.load(tmp_path / "cap" / f"{name}.npy"), whole[name], err_msg=name)
    np.testing.assert_array_equal(read_volume(tmp_path / "cap" / "coded.tif"), whole["coded"])


def test_simulate_of_a_video_too_short_for_its_captures_leaves_nothing(tmp_path, capsys):
    """Found only once the stream runs out: a one-line error naming the video, and no output folder or file."""
    from codedvideo.formats.io import write_video
    from codedvideo.data.synth import make_scene

    write_video(tmp_path / "v.mkv", np.rint(make_scene("default", frames=2 * N + 1, size=(H, W))))
    capsys.readouterr()
    assert main(["-q", "simulate", str(tmp_path / "v.mkv"), "--frames", str(N), "--captures", "3", "--output",
                 str(tmp_path / "cap")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "v.mkv" in err and f"need {3 * N}" in err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["v.mkv"]


def test_a_job_of_more_captures_than_open_files_allows_runs(tmp_path):
    """A job holds one lock per capture's working store: with the soft limit on open files below the
    captures' count, the job raises it (up to the hard limit) and runs; where the hard limit is too low
    the error says so in one line, naming the cache."""
    import resource
    import subprocess
    import sys

    rng = np.random.default_rng(0)
    t = 90
    np.save(tmp_path / "coded.npy", rng.uniform(0, 255, (t, 8, 8)).astype(np.float32))
    np.save(tmp_path / "mask.npy", (rng.random((2, 8, 8)) < 0.5).astype(np.uint8))
    _, hard = resource.getrlimit(resource.RLIMIT_NOFILE)

    def run(soft, hard_limit, name):
        limit = (soft, hard_limit)
        return subprocess.run(
            [sys.executable, "-m", "codedvideo.app.cli", "-q", "reconstruct", "--coded", str(tmp_path / "coded.npy"),
             "--mask", str(tmp_path / "mask.npy"), "--method", "dct", "--independent-captures", "--output",
             str(tmp_path / f"{name}.npy"), "--cache", str(tmp_path / f"cache-{name}")],
            capture_output=True, text=True, preexec_fn=lambda: resource.setrlimit(resource.RLIMIT_NOFILE, limit))

    ok = run(64, hard, "ok")
    assert ok.returncode == 0, ok.stderr
    assert np.load(tmp_path / "ok.npy").shape == (t * 2, 8, 8)
    low = run(64, 64, "low")
    assert low.returncode != 0
    assert "open files" in low.stderr and "cache-low" in low.stderr
    assert "Traceback" not in low.stderr
    assert not (tmp_path / "low.npy").exists()


def test_a_capture_where_nothing_moves_fills_its_never_open_pixels(tmp_path, capsys):
    """Every measured pixel still: the capture is coded / open count without sparse coding, and pixels
    the code never opens take their nearest measured neighbour's value (not 0), counted in the metrics."""
    from codedvideo.data.synth import make_scene

    rng = np.random.default_rng(4)
    frame = make_scene("default", frames=1, size=(H, W))[0]
    mask = (rng.random((N, H, W)) < 0.5).astype(np.uint8)
    mask[:, 10, 12] = 0  # never open
    holes = ~mask.any(0)
    coded = np.stack([(mask * frame).sum(0)] * 2).astype(np.float32)
    np.save(tmp_path / "coded.npy", coded)
    np.save(tmp_path / "mask.npy", mask)
    _run(capsys, "reconstruct", "--coded", tmp_path / "coded.npy", "--mask", tmp_path / "mask.npy", "--output",
         tmp_path / "r.npy", "--cache", tmp_path / "cache", "--method", "dct")
    out = np.load(tmp_path / "r.npy").reshape(2, N, H, W)
    assert np.isfinite(out).all()
    assert np.abs(out[:, :, 10, 12] - frame[10, 12]).max() < 40  # a neighbour's value, not 0
    np.testing.assert_allclose(out[:, :, ~holes], np.broadcast_to(frame[~holes], (2, N, int((~holes).sum()))),
                               atol=1e-3)
    metrics = json.loads((tmp_path / "r.metrics.json").read_text())
    assert all(e["reconstruction"]["never_open_pixels"] == int(holes.sum()) for e in metrics["captures"])
    assert all(e["reconstruction"]["method"] == "static" for e in metrics["captures"])


def test_pixels_never_open_in_several_captures_are_one_warning(tmp_path, capsys):
    """A Bernoulli code new each capture leaves a few pixels of every capture never open: one warning for
    the job (it was one line per capture)."""
    import warnings

    from codedvideo.engine.simulation import simulate_capture
    from codedvideo.model.codes import CodeSpec
    from codedvideo.data.synth import make_scene

    video = make_scene("default", frames=4 * N, size=(H, W))
    cap = simulate_capture(video, code=CodeSpec("bernoulli", bump=2), new_code_per_capture=True, sigma=0, seed=2,
                           captures=4)
    closed = [int((~cap["mask"][t].any(0)).sum()) for t in range(4)]
    assert sum(c > 0 for c in closed) >= 2, closed
    for name in ("coded", "mask"):
        np.save(tmp_path / f"{name}.npy", cap[name])
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        _run(capsys, "reconstruct", "--coded", tmp_path / "coded.npy", "--mask", tmp_path / "mask.npy", "--output",
             tmp_path / "r.npy", "--cache", tmp_path / "cache", "--method", "dct", "--independent-captures")
    said = [str(w.message) for w in caught if "never open" in str(w.message)]
    assert len(said) == 1 and said[0].startswith(f"{sum(closed)} pixels are never open in"), said


def _window_job(tmp_path, monkeypatch, window_tiles, *, scheduler=None, name="w"):
    """Six 48x48 captures (9 tiles of 16 each), capture 3 equal to capture 2 and capture 5 to capture 0, done
    with windows of ``window_tiles`` tiles; the volumes, the open-file room asked for and what each planning of a
    capture saw finished."""
    from codedvideo.engine import locks, windows
    from codedvideo.model.codes import make_code
    from codedvideo.solvers.dictionaries import dct_dictionary
    from codedvideo.model.physics import simulate
    from codedvideo.solvers.region import OmpSettings
    from codedvideo.data.synth import make_scene

    video = make_scene("default", frames=4 * 6, size=(48, 48))
    mask = make_code("hitomi", video.shape[1:], frames=4, bump=2, rng=1)
    codeds = [simulate(video[4 * t : 4 * t + 4], mask, sigma=1.0, rng=t) for t in range(6)]
    codeds[3], codeds[5] = codeds[2], codeds[0]
    cache = tmp_path / name
    monkeypatch.setattr(windows, "WINDOW_TILES", window_tiles)
    asked, planned, solved = [], {}, []
    from codedvideo.engine import parallel

    tile_task = parallel._tile_task
    monkeypatch.setattr(parallel, "_tile_task", lambda *a: (solved.append(1), tile_task(*a))[1])
    allow = locks.allow_open_files
    monkeypatch.setattr(locks, "allow_open_files", lambda needed, c: (asked.append(needed), allow(needed, c)))

    def capture(i):
        if i not in planned:  # its first call plans it: how many tiles of the job were finished by then
            planned[i] = sum(1 for p in cache.glob("recon-*.zarr/digest/c/**/*") if p.is_file())
        return codeds[i], mask, None

    import tqdm.auto

    bars = []

    class Recording(tqdm.auto.tqdm):
        def close(self):
            if not self.disable:  # (a closed bar is disabled: its second close, on deletion, is not counted)
                bars.append((self.total, self.n))
            super().close()

    monkeypatch.setattr(tqdm.auto, "tqdm", Recording)
    out = list(windows.sparse_volumes(6, capture, dct_dictionary(4), settings=OmpSettings(max_atoms=6, tol_rms=0.5),
                                      run=Execution(tile=16, cache=cache, scheduler=scheduler, progress=True)))
    return out, asked, planned, len(solved), bars


def test_a_job_in_windows_equals_one_window_and_holds_a_few_windows_at_a_time(tmp_path, monkeypatch):
    """A long job is planned and computed a window of captures at a time: with a window of one capture the
    volumes are bit for bit those of one window over all six, the first tiles are finished before the last
    captures are planned, no more than two windows' working stores are locked at once (the one handed out and
    the next, planned while it runs), where one window locks all of them, and one progress bar ends full."""
    one, asked_one, planned_one, solved_one, _ = _window_job(tmp_path, monkeypatch, 10**6, name="one")
    small, asked, planned, solved, bars = _window_job(tmp_path, monkeypatch, 1, name="small")
    assert [i for i, _, _ in small] == list(range(6))
    for (_, a, _), (_, b, _) in zip(one, small):
        np.testing.assert_array_equal(a, b)
    assert planned_one[5] == 0  # one window: every capture planned before any tile
    assert planned[5] > 0
    # the room asked for before each new lock: four entries (captures 3 and 5 repeat 2 and 0) at once in one
    # window; one window's entry at a time beside the next one's in windows of one capture
    assert max(asked_one) - 65 == 3
    assert max(asked) - 65 <= 1
    # a capture equal to one of a window still held shares its store, and one equal to a capture done long
    # before finds its tiles in the cache: no tile is solved twice either way (4 distinct captures of 9 tiles)
    assert small[3][2]["work_store"] == small[2][2]["work_store"]
    assert solved == solved_one == 4 * 9
    # one bar for the job, its length estimated window by window, full at the end
    assert bars == [(36, 36)]


def test_a_job_never_waits_for_a_busy_entry_while_it_holds_another(tmp_path, monkeypatch):
    """Windows let go of their entries and take others later, so two runs could each hold what the other waits
    for (found in review: two runs of [A, B, A] hung for ever). Another run holds A and waits for B, which the
    job holds when it asks for A: the job puts A off until it holds nothing, and both finish."""
    import threading

    from codedvideo.engine import windows
    from codedvideo.engine.cache import RECON_VERSION, content_key
    from codedvideo.model.codes import make_code
    from codedvideo.solvers.dictionaries import dct_dictionary
    from codedvideo.model.physics import simulate
    from codedvideo.solvers.region import OmpSettings
    from codedvideo.formats.store import entry_lock
    from codedvideo.data.synth import make_scene

    monkeypatch.setattr(windows, "WINDOW_TILES", 1)
    video = make_scene("default", frames=8, size=(48, 48))
    mask = make_code("hitomi", video.shape[1:], frames=4, bump=2, rng=1)
    codeds = [simulate(video[4 * t : 4 * t + 4], mask, sigma=1.0, rng=t) for t in range(2)]
    D, s, cache = dct_dictionary(4), OmpSettings(max_atoms=6, tol_rms=2.0), tmp_path / "c"
    entry = [cache.absolute() / f"recon-{content_key(RECON_VERSION, c, mask, content_key(D), s.__dict__, 16)}.zarr"
             for c in codeds]  # B (capture 0) and A (capture 1)
    holds_a, job_holds_b, other_done = threading.Event(), threading.Event(), threading.Event()

    def other_run():
        with entry_lock(entry[1]):  # A
            holds_a.set()
            job_holds_b.wait(60)
            with entry_lock(entry[0]):  # B: waits until the job lets go of it
                pass
        other_done.set()

    planned = set()

    def capture(i):
        if i == 1 and i not in planned:  # the job asks for A: it holds B by now
            job_holds_b.set()
        planned.add(i)
        return codeds[i], mask, None

    out = []
    other = threading.Thread(target=other_run, daemon=True)
    other.start()
    assert holds_a.wait(60)
    job = threading.Thread(target=lambda: out.extend(windows.sparse_volumes(2, capture, D, settings=s,
                                                                            run=Execution(tile=16, cache=cache, progress=False))),
                           daemon=True)
    job.start()
    job.join(120)
    assert not job.is_alive() and other_done.is_set(), "the job and the other run waited for each other"
    assert [i for i, _, _ in out] == [0, 1]


def test_heavy_read_noise_leaves_the_sequence_no_worse_than_its_captures_one_by_one(tmp_path, capsys):
    """At sigma 40 the still answer coded / open count is noisier than OMP's estimate and a second capture cannot
    tell slow motion from noise: no pixel is taken as still, so the job is no worse than capture by capture,
    overall and on the moving part (it lost 4 dB overall and 3 dB there when the still answer was taken)."""
    from codedvideo.model.metrics import evaluate

    cap, w = tmp_path / "cap", 96
    _run(capsys, "simulate", "synth:default-static70", "--frames", 8, "--size", 64, w, "--captures", T,
         "--noise-sigma", 40, "--output", cap)
    truth, psnr, still = np.load(cap / "truth.npy"), {}, {}
    moving = slice(int(0.7 * w), None)
    for flag in ([], ["--independent-captures"]):
        out = tmp_path / f"r{len(flag)}.npy"
        _run(capsys, "reconstruct", "--coded", cap / "coded.npy", "--mask", cap / "mask.npy", "--noise-sigma", 40,
             "--output", out, "--cache", tmp_path / "cache", *flag)
        recon = np.load(out)
        psnr[len(flag)] = (evaluate(recon, truth, data_range=255.0)["psnr"], evaluate(recon[..., moving], truth[..., moving], data_range=255.0)["psnr"])
        metrics = json.loads(out.with_name(out.stem + ".metrics.json").read_text())
        still[len(flag)] = sum(e["reconstruction"]["still_pixels"] for e in metrics["captures"])
    assert still[0] == 0
    assert psnr[0][0] >= psnr[1][0] and psnr[0][1] >= psnr[1][1] - 0.1


def test_a_pixel_is_still_only_where_its_still_answer_is_quiet_enough():
    """sigma / open count above STILL_NOISE_MAX: never still; below it a still scene agrees (with a changing code)."""
    from codedvideo.model.sequence import STILL_NOISE_MAX, agreeing_pixels
    from codedvideo.engine.simulation import simulate_capture
    from codedvideo.model.codes import CodeSpec
    from codedvideo.data.synth import make_scene

    still = np.repeat(make_scene("default", frames=1, size=(H, W)), T * 8, axis=0)
    for bump in (2, 3):
        cap = simulate_capture(still, code=CodeSpec("hitomi", bump=bump), new_code_per_capture=True, sigma=0, seed=1,
                               captures=T)
        mask_of = lambda j: cap["mask"][j]  # noqa: E731
        quiet = agreeing_pixels(cap["coded"], mask_of, 1, sigma=STILL_NOISE_MAX * bump)
        loud = agreeing_pixels(cap["coded"], mask_of, 1, sigma=STILL_NOISE_MAX * bump * 1.01)
        assert quiet.mean() > 0.3 and not loud.any()  # (flat regions are left to the single-capture test)


def test_the_still_answer_averages_the_captures_it_agrees_with_and_leaves_the_moving_patches_alone(
        tmp_path, capsys, monkeypatch):
    """Under read noise the still answer is coded / open count averaged over the captures a pixel agrees with:
    less noise than the capture's own value where only still patches cover a pixel, and the very same bits
    wherever a patch that moves does (N = 3: no join)."""
    from codedvideo.model import sequence
    from codedvideo.model.sequence import erode_to_patches, normalised

    cap, n, sigma = tmp_path / "cap", 3, 2
    _run(capsys, "simulate", "synth:default-static70", "--frames", n, "--size", 64, 96, "--captures", T,
         "--noise-sigma", sigma, "--output", cap)
    args = ["reconstruct", "--coded", cap / "coded.npy", "--mask", cap / "mask.npy", "--noise-sigma", sigma, "--method",
            "dct", "--cache", tmp_path / "cache"]
    _run(capsys, *args, "--output", tmp_path / "mean.npy")
    averaged = sequence.still_values

    def own(codeds, masks, i, **options):  # the same still pixels, each with its capture's own value
        values = averaged(codeds, masks, i, **options)
        scale = np.float32(options.get("scale", 1.0))
        return np.where(np.isfinite(values), normalised(codeds[i], masks(i))[0] * scale, np.nan)

    monkeypatch.setattr(sequence, "still_values", own)
    _run(capsys, *args, "--output", tmp_path / "own.npy")
    coded, mask, truth = (np.load(cap / f"{k}.npy") for k in ("coded", "mask", "truth"))
    inner = np.concatenate([np.repeat(erode_to_patches(sequence.agreeing_pixels(coded, lambda j: mask, i, sigma=sigma))[None],
                                      n, axis=0) for i in range(T)])
    mean, mine = np.load(tmp_path / "mean.npy"), np.load(tmp_path / "own.npy")
    assert inner.mean() > 0.2
    np.testing.assert_array_equal(mean[~inner], mine[~inner])
    rms = lambda v: float(np.sqrt(np.mean((v[inner] - truth[inner]) ** 2)))  # noqa: E731
    assert rms(mean) < 0.8 * rms(mine)
    # the metrics' measurement residual is each capture's own, not that of the averaged values it was given
    reported = [e["reconstruction"]["measurement_residual_rms"]
                for e in json.loads((tmp_path / "mean.metrics.json").read_text())["captures"]]
    own_residual = [float(np.sqrt(np.mean(((mean[i * n:(i + 1) * n] * mask).sum(0) - coded[i]) ** 2))) for i in range(T)]
    np.testing.assert_allclose(reported, own_residual, rtol=1e-4)


def test_a_clipped_neighbour_is_never_averaged_into_a_still_answer():
    """--white-level: where the capture after (a longer exposure) is clipped, its value does not pull the still
    answer down (it did, by 3 grey levels on a half-saturated neighbour); the capture before still counts."""
    from codedvideo.model.sequence import still_values
    from codedvideo.engine.simulation import simulate_capture
    from codedvideo.model.codes import CodeSpec
    from codedvideo.data.synth import make_scene

    still = np.repeat(make_scene("default", frames=1, size=(H, W)), T * 8, axis=0)
    short = simulate_capture(still, code=CodeSpec("hitomi", bump=2), sigma=5, seed=1, captures=T)
    long = simulate_capture(still, code=CodeSpec("hitomi", bump=4), sigma=5, seed=2, captures=T)
    codeds, masks = short["coded"].copy(), [short["mask"], short["mask"], long["mask"]]
    white = float(np.percentile(codeds[1], 90))
    codeds[2] = np.minimum(long["coded"][2], white)
    clipped = (codeds[2] >= white) & (codeds[:2] < white).all(0)  # the long exposure clipped, the short ones not
    assert 0.05 < clipped.mean() < 0.95
    with_white = still_values(codeds, masks.__getitem__, 1, sigma=5, white_level=white)
    before_only = still_values(codeds[:2], masks.__getitem__, 1, sigma=5)
    np.testing.assert_array_equal(with_white[clipped], before_only[clipped])
    pulled = still_values(codeds, masks.__getitem__, 1, sigma=5)  # without the white level: averaged in
    assert (pulled[clipped] < before_only[clipped] - 1).sum() > 10


def test_reconstruct_capture_refuses_a_map_of_still_pixels_for_still_values():
    """A bool map where still values are asked would make every pixel still (its 0s and 1s the answer)."""
    from codedvideo.engine.captures import reconstruct_capture

    coded, mask = np.ones((16, 16), np.float32), np.ones((4, 16, 16), np.uint8)
    with pytest.raises(TypeError, match="still values"):
        reconstruct_capture(capture_settings("omp", data_range=None, settings=None), coded, mask,
                            still=np.ones((16, 16), bool))


def test_a_flat_still_background_under_noise_is_no_worse_than_its_captures_one_by_one(tmp_path, capsys):
    """A plain still background at sigma 5: the still answer keeps the noise that the single-capture still test
    removes, so flat regions are left to that test (the background was 10 dB worse than capture by capture)."""
    from codedvideo.model.metrics import evaluate
    from codedvideo.engine.simulation import simulate_capture
    from codedvideo.model.codes import CodeSpec
    from codedvideo.data.synth import make_scene

    video = np.full((T * 8, 48, 64), 100.0, np.float32)
    video[..., 40:] = make_scene("default", frames=T * 8, size=(48, 24))  # something moves on the right
    cap = simulate_capture(video, code=CodeSpec("hitomi", bump=2), sigma=5, seed=0, captures=T)
    for name in ("coded", "mask"):
        np.save(tmp_path / f"{name}.npy", cap[name])
    flat, psnr = (..., slice(0, 28)), {}
    for flag in ([], ["--independent-captures"]):
        out = tmp_path / f"r{len(flag)}.npy"
        _run(capsys, "reconstruct", "--coded", tmp_path / "coded.npy", "--mask", tmp_path / "mask.npy",
             "--noise-sigma", 5, "--data-range", 255, "--output", out, "--cache", tmp_path / "cache", *flag)
        recon = np.load(out)
        psnr[len(flag)] = (evaluate(recon, video, data_range=255.0)["psnr"], evaluate(recon[flat], video[flat], data_range=255.0)["psnr"])
    assert psnr[0][0] >= psnr[1][0] and psnr[0][1] >= psnr[1][1] - 0.5


def test_a_clipped_capture_does_not_pull_its_neighbours_through_the_join(tmp_path, capsys):
    """A still bright scene whose third capture (a longer bump) is half clipped at --white-level: the join drew
    the captures beside it toward its frames (2.7 and 2.4 grey levels RMS against 0.64 capture by capture); now
    pixels clipped in either capture keep both captures' values."""
    from codedvideo.model.codes import make_code

    n, size, white = 8, 48, 500.0
    rng = np.random.default_rng(1)
    scene = (172 + rng.uniform(-1, 1, (size, size))).astype(np.float32)
    scene[:, size // 2:] -= 72
    masks = np.stack([make_code("hitomi", (size, size), frames=n, bump=b, rng=1) for b in (2, 2, 3, 2)])
    coded = np.stack([np.minimum(m.sum(0) * scene + rng.normal(0, 5, scene.shape), white) for m in masks])
    np.save(tmp_path / "coded.npy", coded.astype(np.float32))
    np.save(tmp_path / "mask.npy", masks.astype(np.uint8))
    assert 0.3 < (coded[2] >= white).mean() < 0.7 and (coded[[0, 1, 3]] < white).all()
    errors = {}
    for flag in ([], ["--independent-captures"]):
        out = tmp_path / f"r{len(flag)}.npy"
        _run(capsys, "reconstruct", "--coded", tmp_path / "coded.npy", "--mask", tmp_path / "mask.npy", "--noise-sigma",
             5, "--white-level", white, "--data-range", 255, "--output", out, "--cache", tmp_path / "cache", *flag)
        recon = np.load(out).reshape(4, n, size, size)[..., 8 : size // 2 - 8]  # the bright half
        errors[len(flag)] = np.sqrt(((recon - scene[:, 8 : size // 2 - 8]) ** 2).mean(axis=(1, 2, 3)))
    for i in (1, 3):  # beside the clipped capture
        assert errors[0][i] <= 1.5 * errors[1][i], (i, errors)
