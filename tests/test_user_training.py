"""Training on a user's own videos as users hold them: any units, colour .npy stacks, videos too short
or too small named, long videos read past their first frames."""
import json
from pathlib import Path

import numpy as np
import pytest

from codedvideo.app.cli import main
from codedvideo.formats.store import load_dictionary
from codedvideo.data.synth import make_scene

N = 4


@pytest.fixture(scope="module")
def video8(tmp_path_factory) -> tuple[Path, np.ndarray]:
    """A textured moving clip in 0..255 (float32), 40 frames of 37x53."""
    d = tmp_path_factory.mktemp("videos")
    v = make_scene("coins-translate", frames=40, size=(37, 53)).astype(np.float32)
    return d, v


def train(tmp_path, capsys, *videos, output="d.zarr", extra=()):
    capsys.readouterr()
    rc = main(["-q", "train", "--frames", str(N), "--atoms", "64", "--samples", "3000", "--iterations", "3",
               "--cache", str(tmp_path / "cache"), "--output", str(tmp_path / output), *map(str, extra),
               *map(str, videos)])
    out, err = capsys.readouterr()
    return rc, (json.loads(out) if rc == 0 else None), err


def test_a_video_in_0_1_floats_trains_the_dictionary_its_8_bit_copy_does(tmp_path, capsys, video8):
    d, v = video8
    np.save(d / "v8.npy", v)
    np.save(d / "v01.npy", v / np.float32(255))
    np.save(d / "v16.npy", np.round(v * (65535 / 255)).astype(np.uint16))
    rc8, r8, _ = train(tmp_path, capsys, d / "v8.npy", output="d8.zarr")
    rc01, r01, _ = train(tmp_path, capsys, d / "v01.npy", output="d01.zarr")
    rc16, r16, _ = train(tmp_path, capsys, d / "v16.npy", output="d16.zarr")
    assert rc8 == rc01 == rc16 == 0
    # before: the [0, 1] video learned on its raw values (rmse flat at 0.37, nearly every atom replaced
    # every iteration) and reconstructed 2 dB worse
    assert r01["final_rmse"] == pytest.approx(r8["final_rmse"], rel=1e-4)
    assert r16["final_rmse"] == pytest.approx(r8["final_rmse"], rel=2e-2)
    D8, _ = load_dictionary(tmp_path / "d8.zarr")
    D01, _ = load_dictionary(tmp_path / "d01.zarr")
    np.testing.assert_allclose(D01, D8, atol=1e-2)  # (the same atoms, to the roundoff of v / 255 * 255)


def test_videos_too_short_or_small_are_named_and_left_out(tmp_path, capsys, video8):
    d, v = video8
    np.save(d / "ok.npy", v)
    np.save(d / "short.npy", v[: N - 1])
    np.save(d / "tiny.npy", v[:, :5, :6])
    with pytest.warns(UserWarning) as said:
        rc, r, err = train(tmp_path, capsys, d / "ok.npy", d / "short.npy", d / "tiny.npy")
    assert rc == 0, err
    text = " ".join(str(w.message) for w in said)
    assert "short.npy (3 frames of 37x53)" in text and "tiny.npy (40 frames of 5x6)" in text, text
    _, meta = load_dictionary(tmp_path / "d.zarr")
    assert meta["training_set"] == [str(d / "ok.npy")]  # what was used, not what was named
    rc, _, err = train(tmp_path, capsys, d / "short.npy", d / "tiny.npy", output="none.zarr")
    assert rc == 2 and len(err.strip().splitlines()) == 1
    assert "short.npy" in err and "tiny.npy" in err and "no video is usable" in err, err
    assert not (tmp_path / "none.zarr").exists()


def test_a_dictionary_reused_for_copies_records_this_runs_training_files(tmp_path, capsys, video8):
    """Reported: training on a copy of a clip under another name reused the cached dictionary (the key holds the
    contents) and recorded the first run's file; the record now names this run's, and no synthetic clips."""
    d, v = video8
    np.save(d / "clipA.npy", v)
    np.save(d / "clipB.npy", v)
    np.save(d / "short.npy", v[: N - 1])
    with pytest.warns(UserWarning, match="short.npy"):
        rc, first, err = train(tmp_path, capsys, d / "clipA.npy", d / "short.npy", output="a.zarr")
    assert rc == 0, err
    rc, second, err = train(tmp_path, capsys, d / "clipB.npy", d / "short.npy", output="b.zarr")
    assert rc == 0 and second["reused"], (err, second)
    _, meta = load_dictionary(tmp_path / "b.zarr")
    assert meta["training_set"] == [str(d / "clipB.npy")] and "clips" not in meta, meta
    D_a, _ = load_dictionary(tmp_path / "a.zarr")
    D_b, _ = load_dictionary(tmp_path / "b.zarr")
    np.testing.assert_array_equal(D_a, D_b)


@pytest.mark.parametrize("layout", ["last", "first"])
def test_a_colour_npy_video_trains_on_its_luma(tmp_path, capsys, video8, layout):
    d, v = video8
    rgb = np.stack([v, 0.5 * v, 255 - v], axis=-1 if layout == "last" else 0).astype(np.float32)
    luma = (0.299 * v + 0.587 * 0.5 * v + 0.114 * (255 - v)).astype(np.float32)
    np.save(d / f"rgb-{layout}.npy", rgb)
    np.save(d / "luma.npy", luma)
    rc, r, err = train(tmp_path, capsys, d / f"rgb-{layout}.npy", output="c.zarr")
    assert rc == 0, err  # before: "expected shape (N, H, W)"
    _, r_luma, _ = train(tmp_path, capsys, d / "luma.npy", output="l.zarr")
    assert r["final_rmse"] == pytest.approx(r_luma["final_rmse"], rel=1e-3)


def test_a_video_textured_only_after_its_first_frames_trains(tmp_path, capsys, video8):
    d, v = video8
    late = np.concatenate([np.full((100, *v.shape[1:]), 128, np.float32), v])
    np.save(d / "late.npy", late)
    rc, r, err = train(tmp_path, capsys, d / "late.npy")
    assert rc == 0, err  # before: only the first 64 frames were read, all flat: "every patch drawn is flat"
    # the patches came from the textured frames: the atoms vary in space and time like the clip's own
    D, _ = load_dictionary(tmp_path / "d.zarr")
    atoms = D.reshape(N, 7, 7, -1)
    assert np.abs(np.diff(atoms, axis=0)).mean() > 0.01 and np.abs(np.diff(atoms, axis=2)).mean() > 0.01
    np.save(d / "textured.npy", v)
    _, alone, _ = train(tmp_path, capsys, d / "textured.npy", output="alone.zarr")
    # flat patches fit with no error: had the flat frames been most of what was drawn, the fit error would be
    # near 0 (measured 10.0 here, against 13.5 on the textured frames alone)
    assert r["final_rmse"] > 0.5 * alone["final_rmse"]


def test_samples_that_would_not_fit_in_memory_are_refused_in_one_line(tmp_path, capsys, video8):
    """Reported: 10 M samples at N = 64 passed the checks and ended in a MemoryError traceback after 50 s."""
    d, v = video8
    np.save(d / "ok.npy", v)
    capsys.readouterr()
    rc = main(["-q", "train", "--frames", "64", "--samples", "10000000", "--iterations", "1",
               "--cache", str(tmp_path / "cache"), "--output", str(tmp_path / "d.zarr"), str(d / "ok.npy")])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and len(err.splitlines()) == 1 and "--samples" in err and "GiB" in err, err
    assert not (tmp_path / "d.zarr").exists()


def test_an_allocation_that_fails_is_one_line_not_a_traceback(tmp_path, capsys, monkeypatch, video8):
    from codedvideo.solvers import dictionaries

    def no_memory(*args, **kwargs):
        raise MemoryError("Unable to allocate 350. GiB")

    monkeypatch.setattr(dictionaries, "training_patches", no_memory)
    d, v = video8
    np.save(d / "ok.npy", v)
    rc, _, err = train(tmp_path, capsys, d / "ok.npy")
    assert rc == 2 and err.strip().startswith("codedvideo: error: out of memory") and len(err.strip().splitlines()) == 1


def test_a_test_scene_named_for_training_says_what_to_name(tmp_path, capsys):
    rc, _, err = train(tmp_path, capsys, "synth:default")
    assert rc == 2 and "synth:train" in err and "test scene" in err, err  # before: "image synth:default: no such file"


def test_a_dictionary_adapted_to_a_scene_starts_from_the_one_given(tmp_path, capsys, video8):
    """train --init shipped --no-augment: K-SVD from the shipped N = 8 dictionary, on the patches as they are."""
    from codedvideo.data import shipped
    from codedvideo.engine.cache import dictionary_key
    from codedvideo.engine.config import PipelineConfig

    d, v = video8
    np.save(d / "scene.npy", v)
    capsys.readouterr()
    assert main(["-q", "train", "--frames", "8", "--init", "shipped", "--no-augment", "--iterations", "1",
                 "--samples", "2000", "--cache", str(tmp_path / "cache"), "--output", str(tmp_path / "a.zarr"),
                 str(d / "scene.npy")]) == 0
    D, meta = load_dictionary(tmp_path / "a.zarr")
    D0, _ = load_dictionary(shipped.verified(8))
    assert D.shape == D0.shape and meta["init"] == "shipped" and meta["augment"] is False
    dots = np.sum(D * D0, 0)
    assert np.abs(D - D0).max() > 0.1 and dots.max() > 0.999  # moved from where it started, some atoms kept
    # the keys of dictionaries trained without these settings (the shipped ones among them) are unchanged
    assert dictionary_key(PipelineConfig(frames=8)) == shipped.settings_key(8)


@pytest.mark.parametrize("extra, named", [(["--atoms", "256"], "--atoms"), (["--kind", "dct"], "--init"),
                                          (["--frames", "5"], "no dictionary is shipped for N = 5")])
def test_init_options_that_do_not_apply_are_refused(tmp_path, capsys, video8, extra, named):
    d, v = video8
    np.save(d / "scene.npy", v)
    args = ["-q", "train", "--frames", "8", "--init", "shipped", "--iterations", "1", "--samples", "2000",
            "--cache", str(tmp_path / "cache"), "--output", str(tmp_path / "a.zarr")]
    if extra[0] == "--frames":
        args[3] = "5"
    else:
        args += extra
    capsys.readouterr()
    rc = main([*args, *([] if extra == ["--kind", "dct"] else [str(d / "scene.npy")])])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and named in err and len(err.splitlines()) == 1, err


def test_a_reconstruction_that_overshoots_its_range_keeps_it(tmp_path, video8):
    """A [0, 1] or 8-bit reconstruction with ~1 % of values up to 1.14 times its range keeps that range."""
    from codedvideo.data.scenes import training_videos

    _, v = video8
    over = v.copy()
    hot = np.random.default_rng(0).random(v.shape) < 0.01
    over[hot] = np.linspace(256, 290, int(hot.sum()), dtype=np.float32)
    np.save(tmp_path / "v8.npy", over)
    np.save(tmp_path / "v01.npy", over / np.float32(255))
    assert over.max() / 255 > 1.13
    (v8,), _ = training_videos([str(tmp_path / "v8.npy")], frames=N, clips=1, seed=0)
    (v01,), _ = training_videos([str(tmp_path / "v01.npy")], frames=N, clips=1, seed=0)
    # before: the 8-bit one was taken as 12-bit (scaled by 255/4095) and the [0, 1] one as 8-bit (unscaled)
    np.testing.assert_allclose(v8, over, rtol=1e-6)
    np.testing.assert_allclose(v01, over, rtol=1e-5, atol=1e-3)
