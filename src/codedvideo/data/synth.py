"""Synthetic high-frame-rate videos from real photographs shipped with scikit-image.

No download is needed: the photographs are files inside the installed
scikit-image package, listed with their checksums in ``data_manifest``.
Training motions run at 0.2 to 4 pixels per sub-frame (a 300 to 1000 fps camera
sees up to about 2; ordinary footage more): translation, rotation, zoom, occlusion by a moving object and a
smooth non-rigid deformation, all with sub-pixel accuracy (cubic splines).

Photographs are split once and for all: dictionaries are trained on
``TRAIN_PHOTOS`` only, scenes for evaluation use ``TEST_PHOTOS`` only.
Frames are float32 grey levels in 0..255, time first ``(F, H, W)``.
"""

from __future__ import annotations

import functools
from pathlib import Path

import numpy as np

from codedvideo.model.errors import InputError

# photographs whose scikit-image docstrings state a public-domain or CC0 licence
TRAIN_PHOTOS = ("astronaut", "chelsea", "coffee", "rocket", "brick", "grass", "gravel", "hubble_deep_field", "retina")
TEST_PHOTOS = ("camera", "coins", "text", "cell")
MOTIONS = ("translate", "rotate", "zoom", "occlude", "deform")
#: Speeds of the training motion, pixels per sub-frame (log-uniform).  Up to 2 covers a
#: 300 to 1000 fps camera; up to 4 also covers the faster motion of ordinary footage and
#: measured better on the held-out real clips (+0.3 dB mean, +3 dB on the fastest scene)
#: for 0.4 dB less on the slow synthetic test scenes (README, "Reconstruction quality").
MIN_SPEED, MAX_SPEED = 0.2, 4.0


def photo_path(name: str) -> Path:
    """Path of a photograph inside the installed scikit-image package."""
    import skimage.data

    folder = Path(skimage.data.__file__).parent
    for suffix in (".png", ".jpg"):
        p = folder / f"{name}{suffix}"
        if p.exists():
            return p
    raise InputError(f"photo {name}: not found in {folder} (scikit-image data)")


@functools.lru_cache(maxsize=32)
def _photo_cached(name: str) -> np.ndarray:
    from skimage.color import rgb2gray
    from skimage.io import imread

    img = imread(photo_path(name))
    if img.ndim == 3:
        img = rgb2gray(img[..., :3]) * 255.0
    elif img.dtype == bool:
        img = img * 255.0
    img = np.asarray(img, np.float32)
    if img.max() <= 1.0:
        img = img * 255.0
    img.setflags(write=False)
    return img


def photo(name: str) -> np.ndarray:
    """A photograph as (H, W) float32 grey levels 0..255."""
    return _photo_cached(name).copy()


def _affine_frames(img, size, frames, matrix_at, shift_at, order=3):
    """Frame t samples ``img`` at ``centre + matrix_at(t) @ (p - out_centre) + shift_at(t)``."""
    from scipy import ndimage  # lazy (see baselines.normalized_fill)

    h, w = size
    src_c = np.array(img.shape, float) / 2.0
    out_c = np.array([h, w], float) / 2.0
    coeffs = ndimage.spline_filter(img, order=order, mode="mirror") if order > 1 else img
    out = np.empty((frames, h, w), np.float32)
    for t in range(frames):
        A = matrix_at(t)
        offset = src_c + np.asarray(shift_at(t), float) - A @ out_c
        out[t] = ndimage.affine_transform(coeffs, A, offset=offset, output_shape=(h, w), order=order,
                                          mode="mirror", prefilter=False)
    return np.clip(out, 0, 255)


def translate(img, *, frames, size, velocity=(0.0, 1.0), origin=(0.0, 0.0)):
    """A crop window moving over the photo at ``velocity`` (pixels per sub-frame)."""
    v = np.asarray(velocity, float)
    return _affine_frames(img, size, frames, lambda t: np.eye(2), lambda t: np.asarray(origin) + v * t)


def rotate(img, *, frames, size, omega_deg=0.5):
    """Rotation about the crop centre, ``omega_deg`` degrees per sub-frame."""
    def mat(t):
        a = np.deg2rad(omega_deg * t)
        return np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    return _affine_frames(img, size, frames, mat, lambda t: (0.0, 0.0))


def zoom(img, *, frames, size, rate=0.01):
    """Scale changes by ``(1 + rate)`` per sub-frame about the centre."""
    return _affine_frames(img, size, frames, lambda t: np.eye(2) / (1.0 + rate) ** t, lambda t: (0.0, 0.0))


def deform(img, *, frames, size, amplitude=2.0, wavelength=40.0, speed=0.15):
    """A smooth non-rigid sinusoidal warp whose phase advances ``speed`` rad per sub-frame."""
    from scipy import ndimage  # lazy (see baselines.normalized_fill)

    h, w = size
    yy, xx = np.mgrid[0:h, 0:w].astype(float)
    y0 = (img.shape[0] - h) / 2.0
    x0 = (img.shape[1] - w) / 2.0
    coeffs = ndimage.spline_filter(img, order=3, mode="mirror")
    out = np.empty((frames, h, w), np.float32)
    k = 2 * np.pi / wavelength
    for t in range(frames):
        dy = amplitude * np.sin(k * xx + speed * t)
        dx = amplitude * np.cos(k * yy - speed * t)
        out[t] = ndimage.map_coordinates(coeffs, [yy + y0 + dy, xx + x0 + dx], order=3, mode="mirror", prefilter=False)
    return np.clip(out, 0, 255)


def _disc_alpha(size, centre, radius, softness=1.5):
    yy, xx = np.mgrid[0 : size[0], 0 : size[1]]
    d = np.hypot(yy - centre[0], xx - centre[1])
    return np.clip((radius - d) / softness + 0.5, 0.0, 1.0).astype(np.float32)


def occlude(background, foreground, *, frames, size, velocity=(0.3, 1.5), radius=None, drift=(0.0, 0.0), start=None):
    """A (drifting) background crossed by a moving disc cut from another photo."""
    h, w = size
    disc_radius = radius or 0.22 * min(h, w)
    bg = translate(background, frames=frames, size=size, velocity=drift)
    fg = translate(foreground, frames=frames, size=size, velocity=velocity)
    origin = np.array(start if start is not None else (h * 0.45, w * 0.3), float)
    v = np.asarray(velocity, float)
    out = np.empty_like(bg)
    for t in range(frames):
        a = _disc_alpha(size, origin + v * t, disc_radius)
        out[t] = a * fg[t] + (1 - a) * bg[t]
    return out


def _static70(frames, size):
    """camera, still on the left 70 % of the frame; coins texture moving on the right 30 %."""
    h, w = size
    still = translate(photo("camera"), frames=1, size=size)[0]
    moving = translate(photo("coins"), frames=frames, size=size, velocity=(0.4, 1.2))
    out = np.repeat(still[None], frames, axis=0)
    x_cut = int(round(0.7 * w))
    out[:, :, x_cut:] = moving[:, :, x_cut:]
    return out


def make_scene(spec: str, *, frames: int, size=(256, 256), seed: int = 0) -> np.ndarray:
    """A named scene ``(frames, H, W)``.

    Names: ``default`` (camera drifting slowly, crossed by a disc of coins at
    1.5 px/sub-frame), ``default-static70`` (70 % of the frame still),
    ``PHOTO-MOTION`` for any test photo and motion (e.g. ``coins-rotate``),
    and ``train-K`` for the K-th training clip.
    """
    hw = tuple(int(s) for s in size)
    if spec == "default":
        return occlude(photo("camera"), photo("coins"), frames=frames, size=hw,
                       velocity=(0.4, 1.5), drift=(0.15, 0.25))
    if spec == "default-static70":
        return _static70(frames, hw)
    if spec.startswith("train-"):
        k = int(spec.split("-", 1)[1])
        return training_videos(frames=frames, count=k + 1, size=hw, seed=seed)[k]
    if "-" in spec:
        name, motion = spec.rsplit("-", 1)
        if name in TEST_PHOTOS + TRAIN_PHOTOS and motion in MOTIONS:
            return _clip(name, motion, frames=frames, size=hw, rng=np.random.default_rng(seed), speed=1.0)
    raise InputError(f"scene {spec!r}: unknown synthetic scene (default, default-static70, PHOTO-MOTION, train-K)")


def _clip(name, motion, *, frames, size, rng, speed):
    """One clip of ``motion`` on photo ``name``; ``speed`` in pixels per sub-frame."""
    img = photo(name)
    angle = rng.uniform(0, 2 * np.pi)
    v = speed * np.array([np.sin(angle), np.cos(angle)])
    origin = rng.uniform(-0.25, 0.25, 2) * (np.array(img.shape) - np.array(size)).clip(0)
    if motion == "translate":
        return translate(img, frames=frames, size=size, velocity=v, origin=origin)
    if motion == "rotate":  # edge of the crop moves ~speed px per frame
        return rotate(img, frames=frames, size=size, omega_deg=np.rad2deg(speed / (0.5 * max(size))) * rng.choice([-1, 1]))
    if motion == "zoom":
        return zoom(img, frames=frames, size=size, rate=speed / (0.5 * max(size)) * rng.choice([-1, 1]))
    if motion == "deform":
        return deform(img, frames=frames, size=size, amplitude=1.0 + 2 * rng.random(), wavelength=rng.uniform(20, 60),
                      speed=speed / 2.0)
    if motion == "occlude":
        pool = TEST_PHOTOS if name in TEST_PHOTOS else TRAIN_PHOTOS
        other = pool[(pool.index(name) + 1 + rng.integers(len(pool) - 1)) % len(pool)]
        start = rng.uniform(0.25, 0.75, 2) * np.array(size)
        return occlude(img, photo(other), frames=frames, size=size, velocity=v, start=start,
                       drift=v * rng.uniform(0, 0.3), radius=rng.uniform(0.15, 0.35) * min(size))
    raise InputError(f"motion {motion!r}: unknown (choose from {', '.join(MOTIONS)})")


def training_videos(
    *, frames: int, count: int, size=(64, 64), seed: int = 0, length: int | None = None,
    max_speed: float = MAX_SPEED,
) -> list[np.ndarray]:
    """``count`` random clips from the training photographs only.

    Each clip draws a photo, a motion and a speed (log-uniform from 0.2 to
    ``max_speed`` px per sub-frame) from a seed derived per clip, so clip ``k``
    does not depend on ``count``.
    """
    clip_frames = length or frames
    clips = []
    for k, child in enumerate(np.random.SeedSequence(seed).spawn(count)):
        rng = np.random.default_rng(child)
        name = TRAIN_PHOTOS[rng.integers(len(TRAIN_PHOTOS))]
        motion = MOTIONS[rng.integers(len(MOTIONS))]
        speed = float(np.exp(rng.uniform(np.log(MIN_SPEED), np.log(max_speed))))
        clips.append(_clip(name, motion, frames=clip_frames, size=size, rng=rng, speed=speed))
    return clips
