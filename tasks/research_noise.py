"""Research: the refinement under the measurement (`--refine 24`, solvers/refine.py) with known read noise.

Captures: tasks/research_iterative.case_input (256x256, N = 8, Bernoulli(0.5) and hitomi L = 2), Gaussian
read noise of ``sigma`` grey levels added to the coded image here (np.random.default_rng(1), the same field
for every case).  The start is the pipeline's own `--preset best --refine 0 --noise-sigma SIGMA`
(``cv.reconstruct(noisy, mask, preset="best", refine=0, noise_sigma=SIGMA, data_range=255, workers=1)``:
nonlocal --adapt --adapt-rounds 2 with the residual tolerance auto_tolerance(SIGMA)), cached once per case
under /tmp/research-noise/.  Candidates are refinements from that start, 24 iterations each (the shipped
group prior: refine.denoise, refine.reference_grid, omp_kernel.match_references), each the un-blended
refined volume; the blends 0.3 / 0.5 / 0.7 with the start are formed afterwards (free).

Candidates (sn: the read noise, grey levels):
    base      refine.refine as shipped (accelerated GAP, exact step, sigma 4 -> 1 geometric)
    plain     GAP without the accumulated residual (exact step)
    saA       sigma_k = sqrt(base_k^2 + A sn^2)                  A in 0.25, 0.5, 1
    seB       sigma geometric from max(4, B sn) to max(1, B sn)  B in 0.5, 1
    rC[a|p][f|x]  relaxed step x += S^T (r / (SS^T + lam_k)), lam_k = C sn^2 / sigma_k^2, accelerated (a) or
              plain (p) GAP, the last projection relaxed with lam_end (f) or exact (x)

    NUMBA_NUM_THREADS=1 OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 nice -n 10 \
        python tasks/research_noise.py run --scenes bikes-a,carphone --sigma 4 --tag tune
    python tasks/research_noise.py summary [TAG ...]

Findings (2026-11-27 22:56-23:32, 2 shared cores; gain over the start in dB, mean of 4 cases, blend 0.5 unless said):
- sigma 4, tuning: base +0.28; sa0.25/0.5/1/2/3/4 +0.39/+0.49/+0.62/+0.77/+0.83/+0.87; se0.5/1 +0.37/+0.55;
  plain +0.45; r0.25pf +0.54 (+0.74 blend 0), r1pf +0.51, r0.25af +0.28, r1px +0.41.  Chosen before the
  held-out run (/tmp/research-noise/choice.txt): sa2.
- sigma 4, held out: base +0.09 (worst +0.00), sa2 -0.02 (worst -0.57: bunny -0.37/-0.57), r0.25pf +0.22
  (worst +0.10).  The chosen rule failed: raising the denoiser's level smooths bunny (cf. research_iterative).
- sigma 4, the held clips' next 8 frames: base +0.05 (worst -0.12), sa2 -0.03 (-0.82), r0.25pf +0.18 (+0.03).
- sigma 8: tuning base +0.00, sa2 +0.49, r0.25pf +0.71; held base -0.04, sa2 -0.34 (-0.92), r0.25pf +0.35 (+0.19).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tasks"))
OUT = Path(os.environ.get("RESEARCH_NOISE_OUT", "/tmp/research-noise"))
OUT.mkdir(parents=True, exist_ok=True)

import research_iterative as ri  # noqa: E402

ri.CACHE = OUT / "inputs"
ri.CACHE.mkdir(parents=True, exist_ok=True)
TUNE, HELD, CODES = ri.TUNE, ri.HELD, ri.CODES
ITER = 24
BLENDS = (0.3, 0.5, 0.7)
SECOND = ("sa2", "sa3", "sa4", "sa1p", "sa1r0.25pf")


def noisy_case(scene, code, bump, sigma):
    video, mask, coded = ri.case_input(scene, code, bump)
    noisy = (coded + np.random.default_rng(1).normal(0.0, sigma, coded.shape)).astype(np.float32)
    return video, mask, noisy


def start_of(scene, code, bump, sigma, noisy, mask):
    """The pipeline's --preset best --refine 0 --noise-sigma sigma on the noisy capture (cached)."""
    import codedvideo as cv

    f = OUT / f"start-{scene}-{code}{bump}-s{sigma:g}.npy"
    if f.exists():
        return np.load(f), None
    t = time.perf_counter()
    x0 = cv.reconstruct(noisy, mask, preset="best", refine=0, noise_sigma=float(sigma), data_range=255.0, workers=1)
    s = time.perf_counter() - t
    np.save(f, x0)
    return x0, s


def step(x, mask, y, open2, lam, accumulated=None):
    """x += S^T ((target - S x) / (SS^T + lam)) per pixel (0 where never open); lam 0: refine.to_measurements."""
    s = np.asarray(mask, np.float32)
    predicted = np.einsum("thw,thw->hw", x, s, dtype=np.float32)
    if accumulated is None:
        target = y
    else:
        accumulated += y - predicted
        target = accumulated
    denom = open2 + np.float32(lam)
    g = np.divide(1.0, denom, out=np.zeros_like(denom), where=open2 > 0).astype(np.float32)
    x += s * ((target - predicted) * g)[None]


def refine_variant(y, mask, start, levels, *, accelerated=True, lam=None, final_lam=0.0):
    """The shipped refinement's loop (no blend) with the noise levels ``levels``, the GAP kind and a relaxed
    step: ``lam`` None (exact) or an array, one per iteration.  It ran on the 3D-block prior of
    codedvideo.solvers.refine at commit 35391fb (its figures above); that prior has been replaced since by the 2D
    patches across sub-frames (tasks/research_frames.py, tasks/research_frames_noise.py), so check that commit out
    to run it again."""
    from codedvideo.solvers import refine as R

    if R.recipe().get("prior") == "frame-patches":
        raise SystemExit("research_noise.refine_variant needs the 3D-block refinement of commit 35391fb")
    from codedvideo.model import physics
    from codedvideo.model.patches import PATCH
    from codedvideo.solvers.omp_kernel import match_references

    y = np.asarray(y, np.float32)
    n, h, w = mask.shape
    open2 = physics.forward(mask, mask).astype(np.float32)
    x = np.ascontiguousarray(start, np.float32).copy()
    refs = R.reference_grid(h, w)
    groups = np.empty((refs.size, R.GROUP), np.int64)
    acc = y.copy() if accelerated else None
    for i, sigma in enumerate(levels):
        step(x, mask, y, open2, 0.0 if lam is None else lam[i], acc)
        if i % R.REGROUP == 0:
            match_references(x, refs, w - PATCH + 1, h - PATCH + 1, PATCH, R.WINDOW, R.GROUP, groups)
        x = R.denoise(x, groups, float(sigma))
    step(x, mask, y, open2, final_lam)
    return x


def candidates(sn):
    from codedvideo.solvers import refine as R

    base = R.sigmas(ITER)
    c = {"base": None, "plain": dict(levels=base, accelerated=False)}
    for a in (0.25, 0.5, 1.0):
        c[f"sa{a:g}"] = dict(levels=np.sqrt(base ** 2 + a * sn * sn))
    for b in (0.5, 1.0):
        c[f"se{b:g}"] = dict(levels=R.sigmas(ITER, max(R.SIGMA_START, b * sn), max(R.SIGMA_END, b * sn)))
    for cc, acc, fin in ((0.25, False, True), (1.0, False, True), (0.25, True, True), (1.0, False, False)):
        lam = cc * sn * sn / base ** 2
        c[f"r{cc:g}{'a' if acc else 'p'}{'f' if fin else 'x'}"] = dict(
            levels=base, accelerated=acc, lam=lam, final_lam=float(lam[-1]) if fin else 0.0)
    # second round (combinations of the first round's best, run with --only)
    for a in (2.0, 3.0, 4.0):
        c[f"sa{a:g}"] = dict(levels=np.sqrt(base ** 2 + a * sn * sn))
    c["sa1p"] = dict(levels=np.sqrt(base ** 2 + sn * sn), accelerated=False)
    lv = np.sqrt(base ** 2 + sn * sn)
    lam = 0.25 * sn * sn / lv ** 2
    c["sa1r0.25pf"] = dict(levels=lv, accelerated=False, lam=lam, final_lam=float(lam[-1]))
    return c


def run_case(scene, code, bump, sigma, only=None):
    from codedvideo.solvers import refine as R

    video, mask, noisy = noisy_case(scene, code, bump, sigma)
    x0, start_s = start_of(scene, code, bump, sigma, noisy, mask)
    ps = lambda x: ri.psnr(x, video)  # noqa: E731
    row = dict(scene=scene, code=f"{code}{bump}", sigma=sigma, start=ps(x0), start_s=start_s, gain={}, seconds={})
    for name, kw in candidates(sigma).items():
        if (only and name not in only) or (not only and name in SECOND):
            continue
        t = time.perf_counter()
        if kw is None:  # the shipped function, un-blended (the blends formed below)
            xr = R.refine(noisy, mask, x0, iterations=ITER, blend=0.0)[0]
        else:
            xr = refine_variant(noisy, mask, x0, **kw)
        row["seconds"][name] = time.perf_counter() - t
        for b in (0.0,) + BLENDS:
            row["gain"][f"{name}/{b:g}"] = ps((1 - b) * xr + b * x0) - row["start"]
    return row


def check():
    """refine_variant with the shipped settings is refine.refine (blend 0), bit for bit, on a crop; and the
    pipeline's --preset best --noise-sigma 4 is the start refined by refine.refine (bikes-a hitomi)."""
    import codedvideo as cv
    from codedvideo.solvers import refine as R

    video, mask, noisy = noisy_case("bikes-a", "hitomi", 2, 4.0)
    c = (slice(None), slice(0, 96), slice(0, 96))
    x0 = video[c] + np.random.default_rng(2).normal(0, 5, video[c].shape).astype(np.float32)
    a = R.refine(noisy[c[1:]], mask[c], x0, iterations=ITER, blend=0.0)[0]
    b = refine_variant(noisy[c[1:]], mask[c], x0, R.sigmas(ITER))
    print("variant == shipped (crop):", np.array_equal(a, b), float(np.abs(a - b).max()))
    s0, _ = start_of("bikes-a", "hitomi", 2, 4.0, noisy, mask)
    t = time.perf_counter()
    full = cv.reconstruct(noisy, mask, preset="best", noise_sigma=4.0, data_range=255.0, workers=1)
    t1 = time.perf_counter()
    mine = R.refine(noisy, mask, s0, iterations=ITER)[0]
    t2 = time.perf_counter()
    print(f"pipeline best {ri.psnr(full, video):.3f} dB ({t1 - t:.1f}s), start+refine {ri.psnr(mine, video):.3f} "
          f"({t2 - t1:.1f}s refine), max diff {float(np.abs(full - mine).max()):.3g}")


def main_run(a):
    held = [s for s in a.scenes.split(",") if s in HELD]
    if held and a.sigma == 4 and not (OUT / "choice.txt").exists():
        sys.exit("held-out clips asked before /tmp/research-noise/choice.txt was written")
    only = set(filter(None, a.only.split(",")))
    rows = []
    for scene in a.scenes.split(","):
        for code, bump in CODES:
            r = run_case(scene, code, bump, a.sigma, only)
            r["tag"] = a.tag
            rows.append(r)
            with open(OUT / "results.jsonl", "a") as fh:
                fh.write(json.dumps(r) + "\n")
            g = r["gain"]
            print(f"{scene:<9}{code}{bump:<2} s{a.sigma:g} start {r['start']:.2f} ({r['start_s'] or 0:.0f}s) "
                  + " ".join(f"{k} {v:+.2f}" for k, v in g.items() if k.endswith("/0.5"))
                  + f"  ({np.mean(list(r['seconds'].values())):.1f} s each)", flush=True)
    summarise(rows)


def summarise(rows):
    keys = list(rows[0]["gain"])
    other = sorted({r["scene"] for r in rows} - set(TUNE + HELD))
    for name, sel in (("tune", TUNE), ("held", HELD), ("other", other)):
        for sigma in sorted({r["sigma"] for r in rows}):
            g = [r for r in rows if r["scene"] in sel and r["sigma"] == sigma]
            if not g:
                continue
            print(f"{name} sigma {sigma:g} ({len(g)} cases, start {np.mean([r['start'] for r in g]):.2f} dB)")
            ks = [k for k in keys if all(k in r["gain"] for r in g)]
            for k in sorted(ks, key=lambda k: -np.mean([r["gain"][k] for r in g])):
                v = [r["gain"][k] for r in g]
                print(f"  {k:<12} mean {np.mean(v):+.3f} worst {min(v):+.3f}  "
                      + " ".join(f"{x:+.2f}" for x in v))


def main():
    ap = argparse.ArgumentParser()
    sub = ap.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("run")
    r.add_argument("--scenes", default=",".join(TUNE))
    r.add_argument("--sigma", type=float, default=4.0)
    r.add_argument("--tag", default="")
    r.add_argument("--only", default="")
    sub.add_parser("check")
    s = sub.add_parser("summary")
    s.add_argument("tags", nargs="*")
    a = ap.parse_args()
    if a.cmd == "run":
        main_run(a)
    elif a.cmd == "check":
        check()
    else:
        rows = [json.loads(line) for line in open(OUT / "results.jsonl")]
        tags = a.tags or sorted({r["tag"] for r in rows})
        summarise([r for r in rows if r["tag"] in tags])


if __name__ == "__main__":
    main()
