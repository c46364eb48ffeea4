"""Video files through PyAV: H.264, FFV1 and GIF, decoded a frame at a time and encoded part by part (the only
importer of PyAV); a .npy colour video and a stack of images read as a video too."""

from __future__ import annotations

import contextlib
import os
from pathlib import Path

import numpy as np

from codedvideo.formats.arrays import npy_layout, read_array
from codedvideo.formats.atomic import atomic_output
from codedvideo.formats.atomic import one_line as _one_line
from codedvideo.formats.images import read_stack
from codedvideo.formats.pixels import LUMA, check_color, finite, frames_of, to_gray, to_uint8
from codedvideo.model.errors import InputError, OutputError
from codedvideo.model.units import EIGHT_BIT


#: Prefix of the container comment in which write_video records the frame size (H x W).
SIZE_TAG = "codedvideo size="


VIDEO_SUFFIXES = (".mp4", ".avi", ".mov", ".mkv", ".gif")


def read_video(
    path: str | os.PathLike, *, max_frames: int | None = None, start: int = 0, color: str = "luma"
) -> np.ndarray:
    """Frames of a video file (PyAV) or an image sequence (:func:`read_stack`).

    Grey videos (gray, gray16le pixels, e.g. FFV1) are read exactly; colour
    ones through 8-bit RGB.

    Returns
    -------
    ndarray of shape (F, H, W), or (C, F, H, W) for ``color="channels"``, float32
    """
    check_color(color)
    source = Path(path)
    if source.suffix.lower() == ".npy":
        layout = npy_layout(source)
        if layout is not None and len(layout[0]) == 4:  # a colour video: (F, H, W, C) or (C, F, H, W)
            stack = _npy_colour_video(read_array(source), source, color)
            sl = slice(start, None if max_frames is None else start + max_frames)
            return stack[:, sl] if color == "channels" else stack[sl]
    if source.suffix.lower() not in VIDEO_SUFFIXES:
        stack = read_stack(source, color=color)
        sl = slice(start, None if max_frames is None else start + max_frames)
        return stack[:, sl] if color == "channels" else stack[sl]
    frames = []
    for frame in iter_video(source, color=color, start=start):
        frames.append(frame)
        if max_frames is not None and len(frames) >= max_frames:
            break
    if not frames:
        raise InputError(f"video {source}: no frames decoded (from frame {start})")
    return np.stack(frames, axis=1 if color == "channels" else 0).astype(np.float32)


def _npy_colour_video(arr: np.ndarray, path: Path, color: str) -> np.ndarray:
    """A 4-D .npy video, (F, H, W, C) with C in (3, 4) or (C, F, H, W) with C in (1, 3, 4) (as ``simulate
    --bayer`` writes its truth): (F, H, W) luma, or (C, F, H, W) for ``color="channels"``."""
    if arr.shape[-1] in (3, 4):  # (a grey video 3 or 4 pixels wide could not be used anyway)
        channels_first = np.moveaxis(arr, -1, 0)
    elif arr.shape[0] not in (1, 3, 4):
        raise InputError(f"video {path}: expected shape (F, H, W), (F, H, W, 3) or (3, F, H, W), got {arr.shape}")
    else:
        channels_first = arr
    video = finite(channels_first.astype(np.float32), path, "video")
    channels = video[:1] if video.shape[0] == 1 else video[:3]  # (an alpha channel dropped)
    if color == "channels":
        return np.ascontiguousarray(channels)
    if channels.shape[0] == 1:
        return channels[0]
    if color == "error":
        raise InputError(f"video {path}: has {channels.shape[0]} channels; a single-channel video is required")
    if (channels[0] == channels[1]).all() and (channels[1] == channels[2]).all():
        return channels[0]
    return np.tensordot(LUMA, channels, axes=([0], [0]))


#: Video codecs that keep every value of the frames they hold (a GIF's palette keeps grey exactly).
LOSSLESS_CODECS = ("ffv1", "rawvideo", "png", "huffyuv", "ffvhuff", "utvideo", "gif", "qtrle", "apng")


def lossy_codec(path: str | os.PathLike) -> str | None:
    """The codec of a video file's first video stream when it is not one of :data:`LOSSLESS_CODECS` (H.264, VP9,
    MPEG-4: values changed by the compression), else None (or when the file cannot say: its reader will)."""
    import av

    try:
        with av.open(str(path)) as container:
            if not container.streams.video:
                return None
            name = container.streams.video[0].codec_context.name
    except (av.error.FFmpegError, OSError):
        return None
    return None if name in LOSSLESS_CODECS else name


def iter_video(path: str | os.PathLike, *, color: str = "luma", start: int = 0):
    """The frames of a video file one at a time (:func:`read_video`'s units), from frame ``start``.

    A GIF without its trailer, or a file that decodes to the end with fewer
    frames than its header promises, is an :class:`InputError`.
    """
    import av

    source = Path(path)
    if not source.exists():
        raise InputError(f"video {source}: no such file")
    if source.suffix.lower() == ".gif" and not _gif_complete(source):
        raise InputError(f"video {source}: truncated (no GIF trailer)")
    decoded = 0
    try:
        with av.open(str(source)) as container:
            if not container.streams.video:
                raise InputError(f"video {source}: has no video stream")
            stream = container.streams.video[0]
            # a GIF's frame delays are whole hundredths of a second (30 fps is stored as 3/100 s), so its
            # duration x rate misses the frame count; its trailer, checked above, tells a truncated one
            expected = None if source.suffix.lower() == ".gif" else _expected_frames(container, stream)
            size = _tagged_size(container)
            for i, frame in enumerate(container.decode(video=0)):
                decoded = i + 1
                if i < start:
                    continue
                grey = frame.format.name in ("gray", "gray8", "gray16le")
                if color == "error" and not grey:
                    raise InputError(f"video {source}: frames are in colour ({frame.format.name}); grey frames are required")
                pixels = frame.to_ndarray() if grey else frame.to_ndarray(format="rgb24")
                if size is not None:  # written by write_video: undo the encoder's padding
                    pixels = pixels[: size[0], : size[1]]
                yield to_gray(pixels, source, "channels" if color == "channels" else "luma").astype(np.float32)
            if expected is not None and decoded < expected - 1:  # a stream that ends early was cut short
                raise InputError(f"video {source}: truncated (decoded {decoded} of {expected} frames)")
    except (av.error.FFmpegError, OSError) as exc:
        raise InputError(f"video {source}: cannot decode ({_one_line(exc)})") from exc


def _tagged_size(container) -> tuple[int, int] | None:
    """(H, W) recorded by :func:`write_video` in the container's comment, or None."""
    tag = str(container.metadata.get("comment", ""))
    if tag.startswith(SIZE_TAG):
        try:
            h, w = (int(v) for v in tag[len(SIZE_TAG):].split("x"))
            return h, w
        except ValueError:
            return None
    return None


def _expected_frames(container, stream) -> int | None:
    """Frame count from the container's header (duration x rate), or None when unknown.

    Streaming formats (Matroska) decode a truncated file without error;
    the duration recorded in the header tells how many frames there were
    (to within one frame).  Not for GIF (see :func:`iter_video`).
    """
    rate = stream.average_rate
    if container.duration and rate:
        return int(round(container.duration / 1e6 * float(rate)))
    return None


def _gif_complete(path: Path) -> bool:
    """A complete GIF ends with the trailer byte 0x3B."""
    with open(path, "rb") as fh:
        fh.seek(0, os.SEEK_END)
        if fh.tell() == 0:
            return False
        fh.seek(-1, os.SEEK_END)
        return fh.read(1) == b";"


def _frames_last(frames: np.ndarray, path, what: str) -> np.ndarray:
    """(N, H, W) or (C, N, H, W) with C in (1, 3) -> (N, H, W) grey or (N, H, W, 3) colour (views, no copy)."""
    if not isinstance(frames, np.ndarray) and getattr(frames, "ndim", None) == 3:
        return frames  # frames read one at a time (frames_of)
    arr = np.asarray(frames)
    if arr.ndim == 4:
        if arr.shape[0] not in (1, 3):
            raise InputError(f"{what} {path}: colour frames need 1 or 3 channels, got shape {arr.shape}")
        return arr[0] if arr.shape[0] == 1 else np.moveaxis(arr, 0, -1)
    if arr.ndim != 3:
        raise InputError(f"{what} {path}: expected frames (N, H, W) or (C, N, H, W), got shape {arr.shape}")
    return arr


def write_video(path: str | os.PathLike, frames: np.ndarray, *, data_range: float = EIGHT_BIT, fps: int = 30) -> Path:
    """Write frames as a video: .mp4 (H.264), .mkv/.avi (FFV1, lossless), .gif.

    Parameters
    ----------
    frames : ndarray of shape (N, H, W), or (C, N, H, W) with C = 3 for colour
        Scaled so ``data_range`` maps to 255, then rounded to 8 bits.  FFV1
        stores the 8-bit frames exactly (grey, or RGB as bgr0); GIF is exact
        for grey and quantised to 3-3-2 bit RGB for colour.  H.264 in yuv420p
        needs even sizes: odd sizes are padded by repeating the last
        row/column, and the size is recorded in the container's comment so
        that :func:`read_video` crops the padding off again.
    """
    target = Path(path)
    data = _frames_last(frames, target, "video")
    with video_writer(target, data.shape[1:3], colour=data.ndim == 4, data_range=data_range, fps=fps) as write:
        write(data)
    return target


#: A GIF stores each frame's delay in whole hundredths of a second: no faster rate can be written.
GIF_MAX_FPS = 100


def gif_rate_problem(fps: int) -> str | None:
    """Why a GIF cannot be written at ``fps`` frames a second (None: it can)."""
    if fps > GIF_MAX_FPS:
        return (f"a GIF holds at most {GIF_MAX_FPS} frames a second (its frame delays are whole hundredths of a "
                f"second), not {fps}; choose a lower rate or another format")
    return None


@contextlib.contextmanager
def video_writer(path: str | os.PathLike, size: tuple[int, int], *, colour: bool = False, data_range: float = EIGHT_BIT,
                 fps: int = 30):
    """Encode a video part by part (:func:`write_video`'s formats): yields ``write(frames)``.

    ``frames`` are (n, H, W) grey or (n, H, W, 3) RGB, in order; each part is
    encoded as it comes, a frame at a time (converted to 8 bits one frame at
    a time: no float copy of the part), so a long video is never held whole.
    The file appears under ``path`` only when the block ends without an error.
    """
    import av

    target = Path(path)
    suffix = target.suffix.lower()
    height, width = size
    pad = (0, 0)
    if suffix in (".mp4", ".mov"):
        codec, pix_fmt, options = "libx264", "yuv420p", {"crf": "17", "preset": "medium"}
        pad = (height % 2, width % 2)
    elif suffix in (".mkv", ".avi"):
        codec, pix_fmt, options = "ffv1", "bgr0" if colour else "gray", {}
    elif suffix == ".gif":
        codec, pix_fmt, options = "gif", "rgb8" if colour else "gray", {}
    else:
        raise InputError(f"video {target}: unsupported container {suffix!r} (use .mp4, .mov, .mkv, .avi or .gif)")
    if suffix == ".gif" and fps > GIF_MAX_FPS:
        raise InputError(f"video {target}: {gif_rate_problem(fps)}")
    in_fmt = "rgb24" if colour else "gray"
    with atomic_output(target) as tmp:
        try:
            with av.open(str(tmp), mode="w", options={"fflags": "+bitexact"}) as container:
                # the size before any padding, so read_video returns the frames as given
                container.metadata["comment"] = f"{SIZE_TAG}{height}x{width}"
                stream = container.add_stream(codec, rate=fps)
                stream.width, stream.height = width + pad[1], height + pad[0]
                stream.pix_fmt = pix_fmt
                if options:
                    stream.options = options

                def write(frames: np.ndarray) -> None:
                    for img in frames_of(frames):
                        img = to_uint8(img, data_range)
                        if any(pad):
                            img = np.pad(img, ((0, pad[0]), (0, pad[1])) + (((0, 0),) if colour else ()), mode="edge")
                        frame = av.VideoFrame.from_ndarray(np.ascontiguousarray(img), format=in_fmt)
                        for packet in stream.encode(frame):
                            container.mux(packet)

                yield write
                for packet in stream.encode(None):
                    container.mux(packet)
        except (av.error.FFmpegError, OSError) as exc:
            raise OutputError(f"video {target}: cannot write ({exc})") from exc
