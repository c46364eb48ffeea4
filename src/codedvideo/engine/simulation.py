"""Simulating coded captures of a video: the code drawn, the sensor's noise, one capture or a stream."""

from __future__ import annotations

import dataclasses
from collections.abc import Iterator

import numpy as np

from codedvideo.model import doors
from codedvideo.formats.volumes import load_code_file
from codedvideo.model import physics
from codedvideo.model.codes import CodeSpec, make_code
from codedvideo.model.errors import InputError


def simulate_capture(
    video: np.ndarray,
    *,
    code: CodeSpec,
    sigma: float,
    seed: int,
    sensor: physics.SensorModel | None = None,
    captures: int = 1,
    new_code_per_capture: bool = False,
) -> dict[str, np.ndarray]:
    """Coded capture(s) of a video: mask, coded image(s) (noisy) and the truth.

    Parameters
    ----------
    video : ndarray of shape (T * N, H, W)
        ``captures`` consecutive captures of N sub-frames each.
    code : CodeSpec
        The code (:func:`codedvideo.model.codes.make_code`; its ``path`` for ``file``): a :class:`CodeSpec`, or
        any object with its ``name``, ``bump``, ``p`` and ``path`` (pipeline.yaml's validated ``code:``).
    sigma : float
        Gaussian read noise, grey levels.
    seed : int
        Code and noise use independent streams spawned from it.
    sensor : SensorModel, optional
        Shot noise, quantisation and clipping; its ``read_sigma`` is replaced
        by ``sigma``.  None: read noise only.
    captures : int
        T, the number of coded images (a coded camera's stream).
    new_code_per_capture : bool
        A new code for every capture instead of the same code repeated (as a real sensor repeats its code).

    Returns
    -------
    dict with ``coded`` (H, W) float32 for one capture, else (T, H, W); ``mask``
    (N, H, W) uint8, or (T, N, H, W) with a new code per capture (or a code file
    of several codes, taken in turn); ``truth`` (T * N, H, W) float32
    """
    if captures < 1 or video.shape[0] % captures:
        raise InputError(f"video of {video.shape[0]} frames: not {captures} captures of equal length")
    n = video.shape[0] // captures
    stream = simulate_stream((video[t * n : (t + 1) * n] for t in range(captures)), code=code, sigma=sigma,
                             seed=seed, sensor=sensor, captures=captures, new_code_per_capture=new_code_per_capture)
    coded, masks = [], []
    for one, mask, _ in stream:
        coded.append(one)
        masks.append(mask)
    repeating = all(m is masks[0] for m in masks)  # the same code every capture (a real sensor's)
    return dict(coded=coded[0] if captures == 1 else np.stack(coded),
                mask=masks[0] if repeating else np.stack(masks), truth=np.asarray(video, np.float32))


def simulate_stream(clips, *, code: CodeSpec, sigma: float, seed: int, sensor: physics.SensorModel | None = None,
                    captures: int = 1, new_code_per_capture: bool = False,
                    codes: list | None = None) -> Iterator[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """:func:`simulate_capture` one capture at a time: ``clips`` yields the T clips (N, H, W) in order; yields
    ``(coded (H, W), mask (N, H, W), clip)`` for each, from the same seeded streams (the same captures bit for
    bit).  A repeating code is the same array every capture; a code file of K codes gives capture ``t`` its
    code ``t mod K``.  ``codes``: the masks themselves (the API's arrays), taken in turn as a code file's (then
    ``code`` only names them in messages)."""
    ss = np.random.SeedSequence(seed)
    code_rng, noise_rng = (np.random.default_rng(s) for s in ss.spawn(2))
    sensed = None if sensor is None else dataclasses.replace(sensor, read_sigma=sigma)
    masks = None if codes is None else list(codes)
    warned = False
    for t, clip in enumerate(clips):
        if masks is None:  # every code is drawn first, from its own stream
            masks = [load_code_file(code.path, frames=clip.shape[0], shape=clip.shape[1:]) if code.name == "file"
                     else make_code(code.name, clip.shape[1:], frames=clip.shape[0], bump=code.bump, p=code.p,
                                    rng=code_rng)
                     for _ in range(captures if new_code_per_capture else 1)]
            if masks[0].ndim == 4:  # a code file of one code per capture, in turn
                if new_code_per_capture:
                    raise InputError(f"code file {code.path}: holds {masks[0].shape[0]} codes, one per capture; "
                                     "a new code per capture does not apply")
                masks = list(masks[0])
            if not all(np.any(m) for m in masks):  # (a Bernoulli p of 1e-9, say): nothing would be measured
                p = f" (p = {code.p:g})" if code.name == "bernoulli" else ""
                raise InputError(f"code {code.name}{p}: opens no pixel in any sub-frame; nothing would be measured")
        mask = masks[t % len(masks)]
        # one noise stream, drawn capture after capture
        coded = (physics.simulate(clip, mask, sigma=sigma, rng=noise_rng) if sensed is None
                 else physics.simulate(clip, mask, rng=noise_rng, sensor=sensed))
        top = float(coded.max(initial=0.0))
        share = float(np.mean(coded >= top)) if sensed is not None and top > 0 else 0.0
        if share > 0.5 and not warned:  # the sensor's ceiling (full well / gain, white level, ADC) everywhere
            name = doors.name
            doors.warn(f"{share:.0%} of the pixels of capture {t + 1} are at the sensor's ceiling ({top:g}: the "
                       f"full well over the gain, {name('white_level')} or {name('bits')}): the capture is saturated; "
                       f"give the sensor settings in the video's units (a 16-bit video needs {name('gain')}, "
                       f"{name('full_well')}, {name('bits')})")
            warned = True
        yield coded, mask, clip


def sensor_model(noise) -> physics.SensorModel | None:
    """The :class:`~codedvideo.model.physics.SensorModel` of a ``NoiseConfig`` (None: read noise only)."""
    if not noise.shot_noise and noise.bits is None and noise.white_level is None and not noise.black_level:
        return None
    return physics.SensorModel(shot_noise=noise.shot_noise, full_well=noise.full_well, gain=noise.gain,
                               read_sigma=noise.sigma, bits=noise.bits, white_level=noise.white_level,
                               black_level=noise.black_level)
