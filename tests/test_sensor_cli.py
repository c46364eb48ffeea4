"""Raw captures through the command line: black level, bit depth and defective pixels, each closer to the truth
with its correction than without; a bad-pixel list out of range is a one-line error naming the file."""
import json

import numpy as np
import pytest

from codedvideo.app.cli import main

N, H, W = 8, 64, 64


def _psnr(capsys, tmp_path, cap, *extra, name="r", method="dct"):
    capsys.readouterr()
    out = tmp_path / f"{name}.npy"
    rc = main(["-q", "reconstruct", "--coded", str(cap / "coded.npy"), "--mask", str(cap / "mask.npy"), "--truth",
               str(cap / "truth.npy"), "--method", method, "--output", str(out), "--cache", str(tmp_path / "cache"),
               "--overwrite", *map(str, extra)])
    assert rc == 0, capsys.readouterr().err
    return json.loads(out.with_name(f"{name}.metrics.json").read_text())


@pytest.fixture
def clean(tmp_path):
    cap = tmp_path / "clean"
    assert main(["-q", "simulate", "synth:default", "--frames", str(N), "--size", str(H), str(W), "--output",
                 str(cap)]) == 0
    return cap


def test_black_level_and_bit_depth(tmp_path, capsys):
    cap = tmp_path / "raw"
    assert main(["-q", "simulate", "synth:default", "--frames", str(N), "--size", str(H), str(W), "--black-level", "64",
                 "--bits", "12", "--output", str(cap)]) == 0
    coded = np.load(cap / "coded.npy")
    assert coded.min() >= 64 and coded.max() <= 4095
    without = _psnr(capsys, tmp_path, cap, "--data-range", 255, name="a")["quality"]["psnr"]
    metrics = _psnr(capsys, tmp_path, cap, "--black-level", 64, "--bits", 12, "--data-range", 255, name="b")
    assert metrics["quality"]["psnr"] > without + 3
    assert metrics["reconstruction"]["seconds"]["total"] > 0


def test_bad_pixels_from_a_list_and_detected(tmp_path, capsys, clean):
    rng = np.random.default_rng(0)
    coded = np.load(clean / "coded.npy")
    ys, xs = rng.integers(0, H, 60), rng.integers(0, W, 60)
    coded[ys[:30], xs[:30]] = 2000.0  # hot
    coded[ys[30:], xs[30:]] = 0.0  # dead
    np.save(clean / "coded.npy", coded)
    (tmp_path / "bad.txt").write_text("# y x\n" + "".join(f"{y} {x}\n" for y, x in zip(ys, xs)))
    without = _psnr(capsys, tmp_path, clean, "--data-range", 255, name="a")["quality"]["psnr"]
    listed = _psnr(capsys, tmp_path, clean, "--data-range", 255, "--bad-pixels", tmp_path / "bad.txt", name="b")
    detected = _psnr(capsys, tmp_path, clean, "--data-range", 255, "--detect-bad-pixels", name="c")
    assert listed["quality"]["psnr"] > without + 1 and detected["quality"]["psnr"] > without + 1


def test_a_bad_pixel_list_out_of_range_is_one_line(tmp_path, capsys, clean):
    (tmp_path / "bad.txt").write_text("3 4\n70 5\n")
    capsys.readouterr()
    rc = main(["-q", "reconstruct", "--coded", str(clean / "coded.npy"), "--mask", str(clean / "mask.npy"), "--method",
               "dct", "--output", str(tmp_path / "r.npy"), "--cache", str(tmp_path / "c"), "--bad-pixels",
               str(tmp_path / "bad.txt")])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and len(err.splitlines()) == 1 and "bad.txt" in err and "line 2" in err
    assert not (tmp_path / "r.npy").exists()


def test_a_calibrated_mask_reconstructs_through_the_cli(tmp_path, capsys, clean):
    """A measured (blurred, shifted) response: accepted as the exact forward model, reported non-binary."""
    from codedvideo.model.physics import blur_shift_mask, simulate

    truth = np.load(clean / "truth.npy")
    measured = blur_shift_mask(np.load(clean / "mask.npy"), shift=(0.5, 0.5), sigma=0.5)
    np.save(clean / "mask.npy", measured)
    np.save(clean / "coded.npy", simulate(truth, measured))
    metrics = _psnr(capsys, tmp_path, clean, method="omp")  # the shipped N = 8 dictionary
    assert metrics["quality"]["psnr"] > metrics["trivial"]["psnr"] + 1
    capsys.readouterr()
    assert main(["codes", "check", str(clean / "mask.npy")]) == 0
    assert json.loads(capsys.readouterr().out)["binary"] is False


def test_raw_correction_of_a_stream_holds_one_capture_at_a_time():
    """--black-level (and the other raw options) on a stream of captures: each capture is corrected when
    it is read, never the whole stream at once; --detect-bad-pixels reads it once more first, to vote,
    and the corrections equal the stack's."""
    from codedvideo import api
    from codedvideo.api._job import correct_raw
    from codedvideo.model import sensor

    rng = np.random.default_rng(2)
    t = 6
    mask = (rng.random((N, 16, 16)) < 0.5).astype(np.uint8)
    frames = rng.uniform(0, 200, (t, 16, 16)).astype(np.float32) + 16
    frames[:, 3, 4] = 4000  # a hot pixel in every capture
    reads = []

    class Stream:  # a lazily read stack that records what is read
        def __len__(self):
            return t

        def __getitem__(self, i):
            reads.append(i)
            return frames[i]

    def job():
        return api.Captures(codeds=Stream(), masks=[mask], truths=None, labels=[{}] * t, kind="captures",
                            inputs={}, dtype=np.dtype("float32"), source="stream")

    j = job()
    counts = correct_raw(api.resolve_settings(api.ReconstructSettings(black_level=16.0)), j)
    assert reads == []  # nothing corrected before it is asked for
    fixed = sensor.correct_raw(frames[4], mask, levels=sensor.RawLevels(black_level=16.0))
    np.testing.assert_array_equal(j.codeds[4], fixed.coded)
    assert reads == [4] and counts[4]["black_level"] == 16.0
    reads[:] = []
    j = job()
    counts = correct_raw(api.resolve_settings(api.ReconstructSettings(black_level=16.0, detect_bad_pixels=True)), j)
    assert reads == list(range(t))  # one pass to vote
    stack = sensor.detect_bad_pixels(np.stack([frames[i] - 16 for i in range(t)]), mask)
    assert stack[3, 4] and counts[2]["detected_bad_pixels"] == int(stack.sum())
    assert j.mask(2)[:, 3, 4].sum() == 0 and j.codeds[2][3, 4] == 0


def test_a_warning_is_one_line_that_says_saturated_pixels_are_clipped(tmp_path, capsys):
    """Saturated pixels of an 8-bit file, found without a flag: one 'codedvideo: warning:' line that names them,
    not a Python warning with a source path and line."""
    rng = np.random.default_rng(1)
    mask = (rng.random((N, 24, 24)) < 0.5).astype(np.uint8)
    mask[0] = 1
    coded = np.minimum((mask * rng.uniform(0, 120, (N, 24, 24))).sum(0), 255).astype(np.uint8)
    coded[5:8, 5:8] = 255
    np.save(tmp_path / "coded.npy", coded)
    np.save(tmp_path / "mask.npy", mask)
    import subprocess
    import sys

    proc = subprocess.run([sys.executable, "-m", "codedvideo.app.cli", "-q", "reconstruct", "--coded",
                           str(tmp_path / "coded.npy"), "--mask", str(tmp_path / "mask.npy"), "--method", "dct",
                           "--output", str(tmp_path / "r.npy"), "--cache", str(tmp_path / "cache")],
                          capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    err = [line for line in proc.stderr.splitlines() if line.strip()]
    warned = [line for line in err if "clipped by the sensor" in line]
    assert len(warned) == 1 and warned[0].startswith("codedvideo: warning: ") and "255" in warned[0], err
    assert not any("UserWarning" in line or ".py:" in line for line in err)


def test_bits_on_a_frame_scaled_after_read_out_is_an_error(tmp_path, capsys):
    """--bits describes raw counts: a [0, 1] float capture with --bits 8 would find no saturated pixel where
    the 8-bit capture finds many, so it is refused in one line naming the file, not silently different."""
    rng = np.random.default_rng(3)
    mask = (rng.random((N, 16, 16)) < 0.5).astype(np.uint8)
    counts = np.minimum((mask * rng.integers(0, 120, (N, 16, 16))).sum(0), 255).astype(np.float32)
    np.save(tmp_path / "u8.npy", counts)
    np.save(tmp_path / "f01.npy", counts / 255)
    np.save(tmp_path / "mask.npy", mask)
    common = ["--mask", str(tmp_path / "mask.npy"), "--method", "dct", "--bits", "8", "--cache", str(tmp_path / "c")]
    assert main(["-q", "reconstruct", "--coded", str(tmp_path / "u8.npy"), "--output", str(tmp_path / "a.npy"),
                 *common]) == 0
    capsys.readouterr()
    # the 8-bit capture is reconstructed, and its saturated pixels (255) are treated as missing: the frames
    # measure no more than the coded value where the capture was not clipped
    rec = np.load(tmp_path / "a.npy")
    assert rec.shape == (N, 16, 16) and np.isfinite(rec).all()
    unclipped = counts < 255
    misfit = (mask * rec).sum(0)[unclipped] - counts[unclipped]
    assert np.sqrt(np.mean(misfit**2)) < 0.04 * 255  # a random (not sparse) scene: met in the mean, not exactly
    assert main(["-q", "reconstruct", "--coded", str(tmp_path / "f01.npy"), "--output", str(tmp_path / "b.npy"),
                 *common]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "f01.npy" in err and "whole number" in err
    assert not (tmp_path / "b.npy").exists()


def test_bits_with_a_white_level_takes_frames_in_the_white_levels_units(tmp_path, capsys):
    """simulate --bits 12 --white-level 400 quantises to steps of 400 / 4095 (not whole numbers): the
    same options to reconstruct take them."""
    rng = np.random.default_rng(5)
    mask = (rng.random((N, 16, 16)) < 0.5).astype(np.uint8)
    mask[0] = 1
    step = 400 / 4095
    coded = np.round(np.minimum((mask * rng.uniform(0, 90, (N, 16, 16))).sum(0), 400) / step) * step
    np.save(tmp_path / "c.npy", coded.astype(np.float32))
    np.save(tmp_path / "m.npy", mask)
    assert main(["-q", "reconstruct", "--coded", str(tmp_path / "c.npy"), "--mask", str(tmp_path / "m.npy"),
                 "--method", "dct", "--bits", "12", "--white-level", "400", "--output", str(tmp_path / "r.npy"),
                 "--cache", str(tmp_path / "cache")]) == 0
