"""Bayer colour filter arrays: mosaics, demosaicking, colour scenes (issue 14, "Real sensor data").

A colour coded-exposure sensor records one colour filter per pixel under its
per-pixel shutter code: the coded mosaic is ``I(p) = sum_t S(t, p) E_c(p)(t, p)``
with ``c(p)`` the filter of pixel ``p`` (R, G or B), repeated in 2 x 2 cells
named by their four filters row by row (``RGGB``: R at (0, 0), G at (0, 1) and
(1, 0), B at (1, 1)).  Colour volumes are channels first, ``(3, N, H, W)``
(R, G, B), as the readers' ``color="channels"`` gives them.
"""

from __future__ import annotations

import time
from typing import TYPE_CHECKING

import numpy as np

from codedvideo.model import doors
from codedvideo.engine.methods import SPARSE
from codedvideo.engine.methods import method as method_named
from codedvideo.model.errors import InputError

if TYPE_CHECKING:
    from codedvideo.engine.captures import CaptureSettings

PATTERNS = ("RGGB", "BGGR", "GRBG", "GBRG")
CHANNELS = "RGB"


def check_pattern(pattern: str) -> str:
    """The pattern name (case-insensitive) upper-cased, or a one-line :class:`InputError`."""
    name = str(pattern).upper()
    if name not in PATTERNS:
        raise InputError(f"{doors.name('bayer')} {pattern}: unknown Bayer pattern (choose from {', '.join(PATTERNS)})")
    return name


def check_even(shape: tuple, where: str) -> None:
    """Raise :class:`InputError` naming ``where`` unless H and W are even (whole 2 x 2 Bayer cells)."""
    h, w = shape[-2:]
    if h % 2 or w % 2:
        raise InputError(f"{where}: {h}x{w} pixels is not a whole number of 2x2 Bayer cells under "
                         f"{doors.name('bayer')} (rows and columns must be even)")


def cfa_index(pattern: str, shape: tuple) -> np.ndarray:
    """(H, W) uint8: the channel (0 R, 1 G, 2 B) each pixel of an ``H x W`` mosaic records."""
    name = check_pattern(pattern)
    h, w = shape[-2:]
    cell = np.array([[CHANNELS.index(name[0]), CHANNELS.index(name[1])],
                     [CHANNELS.index(name[2]), CHANNELS.index(name[3])]], np.uint8)
    return np.tile(cell, ((h + 1) // 2, (w + 1) // 2))[:h, :w]


def cfa_masks(pattern: str, shape: tuple) -> np.ndarray:
    """(3, H, W) bool: pixels of each channel."""
    idx = cfa_index(pattern, shape)
    return np.stack([idx == c for c in range(3)])


def mosaic(color: np.ndarray, pattern: str) -> np.ndarray:
    """``(3, ..., H, W)`` colour -> ``(..., H, W)`` mosaic: each pixel keeps its filter's channel."""
    colour = np.asarray(color)
    if colour.ndim < 3 or colour.shape[0] != 3:
        raise InputError(f"mosaic: expected a colour array (3, ..., H, W), got shape {colour.shape}")
    m = cfa_masks(pattern, colour.shape).reshape((3,) + (1,) * (colour.ndim - 3) + colour.shape[-2:])
    return np.where(m, colour, 0).sum(0).astype(colour.dtype)


def _normalised(values: np.ndarray, weights: np.ndarray, kernel: np.ndarray) -> np.ndarray:
    """Normalised convolution: ``conv(values * weights) / conv(weights)`` (0 where no weight reaches)."""
    from scipy import ndimage

    num = ndimage.convolve(values * weights, kernel, mode="constant")
    den = ndimage.convolve(weights, kernel, mode="constant")
    return np.divide(num, den, out=np.zeros_like(num), where=den > 1e-6)


_TENT = np.outer([1.0, 2.0, 1.0], [1.0, 2.0, 1.0])


def demosaic_bilinear(raw: np.ndarray, pattern: str, weights: np.ndarray | None = None) -> np.ndarray:
    """(H, W) mosaic -> (3, H, W): each channel by normalised bilinear interpolation of its own pixels.

    ``weights`` (H, W) (e.g. 0 at pixels never open) weighs each sample; a
    channel's own pixels keep their value wherever their weight is positive.
    """
    values = np.asarray(raw, np.float64)
    w = np.ones_like(values) if weights is None else np.asarray(weights, np.float64)
    out = np.empty((3,) + values.shape)
    for c, m in enumerate(cfa_masks(pattern, values.shape)):
        wc = w * m
        out[c] = np.where(wc > 0, values, _normalised(values, wc, _TENT))
    return out.astype(np.float32)


# Malvar, He and Cutler (ICASSP 2004), gradient-corrected bilinear interpolation, kernels x 8.
_G_AT_RB = np.array([[0, 0, -1, 0, 0], [0, 0, 2, 0, 0], [-1, 2, 4, 2, -1], [0, 0, 2, 0, 0], [0, 0, -1, 0, 0]], float)
_RB_AT_G_ROW = np.array([[0, 0, .5, 0, 0], [0, -1, 0, -1, 0], [-1, 4, 5, 4, -1], [0, -1, 0, -1, 0], [0, 0, .5, 0, 0]],
                        float)  # the missing colour lies left and right of the G pixel
_RB_AT_G_COL = _RB_AT_G_ROW.T  # ... above and below
_RB_AT_BR = np.array([[0, 0, -1.5, 0, 0], [0, 2, 0, 2, 0], [-1.5, 0, 6, 0, -1.5], [0, 2, 0, 2, 0], [0, 0, -1.5, 0, 0]],
                     float)


def demosaic_malvar(raw: np.ndarray, pattern: str) -> np.ndarray:
    """(H, W) mosaic -> (3, H, W) by Malvar-He-Cutler's gradient-corrected interpolation.

    Borders are mirrored about the edge pixel (``mode="mirror"``), which keeps
    the 2 x 2 pattern's parity.
    """
    from scipy import ndimage

    values = np.asarray(raw, np.float64)
    idx = cfa_index(pattern, values.shape)
    conv = {name: ndimage.convolve(values, k / 8.0, mode="mirror")
            for name, k in (("g", _G_AT_RB), ("row", _RB_AT_G_ROW), ("col", _RB_AT_G_COL), ("cross", _RB_AT_BR))}
    out = np.empty((3,) + values.shape)
    for c in (0, 2):
        other = 2 - c
        # rows holding channel c (at either column parity)
        c_row = np.zeros(values.shape, bool)
        for r in (0, 1):
            if (idx[r::2] == c).any():
                c_row[r::2] = True
        est = np.where(idx == c, values,
                       np.where(idx == other, conv["cross"], np.where(c_row, conv["row"], conv["col"])))
        out[c] = est
    out[1] = np.where(idx == 1, values, conv["g"])
    return out.astype(np.float32)


def demosaic(raw: np.ndarray, pattern: str, method: str = "malvar", weights: np.ndarray | None = None) -> np.ndarray:
    """(H, W) mosaic -> (3, H, W): ``malvar`` (default) or ``bilinear`` (the only one that takes ``weights``)."""
    if method == "malvar" and (weights is None or np.all(np.asarray(weights) > 0)):
        return demosaic_malvar(raw, pattern)
    if method in ("malvar", "bilinear"):
        return demosaic_bilinear(raw, pattern, weights)
    raise InputError(f"demosaic: unknown method {method!r} (malvar, bilinear)")


# ----------------------------------------------------------------------------- colour scenes
#: Colour scenes (``synth:NAME`` under ``--bayer``): the motion of the grey scene of the same
#: name without ``color-``, on scikit-image's colour photographs (background, moving disc).
COLOR_SCENES = {"color-default": ("astronaut", "coffee")}


def color_photo(name: str) -> np.ndarray:
    """A colour photograph of scikit-image as (3, H, W) float32 0..255 (checked against ``data_manifest``)."""
    from skimage.io import imread

    from codedvideo.data import manifest
    from codedvideo.data import synth

    manifest.verify_ids((name,))
    img = np.asarray(imread(synth.photo_path(name)), np.float32)
    if img.ndim != 3 or img.shape[-1] < 3:
        raise InputError(f"photo {name}: not a colour photograph (shape {img.shape})")
    return np.moveaxis(img[..., :3], -1, 0).copy()


def color_scene(name: str, *, frames: int, size=(256, 256)) -> np.ndarray:
    """A colour scene ``(3, frames, H, W)`` float32 0..255 (:data:`COLOR_SCENES`).

    ``color-default`` moves exactly as ``synth:default`` (background drifting
    0.15, 0.25 px per sub-frame, a disc crossing at 0.4, 1.5 px per sub-frame):
    the astronaut crossed by a disc of the coffee photograph.  Each channel
    goes through the same (deterministic) motion.
    """
    from codedvideo.data import synth

    if name not in COLOR_SCENES:
        raise InputError(f"scene {name!r}: unknown colour scene (choose from {', '.join(COLOR_SCENES)}, "
                         "or any grey synth: scene, recorded as R = G = B)")
    side = tuple(int(s) for s in size)
    background, foreground = (color_photo(p) for p in COLOR_SCENES[name])
    return np.stack([synth.occlude(bg, fg, frames=frames, size=side, velocity=(0.4, 1.5), drift=(0.15, 0.25))
                     for bg, fg in zip(background, foreground)])


def color_footage(name: str, *, frames: int, size: tuple[int, int] | None = None) -> np.ndarray:
    """A held-out real scene of :mod:`codedvideo.data.footage` in colour, ``(3, frames, H, W)`` float32 0..255."""
    from codedvideo.formats import io as cio
    from codedvideo.data import manifest
    from codedvideo.data.footage import SCENES, SIZE

    if name not in SCENES:
        raise InputError(f"footage {name!r}: unknown scene (choose from {', '.join(SCENES)})")
    entry_id, start, (y0, x0), scale = SCENES[name]
    path = manifest.verify(manifest.lookup(entry_id))
    video = cio.read_video(path, max_frames=frames, start=start, color="channels")
    if video.shape[0] == 1:
        video = np.repeat(video, 3, axis=0)
    if video.shape[1] < frames:
        raise InputError(f"footage {name}: {path} has {video.shape[1]} frames from frame {start}, need {frames}")
    if scale != 1.0:
        from skimage.transform import rescale

        video = np.stack([np.stack([rescale(f, scale, order=3 if scale > 1 else 1, anti_aliasing=scale < 1)
                                    for f in ch]) for ch in video])
    video = video[:, :, y0 : y0 + SIZE, x0 : x0 + SIZE]
    if size is not None:
        h, w = size
        if h > SIZE or w > SIZE:
            raise InputError(f"footage {name}: size {tuple(size)} is larger than the {SIZE}x{SIZE} scene")
        cy, cx = (SIZE - h) // 2, (SIZE - w) // 2
        video = video[..., cy : cy + h, cx : cx + w]
    return np.ascontiguousarray(np.clip(video, 0, 255), dtype=np.float32)


def load_color_video(spec: str, *, frames: int, size: tuple[int, int] | None, seed: int = 0,
                     start: int = 0) -> np.ndarray:
    """A scene in colour, ``(3, frames, H, W)`` float32: what ``simulate --bayer`` films.

    ``synth:color-default`` (:func:`color_scene`), ``footage:NAME`` in colour
    (:func:`color_footage`), or a video / frame-sequence path read with its
    channels.  Grey sources (the other ``synth:`` scenes, grey files) are
    recorded as R = G = B.  Files are centre-cropped to ``size``.
    """
    from codedvideo.data.scenes import load_video, read_clip

    if spec.startswith("synth:"):
        name = spec.split(":", 1)[1]
        if name in COLOR_SCENES:
            return color_scene(name, frames=frames, size=size or (256, 256))
        return np.repeat(load_video(spec, frames=frames, size=size, seed=seed)[None], 3, axis=0)
    if spec.startswith("footage:"):
        return color_footage(spec.split(":", 1)[1], frames=frames, size=size)
    video = read_clip(spec, frames=frames, size=size, start=start, color="channels")
    return np.repeat(video, 3, axis=0) if video.shape[0] == 1 else video


def simulate_bayer(video: np.ndarray, pattern: str, *, where: str = "video", **capture) -> dict[str, np.ndarray]:
    """Coded capture of a colour video through a Bayer filter.

    ``video`` (3, N, H, W) is filtered (:func:`mosaic`: one channel per
    pixel), then coded and measured exactly as a grey video
    (:func:`codedvideo.engine.simulation.simulate_capture` with ``capture``'s keywords:
    code, sigma, seed, sensor, ...).  Returns ``coded`` (H, W) mosaic,
    ``mask`` (N, H, W) and ``truth`` (3, N, H, W), the colour video.
    """
    from codedvideo.engine.simulation import simulate_capture

    colours = check_pattern(pattern)
    frames = np.asarray(video, np.float32)
    if frames.ndim != 4 or frames.shape[0] != 3:
        raise InputError(f"{where}: a Bayer capture needs a colour video (3, N, H, W), got shape {frames.shape}")
    check_even(frames.shape, where)
    cap = simulate_capture(mosaic(frames, colours), **capture)
    return dict(cap, truth=frames)


def static_estimate(coded: np.ndarray, mask: np.ndarray, pattern: str,
                    measured: np.ndarray | None = None) -> np.ndarray:
    """The demosaicked static estimate ``(3, N, H, W)``: every sub-frame = coded / open count, demosaicked.

    Bilinear normalised interpolation of each channel's own pixels (pixels
    never open, or not ``measured`` (H, W) bool, carry no weight).  The
    baseline a Bayer reconstruction must beat.  Malvar-He-Cutler's
    gradient-corrected demosaic is worse here: neighbouring pixels integrate
    different sub-frames, so its cross-channel gradients carry motion
    (docs/research.md, "Bayer mosaics: the joint colour dictionary").
    """
    shutter = np.asarray(mask, np.float32)
    counts = shutter.sum(0)
    weights = counts > 0 if measured is None else (counts > 0) & measured
    frame = np.divide(coded, counts, out=np.zeros(counts.shape, np.float32), where=counts > 0)
    colour = demosaic_bilinear(frame, pattern, weights.astype(np.float32))
    return np.ascontiguousarray(np.broadcast_to(colour[:, None], (3,) + shutter.shape), dtype=np.float32)


# ----------------------------------------------------------------------------- reconstruction
#: Colour directions of the joint dictionary: luminance, then two chroma directions (orthonormal).
COLOR_BASIS = (np.array([[1, 1, 1], [1, 0, -1], [1, -2, 1]], np.float64)
               / np.sqrt([[3.0], [2.0], [6.0]]))
#: Share of the grey atoms (the spatially smoothest) that also serve as chroma atoms: fewer lose colour detail,
#: more lose quality and time (docs/research.md, "Bayer mosaics: the joint colour dictionary").
CHROMA_FRACTION = 0.25


def color_dictionary(D: np.ndarray, frames: int, chroma_fraction: float = CHROMA_FRACTION) -> np.ndarray:
    """A joint colour dictionary ``(3 * N * 49, K + 2 M)`` lifted from a grey one ``(N * 49, K)``.

    Rows are channel-major (R's N x 49, then G's, then B's), the layout of a
    ``(3 N, H, W)`` stack of the colour video.  Every grey atom ``d`` gives a
    luminance atom ``d (1, 1, 1) / sqrt 3``; its ``M = chroma_fraction K``
    smoothest atoms (least spatial gradient energy) also give chroma atoms
    ``d (1, 0, -1) / sqrt 2`` and ``d (1, -2, 1) / sqrt 6``.  So a colour
    patch is sparse in luminance detail plus smooth colour, the prior every
    demosaicking method relies on, and the grey dictionary's motion atoms
    carry both.
    """
    from codedvideo.solvers.dictionaries import prepare_dictionary

    atoms = np.asarray(prepare_dictionary(np.asarray(D, np.float32), f"for {doors.name('bayer')}"), np.float64)
    k = atoms.shape[1]
    cube = atoms.reshape(frames, 7, 7, k)
    rough = (np.diff(cube, axis=1) ** 2).sum((0, 1, 2)) + (np.diff(cube, axis=2) ** 2).sum((0, 1, 2))
    smooth = atoms[:, np.argsort(rough / (cube**2).sum((0, 1, 2)), kind="stable")[: max(1, round(chroma_fraction * k))]]
    blocks = [np.concatenate([COLOR_BASIS[0, c] * atoms for c in range(3)])]
    blocks += [np.concatenate([v[c] * smooth for c in range(3)]) for v in COLOR_BASIS[1:]]
    return np.concatenate(blocks, axis=1).astype(np.float32)


def color_mask(mask: np.ndarray, pattern: str) -> np.ndarray:
    """``(3 N, H, W)``: the grey mask per channel, open only at that channel's pixels (channel-major)."""
    grey = np.asarray(mask)
    cm = cfa_masks(pattern, grey.shape)
    return (cm[:, None] * grey[None]).reshape((3 * grey.shape[0],) + grey.shape[1:]).astype(grey.dtype)


def _channel_residual(coded: np.ndarray, mask: np.ndarray, volume: np.ndarray, pattern: str,
                      measured: np.ndarray) -> np.ndarray:
    """Static correction ``(3, H, W)``: the measurement residual / open count, interpolated per channel."""
    shutter = np.asarray(mask, np.float32)
    counts = shutter.sum(0)
    predicted = mosaic(np.einsum("cthw,thw->chw", volume, shutter), pattern)
    weights = (counts > 0) & measured
    r = np.divide(np.asarray(coded, np.float32) - predicted, counts, out=np.zeros(counts.shape, np.float32),
                  where=weights)
    return np.stack([_normalised(r.astype(np.float64), (m & weights).astype(np.float64), _TENT)
                     for m in cfa_masks(pattern, r.shape)]).astype(np.float32)


def reconstruct_bayer(options: CaptureSettings, coded: np.ndarray, mask: np.ndarray, *,
                      pattern: str) -> tuple[np.ndarray, dict]:
    """A Bayer-coded mosaic ``(H, W)`` and its mask ``(N, H, W)`` -> the colour video ``(3, N, H, W)``.

    ``omp``, ``dct`` and ``nonlocal``: one joint sparse coding of the colour
    video as a ``(3 N, H, W)`` stack, each pixel measuring its own channel
    under its code (:func:`color_mask`), over the grey dictionary lifted to
    colour (:func:`color_dictionary`), through
    :func:`codedvideo.engine.captures.reconstruct_capture` (units, saturation,
    tiles, cache and ``adapt`` as for grey: the non-local method's groups are
    matched as whole colour blocks, and ``adapt`` adapts the lifted
    dictionary itself to the colour result).  Then a static correction: each channel's
    measurement residual / open count, interpolated from its own pixels, is
    added to every sub-frame.  With ``refine``
    (``--refine``, ``--preset best``) the stack is refined under the colour
    mask before the correction, each group within one channel's own
    sub-frames (``blocks=3``, :func:`codedvideo.solvers.refine.refine`;
    docs/quality.md, "Bayer mosaics"); under read noise
    without the correction (:func:`_corrected`).  ``thinout``,
    ``interp`` and ``gaptv``: each channel alone, its other pixels missing (and
    refined alone).
    A mask with one pattern for every pixel carries no temporal information:
    the result is the demosaicked static estimate (:func:`static_estimate`).

    The joint coding beats each channel alone, demosaicking first and the mosaic
    reconstructed as grey (docs/cli.md, "Bayer mosaics"; the methods on colour
    footage: docs/research.md, "Bayer mosaics: the joint colour dictionary").

    ``options``: the method and its options (:class:`~codedvideo.engine.captures.CaptureSettings`: ``method``,
    ``dictionary`` (the grey one), ``white_level``, ``data_range``, ``settings``, ``config``, ``cache``, ...).
    """
    import dataclasses

    from codedvideo.engine.captures import reconstruct_capture

    method, white_level, where = options.method, options.white_level, options.where
    colours = check_pattern(pattern)
    mosaicked = np.asarray(coded, np.float32)
    codes = np.asarray(mask)
    n = codes.shape[0]
    check_even(mosaicked.shape, where)
    t0 = time.perf_counter()
    measured = np.ones(mosaicked.shape, bool) if white_level is None else mosaicked < np.float32(white_level)
    if (codes == codes[:, :1, :1]).all():  # one shutter pattern everywhere: no temporal information
        if not measured.any():
            raise InputError(f"{where}: every pixel is at or above {doors.name('white_level')} {white_level}; nothing "
                             f"is left to reconstruct ({doors.name('trust_saturated')} uses them anyway)")
        volume = static_estimate(mosaicked, codes, colours, measured)
        info = dict(method="static", patches=0, patches_per_second=0.0,
                    seconds=dict(reconstruct=time.perf_counter() - t0), saturated_pixels=int((~measured).sum()))
        return volume, dict(info, bayer=dict(pattern=colours, approach="static"))
    with doors.muted("pixels are never open"):  # a channel's other pixels are missing by design
        if method in SPARSE:
            entry = method_named(method)
            if entry.dictionary:
                dictionary = options.dictionary
            else:  # (dct: its own atoms)
                from codedvideo.solvers.dictionaries import dct_dictionary

                dictionary = dct_dictionary(n)
            lifted = color_dictionary(dictionary, n)
            # (the lifted atoms key the cache; the refinement's groups each within one channel's sub-frames)
            joint = dataclasses.replace(options, method=entry.solver, dictionary=lifted, dictionary_key="",
                                        blocks=3)
            stack, info = reconstruct_capture(joint, mosaicked, color_mask(codes, colours))
            volume = stack.reshape((3, n) + mosaicked.shape)
            # (a code the non-local method's table cannot hold gave the joint OMP: its record says so)
            info = dict(info, method="omp" if info.get("nonlocal_unavailable") else method,
                        dictionary_atoms=int(np.shape(dictionary)[1]))
            approach = "joint"
        else:
            cm = cfa_masks(colours, mosaicked.shape)
            alone = dataclasses.replace(options, dictionary=None)
            parts = [reconstruct_capture(alone, np.where(cm[c], mosaicked, 0).astype(np.float32),
                                         (codes * cm[c]).astype(codes.dtype)) for c in range(3)]
            volume = np.stack([p[0] for p in parts])
            seconds = {k: sum(p[1]["seconds"][k] for p in parts) for k in ("reconstruct", "refine")
                       if k in parts[0][1]["seconds"]}
            info = dict(parts[0][1], seconds=seconds, saturated_pixels=parts[0][1].get("saturated_pixels", 0))
            approach = "per-channel"
    volume, info = _corrected(volume, info, mosaicked, codes, colours, measured,
                              relaxed="refine" in info and options.noise_sigma > 0)
    info["bayer"] = dict(pattern=colours, approach=approach, chroma_fraction=CHROMA_FRACTION if approach == "joint"
                         else None, correction_rms=info.pop("correction_rms"))
    return volume, info


def _corrected(volume: np.ndarray, info: dict, coded: np.ndarray, mask: np.ndarray, pattern: str,
               measured: np.ndarray, *, relaxed: bool = False) -> tuple[np.ndarray, dict]:
    """A colour result ``(3, N, H, W)`` with the static correction added (:func:`_channel_residual`), its seconds
    and ``correction_rms`` in ``info``.  ``relaxed`` (a result refined under read noise): as it is,
    ``correction_rms`` None, since the refinement's steps were relaxed so as not to put the noise back, and the
    correction would; refined without noise it halves the measurement residual at the same PSNR (docs/quality.md,
    "Bayer mosaics")."""
    if relaxed:
        return volume, dict(info, correction_rms=None)
    t0 = time.perf_counter()
    correction = _channel_residual(coded, mask, volume, pattern, measured)
    corrected = (volume + correction[:, None]).astype(np.float32)
    seconds = dict(info.get("seconds", {}), correction=time.perf_counter() - t0)
    return corrected, dict(info, seconds=seconds,
                           correction_rms=float(np.sqrt(np.mean(correction.astype(np.float64) ** 2))))
