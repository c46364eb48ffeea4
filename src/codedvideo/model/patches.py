"""Overlapping patches at stride 1: extraction, its adjoint (overlap-add), coverage.

A patch vector has ``N * M * M`` entries ordered ``(t, dy, dx)``; patches are
ordered by their top-left corner in raster order.  Only windows that lie fully
inside the array exist (no padding: a reflected border would invent patches),
so a border pixel is covered by fewer than ``M * M`` patches and the average
divides by the exact count from :func:`coverage`.
"""

from __future__ import annotations

import numpy as np
from numba import njit

#: Side of the square patches of the method (7x7 in the paper): the one home of this constant.
PATCH = 7


def grid_shape(shape: tuple[int, int], patch: int = PATCH) -> tuple[int, int]:
    """Number of patch positions ``(H - M + 1, W - M + 1)`` in an image."""
    return max(shape[0] - patch + 1, 0), max(shape[1] - patch + 1, 0)


def extract(volume: np.ndarray, patch: int = PATCH) -> np.ndarray:
    """All overlapping ``patch x patch`` patches of a volume or image.

    Parameters
    ----------
    volume : ndarray of shape (N, H, W) or (H, W)

    Returns
    -------
    patches : ndarray of shape (P, N, M*M) or (P, M*M)
        ``P = (H - M + 1) * (W - M + 1)``, a copy.
    """
    vol = np.asarray(volume)
    two_d = vol.ndim == 2
    if two_d:
        vol = vol[None]
    n = vol.shape[0]
    win = np.lib.stride_tricks.sliding_window_view(vol, (patch, patch), axis=(1, 2))
    # win: (N, Hp, Wp, M, M) -> (Hp, Wp, N, M, M)
    hp, wp = win.shape[1:3]
    out = np.ascontiguousarray(win.transpose(1, 2, 0, 3, 4)).reshape(hp * wp, n, patch * patch)
    return out[:, 0, :] if two_d else out


def fold(patches: np.ndarray, shape: tuple[int, int], patch: int = PATCH) -> np.ndarray:
    """Adjoint of :func:`extract`: add every patch back at its place (sums overlaps).

    Parameters
    ----------
    patches : ndarray of shape (P, N, M*M) or (P, N*M*M), or (P,): one value per patch (N = 1)
    shape : (H, W)

    Returns
    -------
    volume : ndarray of shape (N, H, W), float32
    """
    hp, wp = grid_shape(shape, patch)
    p = patches.shape[0]
    if p != hp * wp:
        raise ValueError(f"fold: {p} patches do not tile an image of shape {shape}")
    n = 1 if patches.ndim == 1 else patches.reshape(p, -1).shape[1] // (patch * patch)
    out = np.zeros((n, *shape), dtype=np.float32)
    fold_rows(patches, out, 0, patch)
    return out


def fold_rows(patches: np.ndarray, out: np.ndarray, row: int, patch: int = PATCH,
              skip: np.ndarray | None = None) -> None:
    """Add whole rows of patches into ``out`` in place: a band of :func:`fold`.

    Parameters
    ----------
    patches : ndarray of shape (k * Wp, N, M*M) or (k * Wp, N*M*M), or (k * Wp,)
        The patches whose corners lie in grid rows ``row .. row + k - 1``, in
        raster order (``Wp = W - M + 1``); a vector: one value per patch,
        added to every pixel of the patch (its weight in an average).
    out : ndarray of shape (N, H, W)
        Accumulator, float32.
    row : int
        First grid row of the band.
    skip : bool ndarray of shape (k * Wp,), optional
        Patches left out (whose pixels the caller overwrites anyway).

    Every pixel receives its patches in one fixed order, by patch corner row
    (top first), then by corner column (right first), whatever the band, so
    float32 sums do not depend on how the patch rows are cut into bands
    (batch size, tile size, image origin): tiled and whole-image results
    agree bit for bit.  Compiled (:func:`_fold_kernel`).
    """
    n, h, w = out.shape
    wp = w - patch + 1
    k = patches.shape[0] // wp
    if k * wp != patches.shape[0] or row + k > h - patch + 1:
        raise ValueError(f"fold_rows: {patches.shape[0]} patches are not whole rows of a {h}x{w} grid from row {row}")
    if out.dtype != np.float32 or not out.flags.c_contiguous:
        raise ValueError("fold_rows: the accumulator must be a C-contiguous float32 array")
    scalar = patches.ndim == 1
    pt = np.ascontiguousarray(patches, dtype=np.float32).reshape(k * wp, 1 if scalar else n, -1)
    if not scalar and pt.shape[2] != patch * patch:
        raise ValueError(f"fold_rows: patches of {pt.shape[1] * pt.shape[2]} values are not {n}x{patch}x{patch}")
    if scalar and n != 1:
        raise ValueError("fold_rows: one value per patch folds into a single-frame accumulator")
    skipped = np.zeros(k * wp, np.bool_) if skip is None else np.ascontiguousarray(skip, dtype=np.bool_)
    _fold_kernel(pt, out, row, patch, skipped, scalar)


@njit(nogil=True, cache=True)
def _fold_kernel(pt, out, row, patch, skip, scalar):  # pragma: no cover - compiled
    n, w = out.shape[0], out.shape[2]
    wp = w - patch + 1
    k = pt.shape[0] // wp
    for r in range(k):  # corner rows top first, corner columns right first: the order of fold_rows
        for c in range(wp - 1, -1, -1):
            p = r * wp + c
            if skip[p]:
                continue
            for t in range(n):
                for dy in range(patch):
                    y = row + r + dy
                    for dx in range(patch):
                        out[t, y, c + dx] += pt[p, 0, 0] if scalar else pt[p, t, dy * patch + dx]


def coverage(shape: tuple[int, int], patch: int = PATCH) -> np.ndarray:
    """Exact number of patches covering every pixel, shape (H, W) int32.

    Computed separably: along each axis a pixel at ``i`` is covered by the
    windows starting in ``max(0, i - M + 1) .. min(i, n - M)``.
    """

    def axis_count(n: int) -> np.ndarray:
        i = np.arange(n)
        lo = np.maximum(0, i - patch + 1)
        hi = np.minimum(i, n - patch)
        return np.maximum(hi - lo + 1, 0)

    return (axis_count(shape[0])[:, None] * axis_count(shape[1])[None, :]).astype(np.int32)


def stride_rows(start: int, count: int, total: int, stride: int) -> np.ndarray:
    """Which of the patch corners ``start .. start + count - 1`` (of ``total`` along an axis) are solved.

    Every ``stride``-th corner of the whole image, counted from 0, and the last one, so that every
    pixel stays covered for any stride up to the patch size.  Global indices make a tile choose
    exactly the corners the whole image does.
    """
    g = np.arange(start, start + count)
    return (g % stride == 0) | (g == total - 1)


def uncovered_pixels(open_any: np.ndarray, patch: int = PATCH, stride: int = 1) -> np.ndarray:
    """Pixels that no patch with a measured pixel covers, shape (H, W) bool.

    A patch is measured when any of its pixels is ever open; the average of
    overlapping estimates leaves out unmeasured patches, so these pixels get
    no estimate and are filled from their neighbours instead.
    """
    def box(a: np.ndarray) -> np.ndarray:  # sums over patch x patch windows ending at each index
        c = np.pad(a.astype(np.int64).cumsum(0).cumsum(1), ((patch, 0), (patch, 0)))
        return c[patch:, patch:] - c[:-patch, patch:] - c[patch:, :-patch] + c[:-patch, :-patch]

    h, w = open_any.shape
    measured = np.zeros((h, w), bool)  # at each patch corner: does the patch see a measurement?
    hp, wp = grid_shape((h, w), patch)
    measured[:hp, :wp] = box(open_any)[patch - 1 :, patch - 1 :] > 0
    if stride > 1:
        measured[:hp, :wp] &= stride_rows(0, hp, hp, stride)[:, None] & stride_rows(0, wp, wp, stride)[None, :]
    return box(measured) == 0
