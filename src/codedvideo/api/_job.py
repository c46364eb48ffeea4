"""The one reconstruction job: captures and settings in, frames and their records out.

Both doors run it: :func:`codedvideo.reconstruct` on arrays, and ``codedvideo reconstruct`` on what it read
from files.  The job checks the inputs, corrects raw frames, resolves the dictionary, finds the data range,
reconstructs one capture after another (a stream joined at its boundaries), scores each against the truth
when one is given, and builds the metrics record the command line writes beside its output.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import hashlib
import os
import time
from pathlib import Path

import numpy as np

from codedvideo.model import doors, physics
from codedvideo.api._record import Scores
from codedvideo.api._settings import Resolved, for_noise, setting_name
from codedvideo.solvers.guard import coarse_lattice, sparse_weight
from codedvideo.engine.bayer import check_even, reconstruct_bayer, static_estimate
from codedvideo.engine.captures import CaptureSettings, reconstruct_stream, result_recipe
from codedvideo.engine.methods import SPARSE, WITH_DICTIONARY
from codedvideo.engine.windows import cache_room
from codedvideo.engine.config import omp_settings
from codedvideo.formats.volumes import check_coded, check_mask
from codedvideo.model.codes import short_of_the_truth
from codedvideo.model.errors import InputError
from codedvideo.model.metrics import (IMPLAUSIBLE_SHARE, mean_psnr, mse_psnr, other_units,
                                     volume_extremes, volume_peak)
from codedvideo.model.patches import PATCH
from codedvideo.model.units import capture_units, tolerance_warning

#: The kinds of job: one coded image, a coded camera's stream, a benchmark file's measurements, a colour
#: image's channels (each with the same mask), or one Bayer mosaic.
KINDS = ("single", "captures", "measurements", "channels", "bayer")


@dataclasses.dataclass
class Captures:
    """What a job reconstructs: coded images in the capture's units, and their masks.

    ``codeds`` is a sequence of T coded images (H, W) (a list, an array, or a reader that reads an image when
    asked); ``masks`` one mask shared by all, or one per image; ``truths`` the truth frames or None; ``labels``
    one dict per image for the records (``capture``, ``measurement``, ``channel``); ``inputs`` what the record
    says they were read from; ``dtype`` the type they were stored in (8-bit integers are 0..255 whatever
    they hold); ``source`` their name in messages.
    """

    codeds: object
    masks: list
    truths: object = None
    labels: list | None = None
    kind: str = "single"
    inputs: dict = dataclasses.field(default_factory=dict)
    dtype: object = None
    source: str = "coded image"

    def __post_init__(self):
        if self.kind not in KINDS:
            raise InputError(f"captures: kind {self.kind!r}; one of {', '.join(KINDS)}")
        if self.kind == "bayer":  # whole 2x2 cells of the mosaic
            check_even(self.codeds[0].shape, self.source)
        if self.labels is None:
            count = len(self.codeds)
            self.labels = [{}] if self.kind in ("single", "bayer") else \
                [{self.kind[:-1] if self.kind != "captures" else "capture": i + 1} for i in range(count)]

    def mask(self, i: int) -> np.ndarray:
        return self.masks[i % len(self.masks)]

    def truth(self, i: int):
        """Capture ``i``'s truth, or None: none given, or a stream's truth that ends before it (a CACTI file's
        ``orig`` covers its first measurements only)."""
        if self.truths is None:
            return None
        n = self.mask(i).shape[0]
        if self.kind == "bayer":  # one mosaic, its colour truth (3, N, H, W)
            return self.truths
        if self.kind == "channels":
            return self.truths[i]
        return self.truths[i * n : (i + 1) * n] if len(self.truths) >= (i + 1) * n else None


def check_fit(coded_shape: tuple, mask_shape: tuple, where: str) -> tuple[int, int]:
    """``(T, N)`` of coded images of ``coded_shape`` ((H, W) or (T, H, W)) under masks of ``mask_shape`` ((N, H, W)
    for every capture, (T, N, H, W) one each, or (1, N, H, W) shared, as read); a one-line :class:`InputError`
    naming both shapes where they do not fit."""
    if len(coded_shape) not in (2, 3) or len(mask_shape) not in (3, 4) or \
            tuple(coded_shape[-2:]) != tuple(mask_shape[-2:]):
        raise InputError(f"{where}: coded {tuple(coded_shape)} and mask {tuple(mask_shape)} do not fit: coded is "
                         "(H, W) or (T, H, W), the mask (N, H, W) or (T, N, H, W), of the same H and W")
    count = 1 if len(coded_shape) == 2 else coded_shape[0]
    if len(mask_shape) == 4 and mask_shape[0] not in (1, count):
        raise InputError(f"{where}: {count} coded images, {mask_shape[0]} masks")
    return count, mask_shape[-3]


def array_captures(coded, mask, truth=None, *, bayer: str | None = None,
                   where: str = "reconstruct") -> tuple[Captures, bool]:
    """Arrays as the API takes them -> (:class:`Captures`, whether ``coded`` was one (H, W) image), checked as the
    command line checks what it reads: finite numbers, masks in [0, 1] (the same one-line messages).  With
    ``bayer``, ``coded`` is one mosaic (H, W) and ``truth`` its colour video (3, N, H, W)."""
    if bayer is not None:
        return _bayer_captures(coded, mask, truth, bayer, where), True
    dtype = np.asarray(coded).dtype if hasattr(coded, "dtype") else None
    image = check_coded(coded, f"{where}: coded")
    given = np.asarray(mask)
    check_fit(image.shape, given.shape, where)
    single = image.ndim == 2
    codeds = image[None] if single else image
    masks = [check_mask(m, f"{where}: mask") for m in (given if given.ndim == 4 else [given])]
    truths = None
    if truth is not None:
        truths = check_coded(truth, f"{where}: truth", unit="frame")
        want = (len(codeds) * masks[0].shape[0], *codeds.shape[-2:])
        if truths.shape != want:
            per_capture = truths.shape[0] // len(codeds) if truths.shape[0] % len(codeds) == 0 else 0
            raise InputError(f"{where}: truth {truths.shape} != (T*N, H, W) {want}"
                             + short_of_the_truth(masks[0].shape[0], per_capture))
    kind = "single" if single else "captures"
    return Captures(codeds=codeds, masks=masks, truths=truths, kind=kind, dtype=dtype, source=f"{where}: coded"), \
        single


def _bayer_captures(coded, mask, truth, pattern: str, where: str) -> Captures:
    dtype = np.asarray(coded).dtype
    mosaic = check_coded(coded, f"{where}: coded")
    if mosaic.ndim != 2:
        raise InputError(f"{where}: coded {mosaic.shape}; under bayer= it is one single-channel mosaic (H, W)")
    code = check_mask(mask, f"{where}: mask")
    if code.ndim != 3 or code.shape[-2:] != mosaic.shape:
        raise InputError(f"{where}: coded {mosaic.shape} and mask {code.shape} do not fit: the mask is (N, H, W)")
    truths = None
    if truth is not None:
        truths = check_coded(truth, f"{where}: truth", unit="colour channel")
        if truths.shape != (3, *code.shape):
            raise InputError(f"{where}: truth {truths.shape} != (3, N, H, W) {(3, *code.shape)} (the colour video, "
                             "under bayer=)")
    return Captures(codeds=mosaic[None], masks=[code], truths=truths, kind="bayer", dtype=dtype,
                    source=f"{where}: coded")


class _Lazy:
    """``len`` and ``[i]`` over ``get(i)``: a sequence computed item by item."""

    def __init__(self, count: int, get):
        self._count, self._get = count, get

    def __len__(self) -> int:
        return self._count

    def __getitem__(self, i: int):
        if not -self._count <= i < self._count:
            raise IndexError(i)
        return self._get(i % self._count)


class _RawCorrected:
    """Captures corrected as raw frames one at a time (:func:`correct_raw`): ``coded(i)``, ``mask(i)``,
    ``counts(i)``; the last few are kept, never the stream."""

    def __init__(self, codeds, mask_of, correct, found):
        self._codeds, self._mask_of, self._correct, self.found = codeds, mask_of, correct, found
        self._get = functools.lru_cache(maxsize=4)(self._fix)  # the neighbours a still test and a join ask for

    def _fix(self, i: int):
        from codedvideo.model.sensor import drop_pixels

        fixed = self._correct(self._codeds[i], self._mask_of(i), i)
        coded, mask, counts = fixed.coded, fixed.mask, fixed.counts()
        if self.found is not None:
            coded, mask, counts["detected_bad_pixels"] = drop_pixels(coded, mask, self.found)
        return coded, mask, counts

    def coded(self, i: int) -> np.ndarray:
        return self._get(i)[0]

    def mask(self, i: int) -> np.ndarray:
        return self._get(i)[1]

    def counts(self, i: int) -> dict:
        return self._get(i)[2]


def correct_raw(r: Resolved, job: Captures) -> _Lazy | None:
    """Raw frames to the sum convention (``codedvideo.model.sensor``): the black level subtracted, pixels at the
    bit depth's white level (or the white level given) and defective pixels made missing measurements.
    Changes ``job`` in place, each capture corrected when it is read (a stream is not held whole: detecting
    bad pixels reads it once more first, to vote); returns each image's counts (None: no raw setting)."""
    noise = r.noise
    if not (noise.black_level or noise.bits is not None or r.bad_pixels is not None or r.detect_bad_pixels):
        return None
    from codedvideo.model.sensor import bad_pixel_array, correct_raw as correct_frames, read_bad_pixels, vote_bad_pixels

    count = len(job.labels)
    shape = tuple(job.mask(0).shape[-2:])
    listed = None if r.bad_pixels is None else read_bad_pixels(r.bad_pixels, shape) \
        if isinstance(r.bad_pixels, (str, os.PathLike)) else bad_pixel_array(r.bad_pixels, shape, "bad_pixels")

    files = getattr(job.codeds, "files", None)  # (a folder of images: each capture its file)

    def correct(coded, mask, i):  # (an error names the capture of a stack: one flash must not read as all)
        where = job.source if count == 1 else f"{job.source}, capture {i + 1} of {count}" + \
            (f" ({Path(files[i]).name})" if files is not None and i < len(files) else "")
        return correct_frames(coded, mask, levels=noise, bad_pixels=listed, trust_saturated=r.trust_saturated,
                              where=where)

    codeds, masks = job.codeds, job.masks  # as read (job's own accessors are replaced below)

    def mask_of(i: int) -> np.ndarray:
        return masks[i % len(masks)]

    found = None
    if r.detect_bad_pixels:  # outliers against their neighbourhood, voted across every image
        fixed = (correct(codeds[i], mask_of(i), i) for i in range(count))
        found = vote_bad_pixels(((f.coded, f.mask) for f in fixed), count)  # (one capture: a vote of one, as ever)
    raw = _RawCorrected(codeds, mask_of, correct, found)
    job.codeds, job.masks = _Lazy(count, raw.coded), _Lazy(count, raw.mask)
    return _Lazy(count, raw.counts)


def _clipped_at_type_maximum(captures: Captures, door: str) -> float | None:
    """The white level of integer captures clipped at their type's largest value (said in a warning), or None."""
    from codedvideo.model.units import integer_clipping

    found = integer_clipping(captures.codeds, captures.mask, captures.dtype)
    if found is None:
        return None
    level, held, measured = found
    doors.warn(f"{captures.source}: {held} of {measured} measured pixels ({held / measured:.1%}) hold {level:g}, "
                  f"the largest value of {np.dtype(captures.dtype).name}: clipped by the sensor; they are kept as "
                  f"measurements of at least {level:g} ({setting_name('white_level', door)} sets another level, "
                  f"{setting_name('trust_saturated', door)} takes them as exact)")
    return level


def job_dictionary(r: Resolved, frames: int, one_pattern=lambda: False) -> tuple[np.ndarray | None, str, str]:
    """(D, its key, its name) of the job's method: the dictionary given (an array or a store's path) or the one
    shipped for N; (None, "", "") for a method without one.  ``one_pattern()``: whether every capture's code opens
    every pixel alike (a global shutter, N = 1), solved by the static estimate: with none shipped for N, no
    dictionary is needed (the 3D DCT stands in, never used; no name)."""
    from codedvideo.data import shipped
    from codedvideo.formats.store import check_dictionary, load_dictionary

    if r.method not in WITH_DICTIONARY:
        return None, "", ""
    given = r.dictionary
    if given is None and shipped.verified(frames) is None and one_pattern():
        from codedvideo.solvers.dictionaries import dct_dictionary

        return dct_dictionary(frames), "", ""
    if given is None or isinstance(given, (str, Path)):
        path = given or shipped.required(frames, "reconstruct", f"`{shipped.train_command(frames)}` and give "
                                         f"{doors.name('dictionary')} dict-N{frames}.zarr")
        D, meta = load_dictionary(path)
        check_dictionary(meta, frames, path, D)
        return D, meta.get("sha256", ""), str(path)
    D = np.ascontiguousarray(given, np.float32)
    if D.ndim != 2 or D.shape[0] != frames * PATCH * PATCH:
        raise InputError(f"reconstruct: dictionary of shape {D.shape}; N = {frames} needs "
                         f"({frames * PATCH * PATCH}, K)")
    if not np.isfinite(D).all():
        raise InputError("reconstruct: dictionary: contains NaN or Inf")
    return D, hashlib.sha256(D.tobytes()).hexdigest(), "array"


class ReconstructionJob:
    """One reconstruction: iterate it for ``(i, frames, entry)``, capture after capture, in order; then
    :func:`codedvideo.api._record.job_record` is its metrics record (the command line's ``.metrics.json``).

    Everything a run needs is checked and found when the job is made, before any reconstruction: the raw
    correction, the dictionary, the data range (with its warnings) and the OMP settings.
    """

    def __init__(self, captures: Captures, resolved: Resolved):
        t0 = time.perf_counter()
        self.captures, self.r = captures, resolved
        self.count, self.n = len(captures.labels), captures.mask(0).shape[0]
        self.raw = correct_raw(resolved, captures)  # black level, bit depth, bad pixels: before the data range
        self.dictionary, self.dictionary_key, self.dictionary_name = job_dictionary(
            resolved, self.n, lambda: all((m == m[:, :1, :1]).all() for m in map(np.asarray, captures.masks)))
        if self.dictionary_name and self.dictionary_name != "array":
            captures.inputs["dictionary"] = self.dictionary_name
        noise, rc = resolved.noise, resolved.rc
        self.white = None if resolved.trust_saturated or self.raw else noise.white_level
        door = resolved.door
        if self.white is None and not (resolved.trust_saturated or self.raw):
            self.white = _clipped_at_type_maximum(captures, door)
        self.units = capture_units(
            captures.codeds, captures.mask, dtype=captures.dtype, given=resolved.data_range, white_level=self.white,
            where=captures.source,
            levels=dict(noise_sigma=noise.sigma, tol_rms=rc.tol_rms if rc.tol_rms != "auto" else None,
                        white_level=noise.white_level, black_level=noise.black_level),
            names={k: setting_name(k, door) for k in ("noise_sigma", "data_range", "white_level", "tol_rms",
                                                      "black_level")})
        # the read noise known in working units: heavy noise leaves out a preset's non-local passes, and so do a
        # code that leaves its patches blind (long bumps) and one that samples each sub-frame on a coarse lattice
        mask0 = np.asarray(captures.mask(0)) if resolved.settings.preset else None
        weight, blind = sparse_weight(mask0) if mask0 is not None else (1.0, "")
        self.r = for_noise(resolved, noise.sigma * self.units.scale, blind=blind if weight < 1 else "",
                           lattice=coarse_lattice(mask0) if mask0 is not None else "")
        self.omp = omp_settings(rc, noise.sigma, scale=self.units.scale)
        self._warn_before_work()
        h, w = captures.codeds[0].shape[-2:]
        self.shape = (self.count, self.n, h, w) if captures.kind == "channels" else \
            (3, self.n, h, w) if captures.kind == "bayer" else (self.count * self.n, h, w)
        self.cuts = None
        self.entries: list[dict] = []
        #: Each capture's frames scored against the truth as they come (:class:`codedvideo.api._record.Scores`).
        self.scores = Scores()
        self.seconds_prepared = time.perf_counter() - t0
        #: Seconds spent scoring the results against the truth (part of each result's time).
        self.seconds_scored = 0.0
        self._traces: dict[int, list[dict]] = {}
        self._stages: dict[int, list[dict]] = {}  # capture -> the PSNR after each pass before the last
        self._partial: dict[tuple, dict] = {}  # (capture, iterations) -> the bands' squared errors so far
        self._implausible_said = False

    def _warn_before_work(self) -> None:
        r, job = self.r, self.captures
        if job.truths is not None:  # a truth in other units than the captures': every score would mean nothing
            truth_peak = volume_peak(job.truth(0))  # (the first capture's: a long stream's is not read twice)
            if other_units(self.units.peak, truth_peak):
                doors.warn(f"{job.source.rsplit(':', 1)[0]}: truth peaks at {truth_peak:.4g} and the coded "
                              f"images' coded / open count at {self.units.peak:.4g}; are they in the same units? "
                              f"(every PSNR is taken against the data range {self.units.value:g}, "
                              f"{self.units.source})")
        if r.method in SPARSE:
            message = tolerance_warning(job.codeds[0] * np.float32(self.units.scale), self.omp.tol_rms)
            if message:
                doors.warn(f"{message} (data range {self.units.value:g} from {self.units.source})")
            if r.cache is not None:  # a working store a capture: said before any work when the disk may not hold them
                n, (h, w) = self.n, job.codeds[0].shape[-2:]
                problem = cache_room(r.cache, self.count, (3 * n if job.kind == "bayer" else n, h, w), tile=r.rc.tile,
                                     budget=r.rc.cache_budget, adapt=r.rc.adapt, adapt_rounds=r.rc.adapt_rounds)
                if problem:
                    doors.warn(problem)

    def capture_settings(self, cache) -> CaptureSettings:
        """The engine's settings of this job, working in ``cache``."""
        r = self.r
        return CaptureSettings(r.method, data_range=self.units, settings=self.omp, dictionary=self.dictionary,
                               dictionary_key=self.dictionary_key, dictionary_name=self.dictionary_name,
                               white_level=self.white, where=self.captures.source, config=r.rc, cache=cache,
                               progress=r.progress, noise_sigma=r.noise.sigma,
                               trace=self._trace if self.captures.truths is not None and r.rc.refine else None)

    def _trace(self, i: int, iterations: int | str, volume: np.ndarray, seconds: float, rows: slice) -> None:
        """The rows ``rows`` of capture ``i``'s estimate after ``iterations`` of the refinement (working units), or
        after the pass ``iterations`` names (``"pass 1"``: ``stage_trace``), scored against its truth; once every
        row of the capture is scored (a refinement in bands shows each band's), a point of its error against
        time (``refine_trace`` in its record), the bands' seconds added."""
        if self.captures.truth(i) is None:  # (a stream whose truth ends before this capture)
            return
        t0 = time.perf_counter()
        scale = np.float32(self.units.scale)
        n = volume.shape[0]
        truth = np.asarray(self.captures.truth(i))
        truth = truth.reshape((n, -1, truth.shape[-1]))
        part = self._partial.setdefault((i, iterations), dict(sse=np.zeros(n), rows=0, seconds=0.0))
        for t in range(n):  # a frame at a time in float64 (not the whole volume)
            error = np.asarray(volume[t] / scale, np.float64) - np.asarray(truth[t, rows], np.float64)
            part["sse"][t] += np.sum(error ** 2)
        part["rows"] += volume.shape[1]
        part["seconds"] += float(seconds)
        if part["rows"] == truth.shape[1]:
            del self._partial[(i, iterations)]
            psnr = mean_psnr([mse_psnr(e / truth[0].size, self.units.value) for e in part["sse"]])
            stage = isinstance(iterations, str)
            point = dict(stage=iterations) if stage else dict(iterations=int(iterations))
            (self._stages if stage else self._traces).setdefault(i, []).append(
                dict(point, seconds=part["seconds"], psnr=psnr))
        self.seconds_scored += time.perf_counter() - t0

    def recipe(self) -> dict:
        """What this job's results depend on beside its inputs, its OMP settings and its dictionary (the
        solver's version, the adaptation's and the refinement's settings): a record of a result is keyed by it
        (:func:`codedvideo.engine.captures.result_recipe`)."""
        rc = self.r.rc
        return result_recipe(self.r.method, adapt=rc.adapt, adapt_rounds=rc.adapt_rounds, refine=rc.refine)

    def results(self, cache):
        """The method's results ``(i, volume, info)`` in order, working in ``cache``."""
        r, job = self.r, self.captures
        options = self.capture_settings(cache)
        if job.kind == "bayer":  # one mosaic -> its colour video (3, N, H, W); evaluated as 3N frames
            return iter([(0, *reconstruct_bayer(options, job.codeds[0], job.mask(0), pattern=r.bayer))])
        stream = job.kind in ("captures", "measurements") and self.count > 1 and not r.independent_captures
        if stream:
            from codedvideo.model.sequence import Cuts

            # boundaries whose two captures do not show one scene (a cut, a dark or blown-out capture, a jump
            # of exposure): nothing is averaged or joined across them
            self.cuts = Cuts(job.codeds, job.mask, scale=self.units.scale, white_level=self.white)
        # (a benchmark file's measurements are joined, but share no still answers: each has its own scene)
        return reconstruct_stream(options, job.codeds, job.mask, join=stream, still=job.kind == "captures",
                                  cuts=self.cuts, spill=cache)

    def run(self, cache):
        """Yield ``(i, volume, entry)``: each capture's frames (in the capture's units) and its record entry,
        scored when a truth is given."""
        results = self.results(cache)
        with contextlib.closing(results) if hasattr(results, "close") else contextlib.nullcontext():
            for i, volume, info in results:
                yield i, volume, self._entry(i, volume, info)

    def _warn_implausible(self, i: int, volume) -> None:
        """Say, once a job, a result far outside ``[0, data range]`` (:data:`IMPLAUSIBLE_SHARE`): values no
        intensity takes, from heavy read noise (the frames are not clipped), a range that does not fit, or a code
        whose patterns leave the motion nearly unobserved (long bumps)."""
        if self._implausible_said:
            return
        lo, hi = volume_extremes(volume)
        value = self.units.value
        if lo < -IMPLAUSIBLE_SHARE * value or hi > (1 + IMPLAUSIBLE_SHARE) * value:
            self._implausible_said = True
            where = self.captures.source if self.count == 1 else f"{self.captures.source}, capture {i + 1}"
            sigma = float(self.r.noise.sigma)
            noise = (f"the read noise of {sigma:g} given ({doors.name('noise_sigma')}), which the frames carry "
                     f"unclipped, " if sigma > 0 else "")
            doors.warn(f"{where}: the reconstruction holds values from {lo:.4g} to {hi:.4g}, far outside the data "
                          f"range [0, {value:g}] ({self.units.source}): {noise}a data range or white level that does "
                          f"not fit the captures, or a code that leaves the motion nearly unobserved for the "
                          f"method {self.r.method} (long shutter bumps make it ill-conditioned); compare the "
                          f"trivial estimate in the record, or {doors.name('method')} gaptv")

    def _entry(self, i: int, volume, info: dict) -> dict:
        job = self.captures
        if i in self._stages:  # the PSNR after each pass of the adaptation, and the seconds to each
            info["stage_trace"] = self._stages.pop(i)
        if i in self._traces:  # the PSNR along the refinement's iterations, and the seconds to each
            info["refine_trace"] = self._traces.pop(i)
        entry = dict(job.labels[i], reconstruction=info)
        if self.raw:
            entry["raw"] = self.raw[i]
        self._warn_implausible(i, volume)
        truth = job.truth(i)
        if truth is not None:
            self.seconds_scored += self.scores.add(entry, volume, truth, self._trivial_of(i),
                                                   data_range=self.units.value, stream=job.kind in ("captures", "measurements"))
        self.entries.append(entry)
        return entry

    def _trivial_of(self, i: int) -> np.ndarray:
        job = self.captures
        if job.kind == "bayer":
            return static_estimate(job.codeds[i], job.mask(i), self.r.bayer)
        return physics.static_estimate(job.codeds[i], job.mask(i))
