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
window) are i.i.d. uniform, as in the paper's random code.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .errors import InputError

PATCH = 7

#: Names accepted by :func:`make_code`.
CODE_NAMES = ("hitomi", "hitomi-tiled", "bernoulli", "global")


def _check_bump(frames: int, bump: int, patch: int) -> None:
    if frames < 1:
        raise InputError(f"code: frames must be >= 1, got {frames}")
    if not 1 <= bump <= frames:
        raise InputError(f"code: bump length must be in 1..{frames} (frames), got {bump}")
    if patch * patch * bump < frames:
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
    rng = np.random.default_rng(rng)
    h, w = shape
    nstart = frames - bump + 1
    cover = _covering_starts(frames, bump, rng)
    # the tile: covering roles at random positions, the rest uniform
    tile = rng.integers(0, nstart, size=patch * patch)
    roles = rng.permutation(patch * patch)[: len(cover)]
    tile[roles] = cover
    tile = tile.reshape(patch, patch)
    yy, xx = np.mgrid[0:h, 0:w]
    tiled_starts = tile[yy % patch, xx % patch]
    if tiled:
        return tiled_starts.astype(np.int16)
    is_role = np.zeros(patch * patch, dtype=bool)
    is_role[roles] = True
    role_map = is_role.reshape(patch, patch)[yy % patch, xx % patch]
    free = rng.integers(0, nstart, size=(h, w))
    return np.where(role_map, tiled_starts, free).astype(np.int16)


def starts_to_mask(starts: np.ndarray, *, frames: int, bump: int) -> np.ndarray:
    """Expand bump starts ``(H, W)`` into the binary code ``(N, H, W)`` uint8."""
    t = np.arange(frames)[:, None, None]
    return ((t >= starts[None]) & (t < starts[None] + bump)).astype(np.uint8)


def make_code(
    name: str,
    shape: tuple[int, int],
    *,
    frames: int,
    bump: int = 2,
    p: float = 0.5,
    rng: np.random.Generator | int | None = 0,
) -> np.ndarray:
    """Build a named shutter code.

    Parameters
    ----------
    name : {"hitomi", "hitomi-tiled", "bernoulli", "global"}
        ``hitomi``: the paper's sliding single-bump code; ``hitomi-tiled``: one
        random 7x7 single-bump tile repeated; ``bernoulli``: i.i.d. Bernoulli(p)
        per pixel and sub-frame (the snapshot-compressive-imaging benchmarks);
        ``global``: an ordinary exposure, every pixel open in every sub-frame.
    shape : (H, W)
    frames : int
    bump : int
        Bump length for the single-bump codes.
    p : float
        Open probability of the Bernoulli code.
    rng : Generator or int

    Returns
    -------
    mask : ndarray of shape (N, H, W), uint8
    """
    if name in ("hitomi", "hitomi-tiled"):
        starts = bump_starts(shape, frames=frames, bump=bump, rng=rng, tiled=name == "hitomi-tiled")
        return starts_to_mask(starts, frames=frames, bump=bump)
    rng = np.random.default_rng(rng)
    if name == "bernoulli":
        if not 0.0 < p <= 1.0:
            raise InputError(f"code bernoulli: p must be in (0, 1], got {p}")
        return (rng.random((frames, *shape)) < p).astype(np.uint8)
    if name == "global":
        return np.ones((frames, *shape), dtype=np.uint8)
    raise InputError(f"code: unknown code {name!r}; choose one of {', '.join(CODE_NAMES)}")


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
    """Which hardware constraints a mask meets (see :func:`check_code`)."""

    frames: int
    binary: bool
    single_bump: bool
    fixed_bump: bool
    bump_length: int | None
    window_coverage: bool
    never_open_pixels: int
    open_fraction: float

    def as_dict(self) -> dict:
        return dict(self.__dict__)


def check_code(mask: np.ndarray, patch: int = PATCH) -> CodeReport:
    """Report the hardware constraints that a mask ``(N, H, W)`` meets."""
    mask = np.asarray(mask)
    if mask.ndim != 3:
        raise InputError(f"mask: expected shape (N, H, W), got {mask.shape}")
    binary = bool(np.isin(mask, (0, 1)).all())
    m = (mask != 0).astype(np.int8)
    counts = m.sum(0)
    # a single contiguous bump <=> at most one rising edge (0 -> 1) along time
    rises = (np.diff(np.concatenate([np.zeros_like(m[:1]), m]), axis=0) == 1).sum(0)
    single = bool((rises <= 1).all())
    open_counts = counts[counts > 0]
    fixed = single and open_counts.size > 0 and bool((open_counts == open_counts[0]).all())
    if min(mask.shape[1:]) >= patch:
        covered = bool((window_coverage(m, patch) > 0).all())
    else:
        covered = bool((m.reshape(m.shape[0], -1).max(1) > 0).all())
    return CodeReport(
        frames=int(mask.shape[0]),
        binary=binary,
        single_bump=single,
        fixed_bump=fixed,
        bump_length=int(open_counts[0]) if fixed else None,
        window_coverage=covered,
        never_open_pixels=int((counts == 0).sum()),
        open_fraction=float(m.mean()),
    )
