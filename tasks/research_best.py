"""Issue 31 research: can `--preset best` (nonlocal --adapt) buy quality with its spare time?

`best` takes ~3.3 s as a process at 256x256, N = 8; the target allows 30 s.  Candidates, each built from the
library's own functions (nothing under src/ changed), on the whole image in this one thread
(NUMBA_NUM_THREADS=1), against `nonlocal --adapt` rebuilt the same way (checked against the library's
pipeline, `cv.reconstruct(..., method="nonlocal", adapt=True, workers=1)`):

    base  survey (every 7th reference, from the default's estimate) -> K-SVD adaptation -> second pass
          (every 4th reference, matched on the survey's result, adapted dictionary): `nonlocal --adapt`
    a3/a2 the second pass on every 3rd / 2nd reference
    b     a second adaptation on the second pass's result (K-SVD from the adapted dictionary), then a
          third pass (every 4th) matched on the second pass's result
    c     ADAPT_ITERATIONS 8, ADAPT_SAMPLES 14000, second pass every 3rd
    d     the mean of the second pass and one whose reference grid is offset by 2 (half a step) in both
          axes; d+ adds both grids' sums before dividing and projecting (one aggregation)

Tuning clips bikes-a, carphone; held out bikes-b, bunny; "NAME@8": the clip's frames 8..15.
256x256, N = 8, hitomi L = 2 and Bernoulli(0.5), no noise (tasks/research_iterative.case_input).
Time: each stage timed in this thread; a candidate's time is the sum of its stages (shared stages
counted in each), as a ratio to base's.  Writes /tmp/research-best/results.jsonl.

    NUMBA_NUM_THREADS=1 OMP_NUM_THREADS=1 nice -n 10 python tasks/research_best.py [--scenes ...] [--check]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tasks"))
OUT = Path(os.environ.get("RESEARCH_BEST_OUT", "/tmp/research-best"))
OUT.mkdir(parents=True, exist_ok=True)

import research_iterative as ri  # noqa: E402

ri.CACHE = OUT / "inputs"  # the captures are built by its helper, cached here (nothing written under /work/main)
ri.CACHE.mkdir(parents=True, exist_ok=True)

TUNE, HELD, CODES = ri.TUNE, ri.HELD, ri.CODES


def timed(fn, *a, **k):
    t = time.perf_counter()
    r = fn(*a, **k)
    return r, time.perf_counter() - t


def run_case(scene, code, bump, D, settings, default_settings, check=False):
    from codedvideo.engine import adaptation
    from codedvideo.engine.adaptation import adapt_dictionary
    from codedvideo.engine.windows import reconstruct_volume
    from codedvideo.solvers.nonlocal_sc import finish, nonlocal_region

    video, mask, coded = ri.case_input(scene, code, bump)
    H, W = coded.shape
    T, R = {}, {}
    ps = lambda x: ri.psnr(x, video)  # noqa: E731

    def nl(Dx, first, step, offset=0, sums=False):
        kw = dict(step=step)
        if offset:
            kw.update(origin=(offset, offset), image_shape=(H + offset, W + offset))
        return nonlocal_region(coded, mask, Dx, first, settings, sums=sums, **kw)

    with tempfile.TemporaryDirectory(dir=OUT) as tmp:
        (first, _), T["first"] = timed(reconstruct_volume, coded, mask, D, settings=default_settings, cache=tmp,
                                       workers=1, progress=False)
    (survey, _), T["survey"] = timed(nl, D, first, adaptation.ADAPT_SURVEY_STEP)
    (Da, _), T["adapt"] = timed(adapt_dictionary, survey, D)
    (base, _), T["second4"] = timed(nl, Da, survey, 4)
    pre = T["first"] + T["survey"] + T["adapt"]
    R["base"], tot = ps(base), {"base": pre + T["second4"]}
    # a: denser second pass
    for s in (3, 2):
        (x, _), T[f"second{s}"] = timed(nl, Da, survey, s)
        R[f"a{s}"], tot[f"a{s}"] = ps(x), pre + T[f"second{s}"]
    # b: adapt again on the second pass's result, third pass matched on it
    (Db, _), T["adapt2"] = timed(adapt_dictionary, base, Da)
    (x, _), T["third4"] = timed(nl, Db, base, 4)
    R["b"], tot["b"] = ps(x), tot["base"] + T["adapt2"] + T["third4"]
    # c: more K-SVD, second pass every 3rd
    old = adaptation.ADAPT_ITERATIONS, adaptation.ADAPT_SAMPLES
    adaptation.ADAPT_ITERATIONS, adaptation.ADAPT_SAMPLES = 8, 14000
    try:
        (Dc, _), T["adapt_c"] = timed(adapt_dictionary, survey, D)
    finally:
        adaptation.ADAPT_ITERATIONS, adaptation.ADAPT_SAMPLES = old
    (x, _), T["second3_c"] = timed(nl, Dc, survey, 3)
    R["c"], tot["c"] = ps(x), T["first"] + T["survey"] + T["adapt_c"] + T["second3_c"]
    # d: second pass on a grid offset by half a step, averaged (d) or aggregated together (d+)
    (s0, T["sums0"]) = timed(nl, Da, survey, 4, 0, True)
    (s2, T["sums2"]) = timed(nl, Da, survey, 4, 2, True)
    x0 = finish(s0[0], s0[1], coded, mask)
    x2 = finish(s2[0], s2[1], coded, mask)
    assert abs(ps(x0) - R["base"]) < 1e-6, (ps(x0), R["base"])
    x2 = np.where(np.isnan(x2), x0, x2)  # pixels no group of the offset grid reached (the image's edge)
    R["d"] = ps(0.5 * (x0 + x2))
    R["d+"] = ps(finish(s0[0] + s2[0], s0[1] + s2[1], coded, mask))
    tot["d"] = tot["d+"] = tot["base"] + T["sums2"]
    row = dict(scene=scene, code=f"{code}{bump}", psnr=R, gain={k: R[k] - R["base"] for k in R},
               seconds=tot, ratio={k: tot[k] / tot["base"] for k in tot}, stages=T)
    if check:  # the library's own pipeline, one thread
        import codedvideo as cv

        lib, t_lib = timed(cv.reconstruct, coded, mask, method="nonlocal", adapt=True, data_range=255.0, workers=1)
        row["library"] = dict(psnr=ps(lib), seconds=t_lib, max_abs_diff=float(np.nanmax(np.abs(lib - base))))
    return row


def run_extra(scene, code, bump, D, settings, default_settings):
    """Candidate b's variants: the third pass every 3rd (b3), a fourth round of adaptation and pass (b4x),
    both adaptations with 8 iterations on 14000 patches (bc)."""
    from codedvideo.engine import adaptation
    from codedvideo.engine.adaptation import adapt_dictionary
    from codedvideo.engine.windows import reconstruct_volume
    from codedvideo.solvers.nonlocal_sc import nonlocal_region

    video, mask, coded = ri.case_input(scene, code, bump)
    T, R = {}, {}
    ps = lambda x: ri.psnr(x, video)  # noqa: E731
    nl = lambda Dx, first, step: nonlocal_region(coded, mask, Dx, first, settings, step=step)[0]  # noqa: E731

    with tempfile.TemporaryDirectory(dir=OUT) as tmp:
        (first, _), T["first"] = timed(reconstruct_volume, coded, mask, D, settings=default_settings, cache=tmp,
                                       workers=1, progress=False)
    survey, T["survey"] = timed(nl, D, first, adaptation.ADAPT_SURVEY_STEP)
    (Da, _), T["adapt"] = timed(adapt_dictionary, survey, D)
    base, T["second4"] = timed(nl, Da, survey, 4)
    tot = {"base": sum(T.values())}
    R["base"] = ps(base)
    (Db, _), T["adapt2"] = timed(adapt_dictionary, base, Da)
    xb, T["third4"] = timed(nl, Db, base, 4)
    R["b"], tot["b"] = ps(xb), tot["base"] + T["adapt2"] + T["third4"]
    x, T["third3"] = timed(nl, Db, base, 3)
    R["b3"], tot["b3"] = ps(x), tot["base"] + T["adapt2"] + T["third3"]
    (Dd, _), T["adapt3"] = timed(adapt_dictionary, xb, Db)
    x, T["fourth4"] = timed(nl, Dd, xb, 4)
    R["b4x"], tot["b4x"] = ps(x), tot["b"] + T["adapt3"] + T["fourth4"]
    old = adaptation.ADAPT_ITERATIONS, adaptation.ADAPT_SAMPLES
    adaptation.ADAPT_ITERATIONS, adaptation.ADAPT_SAMPLES = 8, 14000
    try:
        (Dc, _), T["adapt_c"] = timed(adapt_dictionary, survey, D)
        xc, T["second4_c"] = timed(nl, Dc, survey, 4)
        (Dc2, _), T["adapt2_c"] = timed(adapt_dictionary, xc, Dc)
    finally:
        adaptation.ADAPT_ITERATIONS, adaptation.ADAPT_SAMPLES = old
    x, T["third4_c"] = timed(nl, Dc2, xc, 4)
    R["bc"] = ps(x)
    tot["bc"] = T["first"] + T["survey"] + T["adapt_c"] + T["second4_c"] + T["adapt2_c"] + T["third4_c"]
    return dict(scene=scene, code=f"{code}{bump}", psnr=R, gain={k: R[k] - R["base"] for k in R},
                seconds=tot, ratio={k: tot[k] / tot["base"] for k in tot}, stages=T)


def research_settings():
    """The kernels loaded; the shipped N = 8 dictionary, the non-local method's and the default's settings in
    8-bit units, as the command line makes them."""
    from codedvideo.data import shipped
    from codedvideo.engine.config import PipelineConfig, omp_settings
    from codedvideo.formats.store import load_dictionary
    from codedvideo.model.units import infer_data_range
    from codedvideo.solvers.omp_kernel import load_kernels

    load_kernels()
    D, _ = load_dictionary(shipped.verified(8))
    rc = PipelineConfig().reconstruct
    scale = infer_data_range(255.0).scale
    return (D, omp_settings(rc.model_copy(update=dict(method="nonlocal")), 0.0, scale=scale),
            omp_settings(rc, 0.0, scale=scale))


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--scenes", default=",".join(TUNE + HELD))
    ap.add_argument("--check", action="store_true", help="also run the library's nonlocal --adapt")
    ap.add_argument("--tag", default="")
    ap.add_argument("--extra", action="store_true", help="candidate b's variants (run_extra)")
    a = ap.parse_args()
    D, settings, default_settings = research_settings()
    # warm the compiled kernels outside the timings
    v, m, c = ri.case_input(a.scenes.split(",")[0], "hitomi", 2)
    from codedvideo.solvers.nonlocal_sc import nonlocal_region

    nonlocal_region(c[:40, :40], m[:, :40, :40], D, v[:, :40, :40], settings, step=4)
    rows = []
    for scene in a.scenes.split(","):
        for code, bump in CODES:
            r = (run_extra(scene, code, bump, D, settings, default_settings) if a.extra else
                 run_case(scene, code, bump, D, settings, default_settings, check=a.check))
            r["tag"] = a.tag
            rows.append(r)
            with open(OUT / "results.jsonl", "a") as fh:
                fh.write(json.dumps(r) + "\n")
            print(f"{scene:<12}{code}{bump:<4} base {r['psnr']['base']:.2f} "
                  + " ".join(f"{k} {v:+.2f}/{r['ratio'][k]:.2f}x" for k, v in r["gain"].items() if k != "base")
                  + (f"  lib {r['library']['psnr']:.2f} {r['library']['seconds']:.1f}s diff {r['library']['max_abs_diff']:.3g}"
                     if "library" in r else "") + f"  base {r['seconds']['base']:.1f}s", flush=True)
    summarise(rows)


def summarise(rows):
    keys = [k for k in rows[0]["gain"] if k != "base"]
    groups = (("tune", lambda s: s in TUNE), ("held", lambda s: s in HELD), ("other", lambda s: s not in TUNE + HELD))
    print("per case gains: " + "; ".join(f"{r['scene']} {r['code']} " + " ".join(f"{k} {v:+.2f}" for k, v in r["gain"].items()
                                                                                 if k != "base") for r in rows))
    for name, sel in groups:
        g = [r for r in rows if sel(r["scene"])]
        if not g:
            continue
        print(f"{name} ({len(g)} cases, base {np.mean([r['psnr']['base'] for r in g]):.2f} dB):")
        for k in keys:
            gains = [r["gain"][k] for r in g]
            print(f"  {k:<4} mean {np.mean(gains):+.3f} dB, worst {min(gains):+.3f}, "
                  f"time {np.mean([r['seconds'][k] for r in g]) / np.mean([r['seconds']['base'] for r in g]):.2f}x")


if __name__ == "__main__":
    if len(sys.argv) > 1 and sys.argv[1] == "summary":
        rows = [json.loads(line) for line in open(OUT / "results.jsonl")]
        tags = sys.argv[2:] or sorted({r["tag"] for r in rows})
        summarise([r for r in rows if r["tag"] in tags])
    else:
        main()
