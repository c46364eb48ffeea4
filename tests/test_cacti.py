"""CACTI benchmark .mat files (v5 and v7.3) and the command line on them."""
import json
import os

import h5py
import numpy as np
import pytest
import scipy.io

from codedvideo.formats import cacti
from codedvideo.app.cli import main
from codedvideo.model.errors import InputError, OutputError

H, W, N, Q = 24, 30, 4, 2  # H != W so that a transposed read cannot pass


@pytest.fixture
def scene():
    """orig (Q*N, H, W) uint8-valued frames, a binary mask (N, H, W), meas (Q, H, W)."""
    yy, xx = np.mgrid[0:H, 0:W]
    orig = np.stack([np.rint(128 + 90 * np.sin((xx + 1.5 * t) / 4.0) * np.cos((yy - t) / 5.0)) for t in range(Q * N)])
    orig = orig.astype(np.float32)
    mask = (np.random.default_rng(0).random((N, H, W)) < 0.5).astype(np.uint8)
    mask[0] |= ~mask.any(0)  # every pixel open at least once
    meas = np.stack([(mask * orig[q * N : (q + 1) * N]).sum(0) for q in range(Q)]).astype(np.float32)
    return orig, mask, meas


def write_v73(path, variables):
    """A MATLAB v7.3 file as MATLAB writes it: HDF5 with a 512-byte MAT header, arrays stored axes-reversed."""
    with h5py.File(path, "w", userblock_size=512) as fh:
        for name, arr in variables.items():
            ds = fh.create_dataset(name, data=np.asarray(arr).T)  # MATLAB (H, W, F) -> HDF5 (F, W, H)
            ds.attrs["MATLAB_class"] = np.bytes_({"uint8": "uint8", "float64": "double"}.get(str(arr.dtype), "double"))
    header = b"MATLAB 7.3 MAT-file, Platform: GLNXA64, Created on: Mon Jan  1 00:00:00 2024 HDF5 schema 1.00 ."
    with open(path, "r+b") as fh:
        fh.write(header.ljust(116) + b"\x00" * 8 + b"\x00\x02" + b"IM")


def matlab_vars(orig, mask, meas):
    return dict(orig=np.moveaxis(orig, 0, -1).astype(np.uint8), mask=np.moveaxis(mask, 0, -1).astype(np.float64),
                meas=np.moveaxis(meas, 0, -1).astype(np.float64))


def test_v5_round_trip_and_matlab_layout(tmp_path, scene):
    orig, mask, meas = scene
    path = cacti.write_cacti(tmp_path / "s.mat", mask=mask, meas=meas, orig=orig)
    raw = scipy.io.loadmat(path)
    assert raw["orig"].shape == (H, W, Q * N) and raw["orig"].dtype == np.uint8
    assert raw["mask"].shape == (H, W, N) and raw["meas"].shape == (H, W, Q)
    np.testing.assert_array_equal(raw["orig"][:, :, 5], orig[5])
    data = cacti.read_cacti(path)
    assert (data.frames, data.measurements) == (N, Q)
    assert data.mask.dtype == np.uint8 and data.meas.dtype == np.float32 and data.orig.dtype == np.float32
    np.testing.assert_array_equal(data.mask, mask)
    np.testing.assert_array_equal(data.meas, meas)
    np.testing.assert_array_equal(data.orig, orig)
    np.testing.assert_array_equal(data.truth(1), orig[N:])
    # measurement = plain sum of the masked frames
    np.testing.assert_allclose(data.meas[1], (data.mask * data.truth(1)).sum(0))
    # non-integer frames are kept as double
    cacti.write_cacti(tmp_path / "f.mat", mask=mask, meas=meas, orig=orig + 0.25)
    assert scipy.io.loadmat(tmp_path / "f.mat")["orig"].dtype == np.float64
    np.testing.assert_array_equal(cacti.read_cacti(tmp_path / "f.mat").orig, orig + 0.25)


def test_v73_hdf5_file_in_matlab_layout(tmp_path, scene):
    orig, mask, meas = scene
    write_v73(tmp_path / "s73.mat", matlab_vars(orig, mask, meas))
    with h5py.File(tmp_path / "s73.mat", "r") as fh:
        assert fh["orig"].shape == (Q * N, W, H)  # what h5py sees
    data = cacti.read_cacti(tmp_path / "s73.mat")
    np.testing.assert_array_equal(data.mask, mask)
    np.testing.assert_array_equal(data.meas, meas)
    np.testing.assert_array_equal(data.orig, orig)
    # the same through the volume reader used by `evaluate --truth`
    np.testing.assert_array_equal(cacti.read_mat_volume(tmp_path / "s73.mat"), orig)


def test_single_measurement_2d_meas_and_no_orig(tmp_path, scene):
    orig, mask, meas = scene
    scipy.io.savemat(tmp_path / "one.mat", dict(mask=np.moveaxis(mask, 0, -1).astype(float), meas=meas[0].astype(float)))
    data = cacti.read_cacti(tmp_path / "one.mat")
    assert data.meas.shape == (1, H, W) and data.orig is None and data.truth(0) is None


def test_volume_mat_round_trip(tmp_path):
    vol = np.random.default_rng(2).random((5, H, W)).astype(np.float32) * 255
    cacti.write_mat_volume(tmp_path / "r.mat", vol)
    assert scipy.io.loadmat(tmp_path / "r.mat")["recon"].shape == (H, W, 5)
    np.testing.assert_array_equal(cacti.read_mat_volume(tmp_path / "r.mat"), vol)
    colour = np.random.default_rng(3).random((3, 5, H, W)).astype(np.float32)
    cacti.write_mat_volume(tmp_path / "c.mat", colour)
    assert scipy.io.loadmat(tmp_path / "c.mat")["recon"].shape == (H, W, 3, 5)  # MATLAB's colour video layout
    np.testing.assert_array_equal(cacti.read_mat_volume(tmp_path / "c.mat"), colour)


def _one_line_error(fn, *names):
    with pytest.raises(InputError) as info:
        fn()
    msg = str(info.value)
    assert "\n" not in msg
    for name in names:
        assert name in msg, msg
    return msg


def test_bad_cacti_files(tmp_path, scene):
    orig, mask, meas = scene
    mv = matlab_vars(orig, mask, meas)
    scipy.io.savemat(tmp_path / "nomeas.mat", dict(orig=mv["orig"], mask=mv["mask"]))
    _one_line_error(lambda: cacti.read_cacti(tmp_path / "nomeas.mat"), "nomeas.mat", "'meas'", "found: ")
    scipy.io.savemat(tmp_path / "size.mat", dict(mv, meas=mv["meas"][:-1]))
    _one_line_error(lambda: cacti.read_cacti(tmp_path / "size.mat"), "size.mat", "meas is 23x30")
    scipy.io.savemat(tmp_path / "frames.mat", dict(mv, orig=mv["orig"][:, :, :3]))
    _one_line_error(lambda: cacti.read_cacti(tmp_path / "frames.mat"), "frames.mat", "orig has 3 frames")
    scipy.io.savemat(tmp_path / "grey.mat", dict(mv, mask=mv["mask"] * 0.5))
    _one_line_error(lambda: cacti.read_cacti(tmp_path / "grey.mat"), "grey.mat", "not binary")
    nan = mv["meas"].copy()
    nan[1, 1, 0] = np.nan
    scipy.io.savemat(tmp_path / "nan.mat", dict(mv, meas=nan))
    _one_line_error(lambda: cacti.read_cacti(tmp_path / "nan.mat"), "nan.mat", "NaN")
    scipy.io.savemat(tmp_path / "cell.mat", dict(mv, meas=np.array([["a"]], dtype=object)))
    _one_line_error(lambda: cacti.read_cacti(tmp_path / "cell.mat"), "cell.mat", "'meas'")
    # truncated / corrupt v5 and v7.3, a file that is not a .mat, a missing file
    cacti.write_cacti(tmp_path / "ok.mat", mask=mask, meas=meas, orig=orig)
    data = (tmp_path / "ok.mat").read_bytes()
    for frac in (0.05, 0.5, 0.95):
        (tmp_path / "cut.mat").write_bytes(data[: int(len(data) * frac)])
        _one_line_error(lambda: cacti.read_cacti(tmp_path / "cut.mat"), "cut.mat")
    write_v73(tmp_path / "ok73.mat", mv)
    data = (tmp_path / "ok73.mat").read_bytes()
    (tmp_path / "cut73.mat").write_bytes(data[: len(data) // 2])
    _one_line_error(lambda: cacti.read_cacti(tmp_path / "cut73.mat"), "cut73.mat", "v7.3")
    with h5py.File(tmp_path / "struct73.mat", "w", userblock_size=512) as fh:
        fh.create_group("mask")
        fh.create_dataset("meas", data=mv["meas"].T)
    with open(tmp_path / "struct73.mat", "r+b") as fh:
        fh.write(b"MATLAB 7.3 MAT-file".ljust(116) + b"\x00" * 8 + b"\x00\x02" + b"IM")
    _one_line_error(lambda: cacti.read_cacti(tmp_path / "struct73.mat"), "struct73.mat", "struct or cell")
    (tmp_path / "text.mat").write_text("not a mat file at all " * 20)
    _one_line_error(lambda: cacti.read_cacti(tmp_path / "text.mat"), "text.mat")
    _one_line_error(lambda: cacti.read_cacti(tmp_path / "absent.mat"), "absent.mat", "no such file")
    # writing refuses inconsistent arrays too
    _one_line_error(lambda: cacti.write_cacti(tmp_path / "w.mat", mask=mask, meas=meas, orig=orig[:3]), "w.mat")
    assert not (tmp_path / "w.mat").exists()


# ----------------------------------------------------------------------------- command line
def cli(*args):
    return main(["-q", *map(str, args)])


@pytest.fixture
def dct(tmp_path):
    assert cli("train", "--kind", "dct", "--frames", N, "--output", tmp_path / "d.zarr", "--cache", tmp_path / "cache") == 0
    return tmp_path / "d.zarr"


def test_cli_reconstructs_every_measurement(tmp_path, scene, dct, capsys):
    orig, mask, meas = scene
    write_v73(tmp_path / "two.mat", matlab_vars(orig, mask, meas))
    capsys.readouterr()
    out = tmp_path / "recon.mat"
    assert cli("reconstruct", "--cacti", tmp_path / "two.mat", "--dictionary", dct, "--output", out,
               "--tile", 32, "--cache", tmp_path / "cache") == 0
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    metrics = json.loads((tmp_path / "recon.metrics.json").read_text())
    recon = cacti.read_mat_volume(out)
    assert recon.shape == (Q * N, H, W)
    assert [m["measurement"] for m in metrics["measurements"]] == [1, 2]
    per = [m["quality"]["psnr"] for m in metrics["measurements"]]
    assert metrics["quality"]["psnr_per_measurement"] == per
    assert metrics["quality"]["psnr"] == pytest.approx(np.mean(per), abs=1e-9)
    assert summary["psnr"] == pytest.approx(metrics["quality"]["psnr"], abs=0.01)
    assert all(m["quality"]["psnr"] > m["trivial"]["psnr"] for m in metrics["measurements"])
    assert metrics["quality"]["psnr"] > 25
    # evaluate takes the truth straight from the CACTI file
    assert cli("evaluate", "--recon", out, "--truth", tmp_path / "two.mat") == 0
    ev = json.loads(capsys.readouterr().out)
    assert ev["psnr"] == pytest.approx(metrics["quality"]["psnr"], abs=1e-6)
    # one measurement only: the same frames as in the whole run with measurements on their own (no join)
    assert cli("reconstruct", "--cacti", tmp_path / "two.mat", "--dictionary", dct, "--output", tmp_path / "alone.npy",
               "--tile", 32, "--cache", tmp_path / "cache", "--independent-captures") == 0
    assert cli("reconstruct", "--cacti", tmp_path / "two.mat", "--measurement", 2, "--dictionary", dct,
               "--output", tmp_path / "m2.npy", "--tile", 32, "--cache", tmp_path / "cache") == 0
    np.testing.assert_allclose(np.load(tmp_path / "m2.npy"), np.load(tmp_path / "alone.npy")[N:], atol=1e-4)
    # joined, the measurements' frames away from their boundary are those of each on its own
    np.testing.assert_allclose(recon[N + 3 : 2 * N], np.load(tmp_path / "alone.npy")[N + 3 :], atol=1e-4)
    m2 = json.loads((tmp_path / "m2.metrics.json").read_text())
    alone = json.loads((tmp_path / "alone.metrics.json").read_text())
    assert m2["quality"]["psnr"] == pytest.approx(alone["quality"]["psnr_per_measurement"][1], abs=1e-4)


def test_cli_cacti_errors(tmp_path, scene, dct, capsys):
    orig, mask, meas = scene
    cacti.write_cacti(tmp_path / "two.mat", mask=mask, meas=meas, orig=orig)
    args = ("--dictionary", dct, "--output", tmp_path / "x.npy", "--cache", tmp_path / "cache")
    assert cli("reconstruct", "--cacti", tmp_path / "two.mat", "--measurement", 3, *args) == 2
    assert "1..2" in capsys.readouterr().err
    assert cli("reconstruct", "--cacti", tmp_path / "two.mat", "--coded", tmp_path / "c.npy", *args) == 2
    assert "--coded" in capsys.readouterr().err
    assert cli("reconstruct", *args) == 2
    assert "--cacti" in capsys.readouterr().err
    (tmp_path / "bad.mat").write_bytes(b"MATLAB 5.0 MAT-file" + b"\x00" * 20)
    assert cli("reconstruct", "--cacti", tmp_path / "bad.mat", *args) == 2
    err = capsys.readouterr().err
    assert "bad.mat" in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "x.npy").exists()


def test_cli_simulate_writes_a_cacti_file(tmp_path, capsys):
    assert cli("simulate", "synth:default", "--frames", N, "--size", H, W, "--seed", 1, "--output", tmp_path / "cap",
               "--cacti-out", tmp_path / "sim.mat") == 0
    paths = json.loads(capsys.readouterr().out)
    assert paths["cacti"].endswith("sim.mat")
    data = cacti.read_cacti(tmp_path / "sim.mat")
    np.testing.assert_array_equal(data.mask, np.load(tmp_path / "cap" / "mask.npy"))
    np.testing.assert_allclose(data.meas[0], np.load(tmp_path / "cap" / "coded.npy"), rtol=1e-6)
    np.testing.assert_allclose(data.orig, np.load(tmp_path / "cap" / "truth.npy"), rtol=1e-6)
    assert scipy.io.loadmat(tmp_path / "sim.mat")["meas"].shape == (H, W, 1)


def test_a_mat_volume_written_frame_by_frame_is_the_file_written_at_once(tmp_path):
    """cacti.mat_writer: parts in, the same ``recon`` (H, W, F) single as write_mat_volume; a short or
    misshapen stream leaves nothing; a volume past a v5 file's 4 GiB is refused before any work."""
    rng = np.random.default_rng(3)
    vol = rng.uniform(0, 255, (11, 9, 13)).astype(np.float32)
    with cacti.mat_writer(tmp_path / "s.mat", vol.shape) as write:
        for part in (vol[:4], vol[4:8], vol[8:]):
            write(part)
    cacti.write_mat_volume(tmp_path / "w.mat", vol)
    streamed = scipy.io.loadmat(tmp_path / "s.mat")["recon"]
    assert streamed.dtype == np.float32 and streamed.shape == (9, 13, 11)
    np.testing.assert_array_equal(streamed, scipy.io.loadmat(tmp_path / "w.mat")["recon"])
    np.testing.assert_array_equal(cacti.read_mat_volume(tmp_path / "s.mat"), vol)
    with pytest.raises(RuntimeError, match="10 of 11 frames"):
        with cacti.mat_writer(tmp_path / "short.mat", vol.shape) as write:
            write(vol[:10])
    with pytest.raises(ValueError, match="part of shape"):
        with cacti.mat_writer(tmp_path / "odd.mat", vol.shape) as write:
            write(vol[:, :, :5])
    assert sorted(os.listdir(tmp_path)) == ["s.mat", "w.mat"]
    with pytest.raises(OutputError, match="4 GiB"):
        with cacti.mat_writer(tmp_path / "big.mat", (18 * 60, 2160, 3840)):
            pass
    assert not (tmp_path / "big.mat").exists()


def test_frames_that_do_not_compress_are_kept_within_the_mat_limit(tmp_path, monkeypatch):
    """Random bits come out of zlib a little longer than they went in: the size check keeps room for
    that, and were it passed (here: left out), the writer itself refuses by name and leaves nothing."""
    vol = np.random.default_rng(5).integers(0, 2**32, (6, 16, 16), dtype=np.uint32).view(np.float32)
    monkeypatch.setattr(cacti, "MAT_ELEMENT_BYTES", vol.nbytes + 1025)  # 1 byte more than the old check needed
    with pytest.raises(OutputError, match=r"tight\.mat.*4 GiB"):
        cacti.check_mat_size(tmp_path / "tight.mat", vol.shape)
    monkeypatch.setattr(cacti, "check_mat_size", lambda path, shape: None)
    monkeypatch.setattr(cacti, "MAT_ELEMENT_BYTES", vol.nbytes + 8)  # the frames and their header come to more
    with pytest.raises(OutputError, match=r"tight\.mat: the compressed frames"):
        with cacti.mat_writer(tmp_path / "tight.mat", vol.shape) as write:
            write(vol)
    assert os.listdir(tmp_path) == []


def test_a_benchmark_file_as_published_reconstructs_every_measurement_and_scores_the_first(tmp_path, dct, capsys):
    """The field's test files: mask (H, W, N) with pixels never open, meas (H, W, 5) as uint16 and orig (H, W, N)
    as uint8, the truth of the first measurement only.  Refused before ("orig has 8 frames = 1 measurements ...
    but meas holds 5"), even with --measurement 1."""
    yy, xx = np.mgrid[0:H, 0:W]
    q = 5
    orig = np.stack([np.rint(128 + 90 * np.sin((xx + 1.5 * t) / 4.0) * np.cos((yy - t) / 5.0))
                     for t in range(q * N)]).astype(np.float32)
    mask = (np.random.default_rng(3).random((N, H, W)) < 0.5).astype(np.uint8)
    assert not mask.any(0).all()  # pixels never open, as in the published masks
    meas = np.stack([(mask * orig[k * N : (k + 1) * N]).sum(0) for k in range(q)])
    scipy.io.savemat(tmp_path / "bench.mat", dict(mask=np.moveaxis(mask, 0, -1).astype(np.float64),
                                                  meas=np.moveaxis(meas, 0, -1).astype(np.uint16),
                                                  orig=np.moveaxis(orig[:N], 0, -1).astype(np.uint8)))
    out = tmp_path / "recon.npy"
    with pytest.warns(UserWarning, match=r"orig holds the truth of measurement 1 of 5; 1 of the 5 reconstructed"):
        assert cli("reconstruct", "--cacti", tmp_path / "bench.mat", "--dictionary", dct, "--output", out,
                   "--tile", 32, "--cache", tmp_path / "cache") == 0
    metrics = json.loads((tmp_path / "recon.metrics.json").read_text())
    assert np.load(out).shape == (q * N, H, W)
    assert [m["measurement"] for m in metrics["measurements"]] == [1, 2, 3, 4, 5]
    assert "quality" in metrics["measurements"][0] and all("quality" not in m for m in metrics["measurements"][1:])
    assert metrics["quality"]["scored"] == [1] and len(metrics["quality"]["psnr_per_frame"]) == N
    assert metrics["quality"]["psnr"] > metrics["trivial"]["psnr"]
    # --measurement 1 is scored, --measurement 3 is reconstructed without a score (and says so)
    assert cli("reconstruct", "--cacti", tmp_path / "bench.mat", "--measurement", 1, "--dictionary", dct,
               "--output", tmp_path / "m1.npy", "--tile", 32, "--cache", tmp_path / "cache") == 0
    assert "quality" in json.loads((tmp_path / "m1.metrics.json").read_text())
    with pytest.warns(UserWarning, match="without a score"):
        assert cli("reconstruct", "--cacti", tmp_path / "bench.mat", "--measurement", 3, "--dictionary", dct,
                   "--output", tmp_path / "m3.npy", "--tile", 32, "--cache", tmp_path / "cache") == 0
    assert "quality" not in json.loads((tmp_path / "m3.metrics.json").read_text())
    # evaluate against the file scores the frames its orig covers
    capsys.readouterr()
    with pytest.warns(UserWarning, match="the first 4 are scored"):
        assert cli("evaluate", "--recon", out, "--truth", tmp_path / "bench.mat") == 0
    scored = json.loads(capsys.readouterr().out)
    assert scored["scored_frames"] == N
    assert scored["psnr"] == pytest.approx(metrics["quality"]["psnr"], abs=1e-6)
