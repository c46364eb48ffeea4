"""The floor under the dictionary methods: codes on which a patch cannot see what it fits.

Per-patch sparse coding recovers what a 7x7 patch's code measures.  Two kinds of
code leave it blind, and on both GAP-TV (:func:`codedvideo.solvers.baselines.gap_tv`)
was measured above it on held-out footage (docs/research.md, "Long shutter bumps"):

* windows that miss sub-frames: a 7x7 window that no pixel opens in some sub-frame
  has nothing to fit there but the dictionary's guess (``thinout`` with ``N > 7``);
* long single bumps: every pixel of a patch integrates most of the same sub-frames,
  so their differences cancel in the sums, and the few the bump edges show are not
  enough for a dictionary to pick its atoms by.

* pixels open most of the time (a Bernoulli code of p 0.8 or 0.9): as with long bumps,
  what the closed sub-frames show is too little to choose atoms by.

A code that varies along one image axis only (``rowwise``, ``thinout``) gives the 7x7
windows a few patterns to fit by instead of 49, and its sparse estimate's weight is halved
again; one that every pixel shares (``flutter``) shows no motion at all, and its still
estimate is blended half and half.  The global shutter, every pixel open throughout, keeps
coded / N, which GAP-TV gives too.

There the result is a blend, ``w * sparse + (1 - w) * GAP-TV`` (:func:`sparse_weight`);
on the paper's codes ``w`` is 1 and the sparse estimate is the result, unchanged.
"""

from __future__ import annotations

import hashlib
import threading
from collections import OrderedDict

import numpy as np

from codedvideo.model.codes import is_binary
from codedvideo.model.patches import PATCH

#: Bump length times sub-frames up to which a fixed single-bump code is solved by the dictionary alone
#: (N = 8 with L up to 3, the paper's codes; N = 16 or 18 with L up to 2; docs/research.md).
BUMP_SPAN = 24
#: Below this share of sub-frames seen by the average 7x7 window, the result is GAP-TV's alone.
MIN_SEEN = 7 / 8
#: Above this share of open (sub-frame, pixel) entries, a code that is not a fixed single bump is blended too.
MOSTLY_OPEN = 0.6
#: From this share on, a few windows that miss a sub-frame (a sparse random code) leave the dictionary alone.
MOST_SEEN = 0.95
#: The factor on the weight of a code whose pixels share their pattern along a whole row or column (or both).
ONE_AXIS = 0.5
#: The finest lattice spacing, in pixels along each axis, of a code that samples each sub-frame on a regular
#: lattice (:func:`coarse_lattice`): the grid code at N = 16 (4 x 4) and 18 (5 x 5), not at N = 8 (3 x 3).
COARSE_LATTICE = 4


def _opened(mask: np.ndarray) -> np.ndarray:
    """Which (sub-frame, pixel) entries a mask opens: a calibrated mask's weights of at least half its largest."""
    m = np.asarray(mask)
    top = float(m.max(initial=0))
    binary = m.dtype.kind in "bu" and top <= 1 or top <= 1 and is_binary(m)
    return m > 0 if binary else m >= 0.5 * top


def _window_any(a: np.ndarray, k: int, axis: int) -> np.ndarray:
    """Whether any of ``k`` consecutive entries along ``axis`` of the boolean ``a`` is set, for every window
    (length ``n - k + 1``): spans doubled by or-ing shifted copies, a few passes whatever ``k``."""
    def part(x, start, stop):
        return x[(slice(None),) * axis + (slice(start, stop),)]

    out, span = a, 1
    while 2 * span <= k:  # out[i]: any of [i, i + span)
        out = part(out, 0, out.shape[axis] - span) | part(out, span, None)
        span *= 2
    rest = k - span  # (at most span: two spans overlapping cover k)
    return out if rest == 0 else part(out, 0, out.shape[axis] - rest) | part(out, rest, None)


def _seen(opened: np.ndarray, patch: int) -> float:
    """The mean share of the N sub-frames that a ``patch x patch`` window of the open entries ``opened`` (N, H, W)
    opens in (1: every window sees every sub-frame)."""
    return float(_window_any(_window_any(opened, patch, 1), patch, 2).mean())


def _fixed_bump(opened: np.ndarray) -> int | None:
    """The bump length when every pixel that opens does so for one run of the same length (None otherwise)."""
    count = opened.sum(0, dtype=np.int32)
    runs = opened[0].astype(np.int32) + (opened[1:] & ~opened[:-1]).sum(0, dtype=np.int32)
    lengths = np.unique(count[count > 0])
    return int(lengths[0]) if lengths.size == 1 and runs.max(initial=0) <= 1 else None


_weights: OrderedDict = OrderedDict()
_weights_lock = threading.Lock()


def sparse_weight(mask: np.ndarray, patch: int = PATCH) -> tuple[float, str]:
    """The weight of the sparse estimate in a capture's result under ``mask`` (N, H, W), and why (empty: 1,
    the sparse estimate alone); kept for the masks last asked (a stream's captures share theirs).

    * windows that see less than :data:`MIN_SEEN` of the sub-frames: 0 (GAP-TV alone);
    * windows that miss some sub-frames (less than :data:`MOST_SEEN` seen): 1/4;
    * a fixed single bump of length ``L >= 3`` with ``L * N`` above :data:`BUMP_SPAN`: ``1 / (2 L)``;
    * any other code open in a share ``f`` above :data:`MOSTLY_OPEN` of its (sub-frame, pixel) entries:
      ``(1 - f) / (1 - MOSTLY_OPEN)``;

    and times :data:`ONE_AXIS` where every row or every column of pixels shares one pattern.
    """
    m = np.ascontiguousarray(mask)
    key = hashlib.blake2b(m.data, digest_size=16).digest() + repr((m.shape, m.dtype.str, patch)).encode()
    with _weights_lock:
        if key in _weights:
            _weights.move_to_end(key)
            return _weights[key]
    found = _sparse_weight(m, patch)
    with _weights_lock:
        _weights[key] = found
        while len(_weights) > 4:
            _weights.popitem(last=False)
    return found


def shared_by_all(mask: np.ndarray) -> bool:
    """Whether every pixel of ``mask`` (N, H, W) opens in the same sub-frames (``global``, ``flutter``): a capture
    under it agrees with a still scene whatever moved, so its still answer is no more certain than the rest."""
    return bool((mask == mask[:, :1, :1]).all())


def _period(mask: np.ndarray, axis: int, longest: int) -> int | None:
    """The smallest shift of at most ``longest`` pixels along image ``axis`` (1 or 2) that maps ``mask`` onto
    itself (None: none does)."""
    size = mask.shape[axis]
    for p in range(1, min(longest, size - 1) + 1):
        ahead, behind = ((slice(None),) * axis + (slice(p, None),)), ((slice(None),) * axis + (slice(None, -p),))
        if np.array_equal(mask[ahead], mask[behind]):
            return p
    return None


def coarse_lattice(mask: np.ndarray, patch: int = PATCH) -> str:
    """Why ``mask`` (N, H, W) samples each sub-frame on a regular lattice too coarse for the non-local passes
    (empty: it does not): every pixel open in one sub-frame, and the pattern repeating on a cell of
    :data:`COARSE_LATTICE` pixels or more along both axes and smaller than ``patch``, as the grid code is at
    N = 16 and 18.

    Each 7x7 patch then sees every sub-frame at the same few places, so a scene's fine detail is likely to alias
    alike in the patches the non-local passes group together.  On held-out crops under the grid code at N = 16
    and 18, ``best`` fell below the default on 6 of 40, while the per-patch OMP, refined, was above it on all;
    a 3 x 3 grid (N = 8) and a random tile of 7 x 7 lost on none (docs/research.md, "A grid code's repeating
    patterns").
    """
    opened = _opened(mask)
    if not (opened.sum(0) == 1).all():
        return ""
    py, px = _period(opened, 1, patch - 1), _period(opened, 2, patch - 1)
    if py is None or px is None or min(py, px) < COARSE_LATTICE:
        return ""
    return f"each sub-frame sampled on a regular lattice of {py} x {px} pixels"


def _sparse_weight(mask: np.ndarray, patch: int) -> tuple[float, str]:
    """:func:`sparse_weight`, computed."""
    if shared_by_all(mask):  # (the sparse estimate is the still one; its windows are not weighed)
        if _opened(mask).all():  # a global shutter: GAP-TV too gives coded / N, the answer
            return 1.0, ""
        return ONE_AXIS, "one shutter pattern for every pixel, which shows no motion"
    rows, columns = bool((mask == mask[:, :, :1]).all()), bool((mask == mask[:, :1, :]).all())
    weight, reason = _code_weight(mask, patch)
    if weight == 0.0 or not (rows or columns):
        return weight, reason
    shared = f"one pattern along every {'row' if rows else 'column'}"
    return ONE_AXIS * weight, f"{reason}; {shared}" if reason else shared


def _code_weight(mask: np.ndarray, patch: int) -> tuple[float, str]:
    """:func:`sparse_weight` of ``mask`` without the factor for codes shared along an axis."""
    n = mask.shape[0]
    opened = _opened(mask)
    seen = _seen(opened, patch) if min(mask.shape[1:]) >= patch else 1.0
    if seen < MIN_SEEN:
        return 0.0, f"its 7x7 windows see {seen:.0%} of the {n} sub-frames"
    if seen < MOST_SEEN:
        return 0.25, f"some 7x7 windows miss sub-frames (they see {seen:.1%} of them)"
    bump = _fixed_bump(opened)
    if bump is not None:
        if bump >= 3 and bump * n > BUMP_SPAN:
            return 0.5 / bump, f"shutter bumps of {bump} of {n} sub-frames"
        return 1.0, ""
    share = float(opened.mean())
    if share > MOSTLY_OPEN:
        return (1.0 - share) / (1.0 - MOSTLY_OPEN), f"pixels open in {share:.0%} of the sub-frames"
    return 1.0, ""


def blended(volume: np.ndarray, coded: np.ndarray, mask: np.ndarray, weight: float, *,
            data_range: float) -> np.ndarray:
    """``weight * volume + (1 - weight) * GAP-TV`` of the capture (working units; ``volume`` overwritten)."""
    from codedvideo.solvers.baselines import gap_tv

    gap = gap_tv(coded, mask, data_range=data_range)
    np.multiply(volume, np.float32(weight), out=volume)
    np.add(volume, np.float32(1.0 - weight) * gap, out=volume)
    return volume
