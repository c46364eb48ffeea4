"""Issue 16: the non-local method (similar patches under different codes solved together) beside
the default OMP, GAP-TV and the 3D DCT, on case_quality's scenes and codes (256x256, N = 8).

The non-local method's seconds include the default reconstruction it starts from.
Results go to bench/results/nonlocal.json and a table is printed.

    python tasks/bench_nonlocal.py [--quick] [--scenes footage:bikes-a,...]
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tasks"))
from _bench_common import QUALITY_SCENES, _q, default_and_dct, quality_captures, sgemm_gflops  # noqa: E402

RESULTS = ROOT / "bench" / "results"


def case_nonlocal(quick: bool, scenes=None, options: dict | None = None) -> dict:
    """Default OMP, the non-local method (its seconds include the default's), GAP-TV and the 3D DCT
    (same OMP, up to 16 atoms) on held-out real footage and synthetic scenes, N = 8.

    The default and the non-local method run as the pipeline runs them (the tile graph on every
    core); with ``options`` (keyword arguments of ``nonlocal_region`` the pipeline does not take) the
    non-local step runs on the whole image in this thread after the default's tile graph."""
    import codedvideo as cv
    from codedvideo.data import shipped
    from codedvideo.solvers.baselines import gap_tv
    from codedvideo.engine.config import PipelineConfig, omp_settings
    from codedvideo.model.metrics import evaluate
    from codedvideo.solvers.nonlocal_sc import nonlocal_region
    from codedvideo.solvers.omp_kernel import load_kernels
    from codedvideo.data.scenes import load_video
    from codedvideo.engine.simulation import simulate_capture
    from codedvideo.model.codes import CodeSpec
    from codedvideo.engine.windows import Execution, reconstruct_volume
    from codedvideo.formats.store import load_dictionary

    load_kernels()
    D, _ = load_dictionary(shipped.verified(8))
    rc = PipelineConfig().reconstruct
    size = (96, 96) if quick else (256, 256)
    extra = options or {}
    (ROOT / "cache").mkdir(exist_ok=True)
    # compile the non-local kernels outside the timings
    warm = load_video((scenes or QUALITY_SCENES)[0], frames=8, size=(32, 32))
    cap = simulate_capture(warm, code=CodeSpec("hitomi", bump=2), sigma=0.0, seed=0)
    nonlocal_region(cap["coded"], cap["mask"], D, warm, omp_settings(rc, 0.0))
    rows = []
    for video, cap, row in quality_captures(scenes or (QUALITY_SCENES[:2] if quick else QUALITY_SCENES), size):
        sigma = row["sigma"]
        first = default_and_dct(row, video, cap, D, rc, ROOT / "cache")
        if extra:  # parameters the pipeline does not take: the whole image in this thread
            t = time.perf_counter()
            vol, _ = nonlocal_region(cap["coded"], cap["mask"], D, first, omp_settings(rc, sigma), **extra)
            row["nonlocal"] = dict(seconds=row["default"]["seconds"] + time.perf_counter() - t,
                                   **_q(evaluate(vol, video, data_range=255.0)))
        else:  # as `--method nonlocal` runs: the default's tile graph with the groups in each tile
            s = omp_settings(rc.model_copy(update=dict(method="nonlocal")), sigma)
            with tempfile.TemporaryDirectory(dir=ROOT / "cache") as tmp:
                t = time.perf_counter()
                vol, _ = reconstruct_volume(cap["coded"], cap["mask"], D, settings=s,
                                            run=Execution(cache=tmp, progress=False))
                row["nonlocal"] = dict(seconds=time.perf_counter() - t, **_q(evaluate(vol, video, data_range=255.0)))
            with tempfile.TemporaryDirectory(dir=ROOT / "cache") as tmp:  # --adapt: both passes timed
                t = time.perf_counter()
                vol = cv.reconstruct(cap["coded"], cap["mask"], method="nonlocal", adapt=True, dictionary=D,
                                     noise_sigma=sigma, data_range=255.0, cache=tmp, progress=False)
                row["adapt"] = dict(seconds=time.perf_counter() - t, **_q(evaluate(vol, video, data_range=255.0)))
        t = time.perf_counter()
        vol = gap_tv(cap["coded"], cap["mask"])
        row["gaptv"] = dict(seconds=time.perf_counter() - t, **_q(evaluate(vol, video, data_range=255.0)))
        rows.append(row)
        print("  ".join(table_row(row)), flush=True)
    return dict(case="nonlocal", size=list(size), frames=8, options=extra, rows=rows,
                sgemm_gflops=sgemm_gflops())


def table_row(x: dict) -> list[str]:
    cell = lambda v: f"{v['psnr']:6.2f} {v['seconds']:5.2f}s"  # noqa: E731
    return [f"{x['scene']:<24}{x['code'] + ' L=' + str(x['bump']):<12}{x['sigma']:>4.0f}",
            *(f"{cell(x[k]):>14}" for k in ("adapt", "nonlocal", "default", "gaptv", "dct") if k in x),
            f"{x['nonlocal']['psnr'] - x['default']['psnr']:+6.2f}"]


def nonlocal_table(r: dict) -> list[str]:
    methods = [k for k in ("adapt", "nonlocal", "default", "gaptv", "dct") if k in r["rows"][0]]
    heads = {"adapt": "nl --adapt dB/s", "nonlocal": "nonlocal dB/s", "default": "default", "gaptv": "gap-tv",
             "dct": "dct (16)"}
    out = [f"{'scene':<24}{'code':<12}{'sig':>4}  " + "  ".join(f"{heads[k]:>14}" for k in methods) + f"  {'nl-def':>6}"]
    out += ["  ".join(table_row(x)) for x in r["rows"]]
    for kind in ("real", "synthetic"):
        sel = [x for x in r["rows"] if x["kind"] == kind]
        if sel:
            m = {k: np.mean([x[k]["psnr"] for x in sel]) for k in methods}
            sec = {k: np.mean([x[k]["seconds"] for x in sel]) for k in methods if k in ("adapt", "nonlocal", "default")}
            worst = min(x["nonlocal"]["psnr"] - x["default"]["psnr"] for x in sel)
            line = f"mean over {kind} ({len(sel)}): "
            for k in ("adapt", "nonlocal", "default"):
                if k in m:
                    line += (f"{heads[k].split(' dB')[0]} {m[k]:.2f} dB (gap-tv {m[k] - m['gaptv']:+.2f}, "
                             f"{sec[k] / sec['default']:.2f}x the default's time), ")
            out.append(line + f"gap-tv {m['gaptv']:.2f}, dct {m['dct']:.2f}; worst nonlocal-default {worst:+.2f}")
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--scenes", help="comma-separated scene specs (default: case_quality's)")
    ap.add_argument("--options", default="{}", help="JSON keyword arguments of nonlocal_region")
    ap.add_argument("--out", default=str(RESULTS / "nonlocal.json"))
    a = ap.parse_args()
    r = case_nonlocal(a.quick, a.scenes.split(",") if a.scenes else None, json.loads(a.options))
    Path(a.out).parent.mkdir(parents=True, exist_ok=True)
    Path(a.out).write_text(json.dumps(r, indent=1))
    print("\n".join(nonlocal_table(r)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
