"""Issue 31 research: a DeSCI-like prior (2D patches of single frames, grouped across neighbouring frames)
inside the refinement loop of codedvideo.solvers.refine, against the package's 3D-block prior.

Start of every candidate: `nonlocal --adapt --adapt-rounds 2` (b3 of tasks/research_beyond_best.py), computed
once per case with cv.reconstruct and cached in /tmp/research-frames/start-*.npy.  Baseline:
codedvideo.solvers.refine.refine(coded, mask, start, iterations=24).  Candidate: :func:`refine2d`, the same
loop (accelerated GAP via refine.to_measurements, annealed sigma, regrouping, blend with the start) whose
denoiser is :func:`denoise2d` (kernels :func:`match2d`, :func:`shrink2d`, :func:`scatter2d`).

    NUMBA_NUM_THREADS=2 nice -n 10 python tasks/research_frames.py starts --scenes S,... --codes bernoulli0,hitomi2,hitomi3
    NUMBA_NUM_THREADS=2 nice -n 10 python tasks/research_frames.py run --tag T --scenes S,... --codes ... --json '[{...}]'

Rows in /tmp/research-frames/results.jsonl (gain in dB over the start, in-process wall and CPU seconds of the
refinement alone); the choice was written to /tmp/research-frames/choice.txt before the held-out clips ran.

Findings (2026-11-27, 256x256, N = 8, no noise, 2 shared cores under load 2-3, NUMBA_NUM_THREADS=2):
- Chosen on bikes-a / carphone: G3 = patch 8, k 20, references every 10th patch of every frame (grid staggered
  per frame), members within +-2 frames and +-6 px, regrouped every 6, 32 iterations, sigma 4 -> 1, c 2.8,
  blend 0.5; G3s6 the same with sigma 6 -> 1.  Gain over the start, mean (worst):
      tuning (4 cases):          base refine +0.67 (+0.33)   G3 +1.33 (+0.81)   G3s6 +1.68 (+1.07)
      held out (bikes-b, bunny): base refine +0.24 (+0.15)   G3 +0.70 (+0.30)   G3s6 +0.90 (+0.42)
      hitomi L=3, all 4 clips:   base refine +0.32 (+0.20)   G3 +0.67 (+0.39)   G3s6 +0.87 (+0.51)
      next 8 frames of the held-out clips (bikes-b@8, bunny@8, Bernoulli and hitomi L=2):
                                 base refine +0.18 (+0.01)   G3 +0.66 (+0.45)   G3s6 +0.84 (+0.59)
  at the baseline's time (about 11 s in-process each, under load).
- The group search, not the frames: all frames (delta 7) = +-2; patch 8 > 6; k 20 at step 10 / 32 iterations
  beat k 30 and step 8 / 24 iterations at equal time; the 3D/2D alternation lost to 2D alone.
- The eigendecompositions (np.linalg.eigh on 20x20, ~40 us each) are most of the time.  (The runs above used a
  hand-written Householder + QL solver, about 1.4x faster and equal to LAPACK to ~1e-15; it is not kept here.)
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np
from numba import njit, prange

from codedvideo.solvers.refine_kernel import match_frame_patches, scatter_frame_patches

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tasks"))
OUT = Path(os.environ.get("RESEARCH_FRAMES_OUT", "/tmp/research-frames"))
OUT.mkdir(parents=True, exist_ok=True)

import research_iterative as ri  # noqa: E402

ri.CACHE = OUT / "inputs"
ri.CACHE.mkdir(parents=True, exist_ok=True)
TUNE, HELD = ri.TUNE, ri.HELD
CODES = {"bernoulli0": ("bernoulli", 0), "hitomi2": ("hitomi", 2), "hitomi3": ("hitomi", 3)}


def start_of(scene, code, bump):
    """The case's video, mask, coded image and start (nonlocal --adapt --adapt-rounds 2), cached."""
    video, mask, coded = ri.case_input(scene, code, bump)
    f = OUT / f"start-{scene}-{code}{bump}.npy"
    if f.exists():
        return video, mask, coded, np.load(f)
    import codedvideo as cv

    t = time.perf_counter()
    x0 = cv.reconstruct(coded, mask, method="nonlocal", adapt=True, adapt_rounds=2, data_range=255.0)
    x0 = np.nan_to_num(np.asarray(x0, np.float32), nan=0.0)
    np.save(f, x0)
    print(f"start {scene} {code}{bump}: {ri.psnr(x0, video):.2f} dB, {time.perf_counter() - t:.1f} s", flush=True)
    return video, mask, coded, x0


# ------------------------------------------------------------------------------------------------
# kernels: 2D patches (patch x patch of one frame) grouped across frames.  A patch is a flat index
# t * H * W + r * W + c of its top-left corner.


def reference_grid2d(n, h, w, step, patch, stagger=True):
    """Top-left corners (flat) of every ``step``-th patch of every frame, the last row and column included;
    with ``stagger`` frame t's grid is shifted by (t * step // n) in both axes (wrapped), so that the frames'
    references fall on different places."""
    out = []
    for t in range(n):
        o = (t * step // n) % step if stagger else 0
        def axis(m):
            s = np.arange(o, m, step)
            if s.size == 0 or s[0] != 0:
                s = np.concatenate([[0], s])
            return s if s[-1] == m - 1 else np.append(s, m - 1)
        rows, cols = axis(h - patch + 1), axis(w - patch + 1)
        out.append((t * h * w + rows[:, None] * w + cols[None, :]).ravel())
    return np.concatenate(out).astype(np.int64)


# the matching and the frame-by-frame scatter: the package's kernels (shipped with `--refine` since; this
# research had its own copies of the same code)
match2d = match_frame_patches
scatter2d = scatter_frame_patches


@njit(parallel=True, nogil=True, cache=True, fastmath={"reassoc", "contract"})
def shrink2d(vol, groups, patch, sigma2, c, dnoise, est):
    """``est[g * k + i]`` (patch**2 values): member ``i`` of group ``g`` with the group shrunk by weighted
    nuclear norm, the rule of codedvideo.solvers.refine.shrinkage: members less their mean ``M`` (k, d);
    eigenvalues ``s^2`` of the smaller Gram matrix (k x k when k <= d, else d x d); ``s_hat^2 = max(s^2 -
    dnoise sigma2, 0)``; ``f = max(s - c sqrt(k) sigma2 / s_hat, 0) / s``; estimate ``mu + M`` shrunk.
    One group per thread."""
    n, h, w = vol.shape
    hw = h * w
    G, k = groups.shape
    d = patch * patch
    for g in prange(G):
        M = np.empty((k, d), np.float32)
        mu = np.zeros(d, np.float32)
        for i in range(k):
            p = groups[g, i]
            t = p // hw
            r0 = (p % hw) // w
            c0 = p % w
            for yy in range(patch):
                for xx in range(patch):
                    v = vol[t, r0 + yy, c0 + xx]
                    M[i, yy * patch + xx] = v
                    mu[yy * patch + xx] += v
        for e in range(d):
            mu[e] /= k
        for i in range(k):
            for e in range(d):
                M[i, e] -= mu[e]
        q = k if k <= d else d
        C = np.empty((q, q), np.float64)
        if k <= d:
            for i in range(k):
                for j in range(i, k):
                    acc = 0.0
                    for e in range(d):
                        acc += np.float64(M[i, e]) * np.float64(M[j, e])
                    C[i, j] = acc
                    C[j, i] = acc
        else:
            for a in range(d):
                for b in range(a, d):
                    acc = 0.0
                    for i in range(k):
                        acc += np.float64(M[i, a]) * np.float64(M[i, b])
                    C[a, b] = acc
                    C[b, a] = acc
        lam, U = np.linalg.eigh(C)
        f = np.zeros(q)
        for j in range(q):
            if lam[j] > 0.0:
                sq = np.sqrt(lam[j])
                thr = c * np.sqrt(k) * sigma2 / (np.sqrt(max(lam[j] - dnoise * sigma2, 0.0)) + 1e-8)
                f[j] = max(sq - thr, 0.0) / sq
        P = np.empty((q, q), np.float32)  # U diag(f) U^T
        for a in range(q):
            for b in range(a, q):
                acc = 0.0
                for j in range(q):
                    acc += U[a, j] * f[j] * U[b, j]
                P[a, b] = acc
                P[b, a] = acc
        for i in range(k):
            row = est[g * k + i]
            for e in range(d):
                row[e] = mu[e]
        if k <= d:  # rows: P M
            for i in range(k):
                row = est[g * k + i]
                for j in range(k):
                    pij = P[i, j]
                    if pij != 0.0:
                        for e in range(d):
                            row[e] += pij * M[j, e]
        else:  # columns: M P
            for i in range(k):
                row = est[g * k + i]
                for a in range(d):
                    m = M[i, a]
                    for e in range(d):
                        row[e] += m * P[a, e]


# ------------------------------------------------------------------------------------------------

DEFAULT = dict(patch=6, k=40, delta=7, window=8, step=4, regroup=4, sigma_start=4.0, sigma_end=1.0,
               iterations=24, c=2.8, blend=0.5, dnoise=None, stagger=True, hybrid=None, chunk=4096)


class Groups2d:
    """A matching's groups, chunked, each chunk's entries ordered by frame for the scatter."""

    def __init__(self, x, refs, o):
        n, h, w = x.shape
        self.idx = np.empty((refs.size, o["k"]), np.int64)
        match2d(x, refs, o["patch"], o["window"], min(o["delta"], n - 1), o["k"], self.idx)
        self.chunks = []
        hw = h * w
        for s in range(0, refs.size, o["chunk"]):
            part = np.ascontiguousarray(self.idx[s:s + o["chunk"]])
            where = part.ravel()
            frames = where // hw
            order = np.argsort(frames, kind="stable").astype(np.int64)
            bounds = np.searchsorted(frames[order], np.arange(n + 1)).astype(np.int64)
            self.chunks.append((part, where, order, bounds))


def denoise2d(x, groups, sigma, o):
    n, h, w = x.shape
    p, k = o["patch"], o["k"]
    d = p * p
    dnoise = float(d if o["dnoise"] is None else o["dnoise"])
    summed = np.zeros_like(x)
    weight = np.zeros_like(x)
    est = np.empty((min(o["chunk"], groups.idx.shape[0]) * k, d), np.float32)
    for part, where, order, bounds in groups.chunks:
        e = est[:part.shape[0] * k]
        shrink2d(x, part, p, float(sigma) ** 2, float(o["c"]), dnoise, e)
        scatter2d(e, where, order, bounds, p, summed, weight)
    covered = weight > 0
    np.divide(summed, weight, out=summed, where=covered)
    summed[~covered] = x[~covered]
    return summed


def refine2d(coded, mask, start, **opts):
    """refine.refine's loop with the 2D-across-frames denoiser.  (The hybrids with the 3D-block denoiser measured
    above, "alt" and "avg", ran when the package's refine had it; it has been replaced by this prior since.)"""
    from codedvideo.model import physics
    from codedvideo.solvers import refine as R

    o = dict(DEFAULT, **opts)
    if o["hybrid"]:
        raise ValueError("the 3D-block denoiser of the hybrids is no longer in the package")
    t0 = time.perf_counter()
    y = np.asarray(coded, np.float32)
    mask = np.asarray(mask)
    n, h, w = mask.shape
    open2 = physics.forward(mask, mask)
    inv = np.divide(1.0, open2, out=np.zeros_like(open2), where=open2 > 0)
    x0 = np.ascontiguousarray(start, np.float32)
    x = x0.copy()
    refs = reference_grid2d(n, h, w, o["step"], o["patch"], o["stagger"])
    acc = y.copy()
    levels = R.sigmas(o["iterations"], o["sigma_start"], o["sigma_end"])
    groups = None
    for i, sigma in enumerate(levels):
        R.to_measurements(x, mask, y, inv, acc)
        if i % o["regroup"] == 0:
            x = np.ascontiguousarray(x)
            groups = Groups2d(x, refs, o)
        x = denoise2d(x, groups, sigma, o)
    R.to_measurements(x, mask, y, inv)
    x *= np.float32(1.0 - o["blend"])
    x += np.float32(o["blend"]) * x0
    return x, dict(refs=int(refs.size), seconds=time.perf_counter() - t0)


# ------------------------------------------------------------------------------------------------


def warm():
    from codedvideo.solvers import refine as R

    rng = np.random.default_rng(0)
    v = rng.uniform(0, 255, (8, 40, 40)).astype(np.float32)
    m = (rng.uniform(size=(8, 40, 40)) < 0.5).astype(np.uint8)
    c = (v * m).sum(0).astype(np.float32)
    R.refine(c, m, v, iterations=2)
    for k in (20, 40, 60):
        for p in (6, 7, 8):
            refine2d(c, m, v, iterations=2, k=k, patch=p)


def run(tag, scenes, codes, configs, base=True):
    """Each case: the baseline refine (24 iterations) and every config, from the cached start, timed
    in this process (time.perf_counter); rows appended to OUT/results.jsonl."""
    from codedvideo.solvers import refine as R

    choice = OUT / "choice.txt"
    if any(s in HELD for s in scenes) and not choice.exists():
        sys.exit("held-out clips asked before the choice was written")
    warm()
    rows = []
    for scene in scenes:
        for key in codes:
            code, bump = CODES[key]
            video, mask, coded, x0 = start_of(scene, code, bump)
            p0 = ri.psnr(x0, video)
            row = dict(tag=tag, scene=scene, code=key, start=p0, gain={}, seconds={}, load=os.getloadavg()[0])
            if base:
                t, c = time.perf_counter(), time.process_time()
                xb, _ = R.refine(coded, mask, x0, iterations=24)
                row["seconds"]["base"] = time.perf_counter() - t
                row.setdefault("cpu", {})["base"] = time.process_time() - c
                row["gain"]["base"] = ri.psnr(xb, video) - p0
            for j, cfg in enumerate(configs):
                name = cfg.get("name", f"c{j}")
                opts = {a: b for a, b in cfg.items() if a != "name"}
                t, c = time.perf_counter(), time.process_time()
                x, info = refine2d(coded, mask, x0, **opts)
                row["seconds"][name] = time.perf_counter() - t
                row.setdefault("cpu", {})[name] = time.process_time() - c
                row["gain"][name] = ri.psnr(x, video) - p0
            row["configs"] = configs
            rows.append(row)
            with open(OUT / "results.jsonl", "a") as fh:
                fh.write(json.dumps(row) + "\n")
            print(f"{scene:<9}{key:<11} start {p0:.2f} " + " ".join(
                f"{n} {g:+.3f}/{row['seconds'][n]:.1f}s/{row['cpu'][n]:.1f}c" for n, g in row["gain"].items()) + f" load {row['load']:.1f}",
                flush=True)
    names = list(rows[0]["gain"])
    for n in names:
        g = [r["gain"][n] for r in rows]
        s = [r["seconds"][n] for r in rows]
        c = [r["cpu"][n] for r in rows]
        print(f"  {n:<12} mean {np.mean(g):+.3f} worst {min(g):+.3f}  {np.mean(s):.1f} s  cpu {np.mean(c):.1f} s", flush=True)
    return rows


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("cmd", choices=["starts", "run"])
    ap.add_argument("--scenes", default=",".join(TUNE))
    ap.add_argument("--codes", default="bernoulli0,hitomi2")
    ap.add_argument("--tag", default="")
    ap.add_argument("--json", default="[{}]")
    ap.add_argument("--nobase", action="store_true")
    a = ap.parse_args()
    scenes, codes = a.scenes.split(","), a.codes.split(",")
    if a.cmd == "starts":
        for s in scenes:
            for c in codes:
                start_of(s, *CODES[c])
    else:
        run(a.tag, scenes, codes, json.loads(a.json), base=not a.nobase)


if __name__ == "__main__":
    main()
