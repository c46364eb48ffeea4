"""Per-pixel binary shutter codes and their validator.

A code is a binary array ``S`` of shape ``(N, H, W)`` (uint8): ``S[t, y, x] = 1``
when pixel ``(y, x)`` integrates light during sub-frame ``t``.

Hardware constraints of a CMOS sensor with per-pixel exposure control
(Hitomi et al. 2011, Sec. 4):

* binary shutter;
* a single bump: each pixel is open for one contiguous run of sub-frames;
* a fixed bump length ``L`` for every pixel;
* every ``M x M`` window (M = 7) covers all ``N`` sub-frames, so that every patch
  that is reconstructed has seen every instant at least once.

:func:`check_code` reports which of them a mask meets.

Codes
-----
Every code below is built by :func:`make_code` (names in :data:`CODE_NAMES`).
"binary" holds for all of them; "7x7" is the window-coverage constraint.

================  ==========================================  ======  =========  ==========================
name              what it is                                  single  fixed      every 7x7 window covers
                                                              bump    bump       all N sub-frames
================  ==========================================  ======  =========  ==========================
``hitomi``        the paper's sliding single-bump code        yes     yes (L)    yes (needs ``49 L >= N``)
``hitomi-tiled``  one random 7x7 single-bump tile, repeated   yes     yes (L)    yes (needs ``49 L >= N``)
``rowwise``       coded rolling shutter: one random bump per  yes     yes (L)    yes when ``7 L >= N``;
                  row, 7 consecutive rows cover all N                            no guarantee otherwise
``thinout``       draft mode: row ``y`` open at ``y % N``     yes     yes (1)    only when ``N <= 7``
``grid``          ``n x n`` cells (``n = ceil(sqrt N)``),     yes     yes (1)    only when ``n <= 7``
                  each position its own sub-frame                                (``N <= 49``)
``flutter``       one random binary sequence, every pixel     no      no         no (about half the
                  (global flutter shutter)                    (*)                sub-frames are closed)
``bernoulli``     i.i.d. Bernoulli(p) per pixel, sub-frame    no      no         not guaranteed
``shifting``      one Bernoulli(p) image, shifted one pixel   no      no         not guaranteed
                  along x (circularly) per sub-frame
``global``        ordinary exposure, always open              yes     yes (N)    yes
``file``          a mask read from .npy or multi-page TIFF    --      --         checked, not built
================  ==========================================  ======  =========  ==========================

(*) a flutter sequence is a single bump only by chance (e.g. ``N <= 2``).
``thinout``, ``grid`` and ``global`` are deterministic; all other built codes
are deterministic functions of ``rng``.  ``flutter`` and ``global`` are the
same for every pixel (a global shutter, no per-pixel control needed);
``rowwise`` and ``thinout`` need only per-row control (a rolling-shutter
sensor); the others need per-pixel control.

The sliding construction
------------------------
The paper picks bump starts for the top-left ``M x M`` patch so that the union
of its bumps covers ``[0, N)``, then slides the patch one column (or row) at a
time, keeping the starts of the overlapping pixels and drawing the new column
"according to the same constraint".  When a window slides by one column, the
pixel that leaves it and the pixel that enters it have the same position
``(y mod M, x mod M)`` inside the window.  We therefore keep the constraint by
giving every entering pixel that replaces one of the ``ceil(N / L)`` covering
pixels of the first patch the same bump start (its *role*), and by drawing all
other pixels independently at random.  Every window then contains exactly one
pixel of each role, so coverage holds for every window by construction and for
any ``N <= M*M*L``; the non-covering pixels (``M*M - ceil(N/L)`` of the 49 per
window) are i.i.d. uniform, as in the paper's random code.  ``rowwise`` applies
the same idea to rows: roles are ``y mod M``.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass

import numpy as np

from codedvideo.model.errors import InputError
from codedvideo.model.patches import PATCH


#: Names accepted by :func:`make_code`.
CODE_NAMES = (
    "hitomi", "hitomi-tiled", "rowwise", "thinout", "grid", "flutter", "bernoulli", "shifting", "global", "file",
)

#: The open probability of ``bernoulli`` and ``shifting`` when none is given.
OPEN_PROBABILITY = 0.5


@dataclass(frozen=True)
class CodeSpec:
    """The shutter code of a simulated capture (:func:`codedvideo.engine.simulation.simulate_capture`).

    Attributes
    ----------
    name : str
        A code of :func:`make_code`, or ``file``: the mask stored at ``path``.
    bump : int
        Bump length of ``hitomi``, ``hitomi-tiled`` and ``rowwise``.
    p : float
        Open probability of ``bernoulli`` and ``shifting``.
    path : str or Path, optional
        The mask file of ``file`` (:func:`codedvideo.formats.volumes.load_code_file`).
    """

    name: str
    bump: int
    p: float = OPEN_PROBABILITY
    path: str | os.PathLike | None = None


def _check_bump(frames: int, bump: int, patch: int | None) -> None:
    """Validate N and L; with ``patch``, also that ``patch x patch`` windows can cover N."""
    if frames < 1:
        raise InputError(f"code: frames must be >= 1, got {frames}")
    if not 1 <= bump <= frames:
        raise InputError(f"code: bump length must be in 1..{frames} (frames), got {bump}")
    if patch is not None and patch * patch * bump < frames:
        raise InputError(
            f"code: coverage impossible: {patch}x{patch} windows with bump length {bump} "
            f"cover at most {patch * patch * bump} sub-frames < N = {frames}; "
            f"use a bump length >= {math.ceil(frames / (patch * patch))}"
        )


def _covering_starts(frames: int, bump: int, rng: np.random.Generator) -> np.ndarray:
    """Bump starts of ``ceil(N / L)`` bumps whose union is ``[0, N)``.

    The slack ``ceil(N/L) * L - N`` is spread as random overlaps between
    consecutive bumps, so the covering set itself is random.
    """
    count = math.ceil(frames / bump)
    slack = count * bump - frames
    # distribute `slack` overlaps over the count-1 gaps between bumps
    overlaps = np.zeros(max(count - 1, 0), dtype=int)
    if count > 1:
        for _ in range(slack):
            overlaps[rng.integers(count - 1)] += 1
    starts = np.zeros(count, dtype=int)
    for k in range(1, count):
        starts[k] = starts[k - 1] + bump - overlaps[k - 1]
    # clamp: an overlap larger than the bump cannot happen, but starts must fit
    return np.clip(starts, 0, frames - bump)


def bump_starts(
    shape: tuple[int, int],
    *,
    frames: int,
    bump: int,
    rng: np.random.Generator | int | None = 0,
    tiled: bool = False,
    patch: int = PATCH,
) -> np.ndarray:
    """Bump-start times of the sliding (or tiled) single-bump code.

    Parameters
    ----------
    shape : (H, W)
    frames : int
        Number of sub-frames N.
    bump : int
        Bump length L, the same for every pixel.
    rng : Generator or int
        Seed or generator; the code is a deterministic function of it.
    tiled : bool
        If True every pixel copies the start of its position ``(y mod M, x mod M)``
        in one random ``M x M`` tile (code ``hitomi-tiled``); otherwise only the
        covering roles are shared and all other pixels are drawn independently.

    Returns
    -------
    starts : ndarray of shape (H, W), int16
        Start sub-frame of each pixel's bump, in ``0 .. N - L``.
    """
    _check_bump(frames, bump, patch)
    gen = np.random.default_rng(rng)
    h, w = shape
    nstart = frames - bump + 1
    cover = _covering_starts(frames, bump, gen)
    # the tile: covering roles at random positions, the rest uniform
    tile = gen.integers(0, nstart, size=patch * patch)
    roles = gen.permutation(patch * patch)[: len(cover)]
    tile[roles] = cover
    tile = tile.reshape(patch, patch)
    yy, xx = np.mgrid[0:h, 0:w]
    tiled_starts = tile[yy % patch, xx % patch]
    if tiled:
        return tiled_starts.astype(np.int16)
    is_role = np.zeros(patch * patch, dtype=bool)
    is_role[roles] = True
    role_map = is_role.reshape(patch, patch)[yy % patch, xx % patch]
    free = gen.integers(0, nstart, size=(h, w))
    return np.where(role_map, tiled_starts, free).astype(np.int16)


def starts_to_mask(starts: np.ndarray, *, frames: int, bump: int) -> np.ndarray:
    """Expand bump starts ``(H, W)`` into the binary code ``(N, H, W)`` uint8."""
    t = np.arange(frames)[:, None, None]
    return ((t >= starts[None]) & (t < starts[None] + bump)).astype(np.uint8)


def row_starts(
    height: int,
    *,
    frames: int,
    bump: int,
    rng: np.random.Generator | int | None = 0,
    patch: int = PATCH,
) -> np.ndarray:
    """Bump starts of the row-wise code: one start per row (coded rolling shutter).

    The sliding construction of :func:`bump_starts` applied to rows: the
    ``ceil(N / L)`` covering starts are given to random *roles* ``y mod M``
    and every row of a role copies its start; the other rows are drawn
    uniformly.  Every ``M`` consecutive rows then hold one row of each role,
    so their bumps cover ``[0, N)`` -- guaranteed whenever ``M * L >= N``.
    When ``M * L < N`` no ``M`` rows can cover ``N`` sub-frames: every row is
    then drawn uniformly and nothing is guaranteed.

    Parameters
    ----------
    height : int
        Number of rows H.
    frames : int
        Number of sub-frames N.
    bump : int
        Bump length L of every row.
    rng : Generator or int
    patch : int
        M, the number of consecutive rows that must cover all sub-frames.

    Returns
    -------
    starts : ndarray of shape (H,), int16
        Start sub-frame of each row's bump, in ``0 .. N - L``.
    """
    _check_bump(frames, bump, None)
    gen = np.random.default_rng(rng)
    nstart = frames - bump + 1
    free = gen.integers(0, nstart, size=height)
    if patch * bump < frames:
        return free.astype(np.int16)
    cover = _covering_starts(frames, bump, gen)
    roles = gen.permutation(patch)[: len(cover)]
    role_start = np.full(patch, -1)
    role_start[roles] = cover
    by_role = role_start[np.arange(height) % patch]
    return np.where(by_role >= 0, by_role, free).astype(np.int16)


def thinout_code(shape: tuple[int, int], *, frames: int) -> np.ndarray:
    """Draft (thin-out) readout: sub-frame ``t`` reads the rows with ``y % N == t``.

    Every pixel is open for exactly one sub-frame (a single bump of length 1);
    any ``N`` consecutive rows cover all sub-frames, so every 7x7 window does
    when ``N <= 7``.  Deterministic.

    Returns
    -------
    mask : ndarray of shape (N, H, W), uint8
    """
    if frames < 1:
        raise InputError(f"code thinout: frames must be >= 1, got {frames}")
    h, w = shape
    rows = (np.arange(frames)[:, None] == (np.arange(h) % frames)[None, :]).astype(np.uint8)
    return np.ascontiguousarray(np.broadcast_to(rows[:, :, None], (frames, h, w)))


def grid_code(shape: tuple[int, int], *, frames: int) -> np.ndarray:
    """Pixel-wise grid exposure (for 3D interpolation).

    With ``n = ceil(sqrt(N))`` the image is tiled by ``n x n`` cells; the pixel
    at cell position ``k = (y % n) * n + (x % n)`` is open during sub-frame
    ``k % N`` only (so positions ``k >= N`` repeat the first sub-frames).
    Every pixel is open exactly once, every ``n x n`` window (aligned or not)
    covers all ``N`` sub-frames, hence every 7x7 window does when ``n <= 7``.
    Deterministic.

    Returns
    -------
    mask : ndarray of shape (N, H, W), uint8
    """
    if frames < 1:
        raise InputError(f"code grid: frames must be >= 1, got {frames}")
    h, w = shape
    n = math.isqrt(frames - 1) + 1  # ceil(sqrt(N)) without floating point
    yy, xx = np.mgrid[0:h, 0:w]
    slot = ((yy % n) * n + (xx % n)) % frames
    return (np.arange(frames)[:, None, None] == slot[None]).astype(np.uint8)


def flutter_sequence(frames: int, *, rng: np.random.Generator | int | None = 0) -> np.ndarray:
    """A random binary flutter-shutter sequence: ``ceil(N / 2)`` of ``N`` sub-frames open.

    The open sub-frames are a uniformly random subset of that size, so at
    least one is open and about half are.

    Returns
    -------
    seq : ndarray of shape (N,), uint8
    """
    if frames < 1:
        raise InputError(f"code flutter: frames must be >= 1, got {frames}")
    gen = np.random.default_rng(rng)
    seq = np.zeros(frames, np.uint8)
    seq[gen.permutation(frames)[: (frames + 1) // 2]] = 1
    return seq


def make_code(
    name: str,
    shape: tuple[int, int],
    *,
    frames: int,
    bump: int = 2,
    p: float = OPEN_PROBABILITY,
    rng: np.random.Generator | int | None = 0,
) -> np.ndarray:
    """Build a named shutter code (see the table in the module docstring).

    Parameters
    ----------
    name : one of :data:`CODE_NAMES`
        ``hitomi``: the paper's sliding single-bump code; ``hitomi-tiled``: one
        random 7x7 single-bump tile repeated; ``rowwise``: one random bump of
        length ``bump`` per row, every 7 consecutive rows covering all
        sub-frames when ``7 * bump >= frames``; ``thinout``: row ``y`` open in
        sub-frame ``y % N``; ``grid``: each position of an ``n x n`` cell open
        in its own sub-frame; ``flutter``: one random binary sequence for every
        pixel; ``bernoulli``: i.i.d. Bernoulli(p) per pixel and sub-frame (the
        snapshot-compressive-imaging benchmarks); ``shifting``: one
        Bernoulli(p) image shifted one pixel along x per sub-frame; ``global``:
        an ordinary exposure, every pixel open in every sub-frame.  (``file``,
        a mask stored in a file, is read by :func:`codedvideo.formats.volumes.load_code_file`.)
    shape : (H, W)
    frames : int
        Number of sub-frames N.
    bump : int
        Bump length for ``hitomi``, ``hitomi-tiled`` and ``rowwise``.
    p : float
        Open probability of ``bernoulli`` and ``shifting``.
    rng : Generator or int
        Seed or generator of the random codes.

    Returns
    -------
    mask : ndarray of shape (N, H, W), uint8
    """
    if len(tuple(shape)) != 2 or any(int(v) != v or v < 1 for v in shape):
        raise InputError(f"code {name}: shape {tuple(shape)}; a code is made for (H, W) of at least 1 pixel each")
    if int(frames) != frames or frames < 1:
        raise InputError(f"code {name}: frames {frames}; N is a whole number of sub-frames, at least 1")
    if name in ("hitomi", "hitomi-tiled"):
        starts = bump_starts(shape, frames=frames, bump=bump, rng=rng, tiled=name == "hitomi-tiled")
        return starts_to_mask(starts, frames=frames, bump=bump)
    if name == "rowwise":
        starts = row_starts(shape[0], frames=frames, bump=bump, rng=rng)
        cols = np.broadcast_to(starts[:, None], shape)
        return starts_to_mask(cols, frames=frames, bump=bump)
    if name == "thinout":
        return thinout_code(shape, frames=frames)
    if name == "grid":
        return grid_code(shape, frames=frames)
    if name == "file":
        raise InputError("code file: a mask file is read by codedvideo.formats.volumes.load_code_file, not made")
    if name == "flutter":
        seq = flutter_sequence(frames, rng=rng)
        return np.ascontiguousarray(np.broadcast_to(seq[:, None, None], (frames, *shape)))
    gen = np.random.default_rng(rng)
    if name in ("bernoulli", "shifting"):
        if not 0.0 < p <= 1.0:
            raise InputError(f"code {name}: p must be in (0, 1], got {p}")
        if frames < 1:
            raise InputError(f"code {name}: frames must be >= 1, got {frames}")
        if name == "bernoulli":
            return (gen.random((frames, *shape)) < p).astype(np.uint8)
        base = (gen.random(shape) < p).astype(np.uint8)
        return np.stack([np.roll(base, t, axis=1) for t in range(frames)])
    if name == "global":
        return np.ones((frames, *shape), dtype=np.uint8)
    raise InputError(f"code: unknown code {name!r}; choose one of {', '.join(CODE_NAMES)}")


def is_binary(mask: np.ndarray) -> bool:
    """Whether every value of a mask is 0 or 1 (a shutter code rather than calibrated weights)."""
    a = np.asarray(mask)
    if a.dtype == np.bool_:
        return True
    return bool(((a == 0) | (a == 1)).all())


def window_coverage(mask: np.ndarray, patch: int = PATCH) -> np.ndarray:
    """Number of open pixels of every sub-frame in every ``patch x patch`` window.

    Parameters
    ----------
    mask : ndarray of shape (N, H, W)

    Returns
    -------
    counts : ndarray of shape (N, H - patch + 1, W - patch + 1), int
        ``counts[t, y, x]`` = number of pixels of the window with top-left
        ``(y, x)`` open during sub-frame ``t``.
    """
    m = np.asarray(mask, dtype=np.int32)
    c = np.pad(m.cumsum(1).cumsum(2), ((0, 0), (1, 0), (1, 0)))
    return (
        c[:, patch:, patch:] - c[:, :-patch, patch:] - c[:, patch:, :-patch] + c[:, :-patch, :-patch]
    )


@dataclass(frozen=True)
class CodeReport:
    """Which hardware constraints a mask meets (see :func:`check_code`).

    Attributes
    ----------
    frames : int
        N.
    binary : bool
        Every value is 0 or 1.  False for a calibrated mask (fractional
        weights, e.g. a DMD pattern measured through the optics); the other
        constraints then count as open the weights of at least
        ``open_threshold`` (half the largest: leakage of a closed shutter,
        a few per cent, is not an opening).
    single_bump : bool
        Every pixel is open for at most one contiguous run of sub-frames.
    fixed_bump : bool
        Single bump and every pixel that opens is open for the same length.
    bump_length : int or None
        That length, when fixed.
    window_coverage : bool or None
        Every ``patch x patch`` window has an open pixel in every sub-frame
        (None for images smaller than a window: there is none, and
        reconstruction refuses them).
    uncovered_windows : int or None
        Number of windows that miss at least one sub-frame.
    never_open_pixels : int
        Pixels whose every weight is 0 (no measurement at all).
    open_fraction : float
        Share of (sub-frame, pixel) entries that are open (non-zero): the mean
        of a binary mask.
    patch : int
        The window size M used for the coverage test.
    mean_weight : float
        Mean of the values (equal to ``open_fraction`` for a binary mask).
    weight_min, weight_max : float
        Smallest non-zero and largest value (1 and 1 for a binary mask that
        opens anywhere; 0 and 0 for one that never opens).
    """

    frames: int
    binary: bool
    single_bump: bool
    fixed_bump: bool
    bump_length: int | None
    window_coverage: bool | None
    never_open_pixels: int
    open_fraction: float
    uncovered_windows: int | None = 0
    patch: int = PATCH
    mean_weight: float = 0.0
    weight_min: float = 0.0
    weight_max: float = 0.0
    open_threshold: float = 1.0

    def as_dict(self) -> dict:
        return dict(self.__dict__)


def check_code(mask: np.ndarray, patch: int = PATCH) -> CodeReport:
    """Report the hardware constraints that a mask ``(N, H, W)`` meets.

    Parameters
    ----------
    mask : ndarray of shape (N, H, W)
        Any numeric values (a binary code or calibrated weights); non-zero counts as open.
    patch : int
        Window size M of the coverage constraint.

    Returns
    -------
    report : CodeReport
    """
    arr = np.asarray(mask)
    if arr.ndim != 3:
        raise InputError(f"mask: expected shape (N, H, W), got {arr.shape}")
    binary = bool(np.isin(arr, (0, 1)).all())
    nonzero = arr[arr != 0]
    # a calibrated mask's leakage (a closed shutter passing a few per cent) is not an opening
    threshold = 1.0 if binary else 0.5 * float(arr.max(initial=0.0))
    m = ((arr >= threshold) & (arr != 0)).astype(np.int8)
    counts = m.sum(0)
    # a single contiguous bump <=> at most one rising edge (0 -> 1) along time
    rises = (np.diff(np.concatenate([np.zeros_like(m[:1]), m]), axis=0) == 1).sum(0)
    single = bool((rises <= 1).all())
    open_counts = counts[counts > 0]
    fixed = single and open_counts.size > 0 and bool((open_counts == open_counts[0]).all())
    uncovered = None  # no window in an image smaller than one
    if min(arr.shape[1:]) >= patch:
        missing = (window_coverage(m, patch) == 0).any(0)
        uncovered = int(missing.sum())
    return CodeReport(
        frames=int(arr.shape[0]),
        binary=binary,
        single_bump=single,
        fixed_bump=fixed,
        bump_length=int(open_counts[0]) if fixed else None,
        window_coverage=None if uncovered is None else uncovered == 0,
        never_open_pixels=int((~(arr != 0).any(0)).sum()),  # no light at all (leakage is a measurement)
        open_fraction=float(m.mean()),
        uncovered_windows=uncovered,
        patch=patch,
        mean_weight=float(np.mean(arr, dtype=np.float64)) if arr.size else 0.0,
        weight_min=float(nonzero.min()) if nonzero.size else 0.0,
        weight_max=float(arr.max()) if arr.size else 0.0,
        open_threshold=threshold,
    )


def short_of(frames: int, wanted: int) -> str:
    """The question to add to a message when a mask of ``frames`` sub-frames meets an input (the truth, a
    dictionary) made for ``wanted``: a mask folder missing an image reads as a code of fewer sub-frames, and the
    mask is then the input to look at (empty where the mask has as many or more)."""
    if wanted <= frames:
        return ""
    some = "a sub-frame" if wanted - frames == 1 else f"{wanted - frames} sub-frames"
    return f"is {some} missing from the mask (a mask folder needs one image per sub-frame)?"


def short_of_the_truth(frames: int, per_capture: int, mask: str = "the mask") -> str:
    """What to add to a truth's shape error when the truth holds ``per_capture`` frames per coded image and the
    mask (named ``mask``) fewer sub-frames, ``frames`` (empty otherwise)."""
    ask = short_of(frames, per_capture)
    return f"; {mask} has {frames} sub-frames where the truth has {per_capture} frames per coded image: {ask}" \
        if ask else ""
