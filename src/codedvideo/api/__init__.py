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
import functools
import tempfile
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from codedvideo.model import doors
from codedvideo.model.physics import SensorModel
from codedvideo.api._settings import ReconstructSettings
from codedvideo.model.errors import CodedVideoError, ConfigError, InputError
from codedvideo.solvers.dictionaries import KSVD_ATOMS, KSVD_ITERATIONS, KSVD_SAMPLES, KSVD_SPARSITY

__all__ = ["CodedVideoError", "ConfigError", "InputError", "Reconstruction", "ReconstructSettings", "SensorModel",
           "evaluate", "load_dictionary", "make_code", "reconstruct", "simulate", "synthetic_scene", "train"]


def _door(fn):
    """A public function of the API: its warnings and errors name the API's arguments (``noise_sigma``), not the
    command line's options (``--noise-sigma``), and each warning is said when it happens, at the caller's line
    (:mod:`codedvideo.model.doors`)."""

    @functools.wraps(fn)
    def called(*args, **kwargs):
        with doors.through("api"):
            return fn(*args, **kwargs)

    return called


def _check_seed(seed) -> None:
    """A seed as the command line's ``--seed`` takes it (pipeline.yaml's ``seed``), or a ConfigError naming it."""
    from codedvideo.engine.config import PipelineConfig, validated

    validated(PipelineConfig, dict(seed=seed), {"seed": "seed"})


@_door
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
    from codedvideo.engine.config import CodeConfig, validated
    from codedvideo.model.codes import CODE_NAMES, make_code as _make_code

    if name == "file":
        raise ConfigError("make_code: 'file' reads a mask file; load the mask with numpy instead")
    options = {k: v for k, v in dict(bump=bump, p=p).items() if v is not None}
    _check_seed(seed)
    if name in CODE_NAMES:  # (another name: the code's own message, naming the codes there are)
        validated(CodeConfig, dict(name=name, **options), {"bump": "bump", "p": "p"})  # the rules of --bump, --p
    return _make_code(name, tuple(shape), frames=frames, rng=seed, **options)


@_door
def simulate(video: np.ndarray, mask: np.ndarray, *, noise_sigma: float = 0.0,
             sensor: SensorModel | Mapping | None = None, seed: int = 0) -> np.ndarray:
    """The coded image(s) a camera with this code records: ``sensor(noise(S E))``, the command line's
    ``simulate`` on arrays (the same sensor model, options and seeded noise: the same bits).

    Parameters
    ----------
    video : ndarray of shape (N, H, W), or (T*N, H, W) for a stream of T captures, finite
    mask : ndarray of shape (N, H, W) (one code for every capture) or (T, N, H, W), in [0, 1]
    noise_sigma : float
        Gaussian read noise, in the video's units.
    sensor : SensorModel or mapping, optional
        The sensor's read-out beyond the read noise: a :class:`SensorModel` (its ``read_sigma`` left at 0: the
        read noise is ``noise_sigma``) or a mapping of some of its fields (``dict(bits=12)``), checked as the
        command line's options:

        - ``shot_noise``: Poisson photon noise (``full_well`` electrons, ``gain`` electrons per grey level;
          those two only with it; None or not given: the defaults of :class:`SensorModel`);
        - ``bits``: quantise the coded image to this many bits (values at ``2**bits - 1`` and above
          clipped); no noise added.  With ``white_level`` the ``2**bits`` levels span ``[0, white_level]``
          in the video's units (an ADC of that full scale), so the values are not raw counts;
        - ``white_level``: clip the coded image at this level (saturation);
        - ``black_level``: raw output, this offset added once per read-out (then clipping and quantisation).

        None: read noise only.
    seed : int
        The noise's seed (as ``--seed``).

    Returns
    -------
    coded : ndarray of shape (H, W), or (T, H, W) for a stream, float32

    Examples
    --------
    >>> mask = make_code("global", (4, 4), frames=2)
    >>> simulate(np.ones((2, 4, 4)), mask)[0, 0]
    np.float32(2.0)
    """
    from codedvideo.engine.config import NoiseConfig, validated
    from codedvideo.engine.simulation import sensor_model, simulate_stream
    from codedvideo.formats.volumes import check_coded, check_mask
    from codedvideo.model.codes import CodeSpec

    frames = check_coded(video, "simulate: video", unit="frame")
    masks = np.asarray(mask)
    n = masks.shape[-3] if masks.ndim in (3, 4) else 0
    if frames.ndim != 3 or not n or frames.shape[0] % n or frames.shape[1:] != masks.shape[-2:]:
        raise InputError(f"simulate: video {frames.shape} and mask {masks.shape} do not fit: the video is (N, H, W) "
                         "or (T*N, H, W), the mask (N, H, W) or (T, N, H, W)")
    count = frames.shape[0] // n
    if masks.ndim == 4 and masks.shape[0] != count:
        raise InputError(f"simulate: {count} captures in the video, {masks.shape[0]} masks")
    codes = [check_mask(m, "simulate: mask") for m in (masks if masks.ndim == 4 else [masks])]
    noise = validated(NoiseConfig, dict(sigma=noise_sigma, **_sensor_fields(sensor)),
                      {"sigma": "noise_sigma", **{k: k for k in ("shot_noise", "full_well", "gain", "bits")}})
    _check_seed(seed)
    stream = simulate_stream((frames[i * n:(i + 1) * n] for i in range(count)), code=CodeSpec("array", 0),
                             sigma=noise.sigma, seed=seed, sensor=sensor_model(noise), captures=count, codes=codes)
    coded = [one for one, _, _ in stream]
    return coded[0] if count == 1 and masks.ndim == 3 else np.stack(coded)


#: The fields of a :class:`SensorModel` that ``simulate``'s ``sensor`` takes (its read noise is ``noise_sigma``).
_SENSOR_FIELDS = ("shot_noise", "full_well", "gain", "bits", "white_level", "black_level")


def _sensor_fields(sensor) -> dict:
    """``simulate``'s ``sensor`` as the keys of its ``NoiseConfig`` (those given; None: none), or a ConfigError."""
    if sensor is None:
        return {}
    if isinstance(sensor, SensorModel):
        if sensor.read_sigma:
            raise ConfigError(f"sensor: read_sigma {sensor.read_sigma:g}: give the read noise as noise_sigma")
        return {k: getattr(sensor, k) for k in _SENSOR_FIELDS}
    if not isinstance(sensor, Mapping):
        raise ConfigError(f"sensor: a SensorModel or a mapping of its fields ({', '.join(_SENSOR_FIELDS)}), got "
                          f"{type(sensor).__name__}")
    unknown = [k for k in sensor if k not in _SENSOR_FIELDS]
    if unknown:
        raise ConfigError(f"sensor: unknown key {unknown[0]!r}; the keys are {', '.join(_SENSOR_FIELDS)} (the read "
                          "noise is noise_sigma)")
    return {k: v for k, v in sensor.items() if v is not None or k not in ("full_well", "gain")}  # (None: the default)


@_door
def synthetic_scene(name: str = "default", *, frames: int = 8, size: tuple[int, int] = (256, 256)) -> np.ndarray:
    """A synthetic test scene (``synth:NAME`` of the command line) as (N, H, W) float32 in 0..255.

    >>> synthetic_scene(frames=4, size=(16, 16)).shape
    (4, 16, 16)
    """
    from codedvideo.data.synth import make_scene

    return make_scene(name, frames=frames, size=tuple(size))


@_door
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


@_door
def train(videos, *, frames: int, atoms: int = KSVD_ATOMS, samples: int = KSVD_SAMPLES,
          iterations: int = KSVD_ITERATIONS, sparsity: int = KSVD_SPARSITY, seed: int = 0,
          augment: bool = True) -> np.ndarray:
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

    # the settings checked as the command line's and pipeline.yaml's are, before any work (atoms below sparsity,
    # samples too few for the atoms...)
    cfg = plan_training(frames=frames, dictionary=dict(atoms=atoms, samples=samples, iterations=iterations,
                                                       sparsity=sparsity, augment=augment), seed=seed, door="api")
    clips = [working_units(np.array(v, np.float32), what=f"training video {i + 1}") for i, v in enumerate(videos)]
    if not clips:
        raise InputError("train: no training video given")
    D, _ = learn_dictionary(clips, frames=frames, seed=seed, settings=cfg.dictionary.ksvd())
    return D


@dataclass
class Reconstruction:
    """What :func:`reconstruct` found: the frames, the data range it worked with, each capture's record, and the
    whole record (the command line's metrics JSON, without its file names)."""

    frames: np.ndarray
    #: The data range of the capture (:class:`codedvideo.model.units.DataRange`: value, how it was found).
    data_range: object
    #: Per capture: patches, atoms, seconds, the statistics the metrics JSON holds.
    info: list[dict] = field(default_factory=list)
    #: The metrics record: settings, data range, preset, each capture's entry, and the quality with a truth.
    record: dict = field(default_factory=dict)


@_door
def reconstruct(coded, mask, settings: ReconstructSettings | None = None, *, truth=None, full_output: bool = False,
                **options):
    """Coded image(s) -> their video, in the input's units: the command line's ``reconstruct``, on arrays.

    Parameters
    ----------
    coded : ndarray (H, W) for one capture, or (T, H, W) for a stream; or a dask array of either
    mask : ndarray (N, H, W), or (T, N, H, W) for a code per capture, in [0, 1] (0/1, or calibrated weights)
    settings : :class:`ReconstructSettings`, optional
        Every setting in one object; ``options`` given beside it replace its fields.
    truth : ndarray (T*N, H, W), optional
        The true frames: the record then holds PSNR and SSIM (``full_output``).
    full_output : return a :class:`Reconstruction` (frames, data range, per-capture records, the record)
    **options
        Fields of :class:`ReconstructSettings`, e.g. ``method`` (``omp``, the paper's and the default;
        ``nonlocal``; or a baseline: ``dct``, ``thinout``, ``interp``, ``gaptv``), ``preset`` (``fast``,
        ``default``, ``best``), ``adapt``, ``adapt_rounds``, ``refine``, ``dictionary`` (an (N*49, K) array or a
        store's path; None: the one shipped for N), ``noise_sigma`` (read noise in the input's units),
        ``data_range`` (the frames' peak value; None: found from the values as the command line finds it),
        ``white_level``, ``black_level``, ``bits``, ``bad_pixels`` (a file as ``--bad-pixels`` reads, or an array of
        (y, x) rows or a boolean map), ``bayer``, ``workers``, ``progress``,
        ``cache`` (None: a temporary folder, removed; a path: the resumable cache of the command line there) and
        ``independent_captures`` (reconstruct each capture of a stream on its own).

    Returns
    -------
    frames : ndarray of shape (N, H, W) for one capture, (T*N, H, W) for a stream, (3, N, H, W) for a Bayer
        mosaic, float32.  For a dask input a dask array, lazy (nothing is read or computed until it is), one
        chunk per capture, the same frames as the numpy stack's: the stream is reconstructed as one job.

    Raises
    ------
    codedvideo.InputError
        The same one-line messages as the command line: NaN or Inf, a mask outside [0, 1], shapes that do
        not fit.

    Examples
    --------
    >>> mask = make_code("hitomi", (32, 32), frames=8, bump=2)
    >>> video = synthetic_scene(frames=8, size=(32, 32))
    >>> reconstruct(simulate(video, mask), mask).shape
    (8, 32, 32)
    """
    chosen = replaced(settings or ReconstructSettings(), **options)
    if _is_dask(coded):
        if full_output or truth is not None:
            raise ConfigError("reconstruct: a dask input gives a lazy array of frames; full_output and truth "
                              "need numpy arrays")
        return _reconstruct_lazy(coded, mask, chosen)
    return _reconstruct_arrays(coded, mask, chosen, truth=truth, full_output=full_output)


def _reconstruct_arrays(coded, mask, settings, *, truth=None, full_output=False):
    from codedvideo.api._job import array_captures
    from codedvideo.api._settings import resolve

    resolved = resolve(settings, door="api")
    captures, single = array_captures(coded, mask, truth, bayer=settings.bayer)
    job = ReconstructionJob(captures, resolved)
    out = np.empty(job.shape, np.float32)
    n = job.n
    with contextlib.ExitStack() as stack:
        folder = settings.cache if settings.cache is not None else \
            stack.enter_context(tempfile.TemporaryDirectory(prefix="codedvideo-"))
        for i, volume, _ in job.run(folder):
            out[slice(None) if captures.kind == "bayer" else slice(i * n, (i + 1) * n)] = np.asarray(volume)
    record = job_record(job)
    if not full_output:
        return out
    infos = [dict(e["reconstruction"], preset=resolved.preset) if resolved.preset else e["reconstruction"]
             for e in job.entries]
    return Reconstruction(out, job.units, infos, record)


def _is_dask(x) -> bool:
    return type(x).__module__.startswith("dask.")


@_door
@_door
def _stream_frames(stack: np.ndarray, mask: np.ndarray, settings) -> np.ndarray:
    """A dask stream's frames, computed when the graph is (on whichever thread dask runs it): the numpy stack's,
    as one job, its warnings and errors in the API's terms as the numpy path's are (the door is set again there:
    the call that built the graph has returned)."""
    return _reconstruct_arrays(stack, mask, settings)


def _reconstruct_lazy(coded, mask, settings):
    """A lazy dask array of the frames: one task reconstructs the stream as the numpy path does (its data range,
    still answers, cuts and joins across captures), and each capture's frames are a chunk of it."""
    import dask
    import dask.array as da

    from codedvideo.api._settings import resolve

    resolve(settings, door="api")  # the settings checked now; the values when the graph is computed
    from codedvideo.api._job import check_fit

    masks = np.asarray(mask)
    count, n = check_fit(coded.shape, masks.shape, "reconstruct")
    stack = coded[None] if coded.ndim == 2 else coded
    h, w = stack.shape[-2:]
    if settings.bayer is not None:  # one mosaic: its colour video (3, N, H, W), one chunk
        if coded.ndim != 2:
            raise InputError(f"reconstruct: coded {tuple(coded.shape)}; under bayer= it is one single-channel "
                             "mosaic (H, W)")
        whole = dask.delayed(_stream_frames, pure=True)(coded, masks, settings)
        return da.from_delayed(whole, shape=(3, n, h, w), dtype=np.float32, meta=np.empty((0, 0, 0, 0), np.float32))
    whole = dask.delayed(_stream_frames, pure=True)(stack, masks, settings)
    parts = [da.from_delayed(whole[i * n:(i + 1) * n], shape=(n, h, w), dtype=np.float32,
                             meta=np.empty((0, 0, 0), np.float32)) for i in range(count)]
    return da.concatenate(parts) if count > 1 else parts[0]


@_door
def evaluate(recon, truth, *, data_range: float | None = None) -> dict:
    """PSNR and SSIM of a reconstruction against the truth, as the command line reports them.

    Parameters
    ----------
    recon, truth : ndarrays of shape (N, H, W) (or (T*N, H, W)), in the same units; or colour (C, N, H, W), every
        channel's frames scored (colour against grey: the colour one's luma, with a warning)
    data_range : the frames' peak value; None: found from the truth's values (1 for [0, 1] floats, 255 for
        8-bit, ...), so the same video scores the same in any units

    Returns
    -------
    dict with ``psnr``, ``ssim`` (means over frames), ``psnr_per_frame``, ``ssim_per_frame``, ``data_range``,
    ``data_range_source`` and ``psnr_peak`` (the peak used and how it was found)

    >>> v = np.linspace(0, 1, 8 * 16 * 16, dtype=np.float32).reshape(8, 16, 16)
    >>> round(evaluate(v + 0.01, v)["psnr"], 1)
    40.0
    """
    from codedvideo.engine.config import OutputConfig, validated

    validated(OutputConfig, dict(data_range=data_range), {"data_range": "data_range"})  # as the command line checks it
    frames, reference = (v if hasattr(v, "shape") else np.asarray(v, np.float32) for v in (recon, truth))
    return scores(*as_scored(frames, reference), data_range=data_range)


def shipped_frames() -> list[int]:
    """The N for which a dictionary is shipped with the package."""
    from codedvideo.data import shipped

    return shipped.available()


def missing_frame_question(frames: int) -> str:
    """Whether a mask of ``frames`` sub-frames lost one (a dictionary is shipped for one or two more), as a
    question to add to a message; empty otherwise."""
    from codedvideo.data import shipped

    return shipped.missing_frame_question(frames)


def truth_data_range(truth, *, data_range: float | None = None, where: str = "truth"):
    """The data range a reconstruction is scored against (:class:`codedvideo.model.units.DataRange`): the one
    given, or found from the truth's peak (so the same video scores the same in any float scale)."""
    from codedvideo.model.metrics import volume_peak
    from codedvideo.model.units import truth_range

    return truth_range(volume_peak(truth), given=data_range, where=f"evaluate: {where}")


def as_scored(recon, truth, *, names: tuple[str, str] = ("reconstruction", "truth")):
    """A reconstruction and its truth as frames to score: colour (C, N, H, W) against colour, every channel's
    frames; colour against grey, the colour one's luma (warned, ``names`` the two); grey as it is."""
    from codedvideo.formats.io import LUMA

    pair = (recon, truth)
    if len(truth.shape) != len(recon.shape) and 4 in (len(truth.shape), len(recon.shape)):  # colour against grey
        colour, grey = names if len(recon.shape) == 4 else names[::-1]
        doors.warn(f"evaluate: {colour} is colour and {grey} grey; compared as luma")
        pair = tuple(np.tensordot(LUMA, np.asarray(v, np.float32), axes=([0], [0])) if len(v.shape) == 4 else v
                     for v in pair)
    if len(pair[1].shape) == 4 and tuple(pair[0].shape) == tuple(pair[1].shape):  # colour: every channel's frames
        pair = tuple(v.reshape(-1, *v.shape[-2:]) for v in pair)
    return pair


def scores(recon, truth, *, data_range: float | None = None, names: tuple[str, str] = ("reconstruction", "truth"),
           **extra) -> dict:
    """:func:`evaluate` on volumes or lazy stacks (anything with ``shape`` and slices of consecutive frames),
    compared a block of frames at a time; ``names``: what the two are called in messages (their files);
    ``extra``: more keys for the result.  Warns when the two do not look like the same units."""
    from codedvideo.model.metrics import evaluate as _evaluate, json_safe, other_units, volume_peak

    frames = recon if hasattr(recon, "shape") else np.asarray(recon, np.float32)
    reference = truth if hasattr(truth, "shape") else np.asarray(truth, np.float32)
    if tuple(frames.shape) != tuple(reference.shape):
        raise InputError(f"evaluate: reconstruction {tuple(frames.shape)} and truth {tuple(reference.shape)} differ "
                         "in shape")
    units = truth_data_range(reference, data_range=data_range, where=names[1])
    peak, recon_peak = units.peak, volume_peak(frames)
    # another unit: a score that means nothing; against the truth's own peak, not its range (a dark scene's
    # reconstruction peaks as far below 255 as its truth does)
    if other_units(peak, recon_peak):
        doors.warn(f"evaluate: {names[0]} peaks at {recon_peak:.4g} and {names[1]} at {peak:.4g} (data range "
                      f"{units.value:g}, {units.source}); are they in the same units? (a [0, 1] reconstruction "
                      "against 8-bit truth scores about 10 dB)")
    return json_safe(dict(_evaluate(frames, reference, data_range=units.value), data_range_source=units.source,
                          psnr_peak=dict(value=units.value, source=units.source), **extra))


from codedvideo.api._job import Captures, ReconstructionJob  # noqa: E402, F401  (the job the command line runs)
from codedvideo.api._record import job_record  # noqa: E402, F401  (its metrics record)
from codedvideo.formats.volumes import read_scored  # noqa: E402, F401  (a reconstruction or truth as evaluate reads it)
from codedvideo.api._settings import Resolved, replaced, resolve as resolve_settings  # noqa: E402, F401
from codedvideo.api._simulate import (SimulateSettings, SimulationPlan, captures_of, plan_simulation,  # noqa: E402, F401
                                     simulate_captures, simulate_whole)
from codedvideo.api._train import TRAINING_KEYS, plan_training, train_dictionary  # noqa: E402, F401
from codedvideo.api._pipeline import run_pipeline, run_settings  # noqa: E402, F401
from codedvideo.api.cache import clean_cache, verify_cache  # noqa: E402, F401  (codedvideo cache)
from codedvideo.engine.bayer import PATTERNS as BAYER_PATTERNS  # noqa: E402, F401  (the Bayer patterns bayer= takes)
from codedvideo.engine.methods import METHOD_NAMES, REGISTRY as METHODS  # noqa: E402, F401  (the methods, by name)
