"""make bench CASES=robust: the default and best against the simple answers on every code a user can give.

For N = 8, 16 and 18 on held-out real clips the dictionaries never saw (crops of bikes-a, carphone and bunny):
every hitomi bump length 1 to N - 1, Bernoulli p 0.1 to 0.9 and every other code family, without noise;
hitomi L = 2, N / 2 and N - 2 and Bernoulli 0.5 under read noise 4, 15 and 40 grey levels.  Beside each: the
still estimate (coded / open count, a plain long exposure) and GAP-TV on the same capture.  PSNR on [0, 1]
frames; the default is run on the capture in [0, 1] floats and in 8-bit units (its PSNR in both), best on the
[0, 1] capture.  ``cv.reconstruct`` in one process (the command line's bits); seconds per call.

``--noise-crops``: read noise on the corners of the clips as well as their centres (a flat corner does not behave
as the centre does): 64x64 crops at the centre and two corners of bikes-a, bikes-b, carphone and bunny, N = 8,
hitomi L = 2 and Bernoulli 0.5, read noise 4 to 79 grey levels (:data:`NOISE_SIGMAS`), the same figures for each
capture.

``--crops``: the paper's codes, long bumps, Bernoulli 0.5 and the grid code (:data:`CROP_CODES`) on the centre and
the four corners of the same clips and of ``bunny-b`` (:data:`STILL_SCENES`), without noise, the same figures for
each capture.

    python tasks/bench_robust.py [--quick] [--best] [--size 64] [--out bench/results/robust.json]
    python tasks/bench_robust.py --noise-crops [--quick] [--out bench/results/robust_noise.json]
    python tasks/bench_robust.py --crops [--quick] [--out bench/results/robust_crops.json]
"""
from __future__ import annotations

import argparse
import json
import sys
import time
import warnings
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
SCENES = ("bikes-a", "carphone", "bunny")
SIGMAS = (4.0, 15.0, 40.0)
#: ``--noise-crops`` and ``--crops``: the clips.
CROP_SCENES = ("bunny", "carphone", "bikes-a", "bikes-b")
#: ``--crops`` also: a clip whose corners hold still but for their texture (a single capture cannot tell that
#: from motion: docs/research.md, "Telling still from moving in a single capture").
STILL_SCENES = ("bunny-b",)
#: ``--noise-crops``: the corners of the 64x64 crops in the 256x256 scenes (the centre, top left and bottom right),
#: the codes and the read noise levels (grey levels of 255).
NOISE_CROPS = ((96, 96), (0, 0), (192, 192))
NOISE_CODES = (("hitomi", dict(bump=2)), ("bernoulli", dict(p=0.5)))
NOISE_SIGMAS = (4.0, 8.0, 15.0, 20.0, 25.0, 30.0, 40.0, 60.0, 79.0)
#: ``--crops``: ``(N, code, options)`` of each capture, and the corners of the 64x64 crops (the centre and the four
#: corners).
CROP_CODES = ((8, "hitomi", dict(bump=2)), (8, "bernoulli", dict(p=0.5)), (8, "grid", {}),
              (16, "hitomi", dict(bump=2)), (16, "hitomi", dict(bump=8)), (16, "hitomi", dict(bump=14)),
              (16, "bernoulli", dict(p=0.5)), (16, "grid", {}), (18, "hitomi", dict(bump=2)), (18, "grid", {}))
CROPS = ((96, 96), (0, 0), (0, 192), (192, 0), (192, 192))
FAMILIES = (("rowwise", dict(bump=2)), ("rowwise", dict(bump=4)), ("rowwise", dict(bump=6)), ("thinout", {}),
            ("grid", {}), ("flutter", {}), ("shifting", dict(p=0.5)), ("hitomi-tiled", dict(bump=2)),
            ("hitomi-tiled", dict(bump=4)), ("global", {}))


def codes(frames: int, quick: bool):
    """``(name, options, sigmas)`` of every code swept at ``frames``."""
    bumps = (2, frames // 2, frames - 2) if quick else range(1, frames)
    for bump in bumps:
        noisy = bump in (2, frames // 2, frames - 2)
        yield "hitomi", dict(bump=bump), (0.0, *SIGMAS) if noisy and not quick else (0.0,)
    for p in ((0.1, 0.5) if quick else (0.1, 0.2, 0.3, 0.5, 0.7, 0.8, 0.9)):
        yield "bernoulli", dict(p=p), (0.0, *SIGMAS) if p == 0.5 and not quick else (0.0,)
    for name, options in (FAMILIES[3:5] if quick else FAMILIES):
        yield name, options, (0.0,)


def _psnr(frames: np.ndarray, truth: np.ndarray) -> float:
    from codedvideo.model.metrics import evaluate

    return float(evaluate(np.clip(frames, 0, 1), truth, data_range=1.0)["psnr"])


def one_case(video: np.ndarray, name: str, options: dict, sigma: float, best: bool) -> dict:
    """Every figure of one capture: ``video`` (N, H, W) in [0, 1] under code ``name``, read noise ``sigma`` (grey
    levels of 255)."""
    import codedvideo as cv
    from codedvideo.solvers.baselines import gap_tv, static_estimate
    from codedvideo.solvers.guard import sparse_weight

    n, h, w = video.shape
    mask = cv.make_code(name, (h, w), frames=n, seed=0, **options)
    coded = cv.simulate(video, mask, noise_sigma=sigma / 255, seed=1)
    noise = dict(noise_sigma=sigma / 255) if sigma else {}
    row = dict(frames=n, code=name, **options, sigma=sigma, sparse_weight=round(sparse_weight(mask)[0], 4))
    row["trivial"] = _psnr(static_estimate(coded, mask), video)
    row["gaptv"] = _psnr(gap_tv(coded, mask, data_range=1.0), video)
    t = time.perf_counter()
    out = cv.reconstruct(coded, mask, data_range=1.0, progress=False, **noise)
    row["default_seconds"] = time.perf_counter() - t
    row["default"] = _psnr(out, video)
    row["default_range"] = [float(out.min()), float(out.max())]
    eight = cv.reconstruct(coded * 255, mask, data_range=255.0, progress=False,
                           **({"noise_sigma": sigma} if sigma else {}))
    row["default_8bit"] = _psnr(eight / 255, video)
    if best:
        t = time.perf_counter()
        out = cv.reconstruct(coded, mask, data_range=1.0, progress=False, preset="best", **noise)
        row["best_seconds"] = time.perf_counter() - t
        row["best"] = _psnr(out, video)
    row["floor"] = max(row["trivial"], row["gaptv"])
    return row


def sweep(size: int, quick: bool, best: bool, scenes=SCENES, log=sys.stderr) -> list[dict]:
    """Every case of :func:`codes` at N = 8, 16 and 18 on ``scenes`` (``size`` square crops)."""
    from codedvideo.data.footage import footage_scene

    rows = []
    for frames in ((8, 16) if quick else (8, 16, 18)):
        videos = {s: (footage_scene(s, frames=frames, size=(size, size)) / 255).astype(np.float32) for s in scenes}
        for name, options, sigmas in codes(frames, quick):
            for sigma in sigmas:
                for scene, video in videos.items():
                    with warnings.catch_warnings():
                        warnings.simplefilter("ignore")  # (out-of-range and preset warnings: the figures say it)
                        row = dict(scene=scene, **one_case(video, name, options, sigma, best))
                    rows.append(row)
                    print(_line(row), file=log, flush=True)
    return rows


def crop_sweep(frames: int, crops, captures, scenes=CROP_SCENES, log=sys.stderr) -> list[dict]:
    """:func:`one_case` with best on 64x64 crops (their top left corners ``crops`` in the 256x256 ``scenes``) of
    ``frames`` sub-frames, each capture of ``captures`` (``(code, options, read noise)``) on each crop."""
    from codedvideo.data.footage import footage_scene

    rows = []
    for scene in scenes:
        whole = footage_scene(scene, frames=frames) / 255
        for y, x in crops:
            video = whole[:, y:y + 64, x:x + 64].astype(np.float32)
            for name, options, sigma in captures:
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")  # (out-of-range and preset warnings: the figures say it)
                    row = dict(scene=scene, crop=[y, x], **one_case(video, name, options, sigma, True))
                rows.append(row)
                print(_line(row), file=log, flush=True)
    return rows


def noise_sweep(quick: bool, log=sys.stderr) -> list[dict]:
    """Every capture of ``--noise-crops`` (:data:`CROP_SCENES` x :data:`NOISE_CROPS` x :data:`NOISE_CODES` x
    :data:`NOISE_SIGMAS`; ``quick``: the first two crops at 15 and 40 grey levels), each :func:`one_case` with best."""
    sigmas = (15.0, 40.0) if quick else NOISE_SIGMAS
    return crop_sweep(8, NOISE_CROPS[:2] if quick else NOISE_CROPS,
                      [(name, options, sigma) for name, options in NOISE_CODES for sigma in sigmas], log=log)


def crops_sweep(quick: bool, log=sys.stderr) -> list[dict]:
    """Every capture of ``--crops``: :data:`CROP_CODES` on :data:`CROP_SCENES` x :data:`CROPS` (``quick``: the
    first two codes on the first two crops), each :func:`one_case` with best."""
    rows = []
    for frames, name, options in CROP_CODES[:2] if quick else CROP_CODES:
        rows += crop_sweep(frames, CROPS[:2] if quick else CROPS, [(name, options, 0.0)],
                           scenes=CROP_SCENES + STILL_SCENES, log=log)
    return rows


def _code(row: dict) -> str:
    """A row's code and its options: ``hitomi bump=8``."""
    return row["code"] + "".join(f" {k}={row[k]:g}" for k in ("bump", "p") if k in row)


def code_label(row: dict) -> str:
    """A row's N and code, as :func:`crop_summary` groups the rows of ``--crops``: ``N = 16 hitomi bump=8``."""
    return f"N = {row['frames']} {_code(row)}"


def crop_summary(rows: list[dict], key=lambda row: f"{row['sigma']:g}") -> dict:
    """For each value of ``key`` over the rows of :func:`crop_sweep` (the read noise by default, or
    :func:`code_label`): best - the default and the default - the better simple answer, worst and median, dB."""
    out = {}
    for value in dict.fromkeys(map(key, rows)):
        level = [r for r in rows if key(r) == value]
        lead = [r["best"] - r["default"] for r in level]
        margin = [r["default"] - r["floor"] for r in level]
        out[value] = dict(cases=len(level), best_lead_worst=min(lead), best_lead_median=float(np.median(lead)),
                          best_below_default_0_05=sum(x < -0.05 for x in lead),
                          default_margin_worst=min(margin), default_margin_median=float(np.median(margin)),
                          default_below_floor_0_3=sum(x < -0.3 for x in margin))
    return out


def _line(row: dict) -> str:
    code = _code(row)
    best = f" best {row['best']:6.2f}" if "best" in row else ""
    return (f"N={row['frames']:2d} {code:22s} sigma {row['sigma']:4.0f} {row['scene']:9s} trivial {row['trivial']:6.2f}"
            f" gaptv {row['gaptv']:6.2f} default {row['default']:6.2f} ({row['default'] - row['floor']:+.2f})"
            f" 8-bit {row['default_8bit']:6.2f}{best} w {row['sparse_weight']:.2f}")


def summary(rows: list[dict]) -> dict:
    """The targets of the sweep: the worst margins of the default over the better simple answer and of best over
    the default, and the frame values beyond [-0.25, 1.25]."""
    margin = [r["default"] - r["floor"] for r in rows]
    out = dict(cases=len(rows), default_worst_margin=min(margin),
               default_below_floor_0_3=sum(m < -0.3 for m in margin),
               default_8bit_worst_gap=min(r["default_8bit"] - r["default"] for r in rows),
               out_of_range=sum(r["default_range"][0] < -0.25 or r["default_range"][1] > 1.25 for r in rows))
    if all("best" in r for r in rows):
        lead = [r["best"] - r["default"] for r in rows]
        out.update(best_worst_lead=min(lead), best_below_default_0_05=sum(x < -0.05 for x in lead))
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="a few codes at N = 8 and 16, no noise sweep")
    ap.add_argument("--best", action="store_true", help="also --preset best (several times the time)")
    crops = ap.add_mutually_exclusive_group()
    crops.add_argument("--noise-crops", action="store_true",
                       help="read noise 4 to 79 on the centre and two corners of four clips, best included")
    crops.add_argument("--crops", action="store_true",
                       help="ten codes at N = 8, 16 and 18 on the centre and four corners of four clips, best included")
    ap.add_argument("--size", type=int, default=64, help="crop side (default 64)")
    ap.add_argument("--out", default=None, help="results file (default: bench/results/robust.json, or "
                                                "robust_noise.json with --noise-crops, robust_crops.json with "
                                                "--crops)")
    a = ap.parse_args()
    if a.noise_crops:
        rows = noise_sweep(a.quick)
        result = dict(size=64, quick=a.quick, summary=crop_summary(rows), rows=rows)
    elif a.crops:
        rows = crops_sweep(a.quick)
        result = dict(size=64, quick=a.quick, summary=crop_summary(rows, code_label), rows=rows)
    else:
        rows = sweep(a.size, a.quick, a.best)
        result = dict(size=a.size, quick=a.quick, summary=summary(rows), rows=rows)
    name = "robust_noise.json" if a.noise_crops else "robust_crops.json" if a.crops else "robust.json"
    out = Path(a.out or ROOT / "bench" / "results" / name)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=1) + "\n")
    print(json.dumps(result["summary"], indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
