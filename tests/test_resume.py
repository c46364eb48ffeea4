"""Nothing lost: atomic outputs, runs killed with SIGKILL resume from their finished tiles, same seed same result."""
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import zarr

from codedvideo.formats import io as cio
from codedvideo.model.codes import CODE_NAMES, CodeSpec, make_code
from codedvideo.solvers.dictionaries import KsvdSettings, dct_dictionary, learn_dictionary
from codedvideo.model.physics import simulate
from codedvideo.engine.simulation import simulate_capture
from codedvideo.engine.windows import Execution, reconstruct_volume
from codedvideo.formats.volumes import write_capture, write_volume
from codedvideo.solvers.region import OmpSettings
from codedvideo.formats.store import WorkStore, save_dictionary
from codedvideo.data.synth import make_scene

CLI = [sys.executable, "-m", "codedvideo.app.cli", "-q"]


# ----------------------------------------------------------------------------- every writer is atomic
@pytest.fixture
def frames():
    yy, xx = np.mgrid[0:16, 0:18]
    return np.stack([128 + 60 * np.sin((xx + 2 * t) / 5.0) * np.cos(yy / 7.0) for t in range(4)]).astype(np.float32)


WRITERS = ["v.npy", "v.zarr", "v.mat", "v.tif", "v.mkv", "v.gif", "v.mp4", "frames", "capture", "dict.zarr", "m.json"]


def _write(name, target, frames):
    from codedvideo.formats.volumes import write_json

    if name == "capture":
        write_capture(dict(coded=frames[0], mask=(frames > 128).astype(np.uint8), truth=frames), target)
    elif name == "dict.zarr":
        save_dictionary(target, dct_dictionary(1), dict(patch=7, frames=1))
    elif name == "m.json":
        write_json(target, dict(a=1))
    else:
        write_volume(frames, target)


@pytest.mark.parametrize("name", WRITERS)
def test_every_writer_renames_a_finished_temporary_into_place(tmp_path, monkeypatch, frames, name):
    """Each output appears only by a rename of a hidden temporary sibling; a failed rename leaves no trace."""
    renames = []
    real = os.replace

    def spy(src, dst):
        renames.append((Path(src), Path(dst)))
        return real(src, dst)

    monkeypatch.setattr(os, "replace", spy)
    target = tmp_path / name
    _write(name, target, frames)
    outputs = [target] if name != "capture" else [target / f for f in ("coded.npy", "mask.npy", "truth.npy", "coded.tif")]
    for out in outputs:
        hits = [src for src, dst in renames if dst == out]
        assert hits and all(src.name.startswith(".") and src.parent == out.parent for src in hits), (out, renames)
    # the same write failing at its final rename: no output, no temporary left behind
    fail_dir = tmp_path / "fail"
    fail_dir.mkdir()

    def broken(src, dst):
        raise OSError(5, "Input/output error")

    monkeypatch.setattr(os, "replace", broken)
    with pytest.raises(OSError):
        _write(name, fail_dir / name, frames)
    left = [p for p in fail_dir.rglob("*") if not (name == "capture" and p == fail_dir / "capture")]
    assert left == [], left


@pytest.mark.parametrize("name", [w for w in WRITERS if w != "capture"])
def test_a_killed_writers_temporary_is_removed_by_the_next_write(tmp_path, frames, name):
    """SIGKILL leaves the hidden temporary; the next write of that output removes it (a .zarr's was never)."""
    target = tmp_path / name
    stem, suffix = (target.name.split(".", 1)[0], "." + target.name.split(".", 1)[1]) if "." in name else (name, "")
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    left = [tmp_path / f".{stem}.tmp-{int(dead.stdout)}-0123abcd{suffix}",  # atomic_output's name
            tmp_path / f".{name}.tmp-{int(dead.stdout)}-4567cdef"]  # the Zarr stores' name
    for tmp in left:
        tmp.mkdir()
        (tmp / "chunk").write_bytes(b"partial")
    _write(name, target, frames)
    assert target.exists() and not any(tmp.exists() for tmp in left)


def test_no_module_writes_files_outside_the_atomic_writers():
    """Static check: every file write in the package sits inside a ``with ...atomic_output(...)`` block.

    store.py is exempt (whole stores: temporary folder + rename; working stores: tile by tile, resumable),
    and so are writes to in-memory buffers.
    """
    import ast

    import codedvideo

    writes = {"write_text", "write_bytes", "savemat", "save", "savez", "tofile", "savefig", "imwrite"}
    known: set[tuple[str, str]] = set()  # (file name, call) allowed outside atomic_output: none now
    offenders = []
    for path in sorted(Path(codedvideo.__file__).parent.rglob("*.py")):
        if path.name == "store.py":
            continue
        tree = ast.parse(path.read_text())
        parents = {child: node for node in ast.walk(tree) for child in ast.iter_child_nodes(node)}

        def inside_atomic(node):
            while node in parents:
                node = parents[node]
                if isinstance(node, ast.With) and any(
                        isinstance(i.context_expr, ast.Call)
                        and getattr(i.context_expr.func, "attr", getattr(i.context_expr.func, "id", "")) == "atomic_output"
                        for i in node.items):
                    return True
            return False

        for node in ast.walk(tree):
            if not isinstance(node, ast.Call):
                continue
            name = getattr(node.func, "attr", getattr(node.func, "id", ""))
            opens_for_writing = name == "open" and any(
                isinstance(a, ast.Constant) and isinstance(a.value, str) and a.value[:1] in "wax" for a in node.args[1:2])
            if name == "open" and isinstance(node.func, ast.Attribute) and node.func.value.__class__ is ast.Name \
                    and node.func.value.id == "av":
                opens_for_writing = any(k.arg == "mode" and getattr(k.value, "value", "") == "w" for k in node.keywords)
            to_buffer = node.args and isinstance(node.args[0], ast.Name) and node.args[0].id in ("buf", "fh")
            if (name in writes or opens_for_writing) and not to_buffer and not inside_atomic(node) \
                    and (path.name, name) not in known:
                offenders.append(f"{path.name}:{node.lineno} {name}")
    assert offenders == [], offenders


# ----------------------------------------------------------------------------- SIGKILL and resume
def _finished_tiles(cache: Path) -> int:
    """Tiles a rerun may reuse: those whose digest (written last, after the volume and the stats) exists."""
    for store in cache.glob("recon-*.zarr"):
        try:
            digest = zarr.open_group(str(store), mode="r")["digest"][:]
            return int((digest != 0).any(1).sum())
        except Exception:  # not created yet
            return 0
    return 0


@pytest.fixture(scope="module")
def big_capture(tmp_path_factory):
    d = tmp_path_factory.mktemp("big")
    video = make_scene("default", frames=8, size=(96, 128))
    mask = make_code("hitomi", (96, 128), frames=8, bump=2, rng=1)
    np.save(d / "coded.npy", simulate(video, mask, sigma=2.0, rng=1))
    np.save(d / "mask.npy", mask)
    save_dictionary(d / "d.zarr", dct_dictionary(8), dict(patch=7, frames=8))
    return d


def _reconstruct(d, out, cache, workers):
    return [*CLI, "reconstruct", "--coded", str(d / "coded.npy"), "--mask", str(d / "mask.npy"), "--dictionary",
            str(d / "d.zarr"), "--output", str(out), "--cache", str(cache), "--tile", "8", "--workers", str(workers),
            "--tol-rms", "0.5", "--static-atoms", "0"]


@pytest.mark.slow
def test_sigkill_midway_then_rerun_resumes_and_equals_a_clean_run(big_capture, tmp_path):
    d = big_capture
    cache = tmp_path / "cache"
    out = tmp_path / "out" / "r.npy"
    proc = subprocess.Popen(_reconstruct(d, out, cache, workers=1), stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    t0, done = time.monotonic(), 0
    try:
        while proc.poll() is None and time.monotonic() - t0 < 120:
            done = _finished_tiles(cache)
            if done >= 12:
                break
            time.sleep(0.02)
        assert proc.poll() is None, "the run finished before it could be killed; make the scene larger"
        os.kill(proc.pid, signal.SIGKILL)
    finally:
        proc.wait()
    assert proc.returncode == -signal.SIGKILL
    assert not out.exists() and not (tmp_path / "out" / "r.metrics.json").exists()  # nothing half-written
    killed_with = _finished_tiles(cache)
    assert 12 <= killed_with < 192
    rerun = subprocess.run(_reconstruct(d, out, cache, workers=2), capture_output=True, text=True, timeout=300)
    assert rerun.returncode == 0, rerun.stderr
    clean_out = tmp_path / "clean" / "r.npy"
    clean = subprocess.run(_reconstruct(d, clean_out, tmp_path / "cache2", workers=2), capture_output=True, text=True,
                           timeout=300)
    assert clean.returncode == 0, clean.stderr
    np.testing.assert_array_equal(np.load(out), np.load(clean_out))  # bit for bit
    rec = json.loads((tmp_path / "out" / "r.metrics.json").read_text())["reconstruction"]
    assert rec["tiles"] == 192 and rec["tiles_reused"] >= killed_with
    assert rec["tiles_computed"] + rec["tiles_reused"] == rec["tiles"]
    # no temporaries; the hidden records say that codedvideo wrote the two outputs (codedvideo.formats.outputs)
    assert sorted(p.name for p in out.parent.iterdir()) == [".r.metrics.json.codedvideo", ".r.npy.codedvideo",
                                                             "r.metrics.json", "r.npy"]


@pytest.mark.slow
def test_sigterm_midway_leaves_no_partial_output_and_says_so(tmp_path):
    """``kill``, ``timeout`` or a batch scheduler stop a run with SIGTERM: it unwinds as Ctrl-C does."""
    video = make_scene("default", frames=8 * 8, size=(48, 64))
    mask = make_code("hitomi", (48, 64), frames=8, bump=2, rng=1)
    coded = np.stack([simulate(video[8 * t:8 * t + 8], mask, sigma=2.0, rng=t) for t in range(8)])
    np.save(tmp_path / "coded.npy", coded)
    np.save(tmp_path / "mask.npy", mask)
    save_dictionary(tmp_path / "d.zarr", dct_dictionary(8), dict(patch=7, frames=8))
    out = tmp_path / "out" / "r.npy"
    proc = subprocess.Popen([*CLI, "reconstruct", "--coded", str(tmp_path / "coded.npy"), "--mask",
                             str(tmp_path / "mask.npy"), "--dictionary", str(tmp_path / "d.zarr"), "--output", str(out),
                             "--cache", str(tmp_path / "cache"), "--tile", "8", "--workers", "1", "--static-atoms", "0",
                             "--independent-captures"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    t0 = time.monotonic()
    try:  # the stream's temporary exists from the first capture written to the last
        while proc.poll() is None and time.monotonic() - t0 < 120 and not list(out.parent.glob(".r.tmp-*")):
            time.sleep(0.01)
        assert proc.poll() is None, "the run finished before it could be stopped; make the sequence longer"
        os.kill(proc.pid, signal.SIGTERM)
        _, err = proc.communicate(timeout=60)
    finally:
        proc.kill()
        proc.wait()
    assert proc.returncode == 128 + signal.SIGTERM
    assert err.strip().splitlines()[-1] == "codedvideo: terminated"
    assert not out.parent.exists()  # no temporary, no output, no metrics, and not the folder the run made for them


@pytest.fixture(scope="module")
def small():
    video = make_scene("default", frames=4, size=(32, 40))
    mask = make_code("hitomi", (32, 40), frames=4, bump=2, rng=1)
    return simulate(video, mask, sigma=2.0, rng=3), mask, dct_dictionary(4)


@pytest.mark.parametrize("method", ["omp", "nonlocal"])
def test_a_tile_killed_between_its_volume_and_its_statistics_is_recomputed(small, tmp_path, method):
    """The volume chunk was written (here: garbage), the statistics row not: only that tile runs again,
    with the same bits.  (The non-local method's tiles stand on stages that are not stored -- first
    estimates, blocks of groups -- and the rerun computes them again for that one tile.)"""
    import dataclasses

    coded, mask, D = small
    s = dataclasses.replace(OmpSettings(max_atoms=6, tol_rms=2.0), method=method)
    ref, info = reconstruct_volume(coded, mask, D, settings=s, run=Execution(tile=16, cache=tmp_path, progress=False))
    store = WorkStore(info["work_store"])
    store.group["volume"][:, 16:32, 0:16] = 1e30  # tile 3's core, as if half-done
    store.group["stats"][3:4, :] = np.nan
    again, info2 = reconstruct_volume(coded, mask, D, settings=s,
                                      run=Execution(tile=16, cache=tmp_path, progress=False))
    assert info2["tiles_computed"] == 1 and info2["tiles_reused"] == info2["tiles"] - 1
    np.testing.assert_array_equal(again, ref)


def test_a_store_killed_while_being_created_is_rebuilt(small, tmp_path):
    coded, mask, D = small
    s = OmpSettings(max_atoms=6, tol_rms=2.0)
    ref, info = reconstruct_volume(coded, mask, D, settings=s, run=Execution(tile=16, cache=tmp_path, progress=False))
    group = zarr.open_group(info["work_store"], mode="r+")
    del group.attrs["complete_inputs"]  # the last step of creation never happened
    group["coded"][:] = 0  # and its inputs are incomplete
    again, info2 = reconstruct_volume(coded, mask, D, settings=s,
                                      run=Execution(tile=16, cache=tmp_path, progress=False))
    assert info2["tiles_computed"] == info2["tiles"]
    np.testing.assert_array_equal(again, ref)


# ----------------------------------------------------------------------------- same seed, same result
def test_codes_and_captures_are_functions_of_the_seed(tmp_path):
    video = make_scene("default", frames=4, size=(21, 23))
    np.save(tmp_path / "m.npy", make_code("hitomi", (21, 23), frames=4, bump=2, rng=0))
    for name in (n for n in CODE_NAMES if n != "file"):  # (a code file is read, not made)
        kw = dict(frames=4, bump=2)
        a, b = make_code(name, (21, 23), rng=7, **kw), make_code(name, (21, 23), rng=7, **kw)
        np.testing.assert_array_equal(a, b)
        if name in ("hitomi", "hitomi-tiled", "rowwise", "bernoulli", "shifting"):
            assert not np.array_equal(a, make_code(name, (21, 23), rng=8, **kw)), name
    c1 = simulate_capture(video, code=CodeSpec("hitomi", bump=2), sigma=5.0, seed=3)
    c2 = simulate_capture(video, code=CodeSpec("hitomi", bump=2), sigma=5.0, seed=3)
    for key in ("coded", "mask", "truth"):
        np.testing.assert_array_equal(c1[key], c2[key])
    other = simulate_capture(video, code=CodeSpec("hitomi", bump=2), sigma=5.0, seed=4)
    assert not np.array_equal(c1["coded"], other["coded"])


def test_ksvd_dictionaries_are_functions_of_the_seed():
    videos = [make_scene("default", frames=6, size=(24, 24), seed=s) for s in (0, 1)]
    kw = dict(frames=4, settings=KsvdSettings(atoms=60, samples=400, iterations=2, sparsity=3))
    D1, m1 = learn_dictionary(videos, seed=5, **kw)
    D2, m2 = learn_dictionary(videos, seed=5, **kw)
    np.testing.assert_array_equal(D1, D2)
    assert m1["rmse_history"] == m2["rmse_history"]
    assert not np.array_equal(D1, learn_dictionary(videos, seed=6, **kw)[0])


@pytest.fixture(scope="module")
def moving():
    video = make_scene("default", frames=8, size=(40, 52))
    mask = make_code("hitomi", (40, 52), frames=8, bump=2, rng=1)
    return simulate(video, mask, sigma=3.0, rng=2), mask, dct_dictionary(8)


def _volumes(moving, tmp_path, settings, runs):
    coded, mask, D = moving
    out = {}
    for i, (tile, kw) in enumerate(runs):
        run = Execution(tile=tile, cache=tmp_path / str(i), progress=False, **kw)
        out[(i, tile, tuple(kw.items()))] = reconstruct_volume(coded, mask, D, settings=settings, run=run)[0]
    return out


def test_same_result_across_runs_workers_and_schedulers(moving, tmp_path):
    """Default settings (still-scene test on): bit for bit across runs, 1 or 2 worker threads and the sync scheduler."""
    vols = _volumes(moving, tmp_path, OmpSettings(max_atoms=8, tol_rms=3.0),
                    [(16, dict(workers=1)), (16, dict(workers=2)), (16, dict(scheduler="sync")), (16, dict(workers=2))])
    assert len(vols) == 4  # the repeated run is compared too, not overwritten by it
    ref = next(iter(vols.values()))
    for key, vol in vols.items():
        np.testing.assert_array_equal(vol, ref, err_msg=str(key))


def test_same_result_across_tile_sizes_without_the_still_test(moving, tmp_path):
    """Full OMP on every patch: bit for bit across tile sizes 8, 13, 16 and the whole image, 1 and 2 workers."""
    vols = _volumes(moving, tmp_path, OmpSettings(max_atoms=8, tol_rms=0.5, static_atoms=0),
                    [(t, dict(workers=w)) for t in (8, 13, 16, 52) for w in (1, 2)])
    ref = next(iter(vols.values()))
    for key, vol in vols.items():
        np.testing.assert_array_equal(vol, ref, err_msg=str(key))


def test_same_result_across_tile_sizes_with_the_still_test(moving, tmp_path):
    vols = _volumes(moving, tmp_path, OmpSettings(max_atoms=8, tol_rms=3.0),
                    [(t, dict(workers=1)) for t in (8, 13, 16, 52)])
    ref = next(iter(vols.values()))
    for key, vol in vols.items():
        np.testing.assert_array_equal(vol, ref, err_msg=str(key))
