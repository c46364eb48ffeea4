"""Captures of a coded video: what did not change from one capture to the next is left out.

For a scene that does not move, the coded value of a pixel divided by its open
count, ``q = coded / open count``, is the frame value itself, the same in every
capture whatever the code.  A single coded image cannot tell still texture from
motion; two captures can.  A pixel *agrees* when ``q`` agrees, within the
noise, with the capture before or after it, and its still answer (``q``
averaged with the captures it agrees with, :func:`still_values`) is quiet
enough to be worth taking.  A 7x7 patch whose every pixel agrees is still: it
takes the still answer in every sub-frame, with no dictionary search, while
every other patch is solved with all of its measurements, its own; the pixels
averaged from still patches alone (those whose 13x13 neighbourhood agrees) are
the still answer exactly.

Captures reconstructed one by one also meet badly: the first and last
sub-frames of a capture are its least determined, so the step from one capture
to the next is worse than a step inside one, a flicker every N frames
(:class:`StepErrors` measures it).  :func:`join_captures` smooths each such
step along the motion, without moving either capture's measurement.

Both read across a boundary, so neither may where the two captures do not show
one scene: a cut between shots, a dark or blown-out capture, a large change of
exposure.  :class:`Cuts` tests each boundary on the measurements alone and the
join and the still answers leave a boundary it takes as a cut alone: either side
is then what it is capture by capture.
"""

from __future__ import annotations

import time

import numpy as np
from numba import njit

from codedvideo.model.patches import PATCH

#: Smallest difference of ``coded / open count`` taken as change, in working units (data range 255).
STILL_FLOOR = 0.5
#: Noise multiple: a still pixel's two normalised values differ by more with probability about 3e-3.
STILL_SIGMAS = 3.0
#: Largest read noise of the still answer ``coded / open count`` (``sigma / open count``), in working units, for
#: which a pixel may be still.  Above it OMP's estimate of a still patch beats the still answer, and a second
#: capture no longer tells slow motion from noise (docs/research.md, "Streams: still answers under read noise").
STILL_NOISE_MAX = 6.0
#: A still region is *flat* where the variance of ``coded / open count`` over a 7x7 window is at most this
#: multiple of its read noise's: there the single-capture still test (a few 2D DCT atoms fitted within the
#: noise, :func:`codedvideo.solvers.region.still_patches`) removes the noise that the still answer keeps
#: (docs/research.md, "Streams: still answers under read noise").
FLAT_VARIANCE = 1.5


def normalised(coded: np.ndarray, mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(coded / open count, open count)``; 0 where a pixel is never open."""
    k = np.asarray(mask).sum(0, dtype=np.float32)  # (no float copy of the mask: 600 MB at 4K, N = 18)
    return np.where(k > 0, np.asarray(coded, np.float32) / np.maximum(k, 1e-12), 0).astype(np.float32), k


def erode_to_patches(agree: np.ndarray, patch: int = PATCH) -> np.ndarray:
    """The pixels of ``agree`` every ``patch x patch`` patch over which lies inside ``agree``."""
    # every patch containing the pixel lies inside the still region (patches lie inside the image)
    from scipy import ndimage  # lazy: only a job of several captures looks for still pixels

    return ndimage.minimum_filter(agree.view(np.uint8), size=2 * patch - 1, mode="nearest").astype(bool)


def agreeing_pixels(codeds, masks, i: int, *, sigma: float, scale: float = 1.0, cut=None) -> np.ndarray:
    """Pixels of capture ``i`` whose ``coded / open count`` agrees, within the noise, with the capture before or
    after, (H, W) bool: where :func:`still_values` is a number."""
    return np.isfinite(still_values(codeds, masks, i, sigma=sigma, scale=scale, cut=cut))


def still_values(codeds, masks, i: int, *, sigma: float, scale: float = 1.0,
                 white_level: float | None = None, cut=None) -> np.ndarray:
    """The still answer of capture ``i``'s pixels that agree with the capture before or after it; NaN elsewhere.

    A pixel agrees with a neighbouring capture when their ``coded / open count`` differ by at most
    ``STILL_SIGMAS`` times the noise of the difference (at least ``STILL_FLOOR``), and only where both
    values are quiet enough to be worth taking (``sigma / open count`` at most ``STILL_NOISE_MAX``) and
    neither is saturated.  Its still answer is ``coded / open count`` averaged over this capture and the
    neighbours it agrees with, each weighted by its open count squared (the inverse of its noise
    variance): the same value where they are equal (a still scene without noise: exact), and with
    sqrt(3) less noise than the capture's own where two neighbours with its open count agree.

    Parameters
    ----------
    codeds : sequence of (H, W) coded images, in the capture's units
    masks : callable ``masks(j)`` -> the (N, H, W) mask of capture ``j``
    i : the capture
    sigma : read-noise standard deviation, in the capture's units
    scale : factor from the capture's units to working units (:class:`codedvideo.model.units.DataRange`)
    white_level : coded values at or above it (the capture's units) are clipped: never still, never averaged in
    cut : callable ``cut(j)``, optional (:class:`Cuts`): true where captures ``j`` and ``j + 1`` do not show one
        scene; no neighbour across such a boundary is compared or averaged in

    Returns
    -------
    ndarray of shape (H, W), float32, in working units
    """
    work_sigma = sigma * scale

    def usable(j: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Capture j's ``coded / open count`` in working units, its open count, and where it may take part."""
        q, k = normalised(codeds[j], masks(j))
        quiet = (k > 0) & (work_sigma <= STILL_NOISE_MAX * k)
        if white_level is not None:
            quiet &= np.asarray(codeds[j]) < np.float32(white_level)
        return q * np.float32(scale), k, quiet

    q, k, quiet = usable(i)
    if not quiet.any():
        return np.full(q.shape, np.nan, np.float32)
    weight, pull = k * k, np.zeros(q.shape, np.float32)  # sum of w_j (q_j - q): 0 from the capture itself
    agree = np.zeros(q.shape, bool)
    for j in (i - 1, i + 1):
        if not 0 <= j < len(codeds) or (cut is not None and cut(min(i, j))):
            continue
        qj, kj, quiet_j = usable(j)
        with np.errstate(divide="ignore"):
            spread = work_sigma * np.sqrt(1 / np.maximum(k, 1e-12) ** 2 + 1 / np.maximum(kj, 1e-12) ** 2)
        tol = np.maximum(STILL_SIGMAS * spread, STILL_FLOOR)
        near = quiet & quiet_j & (np.abs(q - qj) <= tol)
        agree |= near
        w = np.where(near, kj * kj, 0).astype(np.float32)
        weight, pull = weight + w, pull + w * (qj - q)
    if work_sigma > 0:  # flat regions: left to the single-capture still test, which also removes the noise
        agree &= ~_flat(q, np.where(k > 0, work_sigma / np.maximum(k, 1e-12), 0).astype(np.float32))
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(agree, q + pull / weight, np.nan).astype(np.float32)


# --- boundaries that are not joined (a cut, a dark or blown-out capture, a jump of exposure) -----------

#: Side, in cells, of the coarse image of ``coded / open count`` (block means) that two captures are compared
#: on: block means take out the code (each pixel sees its own sub-frames) and most of the motion of a capture.
CUT_CELLS = 64
#: Smoothing of the coarse image, cells.
CUT_SMOOTH = 1.0
#: Correlation of the two coarse images below which the captures show different scenes: below what ordinary
#: motion gave and above most cuts, leaning to joining fast motion (docs/research.md, "Streams: cuts and joins").
CUT_CORRELATION = 0.2
#: Ratio of the mean ``coded / open count`` of the two captures above which (or below whose inverse) the
#: exposure changed too much to join: between ordinary footage and cuts (docs/research.md, "Streams: cuts and
#: joins").
CUT_GAIN = 1.3
#: A capture is *dark* when its mean ``coded / open count`` is at most this, in working units (data range
#: 255); the gain is taken with this floor, so two dark captures agree.
CUT_DARK = 2.0
#: A coarse image whose standard deviation is at most this (working units) is *flat*: no structure to
#: compare.  Two flat captures are compared on their gain alone; one flat beside one that is not is a cut.
CUT_FLAT = 1.0
#: Share of the open pixels clipped at the white level above which a capture is *blown out*.
CUT_CLIPPED = 0.5


class Cuts:
    """Which boundaries of a stream of captures are not joined: ``cuts(i)`` is None where captures ``i`` and
    ``i + 1`` show one scene, else why not (a dict: ``reason`` and the figures).

    Each capture is summarised once (its coarse image of ``coded / open count``, :data:`CUT_CELLS` cells
    on its long side, and the share of its pixels clipped) and kept: small beside a capture, asked in any
    order.  The test, per boundary (every threshold in working units or scale-free):

    * ``blown``: more than :data:`CUT_CLIPPED` of either capture's open pixels are clipped (``white_level``);
    * ``dark``: one capture's mean is at most :data:`CUT_DARK` and the other's is not;
    * ``exposure``: the means (each at least :data:`CUT_DARK`) differ by more than :data:`CUT_GAIN` times;
    * ``flat``: one coarse image is flat (:data:`CUT_FLAT`) and the other is not;
    * ``scene``: the correlation of the two coarse images is below :data:`CUT_CORRELATION` (gain-free:
      robust to motion, which moves a few cells, and to a small change of exposure).

    ``cuts.found()`` lists the boundaries asked so far that are cuts, for the metrics.
    """

    def __init__(self, codeds, masks, *, scale: float = 1.0, white_level: float | None = None):
        self.codeds, self.masks, self.scale, self.white_level = codeds, masks, float(scale), white_level
        self._summary: dict[int, tuple] = {}
        self._boundary: dict[int, dict | None] = {}

    def summary(self, i: int) -> tuple[np.ndarray, np.ndarray, float, float]:
        """Capture i's coarse image (working units), where it is measured, its mean and its clipped share."""
        if i not in self._summary:
            coded = np.asarray(self.codeds[i])
            q, k = normalised(coded, self.masks(i))
            seen = k > 0
            clipped = 0.0
            if self.white_level is not None:
                white = coded >= np.float32(self.white_level)
                clipped = float((white & seen).sum()) / max(int(seen.sum()), 1)
                seen &= ~white
            q = np.where(seen, q * np.float32(self.scale), 0).astype(np.float32)
            h, w = q.shape
            s = max(1, -(-max(h, w) // CUT_CELLS))
            hc, wc = -(-h // s), -(-w // s)

            def cells(a):  # block sums over s x s cells (the last ones partial)
                padded = np.pad(a, ((0, hc * s - h), (0, wc * s - w)))
                return padded.reshape(hc, s, wc, s).sum((1, 3), dtype=np.float64)

            count = cells(seen.astype(np.float32))
            coarse = cells(q) / np.maximum(count, 1)
            mean = float(q.sum(dtype=np.float64) / max(int(seen.sum()), 1))
            self._summary[i] = (coarse, count > 0, mean, clipped)
        return self._summary[i]

    def __call__(self, i: int) -> dict | None:
        """None where captures i and i + 1 agree (join them), else why not."""
        if i not in self._boundary:
            self._boundary[i] = self._test(i)
        return self._boundary[i]

    def _test(self, i: int) -> dict | None:
        from scipy import ndimage  # lazy (see erode_to_patches)

        (a, seen_a, mean_a, clip_a), (b, seen_b, mean_b, clip_b) = self.summary(i), self.summary(i + 1)
        figures = dict(gain=(max(mean_b, CUT_DARK) / max(mean_a, CUT_DARK)), mean=[mean_a, mean_b])
        if max(clip_a, clip_b) > CUT_CLIPPED:
            return dict(reason="blown", clipped=[clip_a, clip_b], **figures)
        if (mean_a <= CUT_DARK) != (mean_b <= CUT_DARK):
            return dict(reason="dark", **figures)
        if max(figures["gain"], 1 / figures["gain"]) > CUT_GAIN:
            return dict(reason="exposure", **figures)
        both = seen_a & seen_b
        if both.sum() < 2:
            return None
        a, b = (ndimage.gaussian_filter(np.where(both, c, c[both].mean()), CUT_SMOOTH, mode="nearest")[both]
                for c in (a, b))
        spread_a, spread_b = float(a.std()), float(b.std())
        if spread_a <= CUT_FLAT or spread_b <= CUT_FLAT:
            return None if spread_a <= CUT_FLAT and spread_b <= CUT_FLAT else dict(reason="flat", **figures)
        correlation = float(np.mean((a - a.mean()) * (b - b.mean())) / (spread_a * spread_b))
        figures["correlation"] = correlation
        return dict(reason="scene", **figures) if correlation < CUT_CORRELATION else None

    def found(self) -> list[dict]:
        """The boundaries asked so far that are cuts: ``boundary`` i (between captures i and i + 1, from 0) first."""
        return [dict(boundary=i, **why) for i, why in sorted(self._boundary.items()) if why is not None]


def _flat(q: np.ndarray, noise: np.ndarray, patch: int = PATCH) -> np.ndarray:
    """Pixels whose ``patch x patch`` window of ``q`` varies no more than its noise does (``FLAT_VARIANCE``)."""
    from scipy import ndimage  # lazy (see erode_to_patches)

    values = q.astype(np.float64)
    mean = ndimage.uniform_filter(values, patch, mode="nearest")
    spread = ndimage.uniform_filter(values * values, patch, mode="nearest") - mean * mean
    return spread <= FLAT_VARIANCE * ndimage.uniform_filter(noise.astype(np.float64) ** 2, patch, mode="nearest")


class StepErrors:
    """Error of the frame-to-frame step, inside captures and across their boundaries (flicker every N frames).

    ``add(volume, truth)`` capture after capture; the step error of frames
    ``t, t+1`` is the RMS of ``(x[t+1] - x[t]) - (g[t+1] - g[t])``.
    """

    def __init__(self):
        self.inside: list[float] = []
        self.boundary: list[float] = []
        self._last = None

    @staticmethod
    def _rms(a: np.ndarray) -> float:
        return float(np.sqrt(np.mean(np.square(a, dtype=np.float64))))

    def add(self, volume: np.ndarray, truth: np.ndarray) -> None:
        v, g = np.asarray(volume, np.float64), np.asarray(truth, np.float64)
        self.inside += [self._rms((v[t + 1] - v[t]) - (g[t + 1] - g[t])) for t in range(len(v) - 1)]
        if self._last is not None:
            self.boundary.append(self._rms((v[0] - self._last[0]) - (g[0] - self._last[1])))
        self._last = (v[-1], g[-1])

    def summary(self) -> dict:
        inside = float(np.mean(self.inside)) if self.inside else None
        boundary = float(np.mean(self.boundary)) if self.boundary else None
        ratio = boundary / inside if inside and boundary is not None else None
        return dict(step_rms_inside=inside, step_rms_boundary=boundary, boundary_to_inside=ratio,
                    step_rms_per_boundary=self.boundary)


# --- joining consecutive captures (no flicker every N frames) -----------------------------------

#: Blend weights toward the line through the boundary of the frames at each end of a capture that the
#: line is fitted to, the boundary frame first (their number is k, at most N // 2).  The last is 0: that
#: frame moves only to keep the measurement (:func:`_project_out`), which leaves the two nearer the
#: boundary freer to move.
JOIN_WEIGHTS = (1.0, 0.25, 0.0)
#: Frames of a capture that :func:`join_captures` reads at either boundary: given only these (the last of the
#: capture before, the first of the one after), it gives the bits it gives on the whole captures.
JOIN_FRAMES = 2 * len(JOIN_WEIGHTS)
#: Blend gain where the frames agree along the motion, and where they do not at all (above 1: the
#: reconstruction's end frames are worse than the line through their neighbours).
JOIN_GAIN_STILL, JOIN_GAIN_MOVING = 1.25, 0.4
#: Change left along the motion (mean absolute frame step of the motion-compensated frames) at
#: which the gain is halfway between the two, as a fraction of the data range (8 grey levels of 255).
JOIN_MISFIT = 8.0 / 255.0
#: Side of the square over which motion and misfit are pooled (Lucas-Kanade window; misfit: one patch).
JOIN_FLOW_WINDOW, JOIN_MISFIT_WINDOW = 15, 7
#: Presmoothing of the frames the motion is estimated from, pixels.
JOIN_FLOW_SMOOTH = 1.5
#: Largest motion followed, pixels per sub-frame (a linearised estimate beyond it means little).
JOIN_MAX_SPEED = 4.0


def _flow(frames: np.ndarray, skip: int) -> tuple[np.ndarray, np.ndarray]:
    """Lucas-Kanade motion ``(vy, vx)`` (H, W), pixels per frame, of frames ``(F, H, W)`` in [0, 1]-ish units.

    One motion for all ``F - 1`` steps but step ``skip`` (the one across the boundary, not trusted).
    """
    from scipy import ndimage  # lazy: a run of one capture starts without it (0.05 to 0.1 s)

    f = ndimage.gaussian_filter(frames, (0, JOIN_FLOW_SMOOTH, JOIN_FLOW_SMOOTH), mode="nearest")
    gy, gx = np.gradient(f, axis=(1, 2))
    keep = [i for i in range(len(f) - 1) if i != skip]
    gt = (f[1:] - f[:-1])[keep]
    gy = ((gy[1:] + gy[:-1]) / 2)[keep]
    gx = ((gx[1:] + gx[:-1]) / 2)[keep]

    def pool(z):
        return _box_mean(z.sum(0), JOIN_FLOW_WINDOW)

    a, b, c = pool(gx * gx), pool(gx * gy), pool(gy * gy)
    d, e = -pool(gx * gt), -pool(gy * gt)
    # Tikhonov term relative to the texture's own energy (scale-free), plus a floor for flat regions:
    # where there is no texture the motion is 0 (nothing to compensate).
    det = a * c - b * b + 1e-3 * (a + c) ** 2 + 1e-12
    vx = np.clip((c * d - b * e) / det, -JOIN_MAX_SPEED, JOIN_MAX_SPEED)
    vy = np.clip((a * e - b * d) / det, -JOIN_MAX_SPEED, JOIN_MAX_SPEED)
    return vy.astype(np.float32), vx.astype(np.float32)


def _box_mean(z: np.ndarray, size: int) -> np.ndarray:
    """Mean of ``z`` (H, W) over the ``size x size`` square around each pixel, edges repeated: the values of
    ``scipy.ndimage.uniform_filter(z, size, mode="nearest")`` to float roundoff, but each a sum of its own
    window (a direct correlation, not a running sum): the same bits whatever rows lie above it in ``z``, which
    is what lets :func:`_join_region` work a band of rows at a time."""
    from scipy import ndimage  # lazy (see _flow)

    w = np.full(size, 1.0 / size)
    return ndimage.correlate1d(ndimage.correlate1d(z, w, axis=0, mode="nearest"), w, axis=1, mode="nearest")


def _warp(frames: np.ndarray, vy: np.ndarray, vx: np.ndarray, tau: np.ndarray, *, row0: int = 0,
          height: int | None = None, rows: slice | None = None) -> np.ndarray:
    """Frame ``f`` of ``frames`` (F, H, W) sampled at ``(y + vy tau[f], x + vx tau[f])``: (F, H, W) float32.

    Linear interpolation, edges repeated (a coordinate outside the frame is
    moved onto its border).  Linear, not cubic: cubic gained little for twice
    the time of a join (docs/research.md, "Streams: cuts and joins").  Compiled
    (:func:`_warp_kernel`): the values of ``scipy.ndimage.map_coordinates(order=1,
    mode="nearest")`` to the rounding of the coordinates, about ten times faster.

    A band of rows of a taller frame (:func:`_join_region`): ``frames`` are its rows from ``row0`` of a frame
    ``height`` rows high, whose edges are the ones repeated; coordinates are taken in the whole frame's rows,
    so a pixel whose samples lie inside the band gets the whole frame's bits.  ``rows``: only these rows of
    the result (the others are not worked out).
    """
    stack = np.ascontiguousarray(frames, dtype=np.float32)
    h = stack.shape[1]
    first, last, _ = (rows or slice(None)).indices(h)
    out = np.empty((stack.shape[0], max(last - first, 0), stack.shape[2]), np.float32)
    _warp_kernel(stack, np.ascontiguousarray(vy, dtype=np.float32), np.ascontiguousarray(vx, dtype=np.float32),
                 np.ascontiguousarray(tau, dtype=np.float32), int(row0), int(h if height is None else height),
                 int(first), out)
    return out


@njit(nogil=True, cache=True)
def _warp_kernel(frames, vy, vx, tau, row0, height, first, out):  # pragma: no cover - compiled
    nf, h, w = frames.shape
    for f in range(nf):
        for r in range(out.shape[1]):
            i = first + r
            for j in range(w):
                # in the whole frame's rows (row0 + i): the same rounding in a band as in the frame
                y = min(max((row0 + i) + np.float64(vy[i, j]) * tau[f], 0.0), height - 1.0)
                x = min(max(j + np.float64(vx[i, j]) * tau[f], 0.0), w - 1.0)
                y0, x0 = int(y), int(x)
                y1, x1 = min(y0 + 1, height - 1), min(x0 + 1, w - 1)
                fy, fx = y - y0, x - x0
                y0, y1 = min(max(y0 - row0, 0), h - 1), min(max(y1 - row0, 0), h - 1)  # the band's own rows
                top = (1.0 - fx) * frames[f, y0, x0] + fx * frames[f, y0, x1]
                bottom = (1.0 - fx) * frames[f, y1, x0] + fx * frames[f, y1, x1]
                out[f, r, j] = (1.0 - fy) * top + fy * bottom


def _project_out(change: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """``change`` (K, H, W) less its component along ``mask`` (K, H, W), per pixel.

    Afterwards ``sum_t mask[t] * change[t] == 0`` at every pixel, so adding the
    change leaves the capture's measurement as it was.  Pixels whose ``K``
    frames are all closed (``sum_t mask[t]**2 == 0``) keep their change: no
    measurement sees it.
    """
    m = np.broadcast_to(np.asarray(mask, np.float32), change.shape)
    # frame by frame, not einsum: the same bits for a pixel whatever the array's size (a band or the frame)
    energy, along = m[0] * m[0], m[0] * change[0]
    for t in range(1, len(m)):
        energy += m[t] * m[t]
        along += m[t] * change[t]
    seen = energy > 0
    return change - m * np.where(seen, along / np.where(seen, energy, 1), 0).astype(np.float32)


def join_captures(
    before: np.ndarray,
    after: np.ndarray,
    *,
    coded_before: np.ndarray,
    mask_before: np.ndarray,
    coded_after: np.ndarray,
    mask_after: np.ndarray,
    data_range: float | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Smooth the step from one reconstructed capture to the next, keeping both measurements.

    Each capture is reconstructed on its own and its first and last sub-frames
    are its least determined (the fewest pixels of a patch are open in them),
    so the step from the last frame of ``before`` to the first of ``after`` is
    worse than a step inside a capture: a flicker every N frames.  Here the
    motion through the boundary is estimated (Lucas-Kanade, from the last and
    first 4 frames, the boundary step left out); along it, per pixel, a
    straight line is fitted to the last ``k`` frames of ``before`` and the
    first ``k`` of ``after`` (``k = min(3, N // 2)``), and the two frames
    nearest the boundary on each side are drawn toward it (weight 1, then
    1/4), less where the frames disagree along the motion (occlusions, jerky
    or non-rigid motion).  The change is then made invisible to each capture's
    measurement: per pixel, its component along that capture's mask over those
    ``k`` frames is removed (which may move the ``k``-th frame too), so
    ``sum_t mask[t] * x[t]`` stays what it was, equal to the coded image
    wherever the reconstruction met it.

    Call it on a stream capture after capture: (0, 1), then (1, 2) with the
    ``after`` it returned, and so on.  Only ``k <= N // 2`` frames at each end
    change, so the two joins of a capture change different frames and the
    second does not undo the first.

    Parameters
    ----------
    before, after : (N, H, W) float
        Two consecutive reconstructed captures, ``after`` following ``before``
        in time, in the units of the coded images.
    coded_before, coded_after : (H, W) float
        Their coded images; used only to find the data range when
        ``data_range`` is None.
    mask_before, mask_after : (N, H, W) uint8, bool or float weights in [0, 1]
        Their shutter codes (the same array when the code repeats).
    data_range : float, optional
        Peak value of a frame in these units.  Default: the largest
        ``coded / open count`` of the two captures
        (:func:`codedvideo.model.units.static_peak`).  Every threshold is a fraction
        of it, so scaling all the inputs scales the result and changes nothing
        else.

    Returns
    -------
    (before, after) : tuple of two (N, H, W) float32 arrays
        New arrays (the inputs are not modified); only ``before[N - k:]`` and
        ``after[:k]`` differ from the inputs.  A pair whose ``2k`` frames
        around the boundary are all equal comes back exactly as it was, and so
        does every pair when ``N < 4`` (a line through 2 frames fits them).

    Notes
    -----
    Cost: one optical-flow estimate (a few filters over 8 frames) and ten
    linear resamplings (compiled, :func:`_warp`) over the box around the
    pixels that change in those frames, grown by :func:`_join_reach` (41
    pixels at N = 8); about 0.025 s for a whole 256 x 256 frame.  Where the
    scene is still the join leaves the pixels exactly as they were.  The box
    is worked out :data:`JOIN_BAND_ROWS` rows at a time (:func:`_join_region`):
    beyond the two results, the working memory is a band's whatever the frame's
    height, and the values are the same bits as in one band.
    """
    from codedvideo.model.units import static_peak

    b = np.array(before, np.float32)
    a = np.array(after, np.float32)
    if b.ndim != 3 or b.shape != a.shape:
        raise ValueError(f"join_captures: before {b.shape} and after {a.shape} must both be (N, H, W)")
    if min(len(JOIN_WEIGHTS), b.shape[0] // 2) < 2:
        return b, a
    value_range = data_range
    if value_range is None:
        value_range = max(static_peak(coded_before, mask_before), static_peak(coded_after, mask_after))
    _join_region(b, a, mask_before, mask_after, data_range=value_range)
    return b, a


#: Rows of the frame a join works out at a time (:func:`_join_region`), each with :func:`_join_margin` rows
#: more either side: its working memory is about 60 planes of a band whatever the frame's height, and its values
#: are the whole frame's bit for bit (tested); a little slower than one band, for a fraction of its memory
#: (docs/research.md, "Memory").
JOIN_BAND_ROWS = 128
#: Rows of a band's new values written to a file (a spilled capture) at once: it reads and writes whole frames.
JOIN_WRITE_ROWS = 512


def _join_margin(k: int) -> int:
    """Rows either side of a band that the join's values in the band read, through every step.

    A change at a row is the change along the motion (back from the boundary's
    grid: up to ``travel`` rows away, one more for the interpolation) of the
    gain (a misfit pooled over half a window, ``JOIN_MISFIT_WINDOW // 2``)
    times the misfit of the frames aligned along the motion: the frames again
    up to ``travel`` rows away, and the motion, which reads the smoothing
    (scipy's radius, truncate=4), one gradient step and half the Lucas-Kanade
    window.
    """
    smooth = int(4.0 * JOIN_FLOW_SMOOTH + 0.5)
    flow = smooth + 1 + JOIN_FLOW_WINDOW // 2
    travel = int(np.ceil(JOIN_MAX_SPEED * (2 * k - 1) / 2)) + 1
    return travel + JOIN_MISFIT_WINDOW // 2 + max(flow, travel)


def _join_region(before, after, mask_before, mask_after, *, data_range: float | None, region=None,
                 clipped_of=None) -> None:
    """:func:`join_captures` in place, over ``region`` (rows, cols) of the frames, a band of rows at a time.

    ``before`` and ``after`` are (n, H, W): arrays, or anything indexed ``[frames, rows, cols]`` for reading
    and writing (a :class:`codedvideo.volumes.FrameFile`); only the last / first ``k + 1`` frames are read,
    the rows of a band at a time, and the last / first ``k`` written.  ``data_range``: as join_captures'
    (None or not a positive number: the largest magnitude of the frames around the boundary).
    ``clipped_of(rows, cols)``: (h, w) bool, the pixels that keep both captures' values (clipped in either).

    The box around what changes in time (:func:`_around`) is found first, over the whole region; then each
    band of :data:`JOIN_BAND_ROWS` rows of it is worked out from its rows and :func:`_join_margin` more either
    side (cut to the box, whose edges are the edges every step repeats).  Every step reads only rows within
    that margin of a band's row, and each pixel's arithmetic does not depend on where the array it lies in
    starts (:func:`_box_mean`, :func:`_warp`'s row offset, :func:`_project_out`), so a band's values are the
    whole box's bit for bit; the working memory is a band's.
    """
    n, height, width = before.shape
    k = min(len(JOIN_WEIGHTS), n // 2)
    if k < 2:
        return
    side = min(n, k + 1)
    top, bottom, _ = (region[0] if region else slice(None)).indices(height)
    left, right, _ = (region[1] if region else slice(None)).indices(width)
    if bottom <= top or right <= left:
        return
    band = max(int(JOIN_BAND_ROWS), 1)

    def seen(lo: int, hi: int, cols: slice) -> np.ndarray:
        """The frames the motion is estimated from, rows lo..hi: before's last ``side``, after's first."""
        return np.concatenate([np.asarray(before[n - side : n, lo:hi, cols], np.float32),
                               np.asarray(after[:side, lo:hi, cols], np.float32)])

    # What changes in time, over the whole region (the box), whether the 2k frames around the boundary change
    # at all, and their largest magnitude (the data range when none is given): a band at a time.
    changed = np.zeros((bottom - top, right - left), bool)
    moves, peaks = False, []
    for lo in range(top, bottom, band):
        hi = min(lo + band, bottom)
        frames = seen(lo, hi, slice(left, right))
        changed[lo - top : hi - top] = np.any(frames != frames[:1], axis=0)
        window = frames[side - k : side + k]
        moves = moves or bool(np.any(window != window[:1]))
        peaks.append(np.max(np.abs(window)))
        del frames, window
    if not moves:
        return  # nothing changes in time here: nothing to join
    value_range = data_range
    if value_range is None or not np.isfinite(value_range) or value_range <= 0:
        value_range = float(np.max(peaks)) or 1.0
    unit = np.float32(value_range)  # work in fractions of the data range: every constant is scale-free
    # Only near what changes: the join is worked out on the box around it, the same values as over the
    # whole frame (tested).
    rows, cols = _around(changed, _join_reach(k))
    del changed
    r0, r1 = top + rows.start, top + rows.stop
    cols = slice(left + cols.start, left + cols.stop)
    margin = _join_margin(k)
    # A band's new values wait until no later band reads its rows (they are read as they were); into a file
    # (which reads a whole frame to write a part of it) in runs of at least JOIN_WRITE_ROWS rows.
    direct = isinstance(before, np.ndarray) and isinstance(after, np.ndarray)
    pending: list[tuple[int, int, np.ndarray, np.ndarray]] = []

    def write(upto: int, least: int) -> None:
        ready = [p for p in pending if p[1] <= upto]
        if not ready or sum(p[1] - p[0] for p in ready) < least:
            return
        lo, hi = ready[0][0], ready[-1][1]
        b, a = (np.concatenate([p[i] for p in ready], axis=1) for i in (2, 3))
        del pending[: len(ready)]
        for t in range(k):  # a frame at a time
            before[n - k + t, lo:hi, cols] = b[t]
            after[t, lo:hi, cols] = a[t]

    for c0 in range(r0, r1, band):
        c1 = min(c0 + band, r1)
        e0, e1 = max(c0 - margin, r0), min(c1 + margin, r1)
        keep = slice(c0 - e0, c1 - e0)
        change_b, change_a = _join_changes(seen(e0, e1, cols), unit, k, keep=keep, row0=e0 - r0,
                                           height=r1 - r0, mask_b=np.asarray(mask_before)[n - k : n, c0:c1, cols],
                                           mask_a=np.asarray(mask_after)[:k, c0:c1, cols])
        # Keep each capture's measurement: the changes are free of it (_project_out).
        old_b = np.asarray(before[n - k : n, c0:c1, cols], np.float32)
        old_a = np.asarray(after[:k, c0:c1, cols], np.float32)
        b, a = old_b + change_b, old_a + change_a
        if clipped_of is not None:  # clipped in either capture: both as they were
            clipped = clipped_of(slice(c0, c1), cols)
            b[:, clipped], a[:, clipped] = old_b[:, clipped], old_a[:, clipped]
        pending.append((c0, c1, b, a))
        del change_b, change_a, old_b, old_a, b, a
        write(c1 - margin if c1 < r1 else r1, 0 if direct or c1 == r1 else JOIN_WRITE_ROWS)
    write(r1, 0)


def _join_changes(seen: np.ndarray, unit, k: int, *, keep: slice, row0: int, height: int, mask_b, mask_a):
    """The changes a join makes to rows ``keep`` of ``seen`` (2 (k + 1), h, w): to before's last ``k`` frames
    and after's first ``k``, each (k, rows, w) float32, free of each capture's measurement.  ``seen``'s rows
    start at ``row0`` of a box ``height`` rows high (:func:`_join_region`); ``mask_b``, ``mask_a``: the
    captures' codes over those frames and the rows ``keep``."""
    side = len(seen) // 2
    window = seen[side - k : side + k]  # (2k, h, w), the boundary between k-1 and k
    # Motion through the boundary, per pixel and sub-frame, from the frames either side of it.
    vy, vx = _flow(seen / unit, skip=side - 1)
    # Frame j of the window lies tau_j sub-frames from the boundary: what is at p at the boundary is at
    # p + v tau_j in frame j.  Sampled there, the frames follow the motion and a line fits them.
    tau = np.arange(2 * k, dtype=np.float32) - (2 * k - 1) / 2
    aligned = _warp(window / unit, vy, vx, tau, row0=row0, height=height)
    design = np.stack([np.ones_like(tau), tau], 1).astype(np.float64)
    to_line = (design @ np.linalg.pinv(design) - np.eye(2 * k)).astype(np.float32)
    weight = np.zeros(2 * k, np.float32)  # the i-th frame from the boundary, before and after it
    for i, w in enumerate(JOIN_WEIGHTS[:k]):
        weight[[k - 1 - i, k + i]] = w
    drawn = np.flatnonzero(weight)
    # per pixel, the least-squares line less the frames (frame by frame: each pixel's own sums)
    misfit = np.zeros((len(drawn), *aligned.shape[1:]), np.float32)
    for j in range(2 * k):
        misfit += to_line[drawn, j, None, None] * aligned[j]
    # Where the frames still change along the motion (occlusion, jerky or non-rigid motion, a wrong
    # motion estimate; the step across the boundary counts too), a line is a poorer guess of the truth
    # than the reconstruction: draw toward it less.  Pooled over one patch.
    moving = np.abs(np.diff(aligned, axis=0)).mean(0)
    del aligned
    moving = _box_mean(moving, JOIN_MISFIT_WINDOW) / np.float32(JOIN_MISFIT)
    gain = (JOIN_GAIN_MOVING + (JOIN_GAIN_STILL - JOIN_GAIN_MOVING) / (1 + moving)).astype(np.float32)
    change = np.zeros((2 * k, keep.stop - keep.start, seen.shape[2]), np.float32)
    # back from the boundary's grid to each drawn frame's own pixels
    change[drawn] = weight[drawn, None, None] * unit * _warp(gain * misfit, vy, vx, -tau[drawn], row0=row0,
                                                              height=height, rows=keep)
    return _project_out(change[:k], mask_b), _project_out(change[k:], mask_a)


def _join_reach(k: int) -> int:
    """How far from a pixel that changes in time the join must look, for the same result as over the frame.

    A join changes only pixels where the motion can be non-zero: within the
    presmoothing radius plus half the motion window of a change (``near``).
    Its values there are the whole frame's when every input they read lies
    inside the box, away from the box's own edge: the motion (smoothing, one
    gradient step, the window), the farthest sample along it and back (the
    largest speed times the farthest frame, one more pixel for the linear
    interpolation) and the misfit's window.
    """
    smooth = int(4.0 * JOIN_FLOW_SMOOTH + 0.5)  # scipy's gaussian_filter radius (truncate=4)
    near = smooth + JOIN_FLOW_WINDOW // 2
    travel = int(np.ceil(JOIN_MAX_SPEED * (2 * k - 1) / 2)) + 1
    return near + (smooth + 1 + JOIN_FLOW_WINDOW // 2) + JOIN_MISFIT_WINDOW // 2 + travel


def _around(where: np.ndarray, reach: int) -> tuple[slice, slice]:
    """The bounding box of ``where`` (H, W) bool, grown by ``reach`` pixels and cut to the frame."""
    rows, cols = np.flatnonzero(where.any(1)), np.flatnonzero(where.any(0))
    h, w = where.shape
    return (slice(max(rows[0] - reach, 0), min(rows[-1] + reach + 1, h)),
            slice(max(cols[0] - reach, 0), min(cols[-1] + reach + 1, w)))


def joined(results, codeds, mask_of, *, data_range: float | None = None, still_of=None, margin: int = 16,
           white_level: float | None = None, cut=None):
    """A stream of reconstructed captures ``(i, volume, info)`` in order, each joined to the next (:func:`join_captures`).

    A capture is handed on once the next one has arrived and the step between
    them is smoothed, so two volumes are held at a time; ``info["seconds"]["join"]``
    is the time spent on the capture's join with its successor.  With
    ``still_of`` (:func:`still_values`), the join is left out where both
    captures are their still answer exactly (their 13x13 neighbourhoods
    agree): only the box around the rest, with ``margin`` pixels for the
    motion estimate, is joined, and nothing when nothing moves.  With
    ``white_level`` (the captures' units), pixels clipped in either capture
    keep both captures' values: a clipped capture's frames are no line to
    draw its neighbour toward.  With ``cut`` (:class:`Cuts`), a boundary where ``cut(j)`` is true (captures
    ``j`` and ``j + 1`` do not show one scene) is not joined: both keep their values.
    """
    try:
        yield from _joined(results, codeds, mask_of, data_range, still_of, margin, white_level, cut)
    finally:  # a join that fails, or a consumer that stops early, closes the job too (its stores' locks)
        getattr(results, "close", lambda: None)()


def _joined(results, codeds, mask_of, data_range, still_of, margin, white_level, cut):
    held = None
    for i, volume, info in results:
        if held is not None:
            j, before, before_info = held
            t0 = time.perf_counter()
            box = (slice(None), slice(None))
            if cut is not None and cut(j):  # two scenes (or a dark, blown-out, re-exposed capture): not joined
                box = None
            elif still_of is not None:
                moving = ~(erode_to_patches(np.isfinite(still_of(j))) & erode_to_patches(np.isfinite(still_of(i))))
                rows, cols = np.flatnonzero(moving.any(1)), np.flatnonzero(moving.any(0))
                box = None if rows.size == 0 else (
                    slice(max(rows[0] - margin, 0), rows[-1] + margin + 1),
                    slice(max(cols[0] - margin, 0), cols[-1] + margin + 1))
            if box is not None:
                # in place, a band of rows at a time (_join_region): only the frames at the boundary are read,
                # and of them only a band's rows (4K N = 18: the whole frames' copies and temporaries were
                # 2 GB); the data range, when not given, from the whole box as join_captures would find it
                pair_range = data_range
                if pair_range is None:
                    from codedvideo.model.units import static_peak

                    pair_range = max(static_peak(codeds[j][box], mask_of(j)[(slice(None), *box)]),
                                     static_peak(codeds[i][box], mask_of(i)[(slice(None), *box)]))
                clipped_of = None
                if white_level is not None:  # clipped in either capture: both as they were
                    white = np.float32(white_level)

                    def clipped_of(rows, cols, j=j, i=i, white=white):
                        return (np.asarray(codeds[j][rows, cols]) >= white) | (np.asarray(codeds[i][rows, cols]) >= white)
                _join_region(before, volume, mask_of(j), mask_of(i), data_range=pair_range, region=box,
                             clipped_of=clipped_of)
            before_info.setdefault("seconds", {})["join"] = time.perf_counter() - t0
            yield j, before, before_info
        held = (i, volume, info)
    if held is not None:
        yield held
