"""Issue 29: every output format is written a frame (or a band of chunk rows) at a time, the same bits as the
whole-volume conversion, and a capture held on disk (FrameFile) writes the same files."""
import tracemalloc

import numpy as np
import pytest
import scipy.io

from conftest import capture_settings
from codedvideo.formats import io as cio
from codedvideo.formats import images
from codedvideo.formats.store import load_array
from codedvideo.formats.volumes import FrameFile, spilled, volume_writer, write_volume

#: A volume of two captures of N = 6 (odd width: H.264's padding), values past both ends of the data range.
N, H, W, RANGE = 6, 96, 131, 200.0
FORMATS = ("v.npy", "v.zarr", "v.mat", "v.tif", "v.mp4", "v.mkv", "v.gif", "frames")


@pytest.fixture(scope="module")
def volume():
    rng = np.random.default_rng(0)
    yy, xx = np.mgrid[0:H, 0:W]
    frames = [RANGE / 2 + 90 * np.sin((xx + 3 * t) / 7.0) * np.cos(yy / 9.0) for t in range(2 * N)]
    vol = np.stack(frames).astype(np.float32) + rng.normal(0, 8, (2 * N, H, W)).astype(np.float32)
    vol[0, :4, :4] = -30.0  # clipped to 0 in the 8- and 16-bit files
    vol[1, :4, :4] = RANGE + 40.0  # clipped to full scale
    vol[2, 5, 5] = RANGE * 0.5 / 255  # a half step of 8 bits: the rounding
    return vol


def _old_uint8(vol):
    """The 8-bit frames as the whole-volume conversion made them (before issue 29)."""
    return np.clip(np.rint(np.asarray(vol, np.float64) * (255.0 / RANGE)), 0, 255).astype(np.uint8)


def _write(vol_parts, path):
    with volume_writer(path, (2 * N, H, W), data_range=RANGE, fps=30, part=N) as put:
        for i, part in enumerate(vol_parts):
            put(slice(i * N, (i + 1) * N), part)


def _contents(path):
    """What a reader gets from each output: files' bytes where the format is deterministic, else its values."""
    if path.suffix == ".zarr":
        return load_array(path)
    if path.is_dir():
        return {p.name: p.read_bytes() for p in sorted(path.iterdir())}
    if path.suffix == ".npy":  # (the streamed file's header is format 2.0: its values and type compared)
        return np.load(path)
    if path.suffix == ".mkv":  # (Matroska holds a random segment id): the frames decoded, FFV1's input exactly
        return cio.read_video(path)
    if path.suffix == ".mat":
        return scipy.io.loadmat(path)["recon"]  # (its header holds the time of writing)
    return path.read_bytes()


def _same(a, b):
    if isinstance(a, dict):
        return a.keys() == b.keys() and all(a[k] == b[k] for k in a)
    if isinstance(a, np.ndarray):
        return a.dtype == b.dtype and np.array_equal(a, b)
    return a == b


@pytest.fixture
def encoded(monkeypatch):
    """The frames handed to the video encoder, recorded (libx264 is not deterministic from run to run here: an
    H.264 file is compared by what it was given)."""
    import av

    seen = []
    original = av.VideoFrame.from_ndarray

    def record(array, *args, **kwargs):
        seen.append(np.array(array))
        return original(array, *args, **kwargs)

    monkeypatch.setattr(av.VideoFrame, "from_ndarray", record)
    return seen


@pytest.mark.parametrize("name", FORMATS)
def test_each_output_is_the_bits_of_an_independent_reference(tmp_path, volume, name, encoded):
    """Streamed in captures, as an ndarray and as a FrameFile: the same file as a reference made without the
    streaming writers' conversions (the 8-bit formats from the old whole-volume rounding, fed in as uint8 at
    data range 255; the others from the float32 volume itself)."""
    parts = [volume[:N], volume[N:]]
    _write(parts, tmp_path / "a" / name)
    _write([FrameFile(p, tmp_path / "spill") for p in parts], tmp_path / "b" / name)
    ref = tmp_path / "ref" / name
    if name.endswith((".mp4", ".mkv", ".gif")):
        cio.write_video(ref, _old_uint8(volume), data_range=255.0, fps=30)
    elif name == "frames":  # 16-bit TIFF frames, data_range -> 65535
        cio.write_frames(ref, np.zeros((2 * N, H, W)), fmt="tiff16", data_range=RANGE)  # (its names and sidecar)
        expect = np.clip(np.rint(volume * (65535.0 / RANGE)), 0, 65535).astype(np.uint16)  # (float32, as before)
        for k, f in enumerate(cio.frame_files(ref)):
            images._oiio_write(f, [expect[k]], "uint16")
    elif name.endswith(".npy"):
        ref.parent.mkdir()
        np.save(ref, volume)
    elif name.endswith(".mat"):
        ref = None
        assert np.array_equal(scipy.io.loadmat(tmp_path / "a" / name)["recon"], np.moveaxis(volume, 0, -1))
    elif name.endswith(".tif"):
        ref = None
        assert np.array_equal(cio.read_stack(tmp_path / "a" / name), volume)
    elif name.endswith(".zarr"):
        ref = None
        assert np.array_equal(load_array(tmp_path / "a" / name), volume)
    if name.endswith(".mp4"):  # the same frames given to the encoder, three times over
        frames = np.stack(encoded)
        assert len(frames) == 3 * 2 * N and frames.shape[1:] == (H, W + 1)  # (padded to an even width)
        assert np.array_equal(frames[: 2 * N], frames[2 * N : 4 * N]) and np.array_equal(frames[: 2 * N], frames[4 * N :])
        assert np.array_equal(frames[: 2 * N, :, :W], _old_uint8(volume))
        return
    if ref is not None:
        assert _same(_contents(tmp_path / "a" / name), _contents(ref))
    assert _same(_contents(tmp_path / "a" / name), _contents(tmp_path / "b" / name))
    if name.endswith(".mkv"):  # lossless: the rounding itself, read back
        assert np.array_equal(cio.read_video(tmp_path / "a" / name), _old_uint8(volume).astype(np.float32))


@pytest.mark.parametrize("fmt,scale,dtype", [("tiff16", 65535.0, np.uint16), ("png", 255.0, np.uint8),
                                             ("png16", 65535.0, np.uint16), ("exr", 1.0, np.float32)])
def test_frame_folders_hold_the_reference_values(tmp_path, volume, fmt, scale, dtype):
    """Frame folders of each format, written from a FrameFile: each file the reference conversion of its frame."""
    paths = cio.write_frames(tmp_path / fmt, FrameFile(volume, tmp_path), fmt=fmt, data_range=RANGE)
    for k, f in enumerate(paths):
        got = images._oiio_read_all(f, "luma", first_only=True)[0]
        if dtype == np.float32:
            expect = (volume[k] * np.float32(scale / RANGE)).astype(np.float32)
        elif dtype == np.uint8:  # rounded in float64
            expect = np.clip(np.rint(volume[k].astype(np.float64) * (scale / RANGE)), 0, scale).astype(dtype)
        else:  # 16 bits: rounded in float32, as they always were
            expect = np.clip(np.rint(volume[k] * (scale / RANGE)), 0, scale).astype(dtype)
        assert np.array_equal(got, expect.astype(np.float32)), f


def _peak_while(fn) -> int:
    tracemalloc.start()
    try:
        fn()
        return tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()


@pytest.mark.parametrize("name", FORMATS)
def test_writers_hold_a_few_frames_not_the_volume(tmp_path, name):
    """The memory a writer allocates (numpy's allocations, traced) is a few frames, not the volume: 24 frames in
    two parts, the peak under a quarter of the volume's bytes (the whole-part float64 copy of the 8-bit
    formats was the volume's size).  A part given as a FrameFile is read a frame, or a band of rows, at a
    time (a Zarr chunk's rows: an eighth of the volume here): under a quarter too."""
    frames, h, w = 24, 1024, 520
    vol = np.random.default_rng(1).uniform(0, 255, (frames, h, w)).astype(np.float32)
    half = frames // 2

    def write(parts, path):
        with volume_writer(path, vol.shape, data_range=255.0, fps=30, part=half) as put:
            for i, part in enumerate(parts):
                put(slice(i * half, (i + 1) * half), part)

    peak = _peak_while(lambda: write([vol[:half], vol[half:]], tmp_path / "a" / name))
    assert peak < vol.nbytes / 4, f"{name}: {peak / vol.nbytes:.2f} of the volume"
    spilled_parts = [FrameFile(vol[:half], tmp_path), FrameFile(vol[half:], tmp_path)]
    peak = _peak_while(lambda: write(spilled_parts, tmp_path / "b" / name))
    # Zarr from disk: a band of the part's chunk rows read (half a part's 256 rows: an eighth of the volume
    # here) while its chunks are encoded
    bound = 3 * half * 256 * w * 4 if name.endswith(".zarr") else vol.nbytes / 4
    assert peak < bound, f"{name} from disk: {peak / vol.nbytes:.2f} of the volume"


def test_write_volume_makes_no_float_copy_of_a_float32_volume(tmp_path):
    vol = np.random.default_rng(2).uniform(0, 255, (8, 768, 768)).astype(np.float32)  # (9 Zarr chunks)
    for name in ("v.npy", "v.mp4", "v.zarr", "frames"):
        peak = _peak_while(lambda: write_volume(vol, tmp_path / name, data_range=255.0))
        assert peak < vol.nbytes / 2, f"{name}: {peak / vol.nbytes:.2f} of the volume"


def test_spilled_stream_holds_files_and_gives_the_same_bits(tmp_path, volume):
    """spilled() hands on each volume as a FrameFile (nothing of it in memory), whose frames, rows and writes
    back are the volume's, and closes the stream it reads."""
    closed = []

    def results():
        try:
            yield 0, volume[:N].copy(), {}
            yield 1, volume[N:].copy(), {}
        finally:
            closed.append(True)

    stream = spilled(results(), tmp_path)
    got = list(stream)
    assert [i for i, _, _ in got] == [0, 1] and closed
    first = got[0][1]
    assert isinstance(first, FrameFile) and np.array_equal(np.asarray(first), volume[:N])
    box = (slice(N - 3, N), slice(10, 40), slice(5, 77))
    assert np.array_equal(first[box], volume[:N][box])
    first[box] = first[box] + 1  # as the join writes its boundary frames back
    expect = volume[:N].copy()
    expect[box] += 1
    assert np.array_equal(np.asarray(first), expect)
    assert np.array_equal(np.stack(list(first)), expect)


def test_the_join_of_spilled_captures_gives_the_same_bits(tmp_path):
    """sequence.joined over captures kept on disk (spilled, as reconstruct does) gives the bits it gives over
    captures in memory: the join reads and writes back only its boundary frames."""
    from codedvideo.model.physics import forward
    from codedvideo.model.sequence import joined

    rng = np.random.default_rng(3)
    n, t, h, w = 8, 3, 64, 72
    yy, xx = np.mgrid[0:h, 0:w]
    truth = np.stack([120 + 80 * np.sin((xx + 1.5 * f) / 6.0) * np.cos((yy - f) / 8.0) for f in range(n * t)])
    masks = (rng.random((t, n, h, w)) < 0.5).astype(np.uint8)
    codeds = [forward(truth[i * n : (i + 1) * n].astype(np.float32), masks[i]) for i in range(t)]
    recon = (truth + rng.normal(0, 6, truth.shape)).astype(np.float32)  # a reconstruction with a step at each boundary

    def results():
        for i in range(t):
            yield i, recon[i * n : (i + 1) * n].copy(), {}

    kept = [v for _, v, _ in joined(results(), codeds, lambda i: masks[i], data_range=255.0)]
    got = [np.asarray(v) for _, v, _ in joined(spilled(results(), tmp_path), codeds, lambda i: masks[i], data_range=255.0)]
    assert not np.array_equal(np.concatenate(kept), recon)  # the join changed something
    assert all(np.array_equal(a, b) for a, b in zip(kept, got, strict=True))


@pytest.mark.parametrize("method", ["omp", "gaptv"])
def test_a_yielded_capture_is_not_held_by_the_job_while_its_consumer_works(tmp_path, method):
    """The job's generators hand each volume over and keep no reference to it: once the consumer (the join,
    a writer) lets go of a capture, its memory is free before the next one is asked for (at 4K N = 18 the
    job held a 600 MB volume through every join)."""
    import gc
    import weakref

    from codedvideo.engine.captures import reconstruct_captures
    from codedvideo.model.codes import make_code
    from codedvideo.model.physics import simulate
    from codedvideo.model.units import infer_data_range
    from codedvideo.solvers.dictionaries import dct_dictionary
    from codedvideo.solvers.region import OmpSettings
    from codedvideo.data.synth import make_scene

    video = make_scene("default", frames=8, size=(24, 24))
    codeds = [simulate(video[:4], make_code("hitomi", (24, 24), frames=4, bump=2, rng=s)) for s in (1, 2)]
    masks = [make_code("hitomi", (24, 24), frames=4, bump=2, rng=s) for s in (1, 2)]
    results = reconstruct_captures(capture_settings(method, data_range=infer_data_range(255.0, given=255.0),
                                                   settings=OmpSettings(max_atoms=4, tol_rms=2.0),
                                                   dictionary=dct_dictionary(4), cache=tmp_path / "cache", tile=16,
                                                   progress=False),
                                   codeds, masks.__getitem__)
    i, volume, info = next(results)
    assert i == 0 and volume.shape == (4, 24, 24)
    gone = weakref.ref(volume)
    del volume
    gc.collect()
    assert gone() is None  # the suspended job holds nothing of it
    assert next(results)[0] == 1
    results.close()


def test_a_spilled_capture_closes_its_file_when_dropped(tmp_path):
    """A capture held on disk closes its file with it: the collector's 'unclosed file' ResourceWarning, which the
    command line printed as three 'codedvideo: warning:' lines after every stream it joined, is never raised."""
    import gc
    import warnings

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        kept = FrameFile(np.ones((2, 5, 7), np.float32), tmp_path)
        assert np.array_equal(np.asarray(kept), np.ones((2, 5, 7), np.float32))
        del kept
        gc.collect()
    assert [str(w.message) for w in caught if issubclass(w.category, ResourceWarning)] == []
    assert list(tmp_path.iterdir()) == []  # (an unnamed file: nothing left in the folder)


def test_a_joined_stream_on_the_command_line_warns_of_nothing(tmp_path):
    import subprocess
    import sys

    sim = tmp_path / "sim"
    run = [sys.executable, "-m", "codedvideo", "-q"]
    subprocess.run([*run, "simulate", "synth:default", "--frames", "8", "--size", "64", "64", "--captures", "3",
                    "--seed", "0", "--output", str(sim)], check=True, capture_output=True)
    done = subprocess.run([*run, "reconstruct", "--coded", str(sim / "coded.npy"), "--mask", str(sim / "mask.npy"),
                           "--cache", str(tmp_path / "cache"), "--output", str(tmp_path / "rec.npy")],
                          capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    assert done.stderr == ""
    assert np.load(tmp_path / "rec.npy").shape == (24, 64, 64)
