"""Temporal windows: a capture of many sub-frames whose pixels each open briefly, seen as shorter captures too.

A 7x7 patch of a capture at N = 16 or 18 spans every sub-frame, and its dictionary must explain them all at
once: where the scene changes abruptly in a few of them (an occluder sweeping through, a new view), the atoms
that fit those smear the change into the calm sub-frames, which then score far below GAP-TV's.  When every
pixel's exposure is short (:data:`SPAN` consecutive sub-frames at most: hitomi L = 1 or 2, the grid code,
tiled bumps), each pixel measures only a few neighbouring sub-frames, and the capture is also a set of
overlapping captures of :data:`WINDOW` sub-frames (every :data:`STEP`-th start): in each, the pixels whose
exposure lies inside it are measured and the others are not.  Each window is reconstructed with the
dictionary of :data:`WINDOW` sub-frames, the windows are averaged where they overlap (:func:`combined`,
a tent across each window), and the capture's result is ``w * full + (1 - w) * windows``, ``w`` falling from 1
where the full result holds still to :data:`FULL_WEIGHT` where it moves (:func:`full_weights`): a window sees
half of a patch's pixels, and where nothing moves the full capture's every pixel gives the better answer
(docs/research.md, "Short exposures at N = 16 and 18").

Arrays in, arrays out; the engine reconstructs the windows (``engine/captures.py``).
"""

from __future__ import annotations

import numpy as np

from codedvideo.model.codes import is_binary
from codedvideo.model.patches import PATCH

#: Sub-frames of a window (a shipped dictionary's N).
WINDOW = 8
#: Sub-frames between the starts of two windows (the last window ends at the capture's last sub-frame).
STEP = 2
#: The longest exposure, first to last open sub-frame of a pixel, of a code whose captures are windowed.
SPAN = 2
#: The weight of the capture's own result (its every sub-frame solved at once) in the blend with the windows'
#: where that result moves.
FULL_WEIGHT = 0.25
#: The motion of the full result at a pixel (the standard deviation over its sub-frames, averaged over the
#: patch around it; grey levels of an 8-bit capture, the working units) up to which it is kept alone, and from
#: which on it has :data:`FULL_WEIGHT`.
STILL_BELOW = 4.0
MOVING_FROM = 10.0


def recipe() -> dict:
    """What a windowed result depends on (a result's record is keyed by it)."""
    return dict(window=WINDOW, step=STEP, span=SPAN, full_weight=FULL_WEIGHT, still_below=STILL_BELOW,
                moving_from=MOVING_FROM)


def exposure_span(mask: np.ndarray) -> np.ndarray:
    """Each pixel's exposure, from its first open sub-frame to its last, in sub-frames (0: never open)."""
    opened = np.asarray(mask) > 0
    n = opened.shape[0]
    first = np.argmax(opened, axis=0)
    last = n - 1 - np.argmax(opened[::-1], axis=0)
    return np.where(opened.any(0), last - first + 1, 0)


def applies(mask: np.ndarray, sparse_weight: float) -> bool:
    """Whether a capture under ``mask`` (N, H, W) is windowed: a binary code of more than :data:`WINDOW`
    sub-frames whose sparse estimate is not blended with GAP-TV (``sparse_weight`` 1), which some pixel opens in
    every sub-frame, and whose every pixel's exposure spans :data:`SPAN` sub-frames at most."""
    m = np.asarray(mask)
    if m.ndim != 3 or m.shape[0] <= WINDOW or sparse_weight < 1.0 or not is_binary(m):
        return False
    if not m.reshape(m.shape[0], -1).any(1).all():
        return False
    return int(exposure_span(m).max()) <= SPAN


def starts(frames: int) -> list[int]:
    """The first sub-frame of every window of a capture of ``frames`` sub-frames."""
    first = list(range(0, frames - WINDOW + 1, STEP))
    if first[-1] != frames - WINDOW:
        first.append(frames - WINDOW)
    return first


def window_capture(coded: np.ndarray, mask: np.ndarray, start: int) -> tuple[np.ndarray, np.ndarray]:
    """The capture of the window from sub-frame ``start``: ``(coded (H, W), mask (WINDOW, H, W))``, measured
    at the pixels whose every open sub-frame lies inside it (their coded values as they are), the other pixels
    never open there (coded 0)."""
    m = np.asarray(mask)
    inside = m[start:start + WINDOW]
    measured = (inside.sum(0) == m.sum(0)) & m.any(0)
    coded_w = np.where(measured, np.asarray(coded, np.float32), np.float32(0))
    return coded_w, (inside * measured).astype(m.dtype)


def tent() -> np.ndarray:
    """The weight of a window's sub-frames where windows overlap: 1 at its centre falling to about 1/2 at its
    ends, so a sub-frame leans on the windows that see most around it."""
    k = np.arange(WINDOW)
    return (1.0 - np.abs(k - (WINDOW - 1) / 2) / WINDOW).astype(np.float32)


def combined(volumes: list[np.ndarray], first: list[int], frames: int) -> np.ndarray:
    """The windows' volumes ``(WINDOW, H, W)`` (from sub-frames ``first``) as one ``(frames, H, W)`` volume:
    each sub-frame the :func:`tent`-weighted mean of the windows holding it."""
    h, w = volumes[0].shape[1:]
    out = np.zeros((frames, h, w), np.float32)
    total = np.zeros(frames, np.float32)
    weights = tent()
    for volume, s in zip(volumes, first):
        out[s:s + WINDOW] += weights[:, None, None] * volume
        total[s:s + WINDOW] += weights
    return out / total[:, None, None]


def full_weights(full: np.ndarray) -> np.ndarray:
    """The weight (H, W) of the full result ``full`` (N, H, W, working units) at each pixel: 1 where its motion
    (the standard deviation over the sub-frames, averaged over a patch) is below :data:`STILL_BELOW`,
    :data:`FULL_WEIGHT` from :data:`MOVING_FROM` on, linear between."""
    from scipy.ndimage import uniform_filter  # lazy: only a windowed capture needs it

    motion = uniform_filter(np.std(full, axis=0, dtype=np.float32), PATCH, mode="nearest")
    share = np.clip((motion - STILL_BELOW) / (MOVING_FROM - STILL_BELOW), 0, 1)
    return (1 - (1 - FULL_WEIGHT) * share).astype(np.float32)


def blended(full: np.ndarray, windows: np.ndarray) -> np.ndarray:
    """The capture's result: ``w * full + (1 - w) * windows``, ``w`` the :func:`full_weights` of ``full``."""
    w = full_weights(full)
    return (w * full + (1 - w) * windows).astype(np.float32)
