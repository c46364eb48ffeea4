"""The forward model of a coded-exposure camera and its adjoint.

Sum convention (Hitomi et al. 2011, Eq. 1), used everywhere in codedvideo::

    I(y, x) = sum_t S(t, y, x) * E(t, y, x)

A pixel open for ``k`` sub-frames records the *sum* of ``k`` frame values, in the
units of the frames (no division by the bump length).  ``S`` is a binary code,
or a *calibrated* mask: the response of every pixel in every sub-frame as the
sensor measures it (a DMD or LCoS pattern imaged through the optics gives
fractional, slightly misregistered weights in [0, 1]; :func:`blur_shift_mask`
makes one from a binary code).  Every function here takes either as the exact
forward model; a pixel is measured when its weights sum to more than 0.

The measurement of a simulated camera is ``sensor(noise(S E))`` (:func:`measure`,
described by a :class:`SensorModel`), every part optional:

1. photon shot noise: the clean coded image ``S E`` (grey levels) times the
   ``gain`` (electrons per grey level) is the mean of a Poisson electron count,
   which saturates at the ``full_well`` capacity; divided by the gain again it
   is back in grey levels;
2. Gaussian read noise of standard deviation ``read_sigma`` grey levels;
3. the sensor's output: the ``black_level`` offset added once per read-out
   (so that read noise around a dark signal is not clipped), then clipping at
   the ``white_level`` (saturation) and quantisation to ``bits`` bits.  With
   both, the ADC maps ``[0, white_level]`` onto ``2**bits`` levels; with
   ``bits`` alone one level is one grey level (``[0, 2**bits - 1]``).  The
   result stays in grey levels (float32); with a black level it is a *raw*
   value, ``sum of frames + black_level``, which
   :func:`codedvideo.model.sensor.correct_raw` turns back into the sum convention.

Noise streams are independent and seeded: read noise is drawn from the given
generator (so plain read noise is exactly what :func:`add_read_noise` draws),
shot noise from a child of its ``SeedSequence`` (``Generator.spawn``).

A saturated pixel recorded the white level, not the sum of its frames: with
:func:`saturated_as_missing` reconstruction treats it as not measured.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from codedvideo.model.errors import InputError


def check_pair(coded_shape: tuple, mask_shape: tuple, *, where: str = "") -> None:
    """Raise :class:`InputError` unless ``mask (N, H, W)`` matches ``coded (H, W)``."""
    if len(mask_shape) != 3 or tuple(mask_shape[1:]) != tuple(coded_shape):
        pre = f"{where}: " if where else ""
        raise InputError(
            f"{pre}mask shape {tuple(mask_shape)} does not match coded image {tuple(coded_shape)} "
            "(expected (N, H, W) with the coded image's H, W)"
        )


def forward(video: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Coded exposure ``I = sum_t S E``.

    Parameters
    ----------
    video : ndarray of shape (N, H, W)
    mask : ndarray of shape (N, H, W)
        Binary, or calibrated weights in [0, 1] (used in float32).

    Returns
    -------
    coded : ndarray of shape (H, W), float32
    """
    video_arr, mask_arr = np.asanyarray(video), np.asanyarray(mask)
    if video_arr.shape != mask_arr.shape:
        raise InputError(f"forward: video shape {video_arr.shape} != mask shape {mask_arr.shape}")
    n, h, w = video_arr.shape
    coded = np.empty((h, w), np.float32)
    # a band of rows at a time: the float32 copies of a band of the mask (and of a video in another type) stay
    # small (a whole 4K N = 18 mask's copy was a second 600 MB volume); each pixel's sum is the same either way
    rows = max(1, _BAND_ELEMENTS // max(n * w, 1))
    for y in range(0, h, rows):
        band = (slice(None), slice(y, y + rows))
        np.einsum("thw,thw->hw", np.asarray(video_arr[band], np.float32), np.asarray(mask_arr[band], np.float32),
                  out=coded[y:y + rows], dtype=np.float32)
    return coded


#: Elements of a band of :func:`forward`'s rows (its float32 copies of the mask and video: 16 MB each).
_BAND_ELEMENTS = 1 << 22


def adjoint(coded: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Adjoint of :func:`forward`: ``E(t) = S(t) * I``, shape (N, H, W) float32."""
    check_pair(np.shape(coded), np.shape(mask))
    return np.asarray(mask, dtype=np.float32) * np.asarray(coded, dtype=np.float32)[None]


def add_read_noise(coded: np.ndarray, sigma: float, rng: np.random.Generator | int | None) -> np.ndarray:
    """Add Gaussian read noise of standard deviation ``sigma`` (frame units)."""
    if sigma < 0 or not np.isfinite(sigma):
        raise InputError(f"noise: sigma must be finite and >= 0, got {sigma}")
    image = np.asarray(coded, dtype=np.float32)
    if sigma == 0:
        return image.copy()
    gen = np.random.default_rng(rng)
    return (image + gen.normal(0.0, sigma, size=image.shape)).astype(np.float32)


@dataclass(frozen=True)
class SensorModel:
    """Noise and read-out of a simulated sensor (see the module docstring).

    Attributes
    ----------
    shot_noise : bool
        Apply Poisson photon noise (and full-well saturation) to ``S E``.
    full_well : float
        Full-well capacity, electrons (used with ``shot_noise``).
    gain : float
        Electrons per grey level (used with ``shot_noise``): a grey level of
        ``I`` has a shot-noise standard deviation of ``sqrt(I / gain)``.
    read_sigma : float
        Gaussian read noise, standard deviation in grey levels.
    bits : int or None
        Quantise the output to this many bits (None: no quantisation).
    white_level : float or None
        Saturation: outputs are clipped at this grey level (None: no clipping).
    black_level : float
        Offset added to every read-out before clipping and quantisation, grey
        levels (0: none).  The output is then raw, ``S E + noise + black_level``;
        ``white_level`` and ``2**bits - 1`` are raw levels (black included).
    """

    shot_noise: bool = False
    full_well: float = 20000.0
    gain: float = 10.0
    read_sigma: float = 0.0
    bits: int | None = None
    white_level: float | None = None
    black_level: float = 0.0

    def __post_init__(self) -> None:
        if not (math.isfinite(self.full_well) and self.full_well > 0):
            raise InputError(f"sensor: full_well must be finite and > 0 electrons, got {self.full_well}")
        if not (math.isfinite(self.gain) and self.gain > 0):
            raise InputError(f"sensor: gain must be finite and > 0 electrons per grey level, got {self.gain}")
        if not (math.isfinite(self.read_sigma) and self.read_sigma >= 0):
            raise InputError(f"sensor: read_sigma must be finite and >= 0, got {self.read_sigma}")
        if self.bits is not None and not (isinstance(self.bits, (int, np.integer)) and 1 <= self.bits <= 32):
            raise InputError(f"sensor: bits must be an integer in 1..32, got {self.bits}")
        if self.white_level is not None and not (math.isfinite(self.white_level) and self.white_level > 0):
            raise InputError(f"sensor: white_level must be finite and > 0, got {self.white_level}")
        if not (math.isfinite(self.black_level) and self.black_level >= 0):
            raise InputError(f"sensor: black_level must be finite and >= 0, got {self.black_level}")
        if self.full_scale is not None and self.black_level >= self.full_scale:
            raise InputError(f"sensor: black_level {self.black_level} must be below the white level {self.full_scale}")

    @property
    def full_scale(self) -> float | None:
        """The largest output value in grey levels (None when unbounded)."""
        if self.white_level is not None:
            return float(self.white_level)
        if self.bits is not None:
            return float(2**self.bits - 1)
        return None

    @property
    def step(self) -> float | None:
        """The quantisation step in grey levels (None without quantisation)."""
        if self.bits is None:
            return None
        return self.full_scale / (2**self.bits - 1)

    def noise_sigma(self, level: float) -> float:
        """Standard deviation of the measurement noise at a signal ``level`` (grey levels).

        Read, shot (``level / gain``) and quantisation (``step**2 / 12``)
        variances added; clipping is ignored.
        """
        var = self.read_sigma**2
        if self.shot_noise:
            var += max(float(level), 0.0) / self.gain
        if self.bits is not None:
            var += self.step**2 / 12.0
        return float(math.sqrt(var))

    def measure(self, clean: np.ndarray, rng: np.random.Generator | int | None = 0) -> np.ndarray:
        """``sensor(noise(clean))``; see :func:`measure`."""
        return measure(clean, self, rng)


def add_shot_noise(
    coded: np.ndarray, *, gain: float, full_well: float, rng: np.random.Generator | int | None
) -> np.ndarray:
    """Poisson photon noise: ``min(Poisson(gain * coded), full_well) / gain``.

    Parameters
    ----------
    coded : ndarray of shape (H, W)
        Clean coded image, grey levels (negative values count as 0).
    gain : float
        Electrons per grey level.
    full_well : float
        Full-well capacity, electrons.
    rng : Generator or int

    Returns
    -------
    noisy : ndarray of shape (H, W), float32
        Mean ``coded`` and variance ``coded / gain`` below saturation.
    """
    gen = np.random.default_rng(rng)
    electrons = np.clip(np.asarray(coded, dtype=np.float64), 0.0, None) * gain
    # a mean far above the full well saturates whatever is drawn (numpy refuses means past about 1e19)
    electrons = np.minimum(electrons, 4.0 * full_well + 1e3)
    counts = np.minimum(gen.poisson(electrons), full_well)
    return (counts / gain).astype(np.float32)


def quantise(coded: np.ndarray, *, bits: int, full_scale: float) -> np.ndarray:
    """Clip to ``[0, full_scale]`` and round to ``2**bits`` equally spaced levels.

    Returns float32 in grey levels; the top level is exactly ``full_scale``.
    """
    top = 2**bits - 1
    step = full_scale / top
    levels = np.rint(np.clip(np.asarray(coded, dtype=np.float64), 0.0, full_scale) / step)
    return np.where(levels >= top, full_scale, levels * step).astype(np.float32)


def measure(
    clean: np.ndarray, model: SensorModel, rng: np.random.Generator | int | None = 0
) -> np.ndarray:
    """The recorded coded image: ``sensor(noise(clean))``.

    Parameters
    ----------
    clean : ndarray of shape (H, W)
        Noise-free coded image ``S E`` (:func:`forward`), grey levels.
    model : SensorModel
    rng : Generator, int or None
        Seed of the noise.  Read noise is drawn from ``default_rng(rng)``
        itself (identical to :func:`add_read_noise`); shot noise from an
        independent child stream spawned from its ``SeedSequence``.

    Returns
    -------
    coded : ndarray of shape (H, W), float32
    """
    gen = np.random.default_rng(rng)
    out = np.asarray(clean, dtype=np.float32)
    if model.shot_noise:
        (shot_rng,) = gen.spawn(1)
        out = add_shot_noise(out, gain=model.gain, full_well=model.full_well, rng=shot_rng)
    out = add_read_noise(out, model.read_sigma, gen)
    if model.black_level:  # once per read-out, before the ADC clips and rounds
        out = (out + np.float32(model.black_level)).astype(np.float32)
    if model.bits is not None:
        out = quantise(out, bits=model.bits, full_scale=model.full_scale)
    elif model.white_level is not None:
        out = np.minimum(out, np.float32(model.white_level))
    return out


def simulate(
    video: np.ndarray,
    mask: np.ndarray,
    *,
    sigma: float = 0.0,
    rng: np.random.Generator | int | None = 0,
    sensor: SensorModel | None = None,
) -> np.ndarray:
    """``sensor(noise(S E))``: the coded image a camera with this code would record.

    Parameters
    ----------
    video : ndarray of shape (N, H, W)
    mask : ndarray of shape (N, H, W)
    sigma : float
        Gaussian read noise (grey levels) when no ``sensor`` is given.
    rng : Generator, int or None
    sensor : SensorModel, optional
        The full sensor model; then ``sigma`` must be 0 (use ``read_sigma``).

    Returns
    -------
    coded : ndarray of shape (H, W), float32
    """
    if sensor is None:
        return add_read_noise(forward(video, mask), sigma, rng)
    if sigma:
        raise InputError(f"simulate: give the read noise as sensor.read_sigma, not sigma = {sigma}")
    return measure(forward(video, mask), sensor, rng)


def raise_to_white(volume: np.ndarray, saturated: np.ndarray, mask: np.ndarray, white_level: float) -> int:
    """Make every saturated pixel's frames record at least the white level, in place (its measurement is a
    lower bound, ``s . v >= white_level``): the smallest change along its shutter weights ``s``, where the
    reconstruction (which left the pixel out) falls below it.  Returns the pixels raised.

    It never did worse than leaving the pixels out alone (docs/research.md, "Clipped captures").
    """
    clipped = np.asarray(saturated, bool)  # (H, W), and white_level in the units of ``volume``
    s = np.asarray(mask, np.float32)
    recorded = (s * volume).sum(0)
    ss = (s * s).sum(0)
    low = clipped & (recorded < white_level) & (ss > 0)
    if low.any():
        lift = np.zeros(recorded.shape, np.float32)
        lift[low] = (np.float32(white_level) - recorded[low]) / ss[low]
        np.add(volume, (s * lift[None]).astype(volume.dtype), out=volume)  # in place: ``volume += ...``
    return int(low.sum())


def saturated_as_missing(
    coded: np.ndarray, mask: np.ndarray, white_level: float
) -> tuple[np.ndarray, int]:
    """Treat saturated pixels as not measured.

    Parameters
    ----------
    coded : ndarray of shape (H, W)
    mask : ndarray of shape (N, H, W)
    white_level : float
        Pixels with ``coded >= white_level`` (compared in float32) are saturated.

    Returns
    -------
    mask : ndarray of shape (N, H, W)
        A copy of ``mask`` (same dtype) with every sub-frame of every saturated
        pixel set to 0; reconstruction fills those pixels from their neighbours.
    count : int
        Number of saturated pixels.
    """
    check_pair(np.shape(coded), np.shape(mask), where="saturated_as_missing")
    if not (math.isfinite(white_level) and white_level > 0):
        raise InputError(f"white level must be finite and > 0, got {white_level}")
    saturated = np.asarray(coded, dtype=np.float32) >= np.float32(white_level)
    out = np.array(mask, copy=True)
    out[:, saturated] = 0
    return out, int(saturated.sum())


def static_estimate(coded: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """The trivial estimate: every sub-frame = coded / open count of its pixel.

    For a calibrated mask the open count is the sum of the pixel's weights
    (a still scene records ``frame * sum_t mask[t]``).  Pixels that are never
    open (weights summing to 0) get 0 here; reconstruction fills them from
    their neighbours.  Shape (N, H, W) float32.
    """
    check_pair(np.shape(coded), np.shape(mask))
    n_open = np.asarray(mask, dtype=np.float32).sum(0)
    frame = np.divide(coded, n_open, out=np.zeros(np.shape(coded), np.float32), where=n_open > 0)
    return np.broadcast_to(frame, np.shape(mask)).astype(np.float32)


def blur_shift_mask(
    mask: np.ndarray,
    shift: tuple[float, float] = (0.5, 0.5),
    sigma: float = 0.5,
    *,
    mode: str = "nearest",
) -> np.ndarray:
    """A calibrated mask: a code as a sensor sees it through optics, misregistered and blurred.

    Every sub-frame's pattern (a DMD or LCoS pattern of the sensor's pitch) is
    moved by ``shift`` pixels (rows, columns) and blurred by a Gaussian point
    spread of standard deviation ``sigma`` pixels.  The shift interpolates
    linearly, which for a shift below one pixel is exactly the area of the
    sensor pixel that each displaced code pixel covers; weights stay in [0, 1].

    Parameters
    ----------
    mask : ndarray of shape (N, H, W)
        The nominal code (binary or already fractional).
    shift : (float, float)
        Displacement of the pattern on the sensor, pixels (rows, columns).
    sigma : float
        Gaussian blur, pixels (0: none).
    mode : str
        How the pattern continues beyond the image border (:mod:`scipy.ndimage` modes).

    Returns
    -------
    measured : ndarray of shape (N, H, W), float32, values in [0, 1]
    """
    from scipy import ndimage

    m = np.asarray(mask, dtype=np.float64)
    if m.ndim != 3:
        raise InputError(f"blur_shift_mask: expected a mask (N, H, W), got shape {m.shape}")
    if not (math.isfinite(sigma) and sigma >= 0):
        raise InputError(f"blur_shift_mask: sigma must be finite and >= 0, got {sigma}")
    offset = tuple(float(v) for v in shift)
    if len(offset) != 2 or not all(math.isfinite(v) for v in offset):
        raise InputError(f"blur_shift_mask: shift must be two finite numbers (rows, columns), got {offset}")
    out = np.empty(m.shape, np.float64)
    for t in range(m.shape[0]):
        frame = ndimage.shift(m[t], offset, order=1, mode=mode, prefilter=False)
        if sigma > 0:
            frame = ndimage.gaussian_filter(frame, sigma, mode=mode)
        out[t] = frame
    out[np.abs(out) < 1e-7] = 0.0  # interpolation roundoff is not a response
    return np.clip(out, 0.0, 1.0).astype(np.float32)
