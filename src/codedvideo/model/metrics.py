"""Quality metrics: PSNR and SSIM per frame (scikit-image), and their means.

Following the field's benchmarks, PSNR is computed per frame with a fixed
peak (``data_range``, 255 for 8-bit grey levels) and then averaged over frames.
"""

from __future__ import annotations

import math

import numpy as np

from codedvideo.model.errors import InputError
from codedvideo.model.units import EIGHT_BIT, OTHER_UNITS_ABOVE, OTHER_UNITS_BELOW, other_units  # noqa: F401


#: Frames compared at a time: a long video (or a lazy stack of one, :class:`codedvideo.formats.volumes.NpyStack`)
#: is never held whole in float64.
EVALUATE_BLOCK = 16


def volume_peak(v) -> float:
    """The largest value of a volume or a lazy stack, :data:`EVALUATE_BLOCK` frames at a time (never held whole)."""
    return max((float(np.max(np.asarray(v[s:s + EVALUATE_BLOCK], np.float32), initial=0.0))
                for s in range(0, v.shape[0], EVALUATE_BLOCK)), default=0.0)


def volume_extremes(v) -> tuple[float, float]:
    """The smallest and the largest value of a volume or a lazy stack, :data:`EVALUATE_BLOCK` frames at a time."""
    blocks = [np.asarray(v[s:s + EVALUATE_BLOCK], np.float32) for s in range(0, v.shape[0], EVALUATE_BLOCK)]
    return (min((float(b.min(initial=np.inf)) for b in blocks), default=0.0),
            max((float(b.max(initial=-np.inf)) for b in blocks), default=0.0))


#: A reconstruction holding values further than this share of the data range below 0 or above the range is
#: implausible (intensities are never negative, and a frame peaks at its range): the problem is ill-posed for
#: the method or the range does not fit, and the run says so (docs/research.md, "Long shutter bumps").
IMPLAUSIBLE_SHARE = 0.25


#: The most a frame's PSNR counts in a mean (dB).  Rounding a frame to 8 bits costs at most half a grey level in
#: every pixel, 58.9 dB of PSNR or more; below that, a frame reconstructed exactly counts the same whether it
#: was written as floats (infinite PSNR), 16-bit frames or an 8-bit video, and so does the mean.
PSNR_CEILING = 50.0


def mean_psnr(per_frame) -> float:
    """The mean PSNR over frames, each frame's PSNR capped at :data:`PSNR_CEILING` (an exact frame's is infinite;
    capped, it counts as any frame within 8-bit rounding of its truth would, whatever the output's format)."""
    values = np.minimum(np.asarray(per_frame, dtype=np.float64), PSNR_CEILING)
    return float(np.mean(values)) if values.size else float("nan")


def evaluate(recon, truth, *, data_range: float) -> dict:
    """Per-frame and mean PSNR/SSIM of a reconstruction.

    Parameters
    ----------
    recon, truth : ndarray of shape (N, H, W), or anything with ``shape`` and
        slices of consecutive frames (a lazy stack); compared
        :data:`EVALUATE_BLOCK` frames at a time
    data_range : float
        Peak value of the frames, always given (255 for 8-bit grey levels, 1 for [0, 1] floats): a default would
        score frames of another scale against the wrong peak.  :func:`codedvideo.evaluate` finds it from the
        truth's values where it is not given.

    Returns
    -------
    dict with ``psnr``, ``ssim`` (means over frames; the PSNR's with each frame's capped at
    :data:`PSNR_CEILING`, :func:`mean_psnr`), ``exact_frames``, ``psnr_per_frame`` (uncapped:
    infinite where a frame is exact), ``ssim_per_frame`` and ``data_range``.
    """
    rec = recon if hasattr(recon, "shape") else np.asarray(recon)
    ref = truth if hasattr(truth, "shape") else np.asarray(truth)
    if tuple(rec.shape) != tuple(ref.shape):
        raise InputError(f"evaluate: reconstruction shape {tuple(rec.shape)} != truth shape {tuple(ref.shape)}")
    if len(rec.shape) != 3:
        raise InputError(f"evaluate: expected (N, H, W) volumes, got shape {tuple(rec.shape)}")
    # lazy, and only the SSIM module: importing it brings scipy.ndimage (0.1 s of a run's start, paid only when
    # there is a truth to compare with); skimage.metrics' PSNR lives beside an import of scipy.stats (1 s)
    from skimage.metrics import structural_similarity

    psnr = []
    ssim = []
    win = min(7, *ref.shape[1:])
    win -= 1 - win % 2  # odd window no larger than the frame
    for start in range(0, rec.shape[0], EVALUATE_BLOCK):
        part = slice(start, start + EVALUATE_BLOCK)
        recon_part = np.asarray(rec[part], dtype=np.float64)
        if not np.isfinite(recon_part).all():
            raise InputError("evaluate: the reconstruction contains NaN or Inf")
        for r, t in zip(recon_part, np.asarray(ref[part], dtype=np.float64)):
            psnr.append(frame_psnr(r, t, data_range))
            ssim.append(float(structural_similarity(t, r, data_range=data_range, win_size=max(win, 3)))
                        if win >= 3 else float("nan"))
    return dict(
        psnr=mean_psnr(psnr),
        ssim=float(np.mean(ssim)),
        exact_frames=int(np.sum(np.isposinf(psnr))),
        psnr_per_frame=psnr,
        ssim_per_frame=ssim,
        data_range=float(data_range),
    )


def frame_psnr(recon: np.ndarray, truth: np.ndarray, data_range: float) -> float:
    """The PSNR of one frame (float64), infinite where it is exact."""
    return mse_psnr(float(np.mean((np.asarray(recon, np.float64) - np.asarray(truth, np.float64)) ** 2)), data_range)


def mse_psnr(mse: float, data_range: float) -> float:
    """The PSNR of a mean squared error, infinite where it is 0."""
    return float("inf") if mse == 0 else float(10 * np.log10(float(data_range) ** 2 / float(mse)))


def volume_psnr(recon: np.ndarray, truth: np.ndarray, data_range: float) -> float:
    """The PSNR of a volume (N, H, W) as :func:`evaluate` gives it (the mean of its frames', each capped,
    :func:`mean_psnr`), without the SSIM."""
    return mean_psnr([frame_psnr(r, t, data_range) for r, t in zip(recon, truth)])


def json_safe(obj):
    """A copy of ``obj`` that strict JSON can hold: non-finite floats become None.

    ``json.dumps`` writes ``Infinity`` and ``NaN`` by default, which strict
    parsers (``JSON.parse``, ``jq``) reject: the PSNR of identical frames is
    infinite, the SSIM of frames too small for its window NaN.  Python and
    numpy floats (scalars and arrays, also inside dicts, lists and tuples)
    that are NaN or infinite are replaced by None; numpy integers, booleans
    and arrays become plain Python values (arrays as nested lists), tuples
    become lists; dict keys, strings and everything else are kept as they are.

    >>> json_safe({"psnr": float("inf"), "per_frame": [1.5, np.float32("nan")]})
    {'psnr': None, 'per_frame': [1.5, None]}
    """
    if isinstance(obj, dict):
        return {k: json_safe(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [json_safe(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return json_safe(obj.tolist())
    if isinstance(obj, (bool, np.bool_)):
        return bool(obj)
    if isinstance(obj, np.integer):
        return int(obj)
    if isinstance(obj, (float, np.floating)):
        value = float(obj)
        return value if math.isfinite(value) else None
    return obj
