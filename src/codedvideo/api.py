"""The Python API: the method on arrays, in the caller's units, the one door the command line also goes through.

>>> import numpy as np
>>> import codedvideo as cv
>>> video = cv.synthetic_scene("default", frames=8, size=(48, 48)) / 255  # [0, 1] floats
>>> mask = cv.make_code("hitomi", (48, 48), frames=8, bump=2, seed=0)
>>> coded = cv.simulate(video, mask)
>>> frames = cv.reconstruct(coded, mask)
>>> frames.shape, frames.dtype
((8, 48, 48), dtype('float32'))
>>> round(cv.evaluate(frames, video)["psnr"]) > 24
True

Every function takes and returns numpy arrays (:func:`reconstruct` also dask arrays).  Units are the
caller's: a capture in [0, 1] floats, 8-bit, 12-bit or 16-bit gives the same video in its own units
(:mod:`codedvideo.model.units` finds the data range once, as the command line does).
"""

from __future__ import annotations

import contextlib
import hashlib
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from codedvideo.model.errors import ConfigError, InputError

__all__ = ["Reconstruction", "evaluate", "load_dictionary", "make_code", "reconstruct", "simulate",
           "synthetic_scene", "train"]


def make_code(name: str, shape: tuple[int, int], *, frames: int, bump: int | None = None, p: float | None = None,
              seed: int = 0) -> np.ndarray:
    """A shutter code: the (N, H, W) uint8 mask of ``name`` (any code ``--code`` accepts).

    Parameters
    ----------
    name : str
        ``hitomi`` (the paper's single-bump code), ``hitomi-tiled``, ``rowwise``, ``thinout``, ``grid``,
        ``flutter``, ``bernoulli``, ``shifting`` or ``global``.
    shape : (H, W)
    frames : int
        Sub-frames N.
    bump : int, optional
        Bump length L of the single-bump codes (default 2).
    p : float, optional
        Open probability of ``bernoulli`` and ``shifting`` (default 0.5).
    seed : int

    Returns
    -------
    mask : ndarray of shape (N, H, W), uint8

    Examples
    --------
    >>> make_code("hitomi", (14, 14), frames=8, bump=2).sum(0).min()  # every pixel open for L sub-frames
    np.uint64(2)
    """
    from codedvideo.model.codes import make_code as _make_code

    if name == "file":
        raise ConfigError("make_code: 'file' reads a mask file; load the mask with numpy instead")
    options = {}
    if bump is not None:
        options["bump"] = bump
    if p is not None:
        options["p"] = p
    return _make_code(name, tuple(shape), frames=frames, rng=seed, **options)


def simulate(video: np.ndarray, mask: np.ndarray, *, noise_sigma: float = 0.0, shot_noise: bool = False,
             bits: int | None = None, seed: int = 0) -> np.ndarray:
    """The coded image(s) a camera with this code records: ``sensor(noise(S E))``.

    Parameters
    ----------
    video : ndarray of shape (N, H, W), or (T*N, H, W) for a stream of T captures
    mask : ndarray of shape (N, H, W) (one code for every capture) or (T, N, H, W)
    noise_sigma : float
        Gaussian read noise, in the video's units.
    shot_noise : bool
        Poisson photon noise (the 8-bit sensor model of :class:`codedvideo.model.physics.SensorModel`).
    bits : int, optional
        Quantise the coded image to this many bits.
    seed : int

    Returns
    -------
    coded : ndarray of shape (H, W), or (T, H, W) for a stream, float32

    Examples
    --------
    >>> mask = make_code("global", (4, 4), frames=2)
    >>> simulate(np.ones((2, 4, 4)), mask)[0, 0]
    np.float32(2.0)
    """
    from codedvideo.model.physics import SensorModel, simulate as _simulate

    video = np.asarray(video, np.float32)
    mask = np.asarray(mask)
    n = mask.shape[-3]
    if video.ndim != 3 or mask.ndim not in (3, 4) or video.shape[0] % n or video.shape[1:] != mask.shape[-2:]:
        raise InputError(f"simulate: video {video.shape} and mask {mask.shape} do not fit: the video is (N, H, W) "
                         "or (T*N, H, W), the mask (N, H, W) or (T, N, H, W)")
    count = video.shape[0] // n
    if mask.ndim == 4 and mask.shape[0] != count:
        raise InputError(f"simulate: {count} captures in the video, {mask.shape[0]} masks")
    sensor = SensorModel(shot_noise=True, read_sigma=noise_sigma, bits=bits) if shot_noise or bits else None
    rng = np.random.default_rng(seed)
    coded = [_simulate(video[i * n:(i + 1) * n], mask[i] if mask.ndim == 4 else mask,
                       sigma=0.0 if sensor else noise_sigma, rng=rng, sensor=sensor) for i in range(count)]
    return coded[0] if count == 1 and mask.ndim == 3 and video.shape[0] == n else np.stack(coded)


def synthetic_scene(name: str = "default", *, frames: int = 8, size: tuple[int, int] = (256, 256)) -> np.ndarray:
    """A synthetic test scene (``synth:NAME`` of the command line) as (N, H, W) float32 in 0..255.

    >>> synthetic_scene(frames=4, size=(16, 16)).shape
    (4, 16, 16)
    """
    from codedvideo.data.synth import make_scene

    return make_scene(name, frames=frames, size=tuple(size))


def load_dictionary(frames: int | None = None, path: str | Path | None = None) -> np.ndarray:
    """The shipped dictionary for N = ``frames``, or the dictionary stored at ``path``.

    Returns
    -------
    D : ndarray of shape (N * 49, K), float32, unit-norm atoms of 7x7xN patches

    >>> load_dictionary(8).shape
    (392, 512)
    """
    from codedvideo.data import shipped
    from codedvideo.formats.store import load_dictionary as _load

    if (frames is None) == (path is None):
        raise ConfigError("load_dictionary: give frames (the shipped dictionary) or path, one of them")
    if path is not None:
        D, meta = _load(path)
        return D
    found = shipped.required(int(frames), "load_dictionary", f"codedvideo.train(videos, frames={frames}) or "
                             f"`{shipped.train_command(frames)}`")
    return _load(found)[0]


def train(videos, *, frames: int, atoms: int = 512, samples: int = 80000, iterations: int = 20,
          sparsity: int = 6, seed: int = 0, augment: bool = True) -> np.ndarray:
    """A dictionary learned with K-SVD on 7x7xN patches of ``videos`` (the command line's defaults).

    Parameters
    ----------
    videos : sequence of ndarrays of shape (T, H, W), each in its own units (found as the CLI finds them)
    frames : int
        Sub-frames N of the captures the dictionary is for.
    atoms, samples, iterations, sparsity, seed, augment
        As ``codedvideo train``.

    Returns
    -------
    D : ndarray of shape (N * 49, atoms), float32
    """
    from codedvideo.solvers.dictionaries import learn_dictionary
    from codedvideo.data.scenes import working_units

    clips = [working_units(np.array(v, np.float32), what=f"training video {i + 1}") for i, v in enumerate(videos)]
    if not clips:
        raise InputError("train: no training video given")
    D, _ = learn_dictionary(clips, frames=frames, atoms=atoms, samples=samples, iterations=iterations,
                            sparsity=sparsity, seed=seed, augment=augment)
    return D


@dataclass
class Reconstruction:
    """What :func:`reconstruct` found: the frames, the data range it worked with, and each capture's record."""

    frames: np.ndarray
    #: The data range of the capture (:class:`codedvideo.model.units.DataRange`: value, how it was found).
    data_range: object
    #: Per capture: patches, atoms, seconds, the statistics the metrics JSON holds.
    info: list[dict] = field(default_factory=list)


def _layout(coded, mask) -> tuple[int, int, bool]:
    """(T, N, single): the captures' count and sub-frames, and whether ``coded`` is one (H, W) image."""
    if coded.ndim not in (2, 3) or mask.ndim not in (3, 4) or coded.shape[-2:] != mask.shape[-2:]:
        raise InputError(f"reconstruct: coded {tuple(coded.shape)} and mask {tuple(mask.shape)} do not fit: coded is "
                         "(H, W) or (T, H, W), the mask (N, H, W) or (T, N, H, W), of the same H and W")
    count = 1 if coded.ndim == 2 else coded.shape[0]
    if mask.ndim == 4 and mask.shape[0] != count:
        raise InputError(f"reconstruct: {count} coded images, {mask.shape[0]} masks")
    return count, mask.shape[-3], coded.ndim == 2


def _settings(options: dict, workers, noise_sigma: float, scale: float):
    """The ``reconstruct:`` model and OMP settings of a preset's resolved ``options`` (method, adapt, stride, ...)."""
    from codedvideo.engine.config import ReconstructConfig, omp_settings, validated

    method = options["method"]
    rc = validated(ReconstructConfig, dict(options, method=method if method in ("omp", "nonlocal") else "omp",
                                           workers=workers))
    return rc, omp_settings(rc, noise_sigma, scale=scale)


def _preset(preset: str | None, method: str | None, adapt: bool | None,
            adapt_rounds: int | None, refine: int | None = None) -> tuple[dict, dict | None]:
    """The options of ``preset`` with ``method``, ``adapt``, ``adapt_rounds`` and ``refine`` (None: not given) over
    them, and
    the preset's record (:func:`codedvideo.engine.config.preset_record`; a warning says what it left out)."""
    from codedvideo.engine.config import preset_record, resolve_preset

    given = {k: v for k, v in dict(method=method, adapt=adapt, adapt_rounds=adapt_rounds, refine=refine).items()
             if v is not None}
    options, left_out = resolve_preset(preset, given)
    return options, preset_record(preset, options, given, left_out)


def _dictionary(method: str, dictionary, frames: int) -> tuple[np.ndarray | None, str, str]:
    """(D, its key, its name) for the sparse methods; (None, "", "") for the others."""
    from codedvideo.data.shipped import check_dictionary

    if method not in ("omp", "nonlocal"):
        return None, "", ""
    if dictionary is None:
        from codedvideo.data import shipped

        D, name = load_dictionary(frames), str(shipped.path_for(frames))
    elif isinstance(dictionary, (str, Path)):
        from codedvideo.formats.store import load_dictionary as _load

        D, meta = _load(dictionary)
        check_dictionary(meta, frames, dictionary)
        name = str(dictionary)
    else:
        D, name = np.ascontiguousarray(dictionary, np.float32), "array"
        if D.ndim != 2 or D.shape[0] != frames * 49:
            raise InputError(f"reconstruct: dictionary of shape {D.shape}; N = {frames} needs ({frames * 49}, K)")
    return D, hashlib.sha256(D.tobytes()).hexdigest(), name


def reconstruct(coded, mask, *, dictionary=None, method: str | None = None, adapt: bool | None = None,
                adapt_rounds: int | None = None, refine: int | None = None, preset: str | None = None,
                noise_sigma: float | None = None, data_range: float | None = None,
                workers: int | None = None,
                progress: bool = False, cache: str | Path | None = None, independent_captures: bool = False,
                full_output: bool = False):
    """Coded image(s) -> their video, in the input's units: the command line's ``reconstruct``, on arrays.

    Parameters
    ----------
    coded : ndarray (H, W) for one capture, or (T, H, W) for a stream; or a dask array of either
    mask : ndarray (N, H, W), or (T, N, H, W) for a code per capture
    dictionary : ndarray (N*49, K), a path to a dictionary store, or None for the shipped one for N
    method : ``omp`` (the paper; the default), ``nonlocal``, or a baseline: ``dct``, ``thinout``, ``interp``,
        ``gaptv``
    adapt : adapt the dictionary to each capture's first result, then reconstruct again (default False)
    adapt_rounds : with ``adapt``, 2 adapts again to the second result and reconstructs a third time (default 1)
    refine : iterations of GAP with a low-rank prior on groups of similar patches after the result (default 0)
    preset : ``fast``, ``default`` or ``best``: named settings, as ``--preset``
        (:data:`codedvideo.engine.config.PRESETS`); ``method`` and ``adapt`` given beside it win, and a setting
        of the preset the method cannot take is left out with a warning
    noise_sigma : read noise in the input's units (sets the residual tolerance, and relaxes the refinement's steps to
        the measurements, as ``--noise-sigma`` does)
    data_range : the frames' peak value in the input's units; None: found from the values as the CLI does
    workers : threads (default: every core)
    progress : show a progress bar
    cache : None works in a temporary folder that is removed (nothing is left on disk); a path uses the
        resumable, verified cache of the command line there
    independent_captures : reconstruct each capture of a stream on its own (no still answers shared with
        neighbours, no join at boundaries)
    full_output : return a :class:`Reconstruction` (frames, data range, per-capture records)

    Returns
    -------
    frames : ndarray of shape (N, H, W) for one capture, (T*N, H, W) for a stream, float32 (a dask array
        for a dask input: lazy, one chunk per capture; its data range is found when it is called, and its
        captures are reconstructed each on its own, as with ``independent_captures``)

    Examples
    --------
    >>> mask = make_code("hitomi", (32, 32), frames=8, bump=2)
    >>> video = synthetic_scene(frames=8, size=(32, 32))
    >>> reconstruct(simulate(video, mask), mask).shape
    (8, 32, 32)
    """
    from codedvideo.model.units import capture_units

    options, record = _preset(preset, method, adapt, adapt_rounds, refine)
    method, adapt = options["method"], options["adapt"]
    if _is_dask(coded):
        return _reconstruct_lazy(coded, mask, dictionary=dictionary, method=method, adapt=adapt,
                                 adapt_rounds=options["adapt_rounds"], refine=options["refine"], preset=preset,
                                 noise_sigma=noise_sigma,
                                 data_range=data_range, workers=workers, cache=cache)
    coded = np.asarray(coded)
    mask = np.asarray(mask)
    count, n, single = _layout(coded, mask)
    codeds = [coded] if single else [coded[i] for i in range(count)]

    def mask_of(i):
        return mask[i] if mask.ndim == 4 else mask

    sigma = 0.0 if noise_sigma is None else float(noise_sigma)
    units = capture_units(codeds, mask_of, dtype=coded.dtype, given=data_range, noise_sigma=sigma,
                          where="reconstruct")
    rc, settings = _settings(options, workers, sigma, units.scale)
    D, key, name = _dictionary(method, dictionary, n)
    with contextlib.ExitStack() as stack:
        folder = cache if cache is not None else stack.enter_context(tempfile.TemporaryDirectory(prefix="codedvideo-"))
        from codedvideo.engine.captures import CaptureSettings, reconstruct_stream

        results = reconstruct_stream(CaptureSettings(method, data_range=units, noise_sigma=sigma, settings=settings,
                                                     dictionary=D, dictionary_key=key, dictionary_name=name,
                                                     where="reconstruct", tile=rc.tile, cache=folder, workers=workers,
                                                     progress=progress, adapt=adapt, adapt_rounds=rc.adapt_rounds,
                                                     refine=rc.refine),
                                     codeds, mask_of, join=not independent_captures, spill=folder)
        out = np.empty((count * n, *coded.shape[-2:]), np.float32)
        infos = []
        with contextlib.closing(results):
            for i, volume, info in results:
                out[i * n:(i + 1) * n] = np.asarray(volume)  # (a capture the join kept on disk: read back)
                infos.append(dict(info, preset=record) if record else info)
    return Reconstruction(out, units, infos) if full_output else out


def _is_dask(x) -> bool:
    return type(x).__module__.startswith("dask.")


def _one_capture(block, mask, index, options) -> np.ndarray:
    """A dask block of one coded image (1, H, W) -> its N frames (its own job, on the calling thread)."""
    i = index[0][0] if index else 0
    m = mask[i] if mask.ndim == 4 else mask
    return reconstruct(np.asarray(block)[0], m, independent_captures=True, **options)


def _reconstruct_lazy(coded, mask, *, dictionary, method, adapt, adapt_rounds, refine, preset, noise_sigma, data_range,
                      workers, cache):
    import dask.array as da

    from codedvideo.model.units import capture_units

    mask = np.asarray(mask)
    single = coded.ndim == 2
    stack = coded[None] if single else coded
    count, n, _ = _layout(stack, mask)
    if data_range is None:  # found once for the whole stream, as the command line finds it (reads the input)
        data_range = capture_units([np.asarray(stack[i]) for i in range(count)],
                                   lambda i: mask[i] if mask.ndim == 4 else mask,
                                   dtype=stack.dtype, noise_sigma=noise_sigma or 0.0, where="reconstruct").value
    if dictionary is None and method in ("omp", "nonlocal"):
        dictionary = load_dictionary(n)
    options = dict(dictionary=dictionary, method=method, adapt=adapt, adapt_rounds=adapt_rounds, refine=refine,
                   preset=preset, noise_sigma=noise_sigma,
                   data_range=data_range, workers=1 if workers is None else workers, cache=cache)
    stack = stack.rechunk((1, -1, -1))
    h, w = stack.shape[-2:]

    def block(b, block_info=None):
        where = block_info[0]["chunk-location"] if block_info else (0,)
        return _one_capture(b, mask, [where], options)

    return da.map_blocks(block, stack, chunks=((n,) * count, (h,), (w,)), dtype=np.float32,
                         meta=np.empty((0, 0, 0), np.float32))


def evaluate(recon, truth, *, data_range: float | None = None) -> dict:
    """PSNR and SSIM of a reconstruction against the truth, as the command line reports them.

    Parameters
    ----------
    recon, truth : ndarrays of shape (N, H, W) (or (T*N, H, W)), in the same units
    data_range : the frames' peak value; None: found from the truth's values (1 for [0, 1] floats, 255 for
        8-bit, ...), so the same video scores the same in any units

    Returns
    -------
    dict with ``psnr``, ``ssim`` (means over frames), ``psnr_per_frame``, ``ssim_per_frame``, ``data_range``
    and ``psnr_peak`` (the peak used and how it was found)

    >>> v = np.linspace(0, 1, 8 * 16 * 16, dtype=np.float32).reshape(8, 16, 16)
    >>> round(evaluate(v + 0.01, v)["psnr"], 1)
    40.0
    """
    from codedvideo.model.metrics import evaluate as _evaluate
    from codedvideo.model.units import truth_range

    recon, truth = np.asarray(recon, np.float32), np.asarray(truth, np.float32)
    if recon.shape != truth.shape:
        raise InputError(f"evaluate: reconstruction {recon.shape} and truth {truth.shape} differ in shape")
    units = truth_range(float(truth.max(initial=0.0)), given=data_range, where="evaluate: truth")
    return dict(_evaluate(recon, truth, data_range=units.value), psnr_peak=dict(value=units.value, source=units.source))
