"""Units of a capture: its data range, found once and reported, and the scale codedvideo works in.

A capture may come as [0, 1] floats, 0..255 (uint8 or float), 12-bit 0..4095,
uint16 0..65535 or any float scale.  The data range (the peak value of a
frame) is, in order of precedence:

1. ``--data-range`` (``output.data_range``) when given;
2. 255 for 8-bit integer files;
3. from the values: the peak ``p`` of ``coded / open count`` (the static
   estimate, which no frame can exceed without noise) rounded up to the first
   of 1 (floats only), 255, 4095 and 65535 that holds it (with 5 % room
   for noise), else (floats) to the first of those times a power of ten that holds it (a video in
   thousandths of 8-bit units peaks near 255000: its range is 255000, and every figure, PSNR included,
   is the 8-bit run's; the next ``2**b - 1``, 262143, made its PSNR 0.23 dB higher), and (integers
   wider than 16 bits) to the next ``2**b - 1``.

Every number is bounded (:data:`DATA_RANGE_MIN` ...): float32 holds 7 digits at any scale, but the
sums of a patch's squares must stay finite, so values beyond those bounds are refused before any work.

Reconstruction then runs in *working units*, the capture scaled so that its
data range is 255 (8-bit captures are not rescaled at all), and the result is
scaled back.  Every setting in grey levels (``--noise-sigma``, ``--tol-rms``,
``--white-level``) is given in the capture's own units and scaled with it, so
the same capture in any units gives the same video, multiplied by the scale.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from codedvideo.model import doors
from codedvideo.model.patches import PATCH

#: The data range of 8-bit frames: the default of every writer and score that is not told another.
EIGHT_BIT = 255.0
#: The data range working units map to (the units every default was tuned in).
WORKING_RANGE = EIGHT_BIT
#: Data ranges the values are rounded up to, with the room left for noise.
COMMON_RANGES = (1.0, 255.0, 4095.0, 65535.0)
NOISE_ROOM = 1.05
#: The residual tolerance of a capture without read noise, in working units (grey levels of 8-bit frames): OMP's
#: tolerance is never below it (:func:`codedvideo.engine.config.auto_tolerance`), and the still test's temporal
#: profiles take it as the scale of the sub-frame changes they fit (:func:`codedvideo.solvers.region.still_patches`).
TOL_FLOOR = 2.0

#: The bounds of every number in the capture's units, shared by pipeline.yaml's fields (codedvideo.engine.config)
#: and the command line's options.  Work is in float32 (about 3.4e38 at most, 1.2e-38 the smallest normal):
#: a patch's sum of squares reaches (64 frames x 1e12)**2 x 49 x 64, about 1e31, within it, and a range of
#: 1e-6 keeps squared differences a million times the float32 step apart from its smallest normal.
DATA_RANGE_MIN, DATA_RANGE_MAX = 1e-6, 1e12
#: Grey-level settings (noise sigma, tolerance, white and black level) in the capture's units: at most this.
LEVEL_MAX = 1e12
#: ... and at most this many times the data range, once it is known (so that in working units, the
#: data range at 255, every one of them stays below 2.55e8 and its square finite in float32).
LEVELS_PER_RANGE = 1e6


@dataclass(frozen=True)
class DataRange:
    """A capture's data range and how it was found (recorded in the metrics JSON)."""

    value: float
    source: str
    #: Peak of coded / open count, in the capture's units.
    peak: float

    @property
    def scale(self) -> float:
        """Factor from the capture's units to working units."""
        return 1.0 if self.value == WORKING_RANGE else WORKING_RANGE / self.value

    def as_dict(self) -> dict:
        return dict(value=self.value, source=self.source, peak=self.peak, working_scale=self.scale)


def open_ratios(coded: np.ndarray, mask: np.ndarray, step: int = 1, white_level: float | None = None) -> np.ndarray:
    """``coded / open count`` of every pixel ever open (every ``step``-th row and column), flat; with
    ``white_level``, the pixels at or above it (saturated: no measurement) are left out."""
    counts = np.asarray(mask[..., ::step, ::step], np.float32).sum(-3)
    values = np.asarray(coded[..., ::step, ::step], np.float32)
    if counts.shape != values.shape[-2:]:
        counts = np.broadcast_to(counts, values.shape)
    open_ = counts > 0
    if white_level is not None:
        open_ &= values < np.float32(white_level)
    return values[open_] / counts[open_]


def static_peak(coded: np.ndarray, mask: np.ndarray, white_level: float | None = None) -> float:
    """Largest ``coded / open count`` over the pixels that are ever open (0 when none is)."""
    return float(open_ratios(coded, mask, white_level=white_level).max(initial=0.0))


def static_quantile(coded: np.ndarray, mask: np.ndarray, q: float = 0.99, step: int = 3,
                    white_level: float | None = None) -> float:
    """The ``q`` quantile of ``coded / open count`` over the pixels ever open (every ``step``-th row and
    column: a percentile of a 4K frame in milliseconds); 0 when none is."""
    ratios = open_ratios(coded, mask, step, white_level)
    return float(np.quantile(ratios, q)) if ratios.size else 0.0


def count_above(coded: np.ndarray, mask: np.ndarray, level: float,
                white_level: float | None = None) -> tuple[int, int]:
    """(pixels ever open whose ``coded / open count`` lies above ``level``, pixels ever open)."""
    ratios = open_ratios(coded, mask, white_level=white_level)
    return int(np.count_nonzero(ratios > level)), int(ratios.size)


def clipped_level(codeds, mask_of) -> float | None:
    """The coded value the sensor clipped at, when the captures show one: the largest coded value, held by
    at least :data:`CLIPPED_PIXELS` pixels of at least two open counts (a scene's brightest value gives a coded
    value in proportion to the open count; a clipped read-out gives the same value whatever the count)."""
    tops = [float(np.max(np.asarray(c), initial=-np.inf)) for c in codeds]
    top = max(tops, default=-np.inf)
    if not np.isfinite(top) or top <= 0:
        return None
    held, counts = 0, set()
    for i, value in enumerate(tops):
        if value != top:
            continue
        at = np.asarray(codeds[i]) == np.float32(top) if np.asarray(codeds[i]).dtype.kind == "f" \
            else np.asarray(codeds[i]) == top
        k = np.asarray(mask_of(i)).sum(0, dtype=np.float32)[at]
        held += int(np.count_nonzero(k > 0))
        counts.update(np.unique(k[k > 0]).tolist())
    return top if held >= CLIPPED_PIXELS and len(counts) >= 2 else None


#: Pixels that must share the largest coded value for it to be taken as the sensor's clipping level.
CLIPPED_PIXELS = 4


def integer_clipping(codeds, mask_of, dtype) -> tuple[float, int, int] | None:
    """``(level, pixels, measured)`` when captures stored as integers hold pixels at their type's largest value
    (255 for uint8, 65535 for uint16): a sum of frames that reached it was clipped there, whatever the code (a
    single-bump code, every pixel open alike, gives :func:`clipped_level` nothing to compare).  ``pixels``: how
    many ever-open pixels hold it over the captures, of ``measured``; None for float captures, fewer than
    :data:`CLIPPED_PIXELS` such pixels, or captures clipped everywhere (nothing measured below the level)."""
    if dtype is None or np.dtype(dtype).kind not in "iu":
        return None
    level = float(np.iinfo(np.dtype(dtype)).max)
    held = measured = 0
    for i in range(len(codeds)):
        opened = np.asarray(mask_of(i)).any(0)
        held += int(np.count_nonzero((np.asarray(codeds[i]) >= level) & opened))
        measured += int(np.count_nonzero(opened))
    return (level, held, measured) if CLIPPED_PIXELS <= held < measured else None


#: Standard deviations of read noise (``noise``, the capture's units) also allowed above a range.
NOISE_SIGMAS = 5.0
#: A float capture whose values lie in [0, 1] but for a few (``OUTLIER_SHARE`` at most, up to
#: ``OUTLIER_PEAK``: hot pixels, noise on white) is a [0, 1] capture, not an 8-bit one.
OUTLIER_SHARE = 0.01
OUTLIER_PEAK = 8.0


#: A range is widened for read noise only when it is at least this many times the noise: noise as wide as
#: half a range is not noise on that range (sigma 10 on a [0, 1] capture), so it cannot pick that range.
NOISE_RANGE_RATIO = 2.0


def noise_room(value: float, noise: float) -> float:
    """How far above the range ``value`` read noise ``noise`` (the capture's units) may carry values:
    :data:`NOISE_SIGMAS` sigmas, for a range at least :data:`NOISE_RANGE_RATIO` times the noise; else 0."""
    sigma = max(float(noise), 0.0)
    return NOISE_SIGMAS * sigma if value >= NOISE_RANGE_RATIO * sigma else 0.0


def infer_data_range(peak: float, *, dtype=None, given: float | None = None, what: str = "coded / open count",
                     noise: float = 0.0, quantile=None, outlier_ranges: tuple[float, ...] = (1.0,)) -> DataRange:
    """The data range of a capture whose frames peak at ``peak`` (:func:`static_peak`; module docstring).

    ``noise``: the read noise the capture is known to have (``--noise-sigma``), whose peaks may lie above
    the range by more than the 5 % room (sigma 30 on 8-bit frames peaked at 268 and was taken as 12-bit).
    Noise widens a range, it never picks one (:func:`noise_room`): a range is widened only when it is at
    least twice the noise, so a dark 8-bit capture with sigma 10 is not taken for a [0, 1] one.
    ``quantile``: a function giving the ``1 - OUTLIER_SHARE`` quantile of the same values
    (:func:`static_quantile`), asked only for float values that peak just above 1: when that quantile is
    within [0, 1] the few above are outliers and the range is 1 (one hot pixel at 2.5 made a [0, 1]
    capture 8-bit: a black video, its PSNR 50 dB too high).  ``outlier_ranges``: the ranges this applies
    to (up to ``OUTLIER_PEAK`` times each); training videos add 255, since a reconstruction overshoots its
    range (an 8-bit one peaking at 290 was taken as 12-bit).
    """
    peak_value = float(peak)
    if given is not None:
        return DataRange(float(given), "given (--data-range)", peak_value)
    kind = np.dtype(dtype) if dtype is not None else None
    if kind is not None and kind.kind in "iu" and kind.itemsize == 1:
        return DataRange(255.0, f"dtype {kind.name}", peak_value)
    integer = kind is not None and kind.kind in "iub"
    for value in outlier_ranges if not integer and quantile is not None else ():
        if value * NOISE_ROOM + noise_room(value, noise) < peak_value <= value * OUTLIER_PEAK:
            typical = float(quantile())
            if typical <= value * NOISE_ROOM + noise_room(value, noise):
                return DataRange(value, f"values ({1 - OUTLIER_SHARE:.0%} of {what} at most {typical:.4g}; its "
                                        f"peak {peak_value:.4g} taken as outliers)", peak_value)
            break
    for value in COMMON_RANGES:
        if integer and value == 1.0:
            continue
        if peak_value <= value * NOISE_ROOM + noise_room(value, noise):
            return DataRange(value, f"values (peak of {what} {peak_value:.4g})", peak_value)
    if not integer and peak_value > 0:  # a standard range in other decimal units (255000: thousandths of 8 bits)
        value = min((v * 10.0**k for v in COMMON_RANGES for k in range(1, 40)
                     if peak_value <= v * 10.0**k * NOISE_ROOM + noise_room(v * 10.0**k, noise)), default=peak_value)
        return DataRange(float(value), f"values (peak of {what} {peak_value:.4g})", peak_value)
    value = float(2 ** math.ceil(math.log2(peak_value + 1)) - 1)
    return DataRange(value, f"values (peak of {what} {peak_value:.4g})", peak_value)


def check_range(units: DataRange, levels: dict[str, float | None], where: str) -> None:
    """Refuse a data range outside [:data:`DATA_RANGE_MIN`, :data:`DATA_RANGE_MAX`] (one found from values
    too large), values more than :data:`LEVELS_PER_RANGE` times the range, and grey-level settings
    (``levels``: option name -> value in the capture's units) that far above it; one line naming them."""
    from codedvideo.model.errors import ConfigError, InputError

    if not DATA_RANGE_MIN <= units.value <= DATA_RANGE_MAX:
        raise InputError(f"{where}: data range {units.value:.4g} ({units.source}) lies outside [{DATA_RANGE_MIN:g}, "
                         f"{DATA_RANGE_MAX:g}], the values codedvideo works with in float32; scale the capture")
    most = LEVELS_PER_RANGE * units.value
    if units.peak > most:
        raise InputError(f"{where}: values (coded / open count) reach {units.peak:.4g}, more than {LEVELS_PER_RANGE:g} "
                         f"times the data range {units.value:.4g} ({units.source}); give the data range of the frames")
    for option, value in levels.items():
        if value is not None and value > most:
            raise ConfigError(f"option {option} {value:g}: more than {LEVELS_PER_RANGE:g} times the data range "
                              f"{units.value:.4g} ({units.source}); allowed [0, {most:g}] for this capture")


def truth_range(peak: float, *, given: float | None = None, where: str = "truth") -> DataRange:
    """The data range a reconstruction is scored against: ``given``, or found from the truth's ``peak`` (so the
    same video scores the same in any float scale), checked as :func:`check_range` checks a capture's."""
    units = infer_data_range(peak, given=given, what="the truth")
    check_range(units, {}, where)
    return units


def tolerance_warning(coded: np.ndarray, tol_rms: float, patch: int = PATCH) -> str | None:
    """A one-line warning when the residual tolerance is met before the first atom on most patches.

    ``coded`` and ``tol_rms`` in the same (working) units.  OMP's residual
    starts as the patch's coded values, so a patch whose coded RMS is within
    the tolerance gets no atom at all (it takes its still answer, coded / open count: no motion).
    """
    arr = np.asarray(coded, np.float64)
    if not 0 < tol_rms < 1e150:  # (its square must be a float64)
        return None
    if tol_rms <= 0 or min(arr.shape) < patch:
        return None
    # each patch's mean square from running sums (no scipy.ndimage: a run of one capture starts 0.05 s sooner)
    c = np.pad((arr**2).cumsum(0).cumsum(1), ((1, 0), (1, 0)))
    sums = c[patch:, patch:] - c[:-patch, patch:] - c[patch:, :-patch] + c[:-patch, :-patch]
    share = float(np.mean(np.maximum(sums, 0) / patch**2 <= tol_rms**2))
    if share <= 0.5:
        return None
    name = doors.name
    return (f"the residual tolerance ({name('tol_rms')} / {name('noise_sigma')}) is met before the first atom on "
            f"{share:.0%} of the patches: they take their still answer (coded / open count), with no motion "
            f"recovered; check the data range ({name('data_range')}) and the tolerance")


#: The settings a message about the data range names (each as the door of the call names it; a caller may pass
#: its own names).
RANGE_SETTINGS = ("noise_sigma", "data_range", "white_level")


def capture_units(codeds, mask_of, *, dtype=None, given: float | None = None, white_level: float | None = None,
                  levels: dict[str, float | None] | None = None, where: str = "coded image",
                  names: dict[str, str] | None = None) -> DataRange:
    """The data range of a job's captures, found once, checked and warned about: the one inference that the
    command line, ``codedvideo run`` and the Python API all use.

    Parameters
    ----------
    codeds : sequence of T coded images (H, W), in the capture's units
    mask_of : callable ``mask_of(i)`` -> the (N, H, W) mask of capture ``i``
    dtype : the captures' type as stored (8-bit integers are 0..255 whatever their values)
    given : the data range the user gave (``--data-range``), or None to find it from the values
    white_level : the sensor's saturation level in coded units, when known: pixels at or above it hold no
        measurement and do not set the range.  When none is given and the captures show one
        (:func:`clipped_level`), it is used the same way, with a warning.
    levels : setting -> its grey level in the capture's units (None: not set), each refused when far above the
        range.  Among them ``noise_sigma``, the read noise (its peaks may lie above the range; none: 0), and
        ``black_level``, the black level subtracted from the captures (named when nothing lies above 0).
    where : what the captures are called in messages (the file)
    names : what the caller calls the settings in messages (``noise_sigma``, ``data_range``, ``white_level`` and
        those of ``levels``; default: as the door of the call names them)

    Raises :class:`codedvideo.model.errors.InputError` for a capture with nothing above 0 (and no range given) or
    values beyond float32's working bounds; warns (one line each) when values lie above the range found or
    given, and when a range just past 8 bits was found.
    """
    from codedvideo.model.errors import InputError

    given_levels = levels or {}
    labels = dict({k: doors.name(k) for k in (*RANGE_SETTINGS, *given_levels)}, **(names or {}))
    noise_sigma = given_levels.get("noise_sigma") or 0.0
    black_level = given_levels.get("black_level")
    black = f"{labels['black_level']} {black_level:g}" if black_level else "the black level"
    count = len(codeds)
    clip = white_level
    eight_bit = dtype is not None and np.dtype(dtype).kind in "iu" and np.dtype(dtype).itemsize == 1
    if clip is None and given is None and not eight_bit:  # (8-bit integers are 0..255 whatever they hold)
        clip = clipped_level(codeds, mask_of)
        if clip is not None and max(static_peak(codeds[i], mask_of(i), clip) for i in range(count)) <= 0:
            clip = None  # nothing but the clipped pixels: they are the scene
        if clip is not None:
            doors.warn(f"{where}: pixels of different open counts share the largest coded value {clip:.6g}: "
                          f"clipped by the sensor; left out of the data range (give {labels['white_level']} "
                          f"{clip:.6g} to raise their frames to sum to at least it)")
    peak = max(static_peak(codeds[i], mask_of(i), clip) for i in range(count))
    if peak <= 0 and white_level is not None and max(static_peak(codeds[i], mask_of(i)) for i in range(count)) > 0:
        raise InputError(f"{where}: every pixel that is ever open is at or above the white level {white_level:g} "
                         f"({labels['white_level']}): saturated, nothing is measured")
    # a sum of frames is never negative: the wrong file, or a black level taken off twice
    if peak <= 0 and given is None:
        raise InputError(f"{where}: no coded value above 0 where the code is open; nothing to reconstruct "
                         f"(check the file and {black})")
    units = infer_data_range(peak, dtype=dtype, given=given, noise=noise_sigma, quantile=lambda: max(
        static_quantile(codeds[i], mask_of(i), 1 - OUTLIER_SHARE, white_level=clip) for i in range(count)))
    if given is not None:
        units = DataRange(units.value, f"given ({labels['data_range']})", units.peak)
        _warn_far_below(peak, given, labels["data_range"], where)
    check_range(units, {labels[k]: v for k, v in given_levels.items()}, where)
    level = units.value * NOISE_ROOM + noise_room(units.value, noise_sigma)
    if peak > level:  # outliers above a range found, or a range given below the values: clipped in videos and frames
        doors.warn(_above_range(codeds, mask_of, level, clip, peak, units, where))
    if given is None and units.value > 255 and peak <= 2 * 255:  # just past 8 bits: noise, or a dark frame?
        doors.warn(f"{where}: data range {units.value:g} found from a peak of {peak:.4g} (coded / open count), "
                      f"just above 8-bit; if the frames are 8-bit with noise, give {labels['noise_sigma']} or "
                      f"{labels['data_range']} 255")
    return units


#: A volume is taken for another unit than a reference when its peak lies below the reference's divided by
#: the first or above it times the second (a [0, 1] video against 8-bit frames peaks 255 times lower).
OTHER_UNITS_BELOW, OTHER_UNITS_ABOVE = 16.0, 4.0


def other_units(reference_peak: float, peak: float) -> bool:
    """Whether a volume peaking at ``peak`` looks to be in other units than a reference peaking at
    ``reference_peak`` (never when either is black throughout: a black volume says nothing of its units)."""
    if not (math.isfinite(reference_peak) and math.isfinite(peak)):  # (NaN or Inf: refused as such, not as units)
        return False
    return reference_peak > 0 and peak > 0 and \
        not reference_peak / OTHER_UNITS_BELOW <= peak <= OTHER_UNITS_ABOVE * reference_peak


def _warn_far_below(peak: float, given: float, label: str, where: str) -> None:
    """Warn when the captures peak far below the data range given (8-bit frames with a 12-bit sensor's range):
    the tolerance, the PSNR and the videos' full scale would all be taken against a range the values never
    reach.  The bound is the one a truth in other units is told by (:data:`OTHER_UNITS_BELOW`); a dark capture
    of the range's own sensor may lie below it too, so it is a warning."""
    if 0 < peak < given / OTHER_UNITS_BELOW:
        doors.warn(f"{where}: coded / open count peaks at {peak:.4g}, under 1/{OTHER_UNITS_BELOW:g} of the data "
                      f"range {given:g} given ({label}); the tolerance, the PSNR and the videos' full scale are "
                      f"taken against {given:g}: if the frames are in other units (8-bit: 255), give that range")


def _above_range(codeds, mask_of, level: float, clip, peak: float, units: DataRange, where: str) -> str:
    """The warning for values above the data range: their share of the pixels, and in a stream the captures
    that hold them (a single blown-out capture is not the whole stream)."""
    tallies = [count_above(codeds[i], mask_of(i), level, clip) for i in range(len(codeds))]
    above, total = sum(a for a, _ in tallies), sum(t for _, t in tallies)
    share = above / max(total, 1)
    said = f"{where}: {share:.2%} of the pixels (coded / open count, up to {peak:.4g}) lie above the data range " \
           f"{units.value:g} ({units.source})"
    if len(codeds) > 1:
        held = [i for i, (a, _) in enumerate(tallies) if a]
        worst = max(held, key=lambda i: tallies[i][0] / max(tallies[i][1], 1))
        said += (f", in {len(held)} of {len(codeds)} captures (most in capture {worst + 1}: "
                 f"{tallies[worst][0] / max(tallies[worst][1], 1):.2%})")
    return said + "; they are clipped in videos and frames"
