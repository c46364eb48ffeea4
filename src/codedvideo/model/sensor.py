"""Raw sensor data: black level, bit depth and white level, defective pixels.

A real coded-exposure sensor does not give the ideal coded image of the sum
convention (:mod:`codedvideo.model.physics`), but a *raw* frame:

* a **black level** ``b`` (an offset, scalar or a dark frame (H, W)) is added
  once per read-out, however many sub-frames the pixel integrated, so
  ``raw = sum_t S E + b`` (plus noise);
* the ADC has ``bits`` bits: raw values lie in ``0 .. 2**bits - 1`` and a pixel
  at the **white level** (``2**bits - 1``, or a lower saturation level) did
  not record the sum of its frames, only that it is at least that much;
* **defective pixels** (hot: stuck high or with a large dark current; dead:
  stuck low) record nothing useful.

:func:`correct_raw` turns a raw frame into the sum convention: subtract the
black level (values below it clip at 0), mark the pixels at the white level
and the defective ones as *missing measurements* (every weight of the mask set
to 0, exactly as :func:`codedvideo.model.physics.saturated_as_missing` does for
saturation), and count them.  Reconstruction fills missing pixels from their
neighbours.  Defective pixels come from a list (:func:`read_bad_pixels`: a text
file of ``y x`` rows or a ``.npy`` of shape (K, 2)) or are found as outliers
against their neighbourhood (:func:`detect_bad_pixels`, one capture or a
stack of captures).

Masks may be binary codes or calibrated weights in [0, 1]; the open count of
a pixel is the sum of its weights.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass

import numpy as np

from codedvideo.model import doors
from codedvideo.model.errors import InputError
from codedvideo.model.physics import check_pair

#: Scale of the median absolute deviation to a Gaussian standard deviation.
MAD_TO_SIGMA = 1.4826


# ----------------------------------------------------------------------------- black level, white level
@dataclass
class RawCorrection:
    """A raw frame in the sum convention, with its missing measurements (see :func:`correct_raw`).

    Attributes
    ----------
    coded : ndarray of shape (H, W), float32
        ``raw - black_level``, clipped at 0; 0 at missing pixels.
    mask : ndarray of shape (N, H, W)
        The mask (same dtype) with every weight of a missing pixel set to 0.
    missing : ndarray of shape (H, W), bool
        Saturated (unless trusted) or defective pixels.
    saturated_pixels : int
        Pixels at or above the white level (raw units), trusted or not.
    bad_pixels : int
        Defective pixels given (counted once, also when saturated).
    clipped_pixels : int
        Pixels below the black level, set to 0 (read noise around a dark signal).
    white_level : float or None
        The raw white level used (None: no saturation test).
    black_level : float or None
        The scalar black level subtracted (None when a dark frame was given).
    """

    coded: np.ndarray
    mask: np.ndarray
    missing: np.ndarray
    saturated_pixels: int
    bad_pixels: int
    clipped_pixels: int
    white_level: float | None
    black_level: float | None

    @property
    def missing_pixels(self) -> int:
        return int(self.missing.sum())

    def counts(self) -> dict:
        """The numbers for a metrics JSON."""
        return dict(saturated_pixels=self.saturated_pixels, bad_pixels=self.bad_pixels,
                    clipped_pixels=self.clipped_pixels, missing_pixels=self.missing_pixels,
                    white_level=self.white_level, black_level=self.black_level)


@dataclass(frozen=True)
class RawLevels:
    """The levels of a sensor's raw read-out, as :func:`correct_raw` takes them.

    Attributes
    ----------
    black_level : float or ndarray of shape (H, W)
        Offset of every read-out (once per pixel, not per sub-frame): a scalar
        or a dark frame.  Finite and >= 0.
    bits : int, optional
        ADC bit depth: raw values above ``2**bits - 1`` are an error (the wrong
        depth, or data scaled after read-out), and values at ``2**bits - 1``
        are saturated unless ``white_level`` says otherwise.
    white_level : float, optional
        Raw saturation level when it is not ``2**bits - 1`` (e.g. a full well
        below the ADC's top); pixels with ``raw >= white_level`` are saturated.
    """

    black_level: float | np.ndarray = 0.0
    bits: int | None = None
    white_level: float | None = None


def white_level_of(bits: int | None, white_level: float | None = None) -> float | None:
    """The raw white level: ``white_level`` when given, else ``2**bits - 1``, else None."""
    if bits is not None and not (isinstance(bits, (int, np.integer)) and not isinstance(bits, bool) and 1 <= bits <= 32):
        raise InputError(f"bits must be an integer in 1..32, got {bits!r}")
    if white_level is not None:
        if not (math.isfinite(white_level) and white_level > 0):
            raise InputError(f"white level must be finite and > 0, got {white_level}")
        return float(white_level)
    if bits is None:
        return None
    return float(2 ** int(bits) - 1)


def correct_raw(
    coded: np.ndarray,
    mask: np.ndarray,
    *,
    levels: RawLevels = RawLevels(),
    bad_pixels: np.ndarray | None = None,
    clip_negative: bool = True,
    trust_saturated: bool = False,
    where: str = "coded image",
) -> RawCorrection:
    """A raw coded frame -> the sum convention, with saturated and defective pixels missing.

    Parameters
    ----------
    coded : ndarray of shape (H, W)
        Raw values, ``sum of frames + black_level`` (ADC units).
    mask : ndarray of shape (N, H, W)
        Binary code or calibrated weights.
    levels : RawLevels
        The black level (a number or a dark frame), the ADC's bit depth and the
        white level of the raw values; ``RawLevels()`` subtracts nothing and
        tests no saturation.  Any object with those three attributes will do
        (a run passes its validated ``noise:`` settings as they are).
    bad_pixels : ndarray, optional
        Defective pixels: a boolean map (H, W) or integer ``(y, x)`` rows (K, 2)
        (:func:`read_bad_pixels`, :func:`detect_bad_pixels`).
    clip_negative : bool
        Clip ``raw - black_level`` at 0 (the sum of frames is never negative).
    trust_saturated : bool
        Count the pixels at the white level but keep them as measurements
        (``--trust-saturated``).  On overexposed scenes the clipped value is a
        better guess than what the neighbours extrapolate (docs/research.md,
        "Clipped captures").  Leaving them out wins where a pixel at the
        white level holds nothing of the scene (a hot pixel stuck at full scale).
    where : str
        Names the input in error messages.

    Returns
    -------
    RawCorrection
        ``coded`` in the frames' units (the white level of a pixel is then
        ``white_level - black_level``), ``mask`` without the missing pixels.
    """
    arr = np.asarray(coded)
    check_pair(arr.shape, np.shape(mask), where=where)
    raw = arr.astype(np.float32)
    if not np.isfinite(raw).all():
        raise InputError(f"{where}: contains NaN or Inf")
    bits, white_level = levels.bits, levels.white_level
    black = np.asarray(levels.black_level, dtype=np.float32)
    if black.ndim not in (0, 2) or (black.ndim == 2 and black.shape != raw.shape):
        raise InputError(f"{where}: black level of shape {black.shape} is neither a number nor a frame {raw.shape}")
    if not np.isfinite(black).all() or (black < 0).any():
        raise InputError(f"{where}: black level must be finite and >= 0")
    white = white_level_of(bits, white_level)
    if bits is not None:
        top = float(2 ** int(bits) - 1)
        peak = float(raw.max())
        if peak > top:
            raise InputError(f"{where}: value {peak:g} is above {top:g}, the largest {bits}-bit value "
                             f"(wrong {doors.name('bits')}, or the frame was scaled after read-out)")
        fraction = raw != np.round(raw) if white_level is None else np.zeros(raw.shape, bool)
        if fraction.any():  # e.g. [0, 1] floats: their white level is not 2**bits - 1 (a given one: its own scale)
            raise InputError(f"{where}: value {float(raw[fraction][0]):g} is not a whole number, as {bits}-bit raw "
                             f"counts are (the frame was scaled after read-out?); give {doors.name('white_level')} in "
                             f"its units instead of {doors.name('bits')}")
    if white is not None and float(black.max()) >= white:
        raise InputError(f"{where}: black level {float(black.max()):g} is not below the white level {white:g}")
    saturated = raw >= np.float32(white) if white is not None else np.zeros(raw.shape, bool)
    bad = np.zeros(raw.shape, bool) if bad_pixels is None else bad_pixel_map(bad_pixels, raw.shape)
    out = raw - black if black.any() else raw.copy()
    below = out < 0
    clipped = int(below.sum())
    if clip_negative and clipped:
        out[below] = 0.0
    missing = bad | (saturated & (not trust_saturated))
    mask_used = np.array(mask, copy=True)
    if missing.any():
        mask_used[:, missing] = 0
        out[missing] = 0.0
    if not mask_used.any():
        raise InputError(f"{where}: every pixel is saturated, defective or never open; nothing is left to reconstruct")
    return RawCorrection(coded=out.astype(np.float32, copy=False), mask=mask_used, missing=missing,
                         saturated_pixels=int(saturated.sum()), bad_pixels=int(bad.sum()), clipped_pixels=clipped,
                         white_level=white, black_level=float(black) if black.ndim == 0 else None)


def drop_pixels(coded: np.ndarray, mask: np.ndarray, bad: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
    """Defective pixels as missing measurements.

    Parameters
    ----------
    coded : ndarray of shape (H, W)
    mask : ndarray of shape (N, H, W)
    bad : ndarray of shape (H, W) bool, or (K, 2) integer ``(y, x)`` rows

    Returns
    -------
    coded : ndarray (H, W) float32, 0 at the bad pixels
    mask : ndarray (N, H, W), a copy (same dtype) with every weight of a bad pixel 0
    count : int
        Bad pixels.
    """
    check_pair(np.shape(coded), np.shape(mask), where="bad pixels")
    bad_map = bad_pixel_map(bad, np.shape(coded))
    out_coded = np.asarray(coded, dtype=np.float32).copy()
    out_mask = np.array(mask, copy=True)
    out_coded[bad_map] = 0.0
    out_mask[:, bad_map] = 0
    return out_coded, out_mask, int(bad_map.sum())


# ----------------------------------------------------------------------------- bad-pixel lists
def bad_pixel_map(bad: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """A boolean map (H, W) of defective pixels from a map or from ``(y, x)`` rows (K, 2)."""
    arr = np.asarray(bad)
    size = tuple(int(v) for v in shape)
    if arr.dtype == np.bool_ and arr.shape == size:
        return arr.copy()
    if arr.size == 0:
        return np.zeros(size, bool)
    if arr.ndim != 2 or arr.shape[1] != 2:
        raise InputError(f"bad pixels: expected a boolean map {size} or (y, x) rows of shape (K, 2), got {arr.shape}")
    rows = check_bad_rows(arr, size, where="bad pixels")
    out = np.zeros(size, bool)
    out[rows[:, 0], rows[:, 1]] = True
    return out


def check_bad_rows(rows: np.ndarray, shape: tuple[int, int], *, where: str, lines: list[int] | None = None,
                   unit: str = "row") -> np.ndarray:
    """Integer ``(y, x)`` rows inside an image of ``shape``, else a one-line :class:`InputError`.

    ``lines`` (1-based line numbers of a text file) name the offending entry;
    otherwise it is named by its 1-based row.
    """
    yx = np.asarray(rows)
    h, w = shape
    if yx.size and yx.dtype.kind == "f":
        nonint = ~np.isfinite(yx).all(1) | (yx != np.round(yx)).any(1)
        if nonint.any():
            i = int(np.flatnonzero(nonint)[0])
            at = f"line {lines[i]}" if lines else f"{unit} {i + 1}"
            raise InputError(f"{where}: {at} ({yx[i, 0]:g} {yx[i, 1]:g}) is not two integers 'y x'")
        yx = yx.astype(np.int64)
    elif yx.size and yx.dtype.kind not in "iu":
        raise InputError(f"{where}: expected integer (y, x) rows, got dtype {yx.dtype}")
    yx = yx.astype(np.int64).reshape(-1, 2)
    outside = (yx[:, 0] < 0) | (yx[:, 0] >= h) | (yx[:, 1] < 0) | (yx[:, 1] >= w)
    if outside.any():
        i = int(np.flatnonzero(outside)[0])
        at = f"line {lines[i]}" if lines else f"{unit} {i + 1}"
        raise InputError(f"{where}: {at} (y={yx[i, 0]}, x={yx[i, 1]}) is outside the {h}x{w} image "
                         f"(0 <= y < {h}, 0 <= x < {w}); {int(outside.sum())} of {len(yx)} rows are outside")
    return yx


def bad_pixel_array(given, shape: tuple[int, int], where: str) -> np.ndarray:
    """The ``(y, x)`` rows (K, 2) int64 of a list of defective pixels given as an array: (K, 2) rows (``(0,)`` or
    ``(0, 2)`` for none) or a boolean (or 0/1) map of the image's ``shape``; :class:`InputError` naming ``where``
    otherwise (a pixel outside the image among them)."""
    arr = np.asarray(given)
    if arr.size == 0:
        return np.zeros((0, 2), np.int64)
    is_map = arr.dtype == np.bool_ or (arr.ndim == 2 and arr.shape[1] != 2 and arr.dtype.kind in "iuf"
                                        and np.isin(arr, (0, 1)).all())
    if is_map:  # a map of the defects (bool, or 0 and 1)
        if arr.shape != tuple(shape):
            raise InputError(f"{where}: a map of {arr.shape[0]}x{arr.shape[1] if arr.ndim > 1 else 1} pixels, "
                             f"the image has {shape[0]}x{shape[1]}")
        return np.argwhere(arr).astype(np.int64)
    if arr.ndim != 2 or arr.shape[1] != 2:
        raise InputError(f"{where}: expected an array of shape (K, 2) of (y, x) rows, got {arr.shape}")
    if arr.dtype.kind not in "iuf":
        raise InputError(f"{where}: expected integer (y, x) rows, got dtype {arr.dtype}")
    return check_bad_rows(arr, shape, where=where)


def read_bad_pixels(path: str | os.PathLike, shape: tuple[int, int]) -> np.ndarray:
    """Read a list of defective pixels and check it against the image size.

    Parameters
    ----------
    path : str or path
        ``.npy``: an integer array of shape (K, 2) (``y, x`` per row; (0,) or
        (0, 2) for none), or a boolean map of the image's shape.  Any other name: a text file with one ``y x`` pair per
        line (whitespace or a comma between them), ``#`` starting a comment,
        blank lines ignored.
    shape : (H, W)
        The coded image's size.

    Returns
    -------
    rows : ndarray of shape (K, 2), int64
        ``(y, x)`` of every listed pixel (duplicates kept).

    Raises
    ------
    InputError
        One line naming the file and the problem: missing or unreadable, a row
        that is not two integers, or a pixel outside the image (its line, or
        for ``.npy`` its 1-based row, and its coordinates).
    """
    where = f"bad-pixel list {path}"
    p = os.fspath(path)
    if not os.path.exists(p):
        raise InputError(f"{where}: no such file")
    if os.path.isdir(p):
        raise InputError(f"{where}: is a folder, not a file")
    if p.lower().endswith(".npy"):
        try:
            arr = np.load(p, allow_pickle=False)
        except (ValueError, OSError, EOFError) as exc:
            raise InputError(f"{where}: cannot read ({exc})") from None
        return bad_pixel_array(arr, shape, where)
    try:
        with open(p, encoding="utf-8-sig") as fh:  # (a byte-order mark, as some editors write, is no row)
            text = fh.read()
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"{where}: cannot read as text ({exc})") from None
    rows, lines = [], []
    for number, line in enumerate(text.splitlines(), start=1):
        body = line.split("#", 1)[0].replace(",", " ").split()
        if not body:
            continue
        try:
            if len(body) != 2:
                raise ValueError
            y, x = (int(v) for v in body)
        except ValueError:
            raise InputError(f"{where}: line {number} ({line.strip()!r}) is not two integers 'y x'") from None
        rows.append((y, x))
        lines.append(number)
    if not rows:
        return np.zeros((0, 2), np.int64)
    return check_bad_rows(np.array(rows, np.int64), shape, where=where, lines=lines)


# ----------------------------------------------------------------------------- detection
def _open_count(mask: np.ndarray) -> np.ndarray:
    return np.asarray(mask, dtype=np.float32).sum(-3)


def _similar_median(s: np.ndarray, mask: np.ndarray, size: int, min_similarity: float,
                    rows: int = 64) -> tuple[np.ndarray, np.ndarray]:
    """Median of ``s`` over the neighbours (``size x size``, centre excluded) whose shutter weights resemble the pixel's.

    Two pixels are similar when the cosine of their weight vectors is at least
    ``min_similarity``: they integrated mostly the same sub-frames, so a moving
    scene gives them close values.  Computed in bands of ``rows`` rows.

    Returns the median (NaN where no neighbour is similar) and the number of similar neighbours.
    """
    w = np.asarray(mask, dtype=np.float32)
    n, h, wd = w.shape
    r = size // 2
    norm = np.sqrt(np.einsum("thw,thw->hw", w, w))
    wn = w / np.where(norm > 0, norm, 1.0)
    wp = np.pad(wn, ((0, 0), (r, r), (r, r)), mode="reflect")
    sp = np.pad(np.asarray(s, np.float32), r, mode="reflect")
    offsets = [(dy, dx) for dy in range(-r, r + 1) for dx in range(-r, r + 1) if (dy, dx) != (0, 0)]
    med = np.empty((h, wd), np.float32)
    count = np.empty((h, wd), np.int32)
    for y0 in range(0, h, rows):
        y1 = min(h, y0 + rows)
        vals = np.empty((y1 - y0, wd, len(offsets)), np.float32)
        centre = wn[:, y0:y1]
        for j, (dy, dx) in enumerate(offsets):
            other = wp[:, r + y0 + dy : r + y1 + dy, r + dx : r + dx + wd]
            sim = np.einsum("thw,thw->hw", centre, other)
            vals[:, :, j] = np.where(sim >= min_similarity, sp[r + y0 + dy : r + y1 + dy, r + dx : r + dx + wd], np.nan)
        vals.sort(axis=2)  # NaN last
        cnt = np.isfinite(vals).sum(2)
        lo = np.take_along_axis(vals, np.maximum(cnt - 1, 0)[:, :, None] // 2, 2)[:, :, 0]
        hi = np.take_along_axis(vals, (cnt // 2)[:, :, None], 2)[:, :, 0]
        med[y0:y1] = np.where(cnt > 0, 0.5 * (lo + hi), np.nan)
        count[y0:y1] = cnt
    return med, count


def outlier_scores(coded: np.ndarray, mask: np.ndarray, *, size: int = 5, similar_size: int = 7,
                   min_similarity: float = 0.5) -> np.ndarray:
    """How far every pixel's still value lies from its neighbours', in robust local standard deviations.

    The still value is ``s = coded / open count`` (the sum of the pixel's
    weights).  Its deviation is measured twice: from the median of the other
    pixels of the ``size x size`` window, and from the median of the
    neighbours within ``similar_size x similar_size`` whose shutter weights
    resemble its own (cosine >= ``min_similarity``: they saw mostly the same
    instants, so motion does not set them apart; fewer than 3 such
    neighbours: the first median).  Each deviation is divided by a robust
    spread -- the larger of the median of the neighbours' own ``|d|`` (texture
    and edges make it large) and a fifth of the image's median ``|d|``, times
    :data:`MAD_TO_SIGMA` -- and the score is the smaller of the two: a defect
    stands out from both references, a pixel on a moving edge agrees with the
    neighbours that saw the same instants, so it raises far fewer false alarms
    than the plain median alone (docs/research.md, "Defective pixels").  Pixels
    never open score 0.

    Returns
    -------
    score : ndarray of shape (H, W), float32
    """
    from scipy import ndimage

    image = np.asarray(coded, dtype=np.float64)
    check_pair(image.shape, np.shape(mask), where="detect_bad_pixels")
    for name, k in (("size", size), ("similar_size", similar_size)):
        if not (isinstance(k, (int, np.integer)) and k >= 3 and k % 2 == 1):
            raise InputError(f"detect_bad_pixels: {name} must be an odd integer >= 3, got {k}")
    n_open = _open_count(mask).astype(np.float64)
    open_ = n_open > 0
    if not open_.any():
        return np.zeros(image.shape, np.float32)
    s = np.where(open_, image / np.where(open_, n_open, 1.0), 0.0)
    if not open_.all():  # never-open pixels take their nearest open neighbour's value: no false contrast
        _, (iy, ix) = ndimage.distance_transform_edt(~open_, return_indices=True)
        s = s[iy, ix]
    ring = np.ones((size, size), bool)
    ring[size // 2, size // 2] = False
    med_all = ndimage.median_filter(s, footprint=ring, mode="mirror")
    med_sim, count = _similar_median(s, mask, similar_size, min_similarity)
    med_sim = np.where(count >= 3, med_sim, med_all)
    ring_small = np.ones((5, 5), bool)
    ring_small[2, 2] = False
    floor_abs = max(1e-6 * float(np.abs(s[open_]).max()), float(np.finfo(np.float32).tiny))

    def normalised(d: np.ndarray) -> np.ndarray:
        a = np.abs(d)
        local = ndimage.median_filter(a, footprint=ring_small, mode="mirror")
        floor = max(0.2 * float(np.median(a[open_])), floor_abs)
        return a / (MAD_TO_SIGMA * np.maximum(local, floor))

    score = np.minimum(normalised(s - med_all), normalised(s - med_sim))
    return np.where(open_, score, 0.0).astype(np.float32)


def detect_bad_pixels(
    coded: np.ndarray,
    mask: np.ndarray,
    *,
    threshold: float | None = None,
    size: int = 5,
    similar_size: int = 7,
    min_similarity: float = 0.5,
    min_fraction: float = 0.5,
) -> np.ndarray:
    """Defective pixels found as outliers against their neighbourhood.

    Parameters
    ----------
    coded : ndarray of shape (H, W), or (T, H, W): several captures
    mask : ndarray of shape (N, H, W), or (T, N, H, W): one per capture
    threshold : float, optional
        A pixel is an outlier in a capture when :func:`outlier_scores` exceeds
        this many robust standard deviations.  Default 8 for one capture, 6 for
        a stack (the vote across captures removes the false alarms a lower
        threshold lets in).
    size, similar_size, min_similarity
        The neighbourhoods of :func:`outlier_scores`.
    min_fraction : float
        With a stack: a pixel is defective when it is an outlier in more than
        this share of the captures (the default: most of them).  The scene
        moves between captures, a defect stays.

    Returns
    -------
    bad : ndarray of shape (H, W), bool
        Use with :func:`drop_pixels` or ``correct_raw(..., bad_pixels=bad)``.

    A hot pixel (stuck high, or a large dark current) or a dead one (stuck
    low) in a region brighter than the neighbourhood's spread is found; a dead
    pixel in a dark region is not, and barely matters there.  On clean
    captures of the test scenes the default threshold flags no pixel or a
    handful (see the tests); a stack of captures lowers that further.
    """
    data = np.asarray(coded)
    limit = threshold
    if limit is None:
        limit = 8.0 if data.ndim == 2 else 6.0
    if not (math.isfinite(limit) and limit > 0):
        raise InputError(f"detect_bad_pixels: threshold must be finite and > 0, got {limit}")
    if not 0 <= min_fraction < 1:
        raise InputError(f"detect_bad_pixels: min_fraction must be in [0, 1), got {min_fraction}")
    kw = dict(size=size, similar_size=similar_size, min_similarity=min_similarity)
    mask_arr = np.asarray(mask)
    if data.ndim == 2:
        return outlier_scores(data, mask_arr, **kw) > limit
    if data.ndim != 3:
        raise InputError(f"detect_bad_pixels: expected a coded image (H, W) or a stack (T, H, W), got {data.shape}")
    if mask_arr.ndim == 3:
        masks = [mask_arr] * data.shape[0]
    elif mask_arr.ndim == 4 and mask_arr.shape[0] == data.shape[0]:
        masks = list(mask_arr)
    else:
        raise InputError(f"detect_bad_pixels: mask {mask_arr.shape} is neither one (N, H, W) nor one per capture "
                         f"({data.shape[0]}, N, H, W)")
    return vote_bad_pixels(zip(data, masks), data.shape[0], threshold=limit, min_fraction=min_fraction, **kw)


def vote_bad_pixels(captures, count: int, *, threshold: float = 6.0, min_fraction: float = 0.5, **kw) -> np.ndarray:
    """:func:`detect_bad_pixels` of a stack given one capture at a time: ``captures`` yields ``count``
    pairs ``(coded (H, W), mask (N, H, W))``, none of them kept (a long stream is never held whole)."""
    votes = None
    for c, m in captures:
        hit = outlier_scores(c, m, **kw) > threshold
        votes = hit.astype(np.int32) if votes is None else votes + hit
    return votes > min_fraction * count
