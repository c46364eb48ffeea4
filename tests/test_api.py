"""The Python API (codedvideo.api): the command line's answers on arrays, in the caller's units, lazily on dask,
with nothing left on disk unless a cache is asked for."""
import json
import subprocess
import sys
import tempfile

import numpy as np
import pytest

import codedvideo as cv
from codedvideo.app.cli import main
from codedvideo.data.footage import footage_scene

N, SIZE = 8, 48


@pytest.fixture(scope="module")
def footage01():
    """Held-out real footage (carphone) in [0, 1] floats: 3 captures of N = 8, each with its own code."""
    video = footage_scene("carphone", frames=3 * N, size=(SIZE, SIZE)) / np.float32(255)
    masks = np.stack([cv.make_code("hitomi", (SIZE, SIZE), frames=N, bump=2, seed=s) for s in range(3)])
    coded = cv.simulate(video, masks, seed=1)
    return video.astype(np.float32), masks, coded


def _cli(tmp_path, capsys, coded, mask, truth, *extra, name="rec.npy"):
    for label, arr in (("coded", coded), ("mask", mask), ("truth", truth)):
        np.save(tmp_path / f"{label}.npy", arr)
    capsys.readouterr()
    rc = main(["-q", "reconstruct", "--coded", str(tmp_path / "coded.npy"), "--mask", str(tmp_path / "mask.npy"),
               "--truth", str(tmp_path / "truth.npy"), "--output", str(tmp_path / name), "--cache",
               str(tmp_path / "cache"), *extra])
    assert rc == 0, capsys.readouterr().err
    return np.load(tmp_path / name), json.loads((tmp_path / name.replace(".npy", ".metrics.json")).read_text())


def test_one_capture_the_api_gives_the_cli_answer_bit_for_bit(tmp_path, capsys, footage01):
    video, masks, coded = footage01
    by_cli, metrics = _cli(tmp_path, capsys, coded[0], masks[0], video[:N])
    got = cv.reconstruct(coded[0], masks[0], full_output=True)
    np.testing.assert_array_equal(got.frames, by_cli)
    assert got.data_range.value == metrics["data_range"]["value"] == 1.0  # [0, 1] floats found as such
    score = cv.evaluate(got.frames, video[:N])
    assert abs(score["psnr"] - metrics["quality"]["psnr"]) < 0.05 and score["psnr_peak"]["value"] == 1.0
    assert score["psnr"] > 24.0  # a reconstruction, not the trivial estimate (about 21 dB here)


def test_a_stream_is_joined_as_the_cli_joins_it(tmp_path, capsys, footage01):
    video, masks, coded = footage01
    by_cli, metrics = _cli(tmp_path, capsys, coded, masks, video)
    got = cv.reconstruct(coded, masks)
    assert got.shape == (3 * N, SIZE, SIZE)
    np.testing.assert_array_equal(got, by_cli)
    alone = cv.reconstruct(coded, masks, independent_captures=True)
    assert not np.array_equal(alone, got)  # the join changed the boundary frames


def test_units_are_the_callers(footage01):
    """The same capture in 8-bit units: the same frames times 255 (float32 roundoff), the same PSNR."""
    video, masks, coded = footage01
    unit = cv.reconstruct(coded[0], masks[0])
    eight = cv.reconstruct(coded[0] * np.float32(255), masks[0])
    np.testing.assert_allclose(eight, unit * 255, atol=1e-3 * 255)
    assert abs(cv.evaluate(eight, video[:N] * 255)["psnr"] - cv.evaluate(unit, video[:N])["psnr"]) < 0.01


def test_without_a_cache_nothing_is_left_on_disk(tmp_path, monkeypatch, footage01):
    _, masks, coded = footage01
    scratch = tmp_path / "tmp"
    scratch.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(scratch))
    monkeypatch.chdir(tmp_path)
    cv.reconstruct(coded[0], masks[0], method="nonlocal")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["tmp"] and not list(scratch.iterdir())
    cv.reconstruct(coded[0], masks[0], cache=tmp_path / "mine")
    assert (tmp_path / "mine").is_dir() and any((tmp_path / "mine").iterdir())  # asked for: the CLI's cache


def test_a_dask_stack_is_lazy_and_gives_the_numpy_stacks_frames(footage01):
    """Nothing is read at call time (the data range is found in the graph), and the frames are the numpy stack's
    bit for bit: still answers and joins across captures, not each capture on its own."""
    import dask.array as da

    video, masks, coded = footage01
    reads = []

    def counted(block):
        reads.append(1)
        return block

    stack = da.from_array(coded, chunks=(1, SIZE, SIZE)).map_blocks(counted, dtype=coded.dtype,
                                                                   meta=np.empty((0, 0, 0), coded.dtype))
    lazy = cv.reconstruct(stack, masks)
    assert isinstance(lazy, da.Array) and lazy.shape == (3 * N, SIZE, SIZE)
    assert lazy.chunks[0] == (N, N, N) and not reads  # one chunk a capture; nothing computed yet
    joined = cv.reconstruct(coded, masks)
    np.testing.assert_array_equal(lazy.compute(scheduler="threads"), joined)
    assert not np.array_equal(joined, cv.reconstruct(coded, masks, independent_captures=True))  # (the join counts)
    one = cv.reconstruct(da.from_array(coded[0]), masks[0])
    assert one.shape == (N, SIZE, SIZE)
    np.testing.assert_array_equal(one.compute(), cv.reconstruct(coded[0], masks[0]))


def test_a_dask_stack_on_a_distributed_cluster(footage01):
    import dask.array as da
    import distributed

    _, masks, coded = footage01
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1",
                                  dashboard_address=None) as cluster, distributed.Client(cluster):
        got = cv.reconstruct(da.from_array(coded[:2], chunks=(1, SIZE, SIZE)), masks[:2]).compute()
    np.testing.assert_array_equal(got, cv.reconstruct(coded[:2], masks[:2]))


def test_bad_arrays_are_one_line_errors(footage01):
    _, masks, coded = footage01
    with pytest.raises(cv.api.InputError, match="do not fit"):
        cv.reconstruct(coded[0][:40], masks[0])
    with pytest.raises(cv.api.InputError, match="3 coded images, 2 masks"):
        cv.reconstruct(coded, masks[:2])
    with pytest.raises(cv.api.InputError, match="no dictionary is shipped for N = 5"):
        cv.load_dictionary(5)


def test_import_is_light_and_the_docstring_examples_run():
    """`import codedvideo` loads neither numpy nor the engine; the API's examples are doctests."""
    code = "import sys, codedvideo; print(sorted(m for m in ('numpy', 'dask', 'zarr', 'numba') if m in sys.modules))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"
    import doctest

    from codedvideo import api

    result = doctest.testmod(api)
    assert result.attempted >= 10 and result.failed == 0


def test_a_dask_mosaic_under_bayer_gives_the_numpy_paths_colour_frames(tmp_path):
    """`bayer=` with a dask mosaic gave a lazy (N, H, W) array whose computing failed ('coded (1, H, W); under
    bayer= it is one mosaic (H, W)'); it now gives the numpy path's (3, N, H, W) frames."""
    import dask.array as da

    cap = tmp_path / "cap"
    assert main(["-q", "simulate", "synth:color-default", "--frames", str(N), "--bump", "2", "--bayer", "rggb",
                 "--size", "32", "32", "--output", str(cap)]) == 0
    coded, mask = np.load(cap / "coded.npy"), np.load(cap / "mask.npy")
    want = cv.reconstruct(coded, mask, bayer="RGGB")
    lazy = cv.reconstruct(da.from_array(coded), mask, bayer="RGGB")
    assert lazy.shape == want.shape == (3, N, 32, 32)
    np.testing.assert_array_equal(lazy.compute(), want)
