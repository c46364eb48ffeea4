"""Still regions of one capture, told apart by its own code, given the still estimate.

One measurement per pixel fits any still image exactly, so no test on a single pixel or patch tells a still
textured region from a moving one.  The code can, over a region: a pixel records ``z = coded / open count``,
the average of the sub-frames it was open for, centred at its exposure's centroid ``c``.  Where the scene holds
still, two neighbouring pixels differ by the scene's texture alone, whatever their codes; where it changes at a
rate ``g`` per sub-frame, they differ by the texture plus ``g (c_p - c_q)``, and since the code is independent of
the scene, ``E[(z_p - z_q)^2] = texture + g^2 E[(c_p - c_q)^2]``.  The slope of the squared differences of
neighbouring pixels (:data:`OFFSETS`) against the squared differences of their centroids, over a window, estimates
``g^2``: the variogram of the scene in time, read through the code (:func:`motion`).  Its square root times the
spread of a sub-frame's time about the capture's middle is how far the still estimate strays from the frames.

That is weighed against how far the sparse result strays from the measurement: its residual ``coded - S x``
per open sub-frame, averaged over :data:`RESIDUAL_WINDOW` pixels, the read noise taken out (:func:`still_weight`).
A result brought to the measurement afterwards (the non-local method's, without read noise) no longer shows it,
so :data:`PROJECTED_SHARE` of the misfit that the projection took away is counted back.
Where the still estimate's expected error is at most half the result's visible one, the still estimate is taken;
where it is as large, the result is kept; between, a linear blend.  Two guards: the motion is the largest of
the estimates over :data:`WINDOWS` (a small moving object in a still window is seen by the smaller one), and a
pixel where the result itself moves (its standard deviation over the sub-frames, averaged over a patch, above
:data:`MOVING`) keeps the result.  The read noise is the capture's as given, or found from the still estimate
(:func:`read_noise`, the flattest blocks' Laplacian; texture there raises it, which keeps more of the result).

Where it acts: textured regions that hold still, which the dictionary fits to a few grey levels and the still
estimate gives exactly (docs/research.md, "Telling still from moving in a single capture").  Codes that give
every pixel the same exposure (flutter, a global shutter) have no spread of centroids, and codes whose every row
(or column) shares one pattern (row-wise, thin-out) none along it, where the texture across it would read as
motion: nothing is taken there.

Arrays in, arrays out, in working units (the grey levels of an 8-bit capture); memory: a few float32 images
of the capture's size beside the volume.
"""

from __future__ import annotations

import numpy as np

from codedvideo.model import physics
from codedvideo.model.patches import PATCH
from codedvideo.model.sequence import normalised

#: The neighbours ``(dy, dx)`` whose differences make the variogram.
OFFSETS = ((0, 1), (1, 0), (1, 1), (1, -1), (0, 2), (2, 0))
#: Sides of the windows over which the motion is estimated, pixels; each pixel takes the largest estimate.
WINDOWS = (45, 21)
#: Side of the blocks the windows slide by, pixels.
BLOCK = 2
#: Side of the window over which the result's residual is averaged.
RESIDUAL_WINDOW = 15
#: The result's motion at a pixel (grey levels, as :data:`codedvideo.solvers.temporal.STILL_BELOW`) up to which
#: the still estimate may be taken there, and from which it is not: a small object moving in a still window
#: escapes the windows' estimate, but the result shows it move.
MOVING = (2.0, 4.0)
#: The share of the misfit that bringing a result to the measurement took away (the non-local method's
#: projection) counted in its residual: the projected result strays less than its misfit before the projection
#: says (with all of it, `best` lost up to 0.44 dB where a small object moves; docs/research.md, "Telling still
#: from moving in a single capture").
PROJECTED_SHARE = 0.7
#: Side of the blocks whose Laplacian gives the read noise, and the percentile of their estimates taken.
NOISE_BLOCK = 16
NOISE_PERCENTILE = 10.0
#: The share of the found read noise's variance counted against the still estimate (all of it is taken out of
#: the result's residual): texture in the flattest blocks raises the estimate.
NOISE_SHARE = 0.25

#: The standard deviation of the Laplacian ``[[1, -2, 1], [-2, 4, -2], [1, -2, 1]]`` of white noise of unit
#: standard deviation, and the ratio of a normal variable's median absolute value to its deviation.
_LAPLACIAN_GAIN = 6.0
_MAD_TO_SIGMA = 0.6745


def recipe() -> dict:
    """What a result with still regions depends on (a result's record is keyed by it)."""
    return dict(offsets=[list(o) for o in OFFSETS], windows=list(WINDOWS), block=BLOCK, residual_window=RESIDUAL_WINDOW,
                moving=list(MOVING), noise_block=NOISE_BLOCK, noise_percentile=NOISE_PERCENTILE,
                noise_share=NOISE_SHARE, projected_share=PROJECTED_SHARE)


def _box(a: np.ndarray, side: int) -> np.ndarray:
    from scipy.ndimage import uniform_filter

    return uniform_filter(a, side, mode="nearest")


def _centroids(mask: np.ndarray, open_count: np.ndarray) -> np.ndarray:
    """Each pixel's exposure centroid in sub-frames (0 where never open), a sub-frame at a time."""
    total = np.zeros(open_count.shape, np.float32)
    for t in range(mask.shape[0]):
        total += np.float32(t) * np.asarray(mask[t], np.float32)
    return np.divide(total, open_count, out=np.zeros_like(total), where=open_count > 0)


def motion(coded: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Each pixel's estimated motion: the RMS change of the scene about its mean over the sub-frames, in the
    coded image's units per sub-frame (the largest over :data:`WINDOWS`; NaN where the code gives no spread
    of centroids to read it from).  The pairs' moments are summed over blocks of :data:`BLOCK` pixels and the
    windows slide block by block."""
    z, n = normalised(coded, mask)
    if _one_pattern_along_lines(mask):
        return np.full(z.shape, np.nan, np.float32)
    cen = _centroids(mask, n)
    frames = mask.shape[0]
    h, w = z.shape
    moments = np.zeros((5, h, w), np.float32)  # pairs, x, y, x^2, x*y of each pair at its first pixel
    pairs = []
    for dy, dx in OFFSETS:
        a = (slice(0, h - dy), slice(max(0, -dx), w - max(0, dx)))
        b = (slice(dy, h), slice(max(0, dx), w + min(0, dx)))
        pairs.append((a, b, (cen[a] - cen[b]) ** 2))
    mean_x = float(np.mean([x.mean() for _, _, x in pairs]))  # centred: the moments' differences stay exact
    for a, b, x in pairs:
        both = ((n[a] > 0) & (n[b] > 0)).astype(np.float32)
        x = (x - np.float32(mean_x)) * both
        y = np.square(z[a] - z[b]) * both
        for k, v in enumerate((both, x, y, x * x, x * y)):
            moments[k][a] += v
    blocks = _block_sums(moments, BLOCK)
    best = np.zeros(blocks.shape[1:], np.float32)
    for side in WINDOWS:
        f = [_box(m, max(1, round(side / BLOCK))) for m in blocks]
        count = np.maximum(f[0], 1e-6)
        mx, my = f[1] / count, f[2] / count
        vx = f[3] / count - mx * mx
        slope = np.divide(f[4] / count - mx * my, vx, out=np.full_like(vx, np.nan), where=vx > 1e-3)
        best = np.fmax(best, np.sqrt(np.maximum(slope, 0) * np.float32((frames * frames - 1) / 12.0)))
        best[np.isnan(slope)] = np.nan
    return np.repeat(np.repeat(best, BLOCK, 0), BLOCK, 1)[:h, :w]


def _one_pattern_along_lines(mask: np.ndarray) -> bool:
    """Whether every row, or every column, of ``mask`` shares one pattern (row-wise and thin-out codes): the
    neighbours along it have no spread of centroids, and the texture across it would read as motion."""
    m = np.asarray(mask)
    return bool((m == m[:, :, :1]).all() or (m == m[:, :1, :]).all())


def _block_sums(a: np.ndarray, block: int) -> np.ndarray:
    """``a`` (k, H, W) summed over blocks of ``block x block`` pixels (the last ones padded with zeros)."""
    k, h, w = a.shape
    hb, wb = -(-h // block), -(-w // block)
    padded = np.zeros((k, hb * block, wb * block), a.dtype)
    padded[:, :h, :w] = a
    return padded.reshape(k, hb, block, wb, block).sum((2, 4))


def read_noise(coded: np.ndarray, mask: np.ndarray) -> float:
    """The read noise of a capture, in its units, from its still estimate: the median absolute Laplacian of
    each :data:`NOISE_BLOCK`-pixel block, the :data:`NOISE_PERCENTILE`-th percentile of the blocks (the
    flattest), times the typical open count.  Texture raises it (a lone block: the whole image's median)."""
    from scipy.ndimage import convolve

    z, n = normalised(coded, mask)
    if min(z.shape) < 3 or not (n > 0).any():
        return 0.0
    kernel = np.array([[1, -2, 1], [-2, 4, -2], [1, -2, 1]], np.float32)
    lap = np.abs(convolve(z, kernel, mode="nearest")[1:-1, 1:-1])
    b = NOISE_BLOCK
    hb, wb = lap.shape[0] // b, lap.shape[1] // b
    if hb and wb:
        blocks = lap[:hb * b, :wb * b].reshape(hb, b, wb, b).transpose(0, 2, 1, 3).reshape(hb * wb, b * b)
        typical = float(np.percentile(np.median(blocks, axis=1), NOISE_PERCENTILE))
    else:
        typical = float(np.median(lap))
    return typical / (_MAD_TO_SIGMA * _LAPLACIAN_GAIN) * float(np.median(n[n > 0]))


def still_weight(volume: np.ndarray, coded: np.ndarray, mask: np.ndarray, *, noise_sigma: float = 0.0,
                 excluded: np.ndarray | None = None, taken: np.ndarray | None = None) -> np.ndarray:
    """Each pixel's weight (H, W) float32 in [0, 1] of the still estimate against ``volume`` (module text).
    ``noise_sigma``: the read noise given, in the coded image's units (the larger of it and the one found,
    :func:`read_noise`, is taken out of the residual; the given one, or a :data:`NOISE_SHARE` of the found
    one's variance, is counted against the still estimate); ``excluded``: pixels that keep ``volume`` (saturated
    ones); ``taken``: the misfit (H, W) that bringing ``volume`` to the measurement took away, of which
    :data:`PROJECTED_SHARE` is added to its residual."""
    _, n = normalised(coded, mask)
    found = read_noise(coded, mask)
    given = float(noise_sigma)
    per_open = np.divide(1.0, n, out=np.zeros_like(n), where=n > 0) ** 2
    residual = np.asarray(coded, np.float32) - physics.forward(volume, mask)
    if taken is not None:
        residual += np.float32(PROJECTED_SHARE) * np.asarray(taken, np.float32)
    seen2 = _box(residual * residual * per_open, RESIDUAL_WINDOW)
    seen = np.sqrt(np.maximum(seen2 - max(given, found) ** 2 * per_open, 0))
    still = np.sqrt(np.nan_to_num(motion(coded, mask), nan=np.inf) ** 2
                    + max(given * given, NOISE_SHARE * found * found) * per_open)
    weight = np.clip((seen - still) / np.maximum(seen / 2, 1e-6), 0, 1)
    weight *= np.clip((MOVING[1] - _moving(volume)) / (MOVING[1] - MOVING[0]), 0, 1)
    weight[n <= 0] = 0
    if excluded is not None:
        weight[excluded] = 0
    return weight.astype(np.float32)


def _moving(volume: np.ndarray) -> np.ndarray:
    """The standard deviation of ``volume`` over its sub-frames, averaged over the patch around each pixel."""
    mean = np.mean(volume, axis=0, dtype=np.float32)
    squares = np.zeros_like(mean)
    for frame in volume:
        squares += np.square(frame - mean)
    spread = np.sqrt(squares / np.float32(volume.shape[0]))
    return _box(spread, PATCH)


def blended(volume: np.ndarray, coded: np.ndarray, mask: np.ndarray, weight: np.ndarray) -> np.ndarray:
    """``volume`` (overwritten) with each pixel's sub-frames moved toward its still estimate by ``weight``."""
    z, _ = normalised(coded, mask)
    rows = np.flatnonzero(weight.any(1))
    if rows.size:
        band = slice(int(rows[0]), int(rows[-1]) + 1)
        w, target = weight[band], z[band]
        for frame in volume:
            frame[band] += w * (target - frame[band])
    return volume
