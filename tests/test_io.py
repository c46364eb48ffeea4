"""Real files written and read back; bad files give one clear error."""
import numpy as np
import pytest

from codedvideo import io as cio
from codedvideo.errors import InputError


@pytest.fixture
def smooth():
    yy, xx = np.mgrid[0:21, 0:31]
    return np.stack([128 + 60 * np.sin((xx + 2 * t) / 5.0) * np.cos(yy / 7.0) for t in range(5)]).astype(np.float32)


@pytest.mark.parametrize("suffix,dtype,tol", [(".tif", None, 0), (".exr", None, 0), (".tif", np.uint16, 0.5), (".png", None, 0.5), (".npy", None, 0)])
def test_image_round_trip(tmp_path, suffix, dtype, tol):
    img = (np.random.default_rng(0).random((17, 23)) * 250).astype(np.float32)
    path = cio.write_image(tmp_path / f"a{suffix}", img, dtype=dtype) if dtype else cio.write_image(tmp_path / f"a{suffix}", img)
    back = cio.read_image(path)
    assert back.shape == img.shape and back.dtype == np.float32
    assert np.abs(back - img).max() <= tol + 1e-6


def test_stacks_multipage_folder_and_pattern(tmp_path, smooth):
    mask = (smooth > 128).astype(np.uint8)
    cio.write_multipage_tiff(tmp_path / "m.tif", mask)
    np.testing.assert_array_equal(cio.read_stack(tmp_path / "m.tif"), mask)
    cio.write_frames(tmp_path / "frames", smooth, fmt="tiff16")
    np.testing.assert_allclose(cio.read_stack(tmp_path / "frames") * 255 / 65535, smooth, atol=0.01)
    cio.write_frames(tmp_path / "pngs", smooth, fmt="png", prefix="f")
    pat = cio.read_stack(str(tmp_path / "pngs" / "f_%04d.png"))
    np.testing.assert_allclose(pat, np.round(smooth), atol=0.5)
    exr = cio.write_frames(tmp_path / "exr", smooth, fmt="exr")
    assert len(exr) == 5
    np.testing.assert_array_equal(cio.read_stack(tmp_path / "exr"), smooth)


@pytest.mark.parametrize("suffix,tol", [(".mp4", 3.0), (".mkv", 0.5), (".gif", 0.5)])
def test_video_round_trip(tmp_path, smooth, suffix, tol):
    path = cio.write_video(tmp_path / f"v{suffix}", smooth)
    back = cio.read_video(path)
    assert back.shape[0] == 5
    assert np.abs(back[:, :21, :31] - np.round(smooth)).mean() <= tol


def test_bad_files_name_the_file(tmp_path):
    with pytest.raises(InputError, match="nothere.png"):
        cio.read_image(tmp_path / "nothere.png")
    (tmp_path / "bad.png").write_bytes(b"not a png at all")
    with pytest.raises(InputError, match="bad.png"):
        cio.read_image(tmp_path / "bad.png")
    np.save(tmp_path / "t.npy", np.zeros((40, 40), np.float32))
    data = (tmp_path / "t.npy").read_bytes()
    (tmp_path / "t.npy").write_bytes(data[: len(data) // 2])
    with pytest.raises(InputError, match="t.npy"):
        cio.read_image(tmp_path / "t.npy")
    nan = np.zeros((8, 8), np.float32)
    nan[2, 2] = np.nan
    np.save(tmp_path / "nan.npy", nan)
    with pytest.raises(InputError, match="nan.npy: contains NaN"):
        cio.read_image(tmp_path / "nan.npy")
    (tmp_path / "bad.mp4").write_bytes(b"\x00" * 100)
    with pytest.raises(InputError, match="bad.mp4"):
        cio.read_video(tmp_path / "bad.mp4")


def test_colour_policy(tmp_path):
    rgb = np.zeros((6, 6, 3), np.float32)
    rgb[..., 0] = 100
    np.save(tmp_path / "c.npy", rgb)
    np.testing.assert_allclose(cio.read_image(tmp_path / "c.npy"), 29.9, rtol=1e-5)
    with pytest.raises(InputError, match="channels"):
        cio.read_image(tmp_path / "c.npy", color="error")


def test_atomic_output_leaves_nothing_on_failure(tmp_path):
    target = tmp_path / "out.npy"
    cio.write_array(target, np.arange(3))
    with pytest.raises(RuntimeError):
        with cio.atomic_output(target) as tmp:
            tmp.write_bytes(b"partial")
            raise RuntimeError("boom")
    np.testing.assert_array_equal(np.load(target), np.arange(3))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.npy"]
