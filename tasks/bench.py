"""make bench: time reconstruction against GAP-TV, a naive OMP and a matrix multiply.

Cases (issue "Fast reconstruction"):

  a        256x256, N = 8, L = 2: the default settings, beside GAP-TV and the naive OMP
  b        1280x720, N = 18, L = 2: peak memory; also run with one worker (scaling)
  c        512x512, N = 36, L = 3 (the paper's N), sliding and tiled codes
  static   the default scene fully moving against 70 % still, still-scene test on/off
  bayer    the colour default scene through an RGGB filter (N = 8, L = 2): PSNR of the colour
           result and of the demosaicked static estimate, and the time
  units    the default scene in 8-bit floats, [0, 1] floats and 12-bit uint16: PSNR and seconds
  startup  a 256x256 N = 8 reconstruct as a whole process against its in-process time
  calibrated  a code misregistered by half a pixel: nominal binary mask against the measured float mask
  sequence 10 captures (256x256, N = 8) 70 % still, all still and all moving, as one job and
           capture by capture (--independent-captures: no still regions, no join; whole CLI
           processes), the boundary step error; 70 % still against moving at 30 captures;
           peak memory at T = 1, 10, 100; the 70 %-still scene under read noise 10, 20 and 40
  nonlocal the non-local method (issue 16) beside the default, GAP-TV and the DCT on the quality
           case's scenes and codes (tasks/bench_nonlocal.py)
  adapt    reconstruct --adapt (the dictionary adapted to each capture in the same run) beside the
           default and the non-local method, whole CLI processes, 8-bit and [0, 1] captures
  presets  issue 31: GAP-TV, --preset fast, default and best and nonlocal --adapt on the held-out real clips
           (8 cases, 8-bit and [0, 1] captures), and default and best at 256, 512 and 1024 pixels square
           (time against the pixel count), and GAP-TV, nonlocal --adapt and best on the issue's 24 cases (3
           codes x read noise 0 and 4 x 4 clips), whole CLI processes (tasks/bench_presets.py)
  front    issue 39: GAP-TV, the default and best on 768x768 and 1024x1024 mosaics of the held-out clips
           (hitomi L = 2 and Bernoulli, 8-bit and [0, 1]), whole CLI processes: best's time against the
           default's and the default's against GAP-TV's (tasks/bench_presets.py --front)
  video    N = 18: 1280x720 with T = 30 captures and one 3840x2160 capture (whole CLI processes,
           peak resident memory)
  outputs  issue 29: peak resident memory per output format (npy, mp4, mkv, gif, zarr, tif, mat, frames),
           one 1920x1080 N = 18 capture and two as one job, whole CLI processes, fresh caches
  outputs4k  issue 29 at 3840x2160 N = 18: one capture to .npy and .mp4, and streams of 2, 3 and 5 captures
           as one job (.npy: the join): peak resident memory per capture count against the 2 GB target,
           whole CLI processes, fresh caches (about 6 minutes a capture on 2 cores)
  robust   the default and best against the still estimate and GAP-TV on every code a user can give: N = 8, 16
           and 18, every hitomi bump length, Bernoulli p 0.1 to 0.9, the other families, read noise 0 to 40,
           held-out clips at 64x64 (tasks/bench_robust.py; its own results file as well)
  robust-noise  the same figures under read noise 4 to 79 on the centre and two corners of four held-out
           clips (N = 8, hitomi L = 2 and Bernoulli 0.5): best against the default on flat corners as well as
           the centres (tasks/bench_robust.py --noise-crops)
  robust-crops  the same figures without noise on the centre and four corners of the four clips, for hitomi
           L = 2, Bernoulli 0.5 and grid at N = 8, hitomi L = 2, 8 and 14, Bernoulli 0.5 and grid at 16, hitomi
           L = 2 and grid at 18 (tasks/bench_robust.py --crops)
  footage  coded video of held-out real clips (bikes.mp4: 31 captures of 272x640; carphone: 15 of
           144x176; N = 8, read noise 2): simulated and reconstructed by the CLI as one job and
           capture by capture, PSNR, SSIM, boundary step and seconds; the job again in [0, 1] floats

Every case runs in its own process so that its peak resident memory is its
own; each also times a fixed-size SGEMM so figures can be read as ratios
independent of the machine's speed that day.  The small cases (a, static) run
5 times and show the median (the first, cold run is kept as seconds_first);
the compiled OMP kernel is loaded before any timing and its load time shown.
Results go to
bench/results/latest.json (merged with the last full run's other cases; a --quick
smoke run to bench/results/quick.json) and a table is printed.

    python tasks/bench.py [--cases a,b,c,static] [--quick]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
#: Runs of each small case (a, static): the table shows their median; the first
#: (cold: thread pool and caches starting) is kept in the JSON as seconds_first.
REPEATS = 5
RESULTS = ROOT / "bench" / "results"
sys.path.insert(0, str(ROOT / "tasks"))
from _bench_common import QUALITY_SCENES, _cli, _q, default_and_dct, quality_captures, sgemm_gflops  # noqa: E402
from _bench_table import table  # noqa: E402  (the results as the table bench prints)


def peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def dictionary_for(frames: int):
    """The default dictionary for N = 8; for larger N (speed cases only) a shorter K-SVD run
    (20k samples, 10 iterations) with the same number of atoms, so training stays in minutes."""
    from codedvideo.engine.config import PipelineConfig
    from codedvideo.engine.training import train_dictionary
    from codedvideo.formats.store import load_dictionary

    cfg = PipelineConfig(frames=frames, cache=str(ROOT / "cache"))
    if frames != 8:
        cfg = cfg.model_copy(update=dict(dictionary=cfg.dictionary.model_copy(
            update=dict(samples=20000, iterations=10, clips=72))))
    path, _ = train_dictionary(cfg, progress=False)
    return load_dictionary(path)


def capture(scene: str, frames: int, size, code: str, bump: int, seed: int = 0):
    from codedvideo.data.scenes import load_video
    from codedvideo.engine.simulation import simulate_capture
    from codedvideo.model.codes import CodeSpec

    video = load_video(f"synth:{scene}", frames=frames, size=size, seed=seed)
    return simulate_capture(video, code=CodeSpec(code, bump=bump), sigma=0.0, seed=seed)


def timed_reconstruct(cap, D, meta, *, workers=None, static_atoms=None, tile=128, stride=1, repeats=1):
    """Reconstruct ``repeats`` times (each into a fresh store); seconds: the median, seconds_first: the first."""
    from codedvideo.engine.config import PipelineConfig, omp_settings
    from codedvideo.model.metrics import evaluate
    from codedvideo.engine.windows import Execution, reconstruct_volume
    import tempfile

    rc = PipelineConfig().reconstruct
    s = omp_settings(rc.model_copy(update=dict(static_atoms=rc.static_atoms if static_atoms is None else static_atoms,
                                               stride=stride)), 0.0)
    times = []
    for _ in range(repeats):
        with tempfile.TemporaryDirectory(dir=ROOT / "cache") as tmp:  # fresh store: nothing reused
            t = time.perf_counter()
            vol, info = reconstruct_volume(cap["coded"], cap["mask"], D, settings=s,
                                           run=Execution(tile=tile, cache=tmp, workers=workers, progress=False),
                                           dictionary_key=meta["sha256"])
            times.append(time.perf_counter() - t)
    seconds = float(np.median(times))
    q = evaluate(vol, cap["truth"], data_range=255.0)
    return dict(seconds=seconds, seconds_first=times[0], repeats=repeats, psnr=q["psnr"], ssim=q["ssim"], patches=info["patches"],
                patches_per_second=info["patches"] / seconds, static_fraction=info["static_fraction"],
                atoms_mean=info["atoms_mean"], stages=info["seconds"], settings=s.__dict__, workers=workers or os.cpu_count())


def timed_gaptv(cap, repeats=1):
    """GAP-TV timed like :func:`timed_reconstruct` (median of ``repeats``, and the first)."""
    from codedvideo.solvers.baselines import gap_tv
    from codedvideo.model.metrics import evaluate

    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        vol = gap_tv(cap["coded"], cap["mask"])
        times.append(time.perf_counter() - t)
    q = evaluate(vol, cap["truth"], data_range=255.0)
    return dict(seconds=float(np.median(times)), seconds_first=times[0], repeats=repeats, psnr=q["psnr"], ssim=q["ssim"])


def naive_omp(cap, D, *, crop=48):
    """The naive implementation: per patch, build S_p D in Python loops and run textbook OMP."""
    from codedvideo.model import patches as P
    from codedvideo.engine.config import PipelineConfig, auto_tolerance, omp_settings
    from codedvideo.model.metrics import evaluate
    from codedvideo.solvers.omp import omp_reference
    from codedvideo.solvers.region import reconstruct_region

    coded = cap["coded"][:crop, :crop]
    mask = cap["mask"][:, :crop, :crop]
    truth = cap["truth"][:, :crop, :crop]
    n = mask.shape[0]
    rc = PipelineConfig().reconstruct
    tol_rms = auto_tolerance(0.0)
    y = P.extract(coded)
    S = P.extract(mask)
    D3 = D.reshape(n, 49, -1)
    t = time.perf_counter()
    est = np.empty((y.shape[0], D.shape[0]), np.float32)
    for p in range(y.shape[0]):
        A = np.zeros((49, D.shape[1]))
        for i in range(49):
            for tt in range(n):
                if S[p, tt, i]:
                    A[i] += D3[tt, i]
        alpha = omp_reference(A, y[p], max_atoms=rc.max_atoms, tol=49 * tol_rms**2)
        est[p] = D @ alpha
    naive_s = time.perf_counter() - t
    vol = P.fold(est, coded.shape) / P.coverage(coded.shape)[None]
    t = time.perf_counter()
    fast, _ = reconstruct_region(coded, mask, D, omp_settings(rc.model_copy(update=dict(tol_rms=tol_rms, static_atoms=0)),
                                                              0.0))
    fast_s = time.perf_counter() - t
    return dict(crop=crop, patches=int(y.shape[0]), naive_seconds=naive_s, fast_seconds=fast_s,
                naive_psnr=evaluate(vol, truth, data_range=255.0)["psnr"], fast_psnr=evaluate(fast, truth, data_range=255.0)["psnr"],
                naive_seconds_per_patch=naive_s / y.shape[0])


def case_a(quick: bool) -> dict:
    D, meta = dictionary_for(8)
    cap = capture("default", 8, (256, 256), "hitomi", 2)
    out = dict(case="a", size=[256, 256], frames=8, bump=2, sgemm_gflops=sgemm_gflops())
    n = 1 if quick else REPEATS
    out["omp"] = timed_reconstruct(cap, D, meta, repeats=n)
    out["gaptv"] = timed_gaptv(cap, repeats=n)
    tiled = capture("default", 8, (256, 256), "hitomi-tiled", 2)
    out["hitomi-tiled"] = timed_reconstruct(tiled, D, meta, repeats=n)
    out["omp-stride2"] = timed_reconstruct(cap, D, meta, stride=2, repeats=n)
    out["gaptv-tiled"] = timed_gaptv(tiled, repeats=n)
    out["naive"] = naive_omp(cap, D, crop=24 if quick else 48)
    out["naive"]["extrapolated_full_seconds"] = out["naive"]["naive_seconds_per_patch"] * out["omp"]["patches"]
    return out


def case_b(quick: bool) -> dict:
    size = (360, 640) if quick else (720, 1280)
    D, meta = dictionary_for(18)
    cap = capture("default", 18, size, "hitomi", 2)
    out = dict(case="b", size=list(size), frames=18, bump=2, sgemm_gflops=sgemm_gflops())
    out["omp"] = timed_reconstruct(cap, D, meta)
    out["gaptv"] = timed_gaptv(cap)
    out["peak_rss_mb"] = peak_rss_mb()
    return out


def case_b1(quick: bool) -> dict:
    size = (360, 640) if quick else (720, 1280)
    D, meta = dictionary_for(18)
    cap = capture("default", 18, size, "hitomi", 2)
    return dict(case="b1", size=list(size), frames=18, omp=timed_reconstruct(cap, D, meta, workers=1),
                peak_rss_mb=peak_rss_mb(), sgemm_gflops=sgemm_gflops())


def case_c(quick: bool) -> dict:
    size = (256, 256) if quick else (512, 512)
    D, meta = dictionary_for(36)
    out = dict(case="c", size=list(size), frames=36, bump=3, sgemm_gflops=sgemm_gflops())
    for code in ("hitomi", "hitomi-tiled"):
        cap = capture("default", 36, size, code, 3)
        out[code] = timed_reconstruct(cap, D, meta)
    out["gaptv"] = timed_gaptv(capture("default", 36, size, "hitomi", 3))
    out["peak_rss_mb"] = peak_rss_mb()
    return out


def case_static(quick: bool) -> dict:
    D, meta = dictionary_for(8)
    out = dict(case="static", size=[256, 256], frames=8, bump=2, sgemm_gflops=sgemm_gflops())
    for scene in ("default", "default-static70"):
        cap = capture(scene, 8, (256, 256), "hitomi", 2)
        n = 1 if quick else REPEATS
        out[scene] = dict(skip=timed_reconstruct(cap, D, meta, repeats=n),
                          no_skip=timed_reconstruct(cap, D, meta, static_atoms=0, repeats=n))
    return out


def case_quality(quick: bool) -> dict:
    """Issue "quality beyond the paper": default reconstruction against GAP-TV and the 3D DCT
    (same OMP, up to 16 atoms) on held-out real footage and synthetic test scenes, N = 8."""
    from codedvideo.solvers.baselines import gap_tv
    from codedvideo.engine.config import PipelineConfig
    from codedvideo.model.metrics import evaluate

    D, meta = dictionary_for(8)
    rc = PipelineConfig().reconstruct
    size = (96, 96) if quick else (256, 256)
    rows = []
    for video, cap, row in quality_captures(QUALITY_SCENES[:2] if quick else QUALITY_SCENES, size):
        default_and_dct(row, video, cap, D, rc, ROOT / "cache")
        t = time.perf_counter()
        vol = gap_tv(cap["coded"], cap["mask"])
        row["gaptv"] = dict(seconds=time.perf_counter() - t, **_q(evaluate(vol, video, data_range=255.0)))
        rows.append(row)
    return dict(case="quality", size=list(size), frames=8, rows=rows, sgemm_gflops=sgemm_gflops())


def case_bayer(quick: bool) -> dict:
    """Issue 14: a Bayer (RGGB) coded capture of synth:color-default, reconstructed in colour."""
    import tempfile

    import codedvideo as cv
    from codedvideo.engine import bayer
    from codedvideo.model.codes import CodeSpec
    from codedvideo.model.metrics import evaluate

    D, meta = dictionary_for(8)
    size = (96, 96) if quick else (256, 256)
    video = bayer.color_scene("color-default", frames=8, size=size)
    cap = bayer.simulate_bayer(video, "RGGB", code=CodeSpec("hitomi", bump=2), sigma=0.0, seed=0)
    flat = lambda v: v.reshape(-1, *size)  # noqa: E731
    with tempfile.TemporaryDirectory(dir=ROOT / "cache") as tmp:  # (the API's settings path, as a user's run)
        t = time.perf_counter()
        result = cv.reconstruct(cap["coded"], cap["mask"], bayer="RGGB", dictionary=D, cache=tmp, progress=False,
                                full_output=True)
        seconds = time.perf_counter() - t
    vol, info = result.frames, result.info[0]
    q = evaluate(flat(vol), flat(video), data_range=255.0)
    static = evaluate(flat(bayer.static_estimate(cap["coded"], cap["mask"], "RGGB")), flat(video), data_range=255.0)
    return dict(case="bayer", size=list(size), frames=8, bump=2, pattern="RGGB", sgemm_gflops=sgemm_gflops(),
                omp=dict(seconds=seconds, psnr=q["psnr"], ssim=q["ssim"], patches_per_second=info["patches"] / seconds),
                static=dict(psnr=static["psnr"], ssim=static["ssim"]))


def _psnr(recon: np.ndarray, truth: np.ndarray, cols=slice(None)) -> float:
    from codedvideo.model.metrics import evaluate

    return evaluate(recon[..., cols], truth[..., cols], data_range=255.0)["psnr"]


#: Whole-process timings of the sequence case: the median of this many runs (one run varies by 5 % here).
SEQUENCE_REPEATS = 3


def case_sequence(quick: bool) -> dict:
    """Issue 15: coded video. 10 captures (256x256, N = 8) of a 70 %-still scene, a still scene and a fully
    moving one, each reconstructed as one job and capture by capture (--independent-captures), every
    figure the whole CLI process; peak memory at T = 1, 10 and 100."""
    import tempfile

    from codedvideo.engine.simulation import simulate_capture
    from codedvideo.model.codes import CodeSpec
    from codedvideo.data.synth import make_scene

    size, t_count = ((64, 64), 4) if quick else ((256, 256), 10)
    out = dict(case="sequence", size=list(size), frames=8, captures=t_count, sgemm_gflops=sgemm_gflops())
    with tempfile.TemporaryDirectory(dir=ROOT / "cache") as tmp:
        tmp = Path(tmp)
        scenes = {"static70": make_scene("default-static70", frames=8 * t_count, size=size),
                  "still": np.repeat(make_scene("default", frames=1, size=size), 8 * t_count, axis=0),
                  "moving": make_scene("default", frames=8 * t_count, size=size)}
        for name, video in scenes.items():
            cap = simulate_capture(video, code=CodeSpec("hitomi", bump=2), sigma=0.0, seed=0, captures=t_count)
            for key in ("coded", "mask", "truth"):
                np.save(tmp / f"{name}-{key}.npy", cap[key])
        # every timing the median of SEQUENCE_REPEATS whole processes, each on a fresh cache, the runs of all
        # scenes and modes interleaved so that a slow spell of the machine touches them alike
        runs: dict = {}
        for repeat in range(1 if quick else SEQUENCE_REPEATS):
            for name in scenes:
                for mode, flag in (("sequence", []), ("independent", ["--independent-captures"])):
                    result, cache = tmp / f"{name}-{mode}.npy", tmp / f"cache-{name}-{mode}-{repeat}"
                    seconds, peak = _cli(
                        "reconstruct", "--coded", tmp / f"{name}-coded.npy", "--mask", tmp / f"{name}-mask.npy",
                        "--output", result, "--cache", cache, "--overwrite", *flag, cwd=ROOT)
                    # the pipeline's own time, as its metrics JSON reports it (no interpreter start-up or imports)
                    own = json.loads(result.with_suffix(".metrics.json").read_text())["reconstruction"]["seconds"]
                    runs.setdefault((name, mode), []).append((seconds, peak, own["total"]))
                    shutil.rmtree(cache, ignore_errors=True)  # (a still sequence makes no working store)
        for name, video in scenes.items():
            row = {}
            for mode in ("sequence", "independent"):
                recon = np.load(tmp / f"{name}-{mode}.npy")
                times = [t for t, _, _ in runs[(name, mode)]]
                own = [o for _, _, o in runs[(name, mode)]]
                row[mode] = dict(seconds=float(np.median(times)), seconds_runs=times,
                                 seconds_pipeline=float(np.median(own)), seconds_pipeline_runs=own,
                                 peak_rss_mb=max(p for _, p, _ in runs[(name, mode)]), psnr=_psnr(recon, video),
                                 boundary_to_inside=_boundary_ratio(recon, video, 8))
                if name == "static70":  # the moving part: the right 30 % of the frame
                    row[mode]["psnr_moving"] = _psnr(recon, video, slice(int(round(0.7 * size[1])), None))
            row["time_ratio"] = row["sequence"]["seconds"] / row["independent"]["seconds"]
            out[name] = row
        out["moving_vs_still70_time"] = out["static70"]["sequence"]["seconds"] / out["moving"]["sequence"]["seconds"]
        out["moving_vs_still70_pipeline_time"] = (out["static70"]["sequence"]["seconds_pipeline"]
                                                  / out["moving"]["sequence"]["seconds_pipeline"])
        out["still_vs_moving_time"] = out["still"]["sequence"]["seconds"] / out["moving"]["sequence"]["seconds"]
        out["longer"] = _sequence_longer(tmp, size, 3 * t_count, quick)
        out["memory"] = _sequence_memory(tmp, size, quick)
        out["noisy"] = _sequence_noisy(tmp, size, scenes["static70"], t_count, quick)
    return out


def _sequence_longer(tmp: Path, size, longer: int, quick: bool) -> dict:
    """The sequence case's 70 %-still and moving scenes, ``longer`` captures each: the ~1 s that every run pays
    before its first tile (interpreter, imports, numba's set-up, the stores) weighs less."""
    from codedvideo.engine.simulation import simulate_capture
    from codedvideo.model.codes import CodeSpec
    from codedvideo.data.synth import make_scene

    runs: dict = {}
    for name, spec in (("static70", "default-static70"), ("moving", "default")):
        cap = simulate_capture(make_scene(spec, frames=8 * longer, size=size), code=CodeSpec("hitomi", bump=2),
                               sigma=0.0, seed=0, captures=longer)
        np.save(tmp / f"{name}-long-coded.npy", cap["coded"])
        np.save(tmp / f"{name}-long-mask.npy", cap["mask"])
    for repeat in range(1 if quick else SEQUENCE_REPEATS):
        for name in ("static70", "moving"):
            seconds, _ = _cli("reconstruct", "--coded", tmp / f"{name}-long-coded.npy", "--mask",
                              tmp / f"{name}-long-mask.npy", "--output", tmp / f"{name}-long.npy", "--cache",
                              tmp / f"cache-long-{repeat}", "--overwrite", cwd=ROOT)
            runs.setdefault(name, []).append(seconds)
            shutil.rmtree(tmp / f"cache-long-{repeat}", ignore_errors=True)
    return dict(captures=longer, seconds={k: float(np.median(v)) for k, v in runs.items()},
                seconds_runs=runs, moving_vs_still70_time=float(np.median(runs["static70"]) / np.median(runs["moving"])))


def _sequence_memory(tmp: Path, size, quick: bool) -> dict:
    """The peak memory of whole processes by the stream's length T."""
    from codedvideo.engine.simulation import simulate_capture
    from codedvideo.model.codes import CodeSpec
    from codedvideo.data.synth import make_scene

    memory = {}
    for t in ((1, 4) if quick else (1, 10, 100)):
        video = make_scene("default", frames=8 * t, size=size)
        cap = simulate_capture(video, code=CodeSpec("hitomi", bump=2), sigma=0.0, seed=0, captures=t)
        np.save(tmp / "m-coded.npy", cap["coded"])
        np.save(tmp / "m-mask.npy", cap["mask"])
        seconds, peak = _cli("reconstruct", "--coded", tmp / "m-coded.npy", "--mask", tmp / "m-mask.npy", "--output",
                             tmp / f"m{t}.npy", "--cache", tmp / f"cache-m{t}", cwd=ROOT)
        memory[str(t)] = dict(seconds=seconds, peak_rss_mb=peak)
    return memory


def _sequence_noisy(tmp: Path, size, video: np.ndarray, t_count: int, quick: bool) -> dict:
    """Heavy read noise: the still answer is then noisier than OMP's estimate (sequence.STILL_NOISE_MAX)."""
    from codedvideo.engine.simulation import simulate_capture
    from codedvideo.model.codes import CodeSpec

    noisy = {}
    for sigma in ((40,) if quick else (10, 20, 40)):
        cap = simulate_capture(video, code=CodeSpec("hitomi", bump=2), sigma=float(sigma), seed=0, captures=t_count)
        np.save(tmp / "n-coded.npy", cap["coded"])
        np.save(tmp / "n-mask.npy", cap["mask"])
        row = {}
        for mode, flag in (("sequence", []), ("independent", ["--independent-captures"])):
            cache = tmp / f"cache-n{sigma}-{mode}"  # (where nothing is still, both modes make the same stores)
            seconds, _ = _cli("reconstruct", "--coded", tmp / "n-coded.npy", "--mask", tmp / "n-mask.npy",
                              "--noise-sigma", sigma, "--output", tmp / "n.npy", "--cache", cache,
                              "--overwrite", *flag, cwd=ROOT)
            shutil.rmtree(cache)
            recon = np.load(tmp / "n.npy")
            row[mode] = dict(seconds=seconds, psnr=_psnr(recon, video),
                             psnr_moving=_psnr(recon, video, slice(int(round(0.7 * size[1])), None)))
        noisy[str(sigma)] = row
    return noisy


def _boundary_ratio(recon: np.ndarray, truth: np.ndarray, n: int) -> float:
    """Error of the frame-to-frame step across capture boundaries over the error inside captures."""
    from codedvideo.model.sequence import StepErrors

    steps = StepErrors()
    for t in range(len(recon) // n):
        steps.add(recon[t * n : (t + 1) * n], truth[t * n : (t + 1) * n])
    return steps.summary()["boundary_to_inside"]


def case_video(quick: bool) -> dict:
    """Issue 15: coded video at camera sizes, N = 18 (bump 3), whole CLI processes with peak resident memory:
    1280x720 with T = 30 captures (540 frames), and one 3840x2160 capture."""
    import tempfile

    from codedvideo.engine.simulation import simulate_capture
    from codedvideo.model.codes import CodeSpec
    from codedvideo.data.synth import make_scene

    runs = (((128, 160), 3), ((216, 384), 1)) if quick else (((720, 1280), 30), ((2160, 3840), 1))
    out = dict(case="video", frames=18, sgemm_gflops=sgemm_gflops())
    with tempfile.TemporaryDirectory(dir=ROOT / "cache") as tmp:
        tmp = Path(tmp)
        for size, t_count in runs:
            video = make_scene("default", frames=18 * t_count, size=size)
            cap = simulate_capture(video, code=CodeSpec("hitomi", bump=3), sigma=0.0, seed=0, captures=t_count)
            for key in ("coded", "mask"):
                np.save(tmp / f"{key}.npy", cap[key])
            del cap
            seconds, peak = _cli("reconstruct", "--coded", tmp / "coded.npy", "--mask", tmp / "mask.npy",
                                 "--output", tmp / "recon.npy", "--cache", tmp / "cache", cwd=ROOT)
            recon = np.load(tmp / "recon.npy", mmap_mode="r")
            out[f"{size[1]}x{size[0]} T={t_count}"] = dict(
                size=list(size), captures=t_count, seconds=seconds, seconds_per_capture=seconds / t_count,
                peak_rss_mb=peak, psnr=float(np.mean([_psnr(np.asarray(recon[i : i + 18]), video[i : i + 18])
                                                      for i in range(0, 18 * t_count, 18)])))
            del video, recon
    return out


#: Outputs of case outputs: every format reconstruct writes (a name without suffix: a folder of 16-bit TIFF frames).
OUTPUT_FORMATS = ("rec.npy", "rec.mp4", "rec.mkv", "rec.gif", "rec.zarr", "rec.tif", "rec.mat", "frames")


def case_outputs(quick: bool) -> dict:
    """Issue 29: peak resident memory of whole CLI processes per output format, one 1920x1080 N = 18 capture
    (bump 3), a fresh cache each (computed), and two captures as one job (the join); each format's peak
    against the .npy path's."""
    import tempfile

    from codedvideo.engine.simulation import simulate_capture
    from codedvideo.model.codes import CodeSpec
    from codedvideo.data.synth import make_scene

    size = (216, 384) if quick else (1080, 1920)
    out = dict(case="outputs", size=list(size), frames=18, sgemm_gflops=sgemm_gflops(), peaks={})
    with tempfile.TemporaryDirectory(dir=ROOT / "cache") as tmp:
        tmp = Path(tmp)
        for t_count in (1, 2):
            video = make_scene("default", frames=18 * t_count, size=size)
            cap = simulate_capture(video, code=CodeSpec("hitomi", bump=3), sigma=0.0, seed=0, captures=t_count)
            for key in ("coded", "mask"):
                np.save(tmp / f"{key}.npy", cap[key])
            del cap, video
            for name in OUTPUT_FORMATS if t_count == 1 else ("rec.npy", "rec.mp4"):
                shutil.rmtree(tmp / "cache", ignore_errors=True)
                seconds, peak = _cli("reconstruct", "--coded", tmp / "coded.npy", "--mask", tmp / "mask.npy",
                                     "--output", tmp / name, "--cache", tmp / "cache", cwd=ROOT)
                out["peaks"][f"T={t_count} {name}"] = dict(peak_rss_mb=peak, seconds=seconds)
                shutil.rmtree(tmp / name, ignore_errors=True) if (tmp / name).is_dir() else (tmp / name).unlink()
    base = out["peaks"]["T=1 rec.npy"]["peak_rss_mb"]
    for v in out["peaks"].values():
        v["of_npy"] = v["peak_rss_mb"] / base
    return out


#: Case outputs4k: (captures as one job, output) at 3840x2160 N = 18, and the peak a stream must stay within.
OUTPUTS_4K_RUNS = ((1, "rec.npy"), (1, "rec.mp4"), (2, "rec.npy"), (3, "rec.npy"), (5, "rec.npy"))
STREAM_PEAK_TARGET_MB = 2000 * 1e6 / 2**20  # 2 GB


def case_outputs4k(quick: bool) -> dict:
    """Issue 29: "a stream of 4K captures as one job stays within 2 GB whatever the number of captures".  Peak
    resident memory of whole CLI processes, 3840x2160 N = 18 (bump 3, the default scene moving over the whole
    frame), a fresh cache each: one capture to .npy and to .mp4, and 2, 3 and 5 captures as one job to .npy (the
    captures held on disk, the join a band of rows at a time); the peak per capture count, each against the
    one-capture .npy path's and the 2 GB target."""
    import tempfile

    from codedvideo.engine.simulation import simulate_capture
    from codedvideo.model.codes import CodeSpec
    from codedvideo.data.synth import make_scene

    size = (216, 384) if quick else (2160, 3840)
    most = max(t for t, _ in OUTPUTS_4K_RUNS)
    out = dict(case="outputs4k", size=list(size), frames=18, sgemm_gflops=sgemm_gflops(), peaks={},
               target_mb=STREAM_PEAK_TARGET_MB)
    with tempfile.TemporaryDirectory(dir=ROOT / "cache") as tmp:
        tmp = Path(tmp)
        cap = simulate_capture(make_scene("default", frames=18 * most, size=size), code=CodeSpec("hitomi", bump=3),
                               sigma=0.0, seed=0, captures=most)
        np.save(tmp / "mask.npy", cap["mask"])  # one code, repeated: the captures are the first t of the stack
        coded = cap["coded"]
        del cap
        for t_count, name in OUTPUTS_4K_RUNS:
            np.save(tmp / "coded.npy", coded[0] if t_count == 1 else coded[:t_count])
            shutil.rmtree(tmp / "cache", ignore_errors=True)
            seconds, peak = _cli("reconstruct", "--coded", tmp / "coded.npy", "--mask", tmp / "mask.npy",
                                 "--output", tmp / name, "--cache", tmp / "cache", cwd=ROOT)
            out["peaks"][f"T={t_count} {name}"] = dict(captures=t_count, peak_rss_mb=peak, seconds=seconds)
            (tmp / name).unlink()
    base = out["peaks"]["T=1 rec.npy"]["peak_rss_mb"]
    for v in out["peaks"].values():
        v["of_npy"] = v["peak_rss_mb"] / base
    return out


#: Read noise of the footage case's captures, in grey levels (8-bit units).
FOOTAGE_SIGMA = 2.0


def case_footage(quick: bool) -> dict:
    """Issue 15 on held-out real footage, as a user would run a clip of their own: ``simulate --captures all``
    of the whole clip, then ``reconstruct`` as one job and capture by capture (--independent-captures),
    whole CLI processes with ``--truth`` (carphone's the median of 3, interleaved); the job again with the
    capture and truth in [0, 1] floats, and with the 8-bit capture nudged by one float step (np.nextafter):
    how far the answer moves when only the input's last bit does, the yardstick for the [0, 1] difference."""
    import tempfile

    from codedvideo.data import manifest

    clips = ((("carphone", "skv-carphone", 1),) if quick
             else (("bikes", "skv-bikes", 1), ("carphone", "skv-carphone", SEQUENCE_REPEATS)))
    out = dict(case="footage", frames=8, bump=2, noise_sigma=FOOTAGE_SIGMA, sgemm_gflops=sgemm_gflops())
    with tempfile.TemporaryDirectory(dir=ROOT / "cache") as tmp:
        tmp = Path(tmp)
        for name, entry, repeats in clips:
            clip, cap = manifest.verify(manifest.lookup(entry)), tmp / name
            extent = ["--captures", "3", "--size", "64", "64"] if quick else ["--captures", "all"]
            _cli("simulate", clip, "--frames", 8, "--bump", 2, "--noise-sigma", FOOTAGE_SIGMA, "--seed", 0, *extent,
                 "--output", cap, cwd=ROOT)
            coded = np.load(cap / "coded.npy")
            row = dict(captures=int(coded.shape[0]), size=list(coded.shape[1:]))
            variants = {"unit": (1 / 255, lambda c: c * np.float32(1 / 255)),  # as a user holding [0, 1] floats has it
                        "nudged": (1.0, lambda c: np.nextafter(c, np.float32(np.inf)))}
            for key, (scale, change) in variants.items():
                (tmp / f"{name}-{key}").mkdir()
                np.save(tmp / f"{name}-{key}" / "coded.npy", change(coded).astype(np.float32))
                np.save(tmp / f"{name}-{key}" / "truth.npy", (np.load(cap / "truth.npy") * np.float32(scale)).astype(np.float32))
                shutil.copy(cap / "mask.npy", tmp / f"{name}-{key}" / "mask.npy")
            runs = [("sequence", cap, 1.0, []), ("independent", cap, 1.0, ["--independent-captures"])] * repeats + [
                ("sequence [0, 1]", tmp / f"{name}-unit", 1 / 255, []), ("sequence nudged", tmp / f"{name}-nudged", 1.0, [])]
            for label, where, scale, flag in runs:
                result, cache = tmp / f"{name}-{label}.npy", tmp / f"cache-{name}"
                seconds, peak = _cli("reconstruct", "--coded", where / "coded.npy", "--mask", where / "mask.npy",
                                     "--truth", where / "truth.npy", "--noise-sigma", FOOTAGE_SIGMA * scale,
                                     "--output", result, "--cache", cache, "--overwrite", *flag, cwd=ROOT)
                shutil.rmtree(cache)  # every run from a fresh cache
                metrics = json.loads(result.with_suffix(".metrics.json").read_text())
                quality, entries = metrics["quality"], metrics["captures"]
                done = row.setdefault(label, dict(seconds_runs=[]))
                done["seconds_runs"].append(seconds)
                done.update(seconds=float(np.median(done["seconds_runs"])), peak_rss_mb=max(peak, done.get("peak_rss_mb", 0)),
                            psnr=quality["psnr"],
                            ssim=quality["ssim"], boundary_to_inside=quality["boundaries"]["boundary_to_inside"],
                            patches_still=sum(e["reconstruction"]["patches_static"] for e in entries)
                            / sum(e["reconstruction"]["patches"] for e in entries))
            eight = np.load(tmp / f"{name}-sequence.npy")
            for key, label, scale in (("unit", "sequence [0, 1]", 255), ("nudged", "sequence nudged", 1)):
                moved = np.abs(np.load(tmp / f"{name}-{label}.npy") * np.float32(scale) - eight)
                row[f"{key}_max_diff_grey"] = float(moved.max())
                row[f"{key}_share_over_0.01"] = float((moved > 0.01).mean())
            row["time_ratio"] = row["sequence"]["seconds"] / row["independent"]["seconds"]
            out[name] = row
    return out

def case_nonlocal(quick: bool) -> dict:
    """Issue 16: the non-local method beside the default, GAP-TV and the DCT (tasks/bench_nonlocal.py)."""
    from bench_nonlocal import case_nonlocal as run

    return run(quick)


def case_adapt(quick: bool) -> dict:
    """`reconstruct --adapt` (the dictionary adapted to the capture in the same run: README) as whole CLI
    processes, each into a fresh cache, beside the default and the non-local method, on held-out real footage
    (hitomi L = 2 and Bernoulli, sigma 0); the capture in 8-bit units and as [0, 1] floats."""
    import tempfile

    from codedvideo.engine.simulation import simulate_capture
    from codedvideo.model.codes import CodeSpec
    from codedvideo.data.scenes import load_video

    size = (96, 96) if quick else (256, 256)
    runs = (("default", ()), ("omp --adapt", ("--adapt",)), ("nonlocal", ("--method", "nonlocal")),
            ("nonlocal --adapt", ("--method", "nonlocal", "--adapt")))
    rows = []
    with tempfile.TemporaryDirectory(dir=ROOT / "cache") as tmp:
        tmp = Path(tmp)
        for scene in (("footage:bikes-a",) if quick else ("footage:bikes-a", "footage:carphone")):
            video = load_video(scene, frames=8, size=size)
            for code in ("hitomi", "bernoulli"):
                cap = simulate_capture(video, code=CodeSpec(code, bump=2), sigma=0.0, seed=0)
                np.save(tmp / "mask.npy", cap["mask"])
                for units, scale in (("8-bit", 1.0), ("[0, 1]", 255.0)):
                    np.save(tmp / "coded.npy", cap["coded"] / np.float32(scale))
                    row = dict(scene=scene, code=code, units=units)
                    for label, extra in runs:
                        shutil.rmtree(tmp / "c", ignore_errors=True)
                        seconds, _ = _cli("reconstruct", "--coded", tmp / "coded.npy", "--mask", tmp / "mask.npy",
                                          "--cache", tmp / "c", "--overwrite", *extra, "--output", tmp / "r.npy", cwd=ROOT)
                        row[label] = dict(seconds=seconds, psnr=_psnr(np.load(tmp / "r.npy") * np.float32(scale), video))
                    rows.append(row)
    return dict(case="adapt", size=list(size), frames=8, rows=rows, sgemm_gflops=sgemm_gflops())


def case_startup(quick: bool) -> dict:
    """Issue 14: a 256x256 N = 8 reconstruct timed as a whole process against its own in-process time
    (the metrics' total: reading, reconstructing, writing), median of 3, each into a fresh cache."""
    import tempfile

    from codedvideo.formats.volumes import write_capture

    size = (96, 96) if quick else (256, 256)
    cap = capture("default", 8, size, "hitomi", 2)
    walls, inside = [], []
    with tempfile.TemporaryDirectory(dir=ROOT / "cache") as tmp:
        tmp = Path(tmp)
        write_capture(cap, tmp / "cap")
        for i in range(3):
            out = tmp / f"r{i}.npy"
            seconds, _ = _cli("reconstruct", "--coded", tmp / "cap" / "coded.npy", "--mask", tmp / "cap" / "mask.npy",
                              "--output", out, "--cache", tmp / f"cache{i}", cwd=ROOT)
            walls.append(seconds)
            inside.append(json.loads((tmp / f"r{i}.metrics.json").read_text())["reconstruction"]["seconds"]["total"])
    wall, work = float(np.median(walls)), float(np.median(inside))
    return dict(case="startup", size=list(size), frames=8, process_seconds=wall, in_process_seconds=work,
                ratio=wall / work, sgemm_gflops=sgemm_gflops())


def case_units(quick: bool) -> dict:
    """Issue 14: the default scene (N = 8, L = 2) held as a user may hold it: 8-bit floats, [0, 1] floats
    (img_as_float), 12-bit integers (uint16); PSNR and whole-process seconds of `reconstruct` for each."""
    import tempfile

    size = (96, 96) if quick else (256, 256)
    cap = capture("default", 8, size, "hitomi", 2)
    out = dict(case="units", size=list(size), frames=8, sgemm_gflops=sgemm_gflops())
    with tempfile.TemporaryDirectory(dir=ROOT / "cache") as tmp:
        tmp = Path(tmp)
        for name, scale, dtype in (("8-bit float", 1.0, np.float32), ("[0, 1] float", 1 / 255, np.float32),
                                   ("12-bit uint16", 4095 / 255 / 2, np.uint16)):
            coded = cap["coded"] * scale
            coded = np.rint(coded).astype(dtype) if dtype == np.uint16 else coded.astype(dtype)
            np.save(tmp / "coded.npy", coded)
            np.save(tmp / "mask.npy", cap["mask"])
            np.save(tmp / "truth.npy", (cap["truth"] * scale).astype(np.float32))
            result = tmp / f"r-{len(out)}.npy"
            seconds, _ = _cli("reconstruct", "--coded", tmp / "coded.npy", "--mask", tmp / "mask.npy", "--truth",
                              tmp / "truth.npy", "--output", result, "--cache", tmp / f"cache-{len(out)}", cwd=ROOT)
            metrics = json.loads(result.with_name(result.stem + ".metrics.json").read_text())
            out[name] = dict(seconds=seconds, psnr=metrics["quality"]["psnr"], data_range=metrics["data_range"]["value"])
    return out


def case_calibrated(quick: bool) -> dict:
    """Issue 14: a binary code whose optical response is misregistered by half a pixel (and blurred),
    reconstructed with the nominal binary mask and with the measured (float) mask."""
    from codedvideo.model.physics import blur_shift_mask, simulate

    D, meta = dictionary_for(8)
    size = (96, 96) if quick else (256, 256)
    cap = capture("default", 8, size, "hitomi", 2)
    out = dict(case="calibrated", size=list(size), frames=8, bump=2, sgemm_gflops=sgemm_gflops())
    for name, shift, sigma in (("shift 0.5,0.5 blur 0.5", (0.5, 0.5), 0.5), ("shift 0.5,0 no blur", (0.5, 0.0), 0.0)):
        measured = blur_shift_mask(cap["mask"], shift=shift, sigma=sigma)
        coded = simulate(cap["truth"], measured)  # what the sensor records through the real optics
        row = {}
        for label, mask in (("nominal", cap["mask"]), ("measured", measured)):
            row[label] = timed_reconstruct(dict(coded=coded, mask=mask, truth=cap["truth"]), D, meta)
        out[name] = row
    return out


def case_presets(quick: bool) -> dict:
    """Issue 31: the presets on held-out real footage and best's time against the pixel count
    (tasks/bench_presets.py; its own results file is kept as well)."""
    import tempfile

    import bench_presets as bp

    size = (96, 96) if quick else (256, 256)
    (ROOT / "cache").mkdir(exist_ok=True)
    with tempfile.TemporaryDirectory(dir=ROOT / "cache", prefix="bench-presets-") as tmp:
        work = Path(tmp)
        cases = bp.write_captures(work / "captures", size)[: 1 if quick else None]
        bp.warm_up(work)
        presets = dict(bp.presets(cases, work), size=list(size))
        scaling = bp.scaling(work, 1, sides=(64, 128) if quick else bp.SCALING_SIDES)
        issue = bp.write_captures(work / "issue", size, bp.ISSUE_CODES, bp.ISSUE_SIGMAS)[: 1 if quick else None]
        issue_cases = bp.issue_cases(issue, work)
    return dict(case="presets", size=list(size), frames=8, presets=presets, scaling=scaling, issue_cases=issue_cases,
                sgemm_gflops=sgemm_gflops())


def case_front(quick: bool) -> dict:
    """Issue 39: GAP-TV, the default and best on 768x768 and 1024x1024 mosaics of the held-out clips, both codes,
    8-bit and [0, 1], whole processes (tasks/bench_presets.py --front)."""
    import tempfile

    import bench_presets as bp

    (ROOT / "cache").mkdir(exist_ok=True)
    with tempfile.TemporaryDirectory(dir=ROOT / "cache", prefix="bench-front-") as tmp:
        work = Path(tmp)
        bp.warm_up(work)
        front = bp.front(work, sides=(256,) if quick else bp.FRONT_SIDES,
                         units_list=("8-bit",) if quick else ("8-bit", "[0, 1]"))
    return dict(case="front", frames=8, front=front, sgemm_gflops=sgemm_gflops())


def case_robust(quick: bool) -> dict:
    """Issue "never below the simple answers": the sweep of tasks/bench_robust.py, best included."""
    import bench_robust as br

    rows = br.sweep(48 if quick else 64, quick, best=True)
    return dict(case="robust", size=48 if quick else 64, summary=br.summary(rows), rows=rows,
                sgemm_gflops=sgemm_gflops())


def case_robust_noise(quick: bool) -> dict:
    """Issue "never below the simple answers" under read noise, off the centre crops (tasks/bench_robust.py
    --noise-crops)."""
    import bench_robust as br

    rows = br.noise_sweep(quick)
    return dict(case="robust-noise", size=64, summary=br.crop_summary(rows), rows=rows, sgemm_gflops=sgemm_gflops())


def case_robust_crops(quick: bool) -> dict:
    """Issue "never below the simple answers" off the centre crops, without noise (tasks/bench_robust.py
    --crops)."""
    import bench_robust as br

    rows = br.crops_sweep(quick)
    return dict(case="robust-crops", size=64, summary=br.crop_summary(rows, br.code_label), rows=rows,
                sgemm_gflops=sgemm_gflops())


CASES = dict(a=case_a, b=case_b, b1=case_b1, c=case_c, static=case_static, quality=case_quality, bayer=case_bayer,
             sequence=case_sequence, video=case_video, footage=case_footage, calibrated=case_calibrated, startup=case_startup, units=case_units)
CASES["nonlocal"] = case_nonlocal  # a keyword: not a dict() argument
CASES["adapt"] = case_adapt
CASES["outputs"] = case_outputs
CASES["outputs4k"] = case_outputs4k
CASES["presets"] = case_presets
CASES["front"] = case_front
CASES["robust"] = case_robust
CASES["robust-noise"] = case_robust_noise
CASES["robust-crops"] = case_robust_crops


def run_child(name: str, quick: bool) -> dict:
    cmd = [sys.executable, __file__, "--child", name] + (["--quick"] if quick else [])
    proc = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT)
    if proc.returncode != 0:
        return dict(case=name, error=proc.stderr.strip().splitlines()[-1] if proc.stderr.strip() else "failed")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--cases", default="a,static,b,b1,c,quality,nonlocal,adapt,bayer,sequence,video,footage,calibrated,startup,units")
    ap.add_argument("--quick", action="store_true", help="smaller sizes (a smoke run)")
    ap.add_argument("--child", default=None, help=argparse.SUPPRESS)
    a = ap.parse_args()
    (ROOT / "cache").mkdir(exist_ok=True)  # the cases' temporary stores live there (absent in a fresh clone)
    if a.child:
        from codedvideo.solvers.omp_kernel import load_kernels

        load = load_kernels()  # once per process: reported, not inside the first timing
        print(json.dumps(dict(CASES[a.child](a.quick), kernel_load_seconds=load), default=float))
        return 0
    results = dict(machine=dict(platform=platform.platform(), cpus=os.cpu_count(), python=platform.python_version()),
                   quick=a.quick, date=time.strftime("%Y-%m-%d %H:%M:%S"), cases={})
    for name in a.cases.split(","):
        print(f"bench: case {name} ...", file=sys.stderr, flush=True)
        results["cases"][name] = run_child(name, a.quick)
    RESULTS.mkdir(parents=True, exist_ok=True)
    # a smoke run (--quick) has a file of its own: it never replaces the last full run's figures
    latest = RESULTS / ("quick.json" if a.quick else "latest.json")
    if latest.exists() and not a.quick:  # keep the other cases of the last full run, each with its date
        previous = json.loads(latest.read_text())
        if not previous.get("quick"):
            for case in previous.get("cases", {}).values():
                case.setdefault("date", previous.get("date"))
            results["cases"] = {**previous.get("cases", {}), **results["cases"]}
    for case in results["cases"].values():
        case.setdefault("date", results["date"])
    latest.write_text(json.dumps(results, indent=2, default=float) + "\n")
    print(table(results))
    print(f"results: {latest}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
