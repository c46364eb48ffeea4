"""Synthetic high-frame-rate videos made from photographs shipped inside scikit-image.

Every clip is an array ``(frames, H, W)`` float32 of grey levels 0..255, time first. A clip
is a photograph seen through a moving window or warped by a smooth motion field, sampled
with a cubic spline (order 3, ``mode="reflect"``) so that motion is exact to the subpixel.
The speeds are those a 300-1000 fps camera sees in ordinary scenes: about 0.2 to 2 pixels
per sub-frame.

Only files already inside the installed ``skimage/data`` folder are used (nothing is
downloaded; ``data_manifest`` lists them with their sha256). The photographs are split, once
and for all, into

- :data:`TRAIN_PHOTOS` for dictionary learning (:func:`training_videos`), and
- :data:`TEST_PHOTOS` for held-out evaluation (:func:`test_scenes`, the ``default`` scenes),

so a dictionary never sees the photographs it is scored on.

Motions (each a function returning ``(frames, H, W)``):

- :func:`translate`: a crop window moving over the photo (the content moves by ``velocity``);
- :func:`rotate`: rotation about the crop centre;
- :func:`zoom`: magnification changing by ``(1 + rate)`` per frame;
- :func:`occlude`: a soft-edged disc (or rounded blob) cut from a second photo crossing a
  static or slowly drifting background (occlusion and disocclusion);
- :func:`deform`: a smooth sinusoidal non-rigid warp whose phase advances with time.

Determinism: randomness only comes from the :class:`numpy.random.Generator` passed in (or
``default_rng(seed)``); ``rng=None`` means ``default_rng(0)``. Angles and sines are evaluated
with the scalar :mod:`math` library and the colour-to-grey conversion is an explicit weighted
sum, so the generated arrays do not depend on the CPU's SIMD or BLAS code paths.
"""

from __future__ import annotations

import math
import zlib
from functools import lru_cache
from pathlib import Path
from typing import Any, Mapping

import numpy as np
from scipy import ndimage

from .errors import InputError

__all__ = [
    "PHOTO_FILES",
    "TRAIN_PHOTOS",
    "TEST_PHOTOS",
    "MOTIONS",
    "NAMED_SCENES",
    "TEST_SCENES",
    "SPEED_RANGE",
    "ClipList",
    "data_dir",
    "photo_path",
    "photo",
    "translate",
    "rotate",
    "zoom",
    "occlude",
    "deform",
    "make_scene",
    "scene_photos",
    "training_videos",
    "test_scenes",
]

#: photograph name -> file name inside ``skimage/data`` (all present in scikit-image 0.26).
PHOTO_FILES: dict[str, str] = {
    "astronaut": "astronaut.png",
    "chelsea": "chelsea.png",
    "coffee": "coffee.png",
    "rocket": "rocket.jpg",
    "brick": "brick.png",
    "grass": "grass.png",
    "gravel": "gravel.png",
    "motorcycle_left": "motorcycle_left.png",
    "hubble_deep_field": "hubble_deep_field.jpg",
    "retina": "retina.jpg",
    "camera": "camera.png",
    "coins": "coins.png",
    "moon": "moon.png",
    "text": "text.png",
    "page": "page.png",
    "cell": "cell.png",
}

TRAIN_PHOTOS: tuple[str, ...] = (
    "astronaut", "chelsea", "coffee", "rocket", "brick",
    "grass", "gravel", "motorcycle_left", "hubble_deep_field", "retina",
)
TEST_PHOTOS: tuple[str, ...] = ("camera", "coins", "moon", "text", "page", "cell")

MOTIONS: tuple[str, ...] = ("translate", "rotate", "zoom", "occlude", "deform")

#: image-plane speeds (pixels per sub-frame) of the generated motion.
SPEED_RANGE: tuple[float, float] = (0.2, 2.0)

#: the named scenes besides the ``PHOTO-MOTION`` ones.
NAMED_SCENES: tuple[str, ...] = ("default", "default-static70")

#: held-out scenes of :func:`test_scenes`: every motion, on TEST_PHOTOS only.
TEST_SCENES: tuple[str, ...] = (
    "camera-translate", "moon-rotate", "cell-zoom", "coins-occlude", "page-deform", "text-translate",
)

# The foreground photo of a ``PHOTO-occlude`` scene: a partner from the same split.
_PARTNER_TEST = {"camera": "coins", "coins": "camera", "moon": "cell", "cell": "camera", "text": "page", "page": "text"}

# A crop is prefiltered this many pixels beyond the samples it serves, so that its border does
# not change the interpolated values (the cubic prefilter decays by 0.268 per pixel: 1e-7 at 12).
_SPLINE_MARGIN = 12

# skimage.color.rgb2gray's weights (ITU-R BT.709 luma).
_GREY_WEIGHTS = (0.2125, 0.7154, 0.0721)

Size = tuple[int, int]


class ClipList(list):
    """A list of clips that also records how each was made: ``meta`` holds one dict per clip
    (motion, photo, foreground, speed and the motion's parameters); ``photos`` is the set of
    photograph names the clips were cut from."""

    def __init__(self, clips=(), meta=()):
        super().__init__(clips)
        self.meta: list[dict[str, Any]] = list(meta)

    @property
    def photos(self) -> set[str]:
        used: set[str] = set()
        for m in self.meta:
            used.add(m["photo"])
            if m.get("foreground"):
                used.add(m["foreground"])
        return used


# ----------------------------------------------------------------------------- photographs
def data_dir() -> Path:
    """The installed ``skimage/data`` folder."""
    import skimage.data

    return Path(skimage.data.__file__).parent


def photo_path(name: str) -> Path:
    """The file of photograph ``name`` inside ``skimage/data`` (InputError if unknown or absent)."""
    if name not in PHOTO_FILES:
        raise InputError(f"photo {name!r}: not one of the scikit-image photographs ({', '.join(PHOTO_FILES)})")
    path = data_dir() / PHOTO_FILES[name]
    if not path.is_file():
        raise InputError(f"photo {name!r}: {path} is missing from the installed scikit-image")
    return path


def _to_grey(img: np.ndarray, where: str) -> np.ndarray:
    """Grey levels 0..255 float64 from an 8-bit grey, RGB or RGBA image."""
    if img.dtype == bool:
        img = img.astype(np.uint8) * 255
    elif img.dtype != np.uint8:
        raise InputError(f"{where}: expected 8-bit pixels, got {img.dtype}")
    a = img.astype(np.float64)
    if a.ndim == 2:
        return a
    if a.ndim == 3 and a.shape[2] in (3, 4):
        if a.shape[2] == 4:  # composite over white, as skimage.color.rgba2rgb does
            alpha = a[..., 3:4] / 255.0
            a = a[..., :3] * alpha + 255.0 * (1.0 - alpha)
        r, g, b = _GREY_WEIGHTS
        # skimage.color.rgb2gray's weighted sum, written out so that it does not go through a
        # BLAS product (bit-identical on every CPU)
        return a[..., 0] * r + a[..., 1] * g + a[..., 2] * b
    raise InputError(f"{where}: expected a grey or RGB image, got shape {img.shape}")


@lru_cache(maxsize=None)
def _photo_cached(name: str) -> np.ndarray:
    import skimage.io

    path = photo_path(name)
    try:
        img = skimage.io.imread(path)
    except Exception as exc:  # pragma: no cover - a damaged installation
        raise InputError(f"photo {path}: cannot be read ({exc})") from None
    grey = np.clip(_to_grey(np.asarray(img), str(path)), 0.0, 255.0).astype(np.float32)
    grey.setflags(write=False)
    return grey


def photo(name: str) -> np.ndarray:
    """Photograph ``name`` as (H, W) float32 grey levels 0..255 (a fresh, writable copy)."""
    return _photo_cached(name).copy()


def _image(p: str | np.ndarray, where: str) -> np.ndarray:
    """A photo name or a 2-D array -> a 2-D float64 image."""
    if isinstance(p, str):
        return _photo_cached(p).astype(np.float64)
    a = np.asarray(p)
    if a.ndim != 2 or a.shape[0] < 2 or a.shape[1] < 2:
        raise InputError(f"{where}: photo must be a 2-D image (H, W) of at least 2x2, got shape {a.shape}")
    if not np.all(np.isfinite(a)):
        raise InputError(f"{where}: photo contains NaN or infinite values")
    return a.astype(np.float64)


# ----------------------------------------------------------------------------- checks
def _int(v: Any, name: str, where: str, lowest: int) -> int:
    if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < lowest:
        kind = "a positive" if lowest == 1 else "a non-negative"
        raise InputError(f"{where}: {name} must be {kind} integer, got {v!r}")
    return int(v)


def _size(size: Any, where: str) -> Size:
    try:
        vals = tuple(size)
        h, w = (int(v) for v in vals)
        ok = all(float(v) == int(v) for v in vals)
    except (TypeError, ValueError):
        raise InputError(f"{where}: size must be (H, W), got {size!r}") from None
    if not ok or h < 4 or w < 4:
        raise InputError(f"{where}: size must be two integers >= 4, got {size!r}")
    return h, w


def _pair(v: Any, name: str, where: str) -> tuple[float, float]:
    try:
        a, b = (float(x) for x in v)
    except (TypeError, ValueError):
        raise InputError(f"{where}: {name} must be a pair (y, x), got {v!r}") from None
    if not (math.isfinite(a) and math.isfinite(b)):
        raise InputError(f"{where}: {name} must be finite, got {v!r}")
    return a, b


def _finite(v: Any, name: str, where: str) -> float:
    try:
        f = float(v)
    except (TypeError, ValueError):
        raise InputError(f"{where}: {name} must be a number, got {v!r}") from None
    if not math.isfinite(f):
        raise InputError(f"{where}: {name} must be finite, got {v!r}")
    return f


def _positive(v: Any, name: str, where: str) -> float:
    f = _finite(v, name, where)
    if f <= 0:
        raise InputError(f"{where}: {name} must be positive, got {v!r}")
    return f


def _rng(rng: Any, where: str) -> np.random.Generator:
    if rng is None:  # a fixed stream: the same call gives the same clip
        return np.random.default_rng(0)
    if not isinstance(rng, np.random.Generator):
        raise InputError(f"{where}: rng must be a numpy.random.Generator (numpy.random.default_rng(seed))")
    return rng


# ----------------------------------------------------------------------------- sampling
def _render(img: np.ndarray, ys: np.ndarray, xs: np.ndarray) -> np.ndarray:
    """Cubic-spline samples of ``img`` at (ys, xs) with ``mode="reflect"``, float64.

    Only the region the samples need (plus a margin) is prefiltered, once for all frames;
    samples outside the photo see its mirror image, as ``mode="reflect"`` gives.
    """
    m = _SPLINE_MARGIN
    h0, w0 = img.shape
    y0 = int(math.floor(float(ys.min()))) - m
    y1 = int(math.ceil(float(ys.max()))) + m + 1
    x0 = int(math.floor(float(xs.min()))) - m
    x1 = int(math.ceil(float(xs.max()))) + m + 1
    if y1 <= 0 or x1 <= 0 or y0 >= h0 or x0 >= w0:
        raise InputError(f"synth: the samples ({y0}..{y1}, {x0}..{x1}) miss the {h0}x{w0} photo entirely")
    region = img[max(y0, 0) : min(y1, h0), max(x0, 0) : min(x1, w0)]
    pad = [[max(0, -y0), max(0, y1 - h0)], [max(0, -x0), max(0, x1 - w0)]]
    while any(p for pair in pad for p in pair):
        # np.pad's "symmetric" is scipy's "reflect"; each step at most mirrors the whole region
        step = [[min(p, region.shape[ax]) for p in pad[ax]] for ax in range(2)]
        region = np.pad(region, step, mode="symmetric")
        pad = [[p - s for p, s in zip(pad[ax], step[ax])] for ax in range(2)]
    coeffs = ndimage.spline_filter(region, order=3, mode="reflect", output=np.float64)
    return ndimage.map_coordinates(coeffs, [ys - y0, xs - x0], order=3, mode="reflect", prefilter=False)


def _finish(frames: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(np.clip(frames, 0.0, 255.0), dtype=np.float32)


def _fit_scale(shape: tuple[int, int], extent: tuple[float, float]) -> float:
    """Smallest magnification >= 1 of a photo of ``shape`` that holds a window of ``extent``."""
    return max(1.0, (extent[0] + 2.0) / (shape[0] - 1.0), (extent[1] + 2.0) / (shape[1] - 1.0))


def _choose(rng: np.random.Generator, img: np.ndarray, scale: float, extent: tuple[float, float],
            min_std: float, tries: int = 12) -> tuple[float, float]:
    """Top-left corner (in photo coordinates magnified by ``scale``) of a window of ``extent``.

    Drawn uniformly among the positions that keep the window inside the photo; with
    ``min_std > 0`` up to ``tries`` positions are drawn and the first whose photo content has
    that standard deviation (else the most textured one) is kept.
    """
    hi_y = (img.shape[0] - 1.0) * scale - extent[0] - 1.0
    hi_x = (img.shape[1] - 1.0) * scale - extent[1] - 1.0
    best, best_std = (1.0, 1.0), -1.0
    for _ in range(tries if min_std > 0 else 1):
        y = float(rng.uniform(1.0, hi_y)) if hi_y > 1.0 else max(0.0, (hi_y + 1.0) / 2)
        x = float(rng.uniform(1.0, hi_x)) if hi_x > 1.0 else max(0.0, (hi_x + 1.0) / 2)
        if min_std <= 0:
            return y, x
        r0, c0 = int(y / scale), int(x / scale)
        r1, c1 = int((y + extent[0]) / scale) + 1, int((x + extent[1]) / scale) + 1
        std = float(img[r0:r1, c0:c1].std())
        if std >= min_std:
            return y, x
        if std > best_std:
            best, best_std = (y, x), std
    return best


def _grid(size: Size) -> tuple[np.ndarray, np.ndarray]:
    h, w = size
    return np.arange(h, dtype=np.float64)[:, None], np.arange(w, dtype=np.float64)[None, :]


def _scale(scale: Any, img: np.ndarray, ext: tuple[float, float], where: str) -> float:
    return _positive(scale, "scale", where) if scale is not None else _fit_scale(img.shape, ext)


# ----------------------------------------------------------------------------- motions
def translate(photo: str | np.ndarray, *, frames: int, size: Size, velocity: tuple[float, float],
              rng: np.random.Generator | None = None, origin: tuple[float, float] | None = None,
              scale: float | None = None, min_std: float = 0.0) -> np.ndarray:
    """A ``size`` crop window moving over ``photo``; the content moves by ``velocity`` = (vy, vx)
    pixels per frame: ``out[t + 1][y + vy, x + vx] == out[t][y, x]``.

    ``photo``: a photograph name or a 2-D array. ``origin``: coordinates, in the photo magnified
    by ``scale``, of output pixel (0, 0) at t = 0 (drawn with ``rng`` when None). ``scale``:
    magnification of the photo (default 1, or the least that holds the whole path when the
    photo is too small). ``min_std``: prefer a drawn position whose content has this std.
    """
    where = "synth.translate"
    F, (H, W) = _int(frames, "frames", where, 1), _size(size, where)
    vy, vx = _pair(velocity, "velocity", where)
    img = _image(photo, where)
    ext = (H - 1 + abs(vy) * (F - 1), W - 1 + abs(vx) * (F - 1))
    s = _scale(scale, img, ext, where)
    if origin is None:
        top = _choose(_rng(rng, where), img, s, ext, min_std)
        # the window's top-left at time t is origin - v t; the path's bounding box starts at top
        origin = (top[0] + max(0.0, vy * (F - 1)), top[1] + max(0.0, vx * (F - 1)))
    oy, ox = _pair(origin, "origin", where)
    i, j = _grid((H, W))
    t = np.arange(F, dtype=np.float64)[:, None, None]
    ys = np.broadcast_to((oy - vy * t + i[None]) / s, (F, H, W))
    xs = np.broadcast_to((ox - vx * t + j[None]) / s, (F, H, W))
    return _finish(_render(img, ys, xs))


def rotate(photo: str | np.ndarray, *, frames: int, size: Size, omega_deg_per_frame: float,
           rng: np.random.Generator | None = None, centre: tuple[float, float] | None = None,
           scale: float | None = None, min_std: float = 0.0) -> np.ndarray:
    """The content of a ``size`` crop turning about the crop centre by ``omega_deg_per_frame``
    degrees per frame (a pixel at radius r moves r * radians(omega) pixels per frame).

    ``centre``: coordinates, in the photo magnified by ``scale``, of the crop centre (drawn
    when None); ``scale`` and ``min_std`` as in :func:`translate`.
    """
    where = "synth.rotate"
    F, (H, W) = _int(frames, "frames", where, 1), _size(size, where)
    omega = math.radians(_finite(omega_deg_per_frame, "omega_deg_per_frame", where))
    img = _image(photo, where)
    cy, cx = (H - 1) / 2.0, (W - 1) / 2.0
    radius = math.hypot(cy, cx)
    ext = (2 * radius, 2 * radius)
    s = _scale(scale, img, ext, where)
    if centre is None:
        top = _choose(_rng(rng, where), img, s, ext, min_std)
        centre = (top[0] + radius, top[1] + radius)
    py0, px0 = _pair(centre, "centre", where)
    i, j = _grid((H, W))
    py, px = i - cy, j - cx
    ys = np.empty((F, H, W))
    xs = np.empty((F, H, W))
    for t in range(F):
        c, sn = math.cos(omega * t), math.sin(omega * t)
        # sample at R(-theta) p so that the content turns by +theta
        ys[t] = (py0 + c * py + sn * px) / s
        xs[t] = (px0 - sn * py + c * px) / s
    return _finish(_render(img, ys, xs))


def zoom(photo: str | np.ndarray, *, frames: int, size: Size, rate_per_frame: float,
         rng: np.random.Generator | None = None, centre: tuple[float, float] | None = None,
         scale: float | None = None, min_std: float = 0.0) -> np.ndarray:
    """Magnification about the crop centre changing by ``(1 + rate_per_frame)`` per frame:
    frame t shows the crop magnified ``(1 + rate) ** t``, a pixel at radius r moves about
    r * rate pixels per frame; a negative rate zooms out. ``centre``, ``scale``, ``min_std``
    as in :func:`rotate`."""
    where = "synth.zoom"
    F, (H, W) = _int(frames, "frames", where, 1), _size(size, where)
    rate = _finite(rate_per_frame, "rate_per_frame", where)
    if rate <= -1.0:
        raise InputError(f"{where}: rate_per_frame must be > -1, got {rate_per_frame!r}")
    img = _image(photo, where)
    mags = [math.pow(1.0 + rate, t) for t in range(F)]
    zmin = min(mags)
    cy, cx = (H - 1) / 2.0, (W - 1) / 2.0
    ext = ((H - 1) / zmin, (W - 1) / zmin)
    s = _scale(scale, img, ext, where)
    if centre is None:
        top = _choose(_rng(rng, where), img, s, ext, min_std)
        centre = (top[0] + ext[0] / 2, top[1] + ext[1] / 2)
    py0, px0 = _pair(centre, "centre", where)
    i, j = _grid((H, W))
    ys = np.empty((F, H, W))
    xs = np.empty((F, H, W))
    for t, z in enumerate(mags):
        ys[t] = (py0 + (i - cy) / z) / s
        xs[t] = (px0 + (j - cx) / z) / s
    return _finish(_render(img, ys, xs))


def _sin_plane(ky: float, kx: float, phase: list[float], H: int, W: int) -> np.ndarray:
    """sin(ky*i + kx*j + phase[t]) on the (F, H, W) grid from scalar-libm 1-D values:
    sin(a + b) = sin a cos b + cos a sin b with a = ky*i + phase[t] and b = kx*j."""
    a = [[ky * i + p for i in range(H)] for p in phase]
    sa = np.array([[math.sin(v) for v in row] for row in a])[:, :, None]
    ca = np.array([[math.cos(v) for v in row] for row in a])[:, :, None]
    sb = np.array([math.sin(kx * j) for j in range(W)])[None, None, :]
    cb = np.array([math.cos(kx * j) for j in range(W)])[None, None, :]
    return sa * cb + ca * sb


def deform(photo: str | np.ndarray, *, frames: int, size: Size, amplitude: float,
           rng: np.random.Generator | None = None, phase_per_frame: float | None = None,
           wavelength: float | None = None, origin: tuple[float, float] | None = None,
           scale: float | None = None, min_std: float = 0.0) -> np.ndarray:
    """A smooth non-rigid warp of a fixed ``size`` crop: pixel p samples the photo at
    p + amplitude * (sin(k1 . p + phi1 + w t), sin(k2 . p + phi2 + w t)) (two plane waves of
    ``wavelength`` pixels, random directions and phases), w = ``phase_per_frame``: the warp
    travels and points move up to ``amplitude * phase_per_frame`` pixels per frame.

    ``phase_per_frame`` defaults to a peak speed drawn in :data:`SPEED_RANGE` divided by the
    amplitude; ``wavelength`` to a draw in [24, 64]; ``origin``, ``scale``, ``min_std`` as in
    :func:`translate`.
    """
    where = "synth.deform"
    F, (H, W) = _int(frames, "frames", where, 1), _size(size, where)
    A = _finite(amplitude, "amplitude", where)
    if A < 0:
        raise InputError(f"{where}: amplitude must be >= 0, got {amplitude!r}")
    rng = _rng(rng, where)
    img = _image(photo, where)
    lam = _positive(wavelength, "wavelength", where) if wavelength is not None else float(rng.uniform(24.0, 64.0))
    if phase_per_frame is None:
        omega = float(rng.uniform(*SPEED_RANGE)) / A if A > 0 else 0.0
    else:
        omega = _finite(phase_per_frame, "phase_per_frame", where)
    dirs = rng.uniform(0.0, 2 * math.pi, size=2).tolist()
    phis = rng.uniform(0.0, 2 * math.pi, size=2).tolist()
    ext = (H - 1 + 2 * A, W - 1 + 2 * A)
    s = _scale(scale, img, ext, where)
    if origin is None:
        top = _choose(rng, img, s, ext, min_std)
        origin = (top[0] + A, top[1] + A)
    oy, ox = _pair(origin, "origin", where)
    k = 2 * math.pi / lam
    sy = _sin_plane(k * math.sin(dirs[0]), k * math.cos(dirs[0]), [phis[0] + omega * t for t in range(F)], H, W)
    sx = _sin_plane(k * math.sin(dirs[1]), k * math.cos(dirs[1]), [phis[1] + omega * t for t in range(F)], H, W)
    i, j = _grid((H, W))
    ys = (oy + i[None] + A * sy) / s
    xs = (ox + j[None] + A * sx) / s
    return _finish(_render(img, ys, xs))


def _alpha(qy: np.ndarray, qx: np.ndarray, radius: float, edge: float, blob: float, blob_phase: float) -> np.ndarray:
    """Soft matte of a disc (``blob`` = 0) or rounded blob of ``radius`` about q = 0.

    The rim is r(theta) = radius * (1 + blob * (cos(2 theta + phi) + 0.5 cos(3 theta + 2 phi)) / 1.5),
    evaluated from q / |q| by the multiple-angle formulas (no arctan); the matte falls from 1
    to 0 across ``edge`` pixels with a smoothstep.
    """
    d = np.sqrt(qy * qy + qx * qx)
    if blob:
        safe = np.where(d > 0, d, 1.0)
        c, s = qx / safe, qy / safe
        c2, s2 = c * c - s * s, 2 * c * s
        c3, s3 = 4 * c**3 - 3 * c, 3 * s - 4 * s**3
        cp, sp = math.cos(blob_phase), math.sin(blob_phase)
        cp2, sp2 = math.cos(2 * blob_phase), math.sin(2 * blob_phase)
        wobble = (c2 * cp - s2 * sp) + 0.5 * (c3 * cp2 - s3 * sp2)
        rim = radius * (1.0 + blob * wobble / 1.5)
    else:
        rim = radius
    x = np.clip((rim - d) / edge + 0.5, 0.0, 1.0)
    return x * x * (3.0 - 2.0 * x)


def occlude(background: str | np.ndarray, foreground: str | np.ndarray, *, frames: int, size: Size,
            velocity: tuple[float, float], rng: np.random.Generator | None = None, radius: float | None = None,
            background_velocity: tuple[float, float] = (0.0, 0.0), start: tuple[float, float] | None = None,
            background_origin: tuple[float, float] | None = None, background_scale: float | None = None,
            source_centre: tuple[float, float] | None = None, source_radius: float | None = None,
            edge: float = 1.5, blob: float = 0.0, min_std: float = 0.0) -> np.ndarray:
    """An object cut from ``foreground`` crossing ``background`` (occlusion and disocclusion).

    The object is a disc of ``radius`` pixels (default 0.16 * min(H, W)) with a soft edge of
    ``edge`` pixels, or a rounded blob when ``blob`` > 0 (relative rim wobble, < 0.5). It moves
    rigidly by ``velocity`` (vy, vx) px/frame, its centre at ``start`` for t = 0 (default: a
    path through the middle of the frame, drawn with ``rng``). Its texture is the disc of
    ``source_radius`` photo pixels (default ``radius``) about ``source_centre`` (drawn when
    None) of the foreground photo, scaled to ``radius``. The background is :func:`translate` of
    ``background`` by ``background_velocity`` (static by default; ``background_origin`` and
    ``background_scale`` are translate's ``origin`` and ``scale``).
    """
    where = "synth.occlude"
    F, (H, W) = _int(frames, "frames", where, 1), _size(size, where)
    vy, vx = _pair(velocity, "velocity", where)
    rng = _rng(rng, where)
    R = _positive(radius, "radius", where) if radius is not None else 0.16 * min(H, W)
    edge = _positive(edge, "edge", where)
    blob = _finite(blob, "blob", where)
    if not 0 <= blob < 0.5:
        raise InputError(f"{where}: blob must be in [0, 0.5), got {blob!r}")
    bg = translate(background, frames=F, size=(H, W), velocity=background_velocity, rng=rng,
                   origin=background_origin, scale=background_scale, min_std=min_std).astype(np.float64)
    fg_img = _image(foreground, where)
    sr = _positive(source_radius, "source_radius", where) if source_radius is not None else R
    reach = (R * (1.0 + blob) + edge + 2.0)  # beyond this distance the matte is 0
    fg_scale = R / sr  # output pixels per source pixel
    if source_centre is None:
        ext = (2 * reach / fg_scale, 2 * reach / fg_scale)
        s_fit = _fit_scale(fg_img.shape, ext)
        top = _choose(rng, fg_img, s_fit, ext, min_std)
        source_centre = ((top[0] + ext[0] / 2) / s_fit, (top[1] + ext[1] / 2) / s_fit)
    scy, scx = _pair(source_centre, "source_centre", where)
    blob_phase = float(rng.uniform(0.0, 2 * math.pi)) if blob else 0.0
    if start is None:
        mid = ((H - 1) / 2 + float(rng.uniform(-0.15, 0.15)) * H, (W - 1) / 2 + float(rng.uniform(-0.15, 0.15)) * W)
        start = (mid[0] - vy * (F - 1) / 2, mid[1] - vx * (F - 1) / 2)
    c0y, c0x = _pair(start, "start", where)
    i, j = _grid((H, W))
    t = np.arange(F, dtype=np.float64)[:, None, None]
    qy = np.broadcast_to(i[None] - (c0y + vy * t), (F, H, W))
    qx = np.broadcast_to(j[None] - (c0x + vx * t), (F, H, W))
    alpha = _alpha(qy, qx, R, edge, blob, blob_phase)
    # texture coordinates, clamped where the matte is 0 so that the sampled region stays small
    fy = scy + np.clip(qy, -reach, reach) / fg_scale
    fx = scx + np.clip(qx, -reach, reach) / fg_scale
    fg = _render(fg_img, fy, fx)
    return _finish(np.where(alpha > 0, alpha * fg + (1.0 - alpha) * bg, bg))


# ----------------------------------------------------------------------------- scenes
#: the default scenes' parameters (pixels per frame; photo coordinates of camera / coins).
DEFAULT_DRIFT = (-0.12, -0.22)        # mild global drift of the background, 0.25 px/frame
DEFAULT_FG_VELOCITY = (0.30, 0.95)    # the coin, 1.0 px/frame
_DEFAULT_BG_CENTRE = (192.0, 262.0)   # camera: the cameraman's head, camera and skyline
_DEFAULT_COIN = (186.0, 347.0, 34.0)  # coins: centre and radius of the disc cut around a coin


def _default_scene(*, frames: int, size: Size, static70: bool) -> np.ndarray:
    """The ``default`` scene (or ``default-static70``): see :func:`make_scene`."""
    F, (H, W) = frames, size
    cam = _photo_cached("camera").astype(np.float64)
    coins = _photo_cached("coins").astype(np.float64)
    dy, dx = DEFAULT_DRIFT
    ext = (H - 1 + abs(dy) * (F - 1), W - 1 + abs(dx) * (F - 1))
    s = _fit_scale(cam.shape, ext)
    top_y = min(max(1.0, _DEFAULT_BG_CENTRE[0] * s - ext[0] / 2), (cam.shape[0] - 1) * s - ext[0] - 1)
    top_x = min(max(1.0, _DEFAULT_BG_CENTRE[1] * s - ext[1] / 2), (cam.shape[1] - 1) * s - ext[1] - 1)
    origin = (top_y + max(0.0, dy * (F - 1)), top_x + max(0.0, dx * (F - 1)))
    if static70:  # the motion is confined to a centred box of 30% of the area
        bh, bw = max(4, round(math.sqrt(0.3) * H)), max(4, round(math.sqrt(0.3) * W))
        by, bx = (H - bh) // 2, (W - bw) // 2
        mid = (by + (bh - 1) / 2, bx + (bw - 1) / 2)
        radius = 0.16 * min(bh, bw)
    else:
        mid = (0.45 * (H - 1), 0.40 * (W - 1))
        radius = 0.16 * min(H, W)
    vy, vx = DEFAULT_FG_VELOCITY
    start = (mid[0] - vy * (F - 1) / 2, mid[1] - vx * (F - 1) / 2)
    rng = np.random.default_rng(0)  # not drawn from: every placement below is explicit
    cy, cx, cr = _DEFAULT_COIN
    dyn = occlude(cam, coins, frames=F, size=(H, W), velocity=DEFAULT_FG_VELOCITY, rng=rng, radius=radius,
                  background_velocity=DEFAULT_DRIFT, background_origin=origin, background_scale=s, start=start,
                  source_centre=(cy, cx), source_radius=cr, edge=1.5, blob=0.0)
    if not static70:
        return dyn
    static = translate(cam, frames=1, size=(H, W), velocity=(0.0, 0.0), origin=origin, scale=s)[0]
    ramp = max(2.0, 0.03 * min(H, W))  # a soft border inside the box
    i = np.arange(H, dtype=np.float64)
    j = np.arange(W, dtype=np.float64)
    wy = np.clip(np.minimum(i - by + 0.5, by + bh - i - 0.5) / ramp, 0.0, 1.0)
    wx = np.clip(np.minimum(j - bx + 0.5, bx + bw - j - 0.5) / ramp, 0.0, 1.0)
    w = (wy[:, None] * wx[None, :])[None]
    still = static[None].astype(np.float64)
    return _finish(np.where(w > 0, w * dyn + (1.0 - w) * still, still))


def _partner(name: str) -> str:
    """The foreground photo of ``NAME-occlude``: another photo of the same split."""
    if name in _PARTNER_TEST:
        return _PARTNER_TEST[name]
    group = TRAIN_PHOTOS if name in TRAIN_PHOTOS else tuple(PHOTO_FILES)
    return group[(group.index(name) + 1) % len(group)]


def _standard_scene(name: str, motion: str, *, frames: int, size: Size, rng: np.random.Generator) -> np.ndarray:
    """``PHOTO-MOTION`` scenes: fixed speeds of about 1 px/frame, placement drawn from ``rng``."""
    H, W = size
    r = min(H, W) / 2.0
    common: dict[str, Any] = dict(frames=frames, size=size, rng=rng, min_std=20.0)
    if motion == "translate":  # 1.03 px/frame
        return translate(name, velocity=(0.5, 0.9), **common)
    if motion == "rotate":  # the inscribed circle moves 1 px/frame
        return rotate(name, omega_deg_per_frame=math.degrees(1.0 / r), **common)
    if motion == "zoom":  # the inscribed circle moves 1 px/frame
        return zoom(name, rate_per_frame=1.0 / r, **common)
    if motion == "occlude":  # a disc of radius 0.16 min(H, W) at 1.01 px/frame, static background
        return occlude(name, _partner(name), velocity=(0.35, 0.95), **common)
    if motion == "deform":  # 3 px waves of 48 px, peak speed 1 px/frame
        return deform(name, amplitude=3.0, phase_per_frame=1.0 / 3.0, wavelength=48.0, **common)
    raise AssertionError(motion)  # pragma: no cover


def _split_scene_name(spec: str) -> tuple[str, str] | None:
    if "-" not in spec:
        return None
    name, motion = spec.rsplit("-", 1)
    if name in PHOTO_FILES and motion in MOTIONS:
        return name, motion
    return None


def _known_scenes() -> str:
    return "expected " + ", ".join(NAMED_SCENES) + " or PHOTO-MOTION such as " + ", ".join(TEST_SCENES[:3])


def scene_photos(spec: str | Mapping[str, Any]) -> tuple[str, ...]:
    """Names of the photographs a scene spec is made from (``"train"``: the training set's)."""
    if isinstance(spec, Mapping):
        names = [spec.get(k) for k in ("photo", "background", "foreground")]
        return tuple(n for n in names if isinstance(n, str))
    if spec in NAMED_SCENES:
        return ("camera", "coins")
    if spec == "train":
        return TRAIN_PHOTOS
    parts = _split_scene_name(spec)
    if parts is None:
        raise InputError(f"synth:{spec}: unknown scene ({_known_scenes()})")
    name, motion = parts
    return (name, _partner(name)) if motion == "occlude" else (name,)


def _scene_rng(name: str, seed: int) -> np.random.Generator:
    return np.random.default_rng([int(seed), zlib.crc32(name.encode())])


def make_scene(spec: str | Mapping[str, Any], *, frames: int, size: Size = (256, 256), seed: int = 0) -> np.ndarray:
    """A scene (frames, H, W) float32 from a generator spec.

    ``spec`` is

    - ``"default"``: the ``camera`` photo (the cameraman's head, camera and skyline) as the
      background, drifting 0.25 px/frame (mild global camera drift), with a coin cut from
      ``coins`` (a soft-edged disc of radius 0.16 * min(H, W): 41 px at 256x256) crossing it at
      1.0 px/frame through the upper-left middle of the frame, in front of the head;
    - ``"default-static70"``: the same, but the drift and the coin (radius 22 px at 256x256)
      are confined to a centred box of 30% of the frame area (with a soft border inside the
      box): the other 70% of the pixels are exactly constant over time;
    - ``"PHOTO-MOTION"`` (e.g. ``"camera-translate"``, ``"coins-occlude"``): that motion of that
      photograph at about 1 px/frame, placed at random by ``seed``;
    - a dict ``{"motion": M, "photo": P, ...}`` with the keyword arguments of the motion
      function (``"foreground"`` for ``occlude``); ``seed`` draws what is not given.

    The two ``default`` scenes are fixed: they do not depend on ``seed``.
    """
    where = f"synth:{spec}" if isinstance(spec, str) else "synth:{...}"
    F = _int(frames, "frames", where, 1)
    hw = _size(size, where)
    seed = _int(seed, "seed", where, 0)
    if isinstance(spec, Mapping):
        return _dict_scene(dict(spec), frames=F, size=hw, seed=seed)
    if not isinstance(spec, str):
        raise InputError(f"synth: a scene spec is a name or a dict, got {type(spec).__name__}")
    if spec in NAMED_SCENES:
        return _default_scene(frames=F, size=hw, static70=spec == "default-static70")
    if spec == "train":
        raise InputError(f"{where}: the training set is many clips; use synth.training_videos")
    parts = _split_scene_name(spec)
    if parts is None:
        raise InputError(f"{where}: unknown scene ({_known_scenes()})")
    return _standard_scene(parts[0], parts[1], frames=F, size=hw, rng=_scene_rng(spec, seed))


_MOTION_FUNCS = {"translate": translate, "rotate": rotate, "zoom": zoom, "occlude": occlude, "deform": deform}


def _dict_scene(spec: dict[str, Any], *, frames: int, size: Size, seed: int) -> np.ndarray:
    motion = spec.pop("motion", None)
    where = f"synth:{{motion: {motion}}}"
    if motion not in _MOTION_FUNCS:
        raise InputError(f"{where}: 'motion' must be one of {', '.join(MOTIONS)}")
    for key in ("frames", "size", "rng", "seed"):
        if key in spec:
            raise InputError(f"{where}: {key!r} is not a scene key (frames, size and seed are arguments)")
    key = "background" if motion == "occlude" and "background" in spec else "photo"
    name = spec.pop(key, None)
    if not isinstance(name, str):
        raise InputError(f"{where}: needs 'photo' (a scikit-image photograph name)")
    args: list[str] = [name]
    if motion == "occlude":
        fg = spec.pop("foreground", None)
        if not isinstance(fg, str):
            raise InputError(f"{where}: needs 'foreground' (a scikit-image photograph name)")
        args.append(fg)
    spec = {k: tuple(v) if isinstance(v, list) else v for k, v in spec.items()}
    rng = _scene_rng(":".join([motion, *args]), seed)
    try:
        return _MOTION_FUNCS[motion](*args, frames=frames, size=size, rng=rng, **spec)
    except TypeError as exc:
        raise InputError(f"{where}: bad key ({exc})") from None


# ----------------------------------------------------------------------------- sets
def _direction(rng: np.random.Generator, speed: float) -> tuple[float, float]:
    a = float(rng.uniform(0.0, 2 * math.pi))
    return speed * math.sin(a), speed * math.cos(a)


def training_videos(*, frames: int, count: int, size: Size = (64, 64), seed: int = 0,
                    length: int | None = None) -> ClipList:
    """``count`` random clips (length, H, W) float32 cut ONLY from :data:`TRAIN_PHOTOS`.

    Each clip has a random motion among :data:`MOTIONS` with image speeds drawn in
    :data:`SPEED_RANGE` (translation: speed and direction; rotation and zoom: the speed of the
    crop's inscribed circle; occlusion: the object's speed over a background that is static or
    drifts up to 0.3 px/frame; deformation: the peak speed of the warp), placed where the photo
    has texture. ``length`` (default ``frames``) may be longer than the number of sub-frames.
    The returned list carries ``.meta`` (one dict per clip) and ``.photos`` (names used).
    """
    where = "synth.training_videos"
    F = _int(frames, "frames", where, 1)
    L = F if length is None else _int(length, "length", where, 1)
    if L < F:
        raise InputError(f"{where}: length {L} is shorter than frames {F}")
    n = _int(count, "count", where, 0)
    H, W = _size(size, where)
    rng = np.random.default_rng(_int(seed, "seed", where, 0))
    r = min(H, W) / 2.0
    clips: list[np.ndarray] = []
    meta: list[dict[str, Any]] = []
    for _ in range(n):
        motion = MOTIONS[int(rng.integers(len(MOTIONS)))]
        name = TRAIN_PHOTOS[int(rng.integers(len(TRAIN_PHOTOS)))]
        speed = float(rng.uniform(*SPEED_RANGE))
        sign = 1.0 if rng.random() < 0.5 else -1.0
        common: dict[str, Any] = dict(frames=L, size=(H, W), rng=rng, min_std=10.0)
        m: dict[str, Any] = {"motion": motion, "photo": name, "foreground": None, "speed": speed}
        if motion == "translate":
            m["velocity"] = _direction(rng, speed)
            clip = translate(name, velocity=m["velocity"], **common)
        elif motion == "rotate":
            m["omega_deg_per_frame"] = sign * math.degrees(speed / r)
            clip = rotate(name, omega_deg_per_frame=m["omega_deg_per_frame"], **common)
        elif motion == "zoom":
            m["rate_per_frame"] = max(-0.5, sign * speed / r)
            clip = zoom(name, rate_per_frame=m["rate_per_frame"], **common)
        elif motion == "occlude":
            others = [p for p in TRAIN_PHOTOS if p != name]
            fg = others[int(rng.integers(len(others)))]
            v = _direction(rng, speed)
            bgv = (0.0, 0.0) if rng.random() < 0.5 else _direction(rng, float(rng.uniform(0.0, 0.3)))
            radius = float(rng.uniform(0.2, 0.45)) * min(H, W)
            m.update(foreground=fg, velocity=v, background_velocity=bgv, radius=radius,
                     blob=float(rng.uniform(0.0, 0.15)), source_radius=radius * float(rng.uniform(0.7, 1.4)))
            clip = occlude(name, fg, velocity=v, background_velocity=bgv, radius=radius, blob=m["blob"],
                           source_radius=m["source_radius"], **common)
        else:  # deform
            amp = float(rng.uniform(1.0, 4.0))
            m.update(amplitude=amp, phase_per_frame=speed / amp,
                     wavelength=max(8.0, float(rng.uniform(0.4, 1.2)) * min(H, W)))
            clip = deform(name, amplitude=amp, phase_per_frame=m["phase_per_frame"], wavelength=m["wavelength"],
                          **common)
        clips.append(clip)
        meta.append(m)
    return ClipList(clips, meta)


def test_scenes(*, frames: int, size: Size = (256, 256), seed: int = 0) -> dict[str, np.ndarray]:
    """The held-out scenes :data:`TEST_SCENES` (TEST_PHOTOS only, every motion type)."""
    return {name: make_scene(name, frames=frames, size=size, seed=seed) for name in TEST_SCENES}


test_scenes.__test__ = False  # a generator, not a pytest test, despite its name
