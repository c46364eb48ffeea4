"""Real files written and read back; bad files give one clear error."""
import warnings

import numpy as np
import pytest

import codedvideo as cv
from codedvideo.app.cli import main
from codedvideo.formats import io as cio
from codedvideo.model.errors import InputError

N, SIZE = 8, 16


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
    # EXR: the data range at 1.0 (white), not clipped; the sidecar takes it back to frame units
    np.testing.assert_allclose(cio.read_stack(tmp_path / "exr"), smooth / 255, rtol=1e-6)
    np.testing.assert_allclose(cio.read_stack(tmp_path / "exr") * cio.read_frames_scale(tmp_path / "exr"), smooth,
                               rtol=1e-5)


@pytest.mark.parametrize("suffix,tol", [(".mp4", 3.0), (".mov", 3.0), (".mkv", 0.0), (".gif", 0.0)])
def test_video_round_trip(tmp_path, smooth, suffix, tol):
    path = cio.write_video(tmp_path / f"v{suffix}", smooth)
    back = cio.read_video(path)
    assert back.shape == smooth.shape  # odd 21x31: the encoder's padding is cropped off on reading
    assert np.abs(back - np.round(smooth)).mean() <= tol


@pytest.mark.parametrize("frames,fps", [(24, 30), (27, 30), (40, 60)])
def test_a_long_gif_at_a_rate_hundredths_of_a_second_cannot_hold_reads_back_whole(tmp_path, frames, fps):
    """GIF delays are whole hundredths of a second (30 fps is stored as 3/100 s): the duration x rate of
    the header is not the frame count, and a complete file must not read as truncated."""
    video = np.random.default_rng(frames).uniform(0, 255, (frames, 16, 24)).astype(np.float32)
    back = cio.read_video(cio.write_video(tmp_path / "v.gif", video, fps=fps))
    assert back.shape == video.shape


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


# ----------------------------------------------------------------------------- every image format and pixel type
INT_IMG = np.random.default_rng(5).integers(0, 256, (17, 23)).astype(np.float32)
INT16_IMG = np.random.default_rng(6).integers(0, 65536, (17, 23)).astype(np.float32)
FLOAT_IMG = (np.random.default_rng(7).random((17, 23)) * 1000 - 20).astype(np.float32)


@pytest.mark.parametrize("suffix,dtype,img", [
    (".png", np.uint8, INT_IMG), (".png", np.uint16, INT16_IMG),
    (".tif", np.uint8, INT_IMG), (".tif", np.uint16, INT16_IMG), (".tif", np.float32, FLOAT_IMG),
    (".exr", np.float32, FLOAT_IMG), (".exr", np.float16, INT_IMG),
    (".dpx", np.uint8, INT_IMG), (".dpx", np.uint16, INT16_IMG), (".dpx", np.float32, FLOAT_IMG),
])
def test_image_formats_round_trip_exactly(tmp_path, suffix, dtype, img):
    path = cio.write_image(tmp_path / f"a{suffix}", img, dtype=dtype)
    back = cio.read_image(path)
    assert back.dtype == np.float32
    np.testing.assert_array_equal(back, img)  # the file's units, no scaling


def test_unsupported_pixel_type_and_format(tmp_path):
    with pytest.raises(InputError, match="cannot hold float32"):
        cio.write_image(tmp_path / "a.png", INT_IMG, dtype=np.float32)
    with pytest.raises(InputError, match="unsupported format"):
        cio.write_image(tmp_path / "a.bmp", INT_IMG)
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("suffix,dtype", [(".tif", np.uint8), (".tif", np.uint16), (".tif", np.float32),
                                          (".exr", np.float32)])
def test_multipage_stacks_round_trip_exactly(tmp_path, smooth, suffix, dtype):
    stack = np.rint(smooth) if np.dtype(dtype).kind == "u" else smooth
    cio.write_stack(tmp_path / f"s{suffix}", stack, dtype=dtype)
    np.testing.assert_array_equal(cio.read_stack(tmp_path / f"s{suffix}"), stack)


def test_folders_and_patterns(tmp_path, smooth):
    frames = np.rint(smooth)
    (tmp_path / "f").mkdir()
    for i, frame in enumerate(frames):  # unpadded numbers: natural order, not f_10 before f_2
        cio.write_image(tmp_path / "f" / f"f_{i * 5}.png", frame)
    (tmp_path / "f" / "notes.txt").write_text("ignored")
    np.testing.assert_array_equal(cio.read_stack(tmp_path / "f"), frames)
    (tmp_path / "p").mkdir()
    for i, frame in enumerate(frames):  # numbered from 1, a gap ends the sequence
        cio.write_image(tmp_path / "p" / f"{i + 1:04d}.tif", frame, dtype=np.uint8)
    cio.write_image(tmp_path / "p" / "0009.tif", frames[0], dtype=np.uint8)
    np.testing.assert_array_equal(cio.read_stack(str(tmp_path / "p" / "%04d.tif")), frames)
    np.testing.assert_array_equal(cio.read_video(str(tmp_path / "p" / "%04d.tif"), start=1, max_frames=2), frames[1:3])
    with pytest.raises(InputError, match="no file matches"):
        cio.read_stack(str(tmp_path / "p" / "%03d.png"))
    (tmp_path / "empty").mkdir()
    with pytest.raises(InputError, match="no image files"):
        cio.read_stack(tmp_path / "empty")
    cio.write_image(tmp_path / "p" / "0006.tif", frames[0, :5], dtype=np.uint8)
    with pytest.raises(InputError, match="differ in shape"):
        cio.read_stack(str(tmp_path / "p" / "%04d.tif"))


# ----------------------------------------------------------------------------- colour: luma or channels
@pytest.mark.parametrize("suffix,dtype", [(".png", np.uint8), (".tif", np.uint16), (".exr", np.float32), (".dpx", np.uint16)])
def test_colour_luma_or_channels(tmp_path, suffix, dtype):
    rgb = np.random.default_rng(1).integers(0, 256, (3, 9, 11)).astype(np.float32)
    path = cio.write_image(tmp_path / f"c{suffix}", rgb, dtype=dtype)
    np.testing.assert_array_equal(cio.read_image(path, color="channels"), rgb)
    luma = np.tensordot(cio.LUMA, rgb, axes=1)
    np.testing.assert_allclose(cio.read_image(path), luma, rtol=1e-6, atol=1e-4)  # the default
    with pytest.raises(InputError, match="3 channels"):
        cio.read_image(path, color="error")


def test_colour_channels_shapes(tmp_path, smooth):
    rgba = np.random.default_rng(2).integers(0, 256, (4, 9, 11)).astype(np.float32)
    cio.write_image(tmp_path / "a.png", rgba)
    np.testing.assert_array_equal(cio.read_image(tmp_path / "a.png", color="channels"), rgba[:3])  # alpha dropped
    cio.write_image(tmp_path / "g.png", INT_IMG)
    assert cio.read_image(tmp_path / "g.png", color="channels").shape == (1, 17, 23)
    np.save(tmp_path / "hwc.npy", np.moveaxis(rgba[:3], 0, -1))
    np.testing.assert_array_equal(cio.read_image(tmp_path / "hwc.npy", color="channels"), rgba[:3])
    colour = np.stack([smooth, smooth[::-1], 255 - smooth]).round()
    cio.write_frames(tmp_path / "cf", colour, fmt="png", data_range=255)
    np.testing.assert_array_equal(cio.read_stack(tmp_path / "cf", color="channels"), colour)
    assert cio.read_stack(tmp_path / "cf").shape == smooth.shape
    with pytest.raises(InputError, match="unknown choice 'rgb'"):
        cio.read_image(tmp_path / "a.png", color="rgb")


# ----------------------------------------------------------------------------- video
def test_lossless_video_is_exact(tmp_path, smooth):
    frames = np.rint(smooth)
    for name in ("v.mkv", "v.gif"):  # FFV1 grey, GIF grey palette
        np.testing.assert_array_equal(cio.read_video(cio.write_video(tmp_path / name, frames)), frames)
    colour = np.stack([frames, frames[:, ::-1], 255 - frames])
    back = cio.read_video(cio.write_video(tmp_path / "c.mkv", colour), color="channels")
    np.testing.assert_array_equal(back, colour)  # FFV1 RGB (bgr0)
    assert cio.read_video(tmp_path / "v.mkv", color="channels").shape == (1, *frames.shape)


@pytest.mark.parametrize("suffix,tol", [(".mp4", 4.0), (".gif", 20.0)])
def test_colour_lossy_video(tmp_path, smooth, suffix, tol):
    colour = np.stack([smooth, smooth[:, ::-1], 255 - smooth])
    back = cio.read_video(cio.write_video(tmp_path / f"c{suffix}", colour), color="channels")
    assert back.shape == colour.shape
    assert np.abs(back - colour).mean() <= tol
    # a palette GIF is lossy enough (16.5 measured) that the tolerance alone would pass a frozen video (17.6):
    # every frame read back is nearer its own frame than the first frame
    for t in range(1, colour.shape[1]):
        assert np.abs(back[:, t] - colour[:, t]).mean() < np.abs(back[:, t] - colour[:, 0]).mean(), t


# ----------------------------------------------------------------------------- write_volume / read_volume
@pytest.mark.parametrize("name,tol", [("v.npy", 0), ("v.zarr", 0), ("v.mat", 0), ("v.tif", 0), ("v.mkv", 0.5),
                                      ("frames", 255 / 65535), ("v.mp4", 3.0), ("v.gif", 0.5)])
def test_volume_outputs_round_trip(tmp_path, smooth, name, tol):
    from codedvideo.formats.volumes import read_volume, write_volume

    write_volume(smooth, tmp_path / name)
    back = read_volume(tmp_path / name)
    assert back.shape == smooth.shape and back.dtype == np.float32
    if name.endswith(".mp4"):
        assert np.abs(back - smooth).mean() <= tol
    else:
        assert np.abs(back - smooth).max() <= tol + 1e-4


def test_colour_volume_outputs(tmp_path, smooth):
    from codedvideo.formats.volumes import read_volume, write_volume

    colour = np.stack([smooth, smooth[:, ::-1], 255 - smooth])
    for name in ("c.npy", "c.zarr", "c.mat"):
        write_volume(colour, tmp_path / name)
        np.testing.assert_array_equal(read_volume(tmp_path / name), colour)
    for name, scale, tol in (("c.mkv", 1, 0.5), ("cf", 1, 255 / 65535 + 1e-4)):  # frame folders: frame units
        write_volume(colour, tmp_path / name)
        assert np.abs(read_volume(tmp_path / name, color="channels") * scale - colour).max() <= tol


# ----------------------------------------------------------------------------- truncated and corrupt files
@pytest.mark.parametrize("name", ["i.png", "i.tif", "i.exr", "i.dpx", "s.tif", "v.npy", "v.mat", "v.mp4", "v.mkv", "v.gif"])
@pytest.mark.parametrize("frac", [0.02, 0.5, 0.7])  # (a stream cut within its last frame can pass)
def test_truncated_files_give_one_line_errors(tmp_path, smooth, name, frac):
    from codedvideo.formats.volumes import read_volume, write_volume

    if name.startswith("i."):
        cio.write_image(tmp_path / name, smooth[0], dtype=np.uint16 if name.endswith(".dpx") else None)
        read = cio.read_image
    else:
        cio.write_stack(tmp_path / name, smooth) if name == "s.tif" else write_volume(smooth, tmp_path / name)
        read = read_volume
    data = (tmp_path / name).read_bytes()
    cut = tmp_path / f"cut_{name}"
    cut.write_bytes(data[: max(int(len(data) * frac), 1)])
    with pytest.raises(InputError) as info:
        read(cut)
    assert cut.name in str(info.value) and "\n" not in str(info.value)


def test_corrupt_zarr_and_garbage_files(tmp_path, smooth):
    from codedvideo.formats.volumes import read_volume, write_volume

    write_volume(smooth, tmp_path / "v.zarr")
    meta = next(p for p in (tmp_path / "v.zarr").rglob("zarr.json"))
    meta.write_text("{ not json")
    with pytest.raises(InputError, match="v.zarr"):
        read_volume(tmp_path / "v.zarr")
    for name in ("g.png", "g.tif", "g.exr", "g.dpx", "g.mat", "g.mkv", "g.gif", "g.mp4"):
        (tmp_path / name).write_bytes(b"\x13\x37garbage" * 40)
        with pytest.raises(InputError) as info:
            read_volume(tmp_path / name)
        assert name in str(info.value) and "\n" not in str(info.value)


# ----------------------------------------------------------------------------- reconstruct --color channels
def test_cli_reconstruct_colour_channels(tmp_path, smooth, capsys):
    import json

    from codedvideo.model import physics
    from codedvideo.app.cli import main

    n = 4
    video = np.stack([np.rint(smooth[:n]), np.rint(smooth[:n, ::-1]), np.rint(255 - smooth[:n])])  # (3, N, H, W)
    mask = (np.random.default_rng(0).random((n, 21, 31)) < 0.5).astype(np.uint8)
    mask[0] |= ~mask.any(0)
    coded = np.stack([physics.forward(v, mask) for v in video])
    cio.write_image(tmp_path / "coded.tif", coded)  # 3-channel float TIFF
    np.save(tmp_path / "mask.npy", mask)
    np.save(tmp_path / "truth.npy", video)
    assert main(["-q", "train", "--kind", "dct", "--frames", str(n), "--output", str(tmp_path / "d.zarr"),
                 "--cache", str(tmp_path / "cache")]) == 0
    common = ["--mask", str(tmp_path / "mask.npy"), "--dictionary", str(tmp_path / "d.zarr"), "--tile", "32",
              "--cache", str(tmp_path / "cache")]
    assert main(["-q", "reconstruct", "--coded", str(tmp_path / "coded.tif"), "--color", "channels", *common,
                 "--output", str(tmp_path / "rgb.mkv"), "--truth", str(tmp_path / "truth.npy")]) == 0
    metrics = json.loads((tmp_path / "rgb.metrics.json").read_text())
    assert [c["channel"] for c in metrics["channels"]] == [0, 1, 2]
    assert all(c["quality"]["psnr"] > c["trivial"]["psnr"] for c in metrics["channels"])
    back = cio.read_video(tmp_path / "rgb.mkv", color="channels")
    assert back.shape == video.shape
    # each channel equals the grey reconstruction of that channel alone
    cio.write_image(tmp_path / "green.tif", coded[1])
    capsys.readouterr()
    assert main(["-q", "reconstruct", "--coded", str(tmp_path / "green.tif"), *common, "--output", str(tmp_path / "g.npy")]) == 0
    green = np.clip(np.rint(np.load(tmp_path / "g.npy")), 0, 255)
    np.testing.assert_array_equal(back[1], green)
    # the default (luma) gives one grey video
    assert main(["-q", "reconstruct", "--coded", str(tmp_path / "coded.tif"), *common, "--output", str(tmp_path / "l.npy")]) == 0
    assert np.load(tmp_path / "l.npy").shape == mask.shape


@pytest.mark.parametrize("fmt,tol", [("tiff16", 255 / 65535), ("png", 0.5), ("exr", 0.0)])
def test_frame_folders_read_back_in_frame_units(tmp_path, fmt, tol):
    """evaluate on a folder of frames compares like with like: stored full scale maps back to data_range."""
    from codedvideo.formats.io import write_frames
    from codedvideo.formats.volumes import read_volume

    vol = np.random.default_rng(0).uniform(0, 255, (3, 9, 11)).astype(np.float32)
    write_frames(tmp_path / "f", vol, fmt=fmt)
    back = read_volume(tmp_path / "f")
    assert back.shape == vol.shape
    np.testing.assert_allclose(back, vol, atol=tol + 1e-4)


def test_a_stack_written_part_by_part_refuses_a_page_of_another_size_and_leaves_nothing(tmp_path):
    from codedvideo.model.errors import OutputError

    with pytest.raises(OutputError, match="page 3 is 8x9x1"):
        with cio.stack_writer(tmp_path / "s.tif", 4) as write:
            write(np.zeros((2, 8, 8), np.float32))
            write(np.zeros((1, 8, 9), np.float32))
    assert list(tmp_path.iterdir()) == []


def test_frame_names_sort_in_frame_order_past_ten_thousand_frames(tmp_path):
    """Reported: frame_%04d names misordered by name after 9999 frames (frame_1000 before frame_10000)."""
    frames = np.zeros((2, 8, 8), np.float32)
    with cio.frames_writer(tmp_path / "f", fmt="png", total=10001) as write:
        names = write(frames)
    assert [p.name for p in names] == ["frame_00000.png", "frame_00001.png"]
    assert [p.name for p in cio.write_frames(tmp_path / "g", frames, fmt="png")] == ["frame_0000.png", "frame_0001.png"]


@pytest.mark.parametrize("name", ["a.tif", "a.exr", "a.png"])
def test_an_image_written_again_later_is_the_same_bytes(tmp_path, name):
    """Reported: coded.tif embedded the time it was written (TIFF DateTime), so two runs of one seed differed."""
    import time

    from codedvideo.formats.io import write_image

    image = np.linspace(0, 1, 64, dtype=np.float32).reshape(8, 8) * (255 if name.endswith(".png") else 1)
    written = []
    for run in ("1", "2"):
        (tmp_path / run).mkdir()
        written.append(write_image(tmp_path / run / name, image).read_bytes())
        time.sleep(1.1)  # a new second on the clock
    assert written[0] == written[1]


@pytest.mark.parametrize("suffix", [".mkv", ".avi", ".mp4"])
def test_a_video_written_again_is_the_same_bytes(tmp_path, suffix):
    """Reruns wrote .mkv files that differed in their container's date and segment id (the frames the same): the
    muxers now run bit-exact, so the same frames give the same file."""
    import time

    frames = (np.random.default_rng(0).random((4, 16, 18)) * 255).astype(np.float32)
    first = cio.write_video(tmp_path / f"a{suffix}", frames).read_bytes()
    time.sleep(1.1)  # (a date in whole seconds would differ)
    assert cio.write_video(tmp_path / f"b{suffix}", frames).read_bytes() == first


@pytest.mark.parametrize("planes", [2, 4, 5])
def test_color_channels_refuses_an_npy_of_other_than_1_or_3_planes_before_any_work(tmp_path, capsys, planes):
    """`--color channels` on a (5, H, W) .npy (a stream of captures) took it for 5 colour channels, ran the whole
    reconstruction and failed only at the video writer; now it is refused first, naming the file."""
    video = cv.synthetic_scene("default", frames=N, size=(SIZE, SIZE))
    mask = cv.make_code("hitomi", (SIZE, SIZE), frames=N, bump=2, seed=0)
    coded = cv.simulate(video, mask)
    np.save(tmp_path / "coded.npy", np.stack([coded] * planes))
    np.save(tmp_path / "mask.npy", mask)
    cache = tmp_path / "cache"
    capsys.readouterr()
    rc = main(["-q", "reconstruct", "--coded", str(tmp_path / "coded.npy"), "--mask", str(tmp_path / "mask.npy"),
               "--color", "channels", "--cache", str(cache), "--output", str(tmp_path / "out.mp4")])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and len(err.splitlines()) == 1, err
    assert "coded.npy" in err and f"{planes} colour channels" in err, err
    assert not (tmp_path / "out.mp4").exists() and not (cache.exists() and any(cache.iterdir()))


def test_color_channels_refuses_a_stack_of_other_than_1_or_3_channels(tmp_path):
    from codedvideo.formats.io import read_stack

    np.save(tmp_path / "mask.npy", np.ones((5, N, SIZE, SIZE), np.float32))
    with pytest.raises(cv.InputError, match="mask.npy: 5 colour channels"):
        read_stack(tmp_path / "mask.npy", color="channels")
    np.save(tmp_path / "rgb.npy", np.ones((3, N, SIZE, SIZE), np.float32))
    assert read_stack(tmp_path / "rgb.npy", color="channels").shape == (3, N, SIZE, SIZE)


def test_a_coded_stream_read_from_a_lossy_video_is_warned_of(tmp_path):
    """An H.264 .mp4 was taken as the coded stream without a word, though its compression changes the values the
    sensor recorded (the docs ask for a lossless video); FFV1 in .mkv is read as it is, silently."""
    from codedvideo.formats.io import write_video
    from codedvideo.formats.volumes import read_coded_stack

    mask = cv.make_code("hitomi", (SIZE, SIZE), frames=N, bump=2, seed=0)
    video = cv.synthetic_scene("default", frames=3 * N, size=(SIZE, SIZE))
    coded = np.round(cv.simulate(video, np.stack([mask] * 3)) / 2).astype(np.float32)  # (3, H, W), within 8 bits
    write_video(tmp_path / "c.mp4", coded)
    write_video(tmp_path / "c.mkv", coded)
    with pytest.warns(UserWarning, match="c.mp4: a h264 video, whose compression changes the values"):
        read_coded_stack(tmp_path / "c.mp4")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        stack = read_coded_stack(tmp_path / "c.mkv")
    np.testing.assert_array_equal(np.stack([stack[i] for i in range(len(stack))]), coded)


def test_a_tiff_of_separate_planes_read_as_one_capture_is_said(tmp_path):
    """tifffile stores a (3, H, W) array as planar RGB: a stack of three captures saved so was read as one capture,
    their luma, with no word.  It is now warned of; an interleaved colour TIFF is not."""
    tifffile = pytest.importorskip("tifffile")
    from codedvideo.formats import io as cio

    stack = np.arange(3 * 8 * 8, dtype=np.uint16).reshape(3, 8, 8)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)  # (tifffile's own, about this very layout)
        tifffile.imwrite(tmp_path / "planes.tif", stack)
    tifffile.imwrite(tmp_path / "rgb.tif", np.moveaxis(stack, 0, -1), photometric="rgb")
    for name, warned in (("planes.tif", True), ("rgb.tif", False)):
        with warnings.catch_warnings(record=True) as said:
            warnings.simplefilter("always")
            assert cio.read_image(tmp_path / name).shape == (8, 8)
        messages = [str(w.message) for w in said if "separate planes" in str(w.message)]
        assert bool(messages) == warned, name
        if warned:
            assert "planes.tif" in messages[0] and "3 channels" in messages[0], messages


def test_float_tiffs_read_back_without_optional_codecs(tmp_path):
    """The float TIFFs codedvideo writes used libtiff's floating-point predictor, which tifffile and scikit-image
    decode only with the optional imagecodecs package; they are now plain deflate, read by both as written."""
    tifffile = pytest.importorskip("tifffile")
    from codedvideo.formats import io as cio

    frames = np.random.default_rng(0).random((3, 8, 8)).astype(np.float32)
    cio.write_stack(tmp_path / "s.tif", frames)
    cio.write_image(tmp_path / "f.tif", frames[0])
    with tifffile.TiffFile(tmp_path / "s.tif") as tif:
        assert tif.pages[0].predictor == 1 and tif.pages[0].compression == 8  # none, deflate
    assert np.array_equal(tifffile.imread(tmp_path / "s.tif"), frames)
    assert np.array_equal(tifffile.imread(tmp_path / "f.tif"), frames[0])


def test_a_folder_with_one_image_of_another_size_names_it(tmp_path, capsys):
    """A mask folder with one odd-sized image said `frames differ in shape [(32, 32), (64, 64)]`, naming no file."""
    from codedvideo.formats import io as cio

    (tmp_path / "m").mkdir()
    for i in range(3):
        cio.write_image(tmp_path / "m" / f"m{i}.png", np.full((16, 16) if i == 2 else (32, 32), 255, np.uint8))
    np.save(tmp_path / "coded.npy", np.ones((32, 32), np.float32))
    assert main(["reconstruct", "--coded", str(tmp_path / "coded.npy"), "--mask", str(tmp_path / "m"),
                 "--output", str(tmp_path / "r.npy")]) == 2
    assert "m2.png is (16, 16), m0.png (32, 32)" in capsys.readouterr().err
    assert not (tmp_path / "r.npy").exists()


def test_a_raw_value_beyond_the_bits_in_a_folder_names_its_file(tmp_path, capsys):
    """`--bits 8` on a folder of 16-bit PNGs named the folder and the capture's number, not the file."""
    from codedvideo.formats import io as cio

    (tmp_path / "coded").mkdir()
    for i in range(3):
        cio.write_image(tmp_path / "coded" / f"c{i}.png", np.full((32, 32), 300 if i == 1 else 100, np.uint16),
                        dtype="uint16")
    np.save(tmp_path / "mask.npy", np.ones((8, 32, 32), np.uint8))
    assert main(["reconstruct", "--coded", str(tmp_path / "coded"), "--mask", str(tmp_path / "mask.npy"),
                 "--bits", "8", "--output", str(tmp_path / "r.npy")]) == 2
    assert "capture 2 of 3 (c1.png): value 300 is above 255" in capsys.readouterr().err
