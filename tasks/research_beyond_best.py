"""Issue 31 research: what can be added ON TOP OF `--preset best` (b3 of tasks/research_best.py)?

b3 = first (default per-patch OMP) -> survey (nonlocal, every 7th reference) -> Da = K-SVD(survey, D) ->
base (every 4th, Da, matched on the survey: `nonlocal --adapt`) -> Db = K-SVD(base, Da) -> b3 (every 3rd,
Db, matched on base).  Candidates, each on top of b3 (gains against b3, time as a ratio to b3's total):

    e2      the last pass on every 2nd reference instead of every 3rd
    eg24    the last pass with groups of 24 (window 6); eg24w9 groups of 24, window 9
    eavg    the mean of base and b3 (both reproduce the measurements, so their mean does: no projection)
    esum    the second and the last pass's sums added before one `finish` (as d+ of research_best)
    eoff1   the last pass also on the reference grid offset by 1 px in both axes, sums added, one finish;
            eoff12 also the grid offset by 2 (every reference on the diagonal classes)
    ewnnm4  research_prior.refine from b3 with research_prior.BEST (accelerated GAP + WNNM, sigma 4 -> 1,
            24 iterations, groups of 16 within 6 px of every 4th reference, regrouped every 4, c 2.8,
            averaged with its start); ewnnm3 the same with sigma 3 -> 1, 12 iterations
    e3r     Dc = K-SVD(b3, Db), a fourth pass (every 3rd, Dc, matched on b3)
    e3r+    (own idea) the third and fourth passes' sums added before one finish

Tuning clips bikes-a, carphone; held out bikes-b, bunny (tasks/research_iterative: case_input, CODES:
Bernoulli(0.5) and hitomi L = 2, 256x256, N = 8, no noise).  Protocol: run the tuning clips, record the
chosen candidates (`choose`), then the held-out clips.  Every stage timed in this thread with
time.perf_counter (and time.thread_time, CPU seconds, less sensitive to a busy other core); a candidate's
time is the sum of its stages, shared stages counted in each.  Writes /tmp/research-beyond/results.jsonl.

    NUMBA_NUM_THREADS=1 OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 MKL_NUM_THREADS=1 nice -n 10 \
        python tasks/research_beyond_best.py run --scenes bikes-a,carphone --tag tune
    python tasks/research_beyond_best.py choose e3r,esum --why "..."
    ... run --scenes bikes-b,bunny --tag held
    python tasks/research_beyond_best.py summary [TAGS...]
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
OUT = Path(os.environ.get("RESEARCH_BEYOND_OUT", "/tmp/research-beyond"))
OUT.mkdir(parents=True, exist_ok=True)
os.environ["RESEARCH_BEST_OUT"] = str(OUT)  # research_best puts its (and research_iterative's) input cache there

import research_best as rb  # noqa: E402  (its import also points the input cache under OUT)
import research_iterative as ri  # noqa: E402

TUNE, HELD, CODES = ri.TUNE, ri.HELD, ri.CODES
CANDIDATES = ("e2", "eg24", "eg24w9", "eavg", "esum", "eoff1", "eoff12", "ewnnm4", "ewnnm3", "e3r", "e3r+")


def timed(fn, *a, **k):
    t, c = time.perf_counter(), time.thread_time()
    r = fn(*a, **k)
    return r, (time.perf_counter() - t, time.thread_time() - c)


def run_case(scene, code, bump, D, settings, default_settings, skip=()):
    import research_prior as rp
    from codedvideo.engine import adaptation
    from codedvideo.engine.adaptation import adapt_dictionary
    from codedvideo.engine.windows import reconstruct_volume
    from codedvideo.solvers.baselines import gap_tv
    from codedvideo.solvers.nonlocal_sc import finish, nonlocal_region

    video, mask, coded = ri.case_input(scene, code, bump)
    H, W = coded.shape
    T, C, R = {}, {}, {}  # wall and CPU seconds of each stage, PSNR of each result
    ps = lambda x: ri.psnr(x, video)  # noqa: E731

    def stage(name, fn, *a, **k):
        r, (T[name], C[name]) = timed(fn, *a, **k)
        return r

    def sums(Dx, start, step, offset=0, **kw):
        if offset:
            kw.update(origin=(offset, offset), image_shape=(H + offset, W + offset))
        s, w, _ = nonlocal_region(coded, mask, Dx, start, settings, step=step, sums=True, **kw)
        return s, w

    def nl(Dx, start, step, **kw):
        """A pass: its sums and its volume (what the pass without ``sums`` returns: finish, projected)."""
        s, w = sums(Dx, start, step, **kw)
        return finish(s, w, coded, mask), (s, w)

    fin = lambda *sw: finish(sum(s for s, _ in sw), sum(w for _, w in sw), coded, mask)  # noqa: E731

    with tempfile.TemporaryDirectory(dir=OUT) as tmp:
        first, _ = stage("first", reconstruct_volume, coded, mask, D, settings=default_settings, cache=tmp,
                         workers=1, progress=False)
    survey, _ = stage("survey", nl, D, first, adaptation.ADAPT_SURVEY_STEP)
    Da, _ = stage("adapt", adapt_dictionary, survey, D)
    base, s2 = stage("second4", nl, Da, survey, 4)
    Db, _ = stage("adapt2", adapt_dictionary, base, Da)
    b3, s3 = stage("third3", nl, Db, base, 3)
    chain = ("first", "survey", "adapt", "second4", "adapt2", "third3")
    tot = {"b3": sum(T[k] for k in chain)}
    cpu = {"b3": sum(C[k] for k in chain)}
    R["base"], R["b3"] = ps(base), ps(b3)
    nan_b3 = int(np.isnan(b3).sum())

    def add(name, x, extra=(), drop=()):
        R[name] = ps(x)
        tot[name] = tot["b3"] + sum(T[k] for k in extra) - sum(T[k] for k in drop)
        cpu[name] = cpu["b3"] + sum(C[k] for k in extra) - sum(C[k] for k in drop)

    want = lambda k: k not in skip  # noqa: E731
    if want("e2"):
        add("e2", stage("third2", nl, Db, base, 2)[0], ["third2"], ["third3"])
    if want("eg24"):
        add("eg24", stage("third3_g24", nl, Db, base, 3, group=24)[0], ["third3_g24"], ["third3"])
    if want("eg24w9"):
        add("eg24w9", stage("third3_g24w9", nl, Db, base, 3, group=24, window=9)[0], ["third3_g24w9"], ["third3"])

    def mean2(a, b):
        return np.where(np.isnan(a), b, np.where(np.isnan(b), a, 0.5 * (a + b))).astype(np.float32)

    if want("eavg"):
        add("eavg", stage("avg", mean2, base, b3), ["avg"])
    if want("esum"):
        add("esum", stage("fin_sum", fin, s2, s3), ["fin_sum"])
    if want("eoff1") or want("eoff12"):
        so1 = stage("third3_off1", sums, Db, base, 3, offset=1)
        add("eoff1", stage("fin_off1", fin, s3, so1), ["third3_off1", "fin_off1"])
        if want("eoff12"):
            so2 = stage("third3_off2", sums, Db, base, 3, offset=2)
            add("eoff12", stage("fin_off12", fin, s3, so1, so2), ["third3_off1", "third3_off2", "fin_off12"])
    start = np.nan_to_num(b3, nan=0.0)
    if want("ewnnm4"):
        add("ewnnm4", stage("wnnm4", rp.refine, coded, mask, start, data_range=255.0, **rp.BEST), ["wnnm4"])
    if want("ewnnm3"):
        add("ewnnm3", stage("wnnm3", rp.refine, coded, mask, start, data_range=255.0,
                            **dict(rp.BEST, iters=12, s_hi=3.0)), ["wnnm3"])
    if want("e3r"):
        Dc, _ = stage("adapt3", adapt_dictionary, b3, Db)
        x4, s4 = stage("fourth3", nl, Dc, b3, 3)
        add("e3r", x4, ["adapt3", "fourth3"])
        add("e3r+", stage("fin_34", fin, s3, s4), ["adapt3", "fourth3", "fin_34"])
    g = gap_tv(coded, mask)  # outside every timing: only to place the figures against GAP-TV
    return dict(scene=scene, code=f"{code}{bump}", psnr=R, gaptv=ps(g), nan_b3=nan_b3,
                gain={k: R[k] - R["b3"] for k in R}, seconds=tot, cpu_seconds=cpu,
                ratio={k: tot[k] / tot["b3"] for k in tot}, cpu_ratio={k: cpu[k] / cpu["b3"] for k in cpu},
                stages=T, stages_cpu=C)


def setup(first_scene):
    from codedvideo.engine.adaptation import adapt_dictionary
    from codedvideo.solvers.nonlocal_sc import nonlocal_region

    import research_prior as rp

    D, settings, default_settings = rb.research_settings()
    # warm the compiled kernels outside the timings
    v, m, c = ri.case_input(first_scene, "hitomi", 2)
    nonlocal_region(c[:40, :40], m[:, :40, :40], D, v[:, :40, :40], settings, step=4)
    rp.refine(c[:40, :40], m[:, :40, :40], v[:, :40, :40], data_range=255.0, **dict(rp.BEST, iters=2))
    try:
        adapt_dictionary(v[:, :96, :96], D)
    except Exception as e:  # noqa: BLE001 (a warm-up only)
        print("adapt warm-up:", e)
    return D, settings, default_settings


def main_run(a):
    choice = OUT / "choice.json"
    held = [s for s in a.scenes.split(",") if s in HELD]
    if held and not choice.exists():
        sys.exit("held-out clips asked before any choice was recorded (run `choose` on the tuning figures first)")
    if choice.exists():
        print("choice recorded before the held-out run:", choice.read_text().strip(), flush=True)
    D, settings, default_settings = setup(a.scenes.split(",")[0])
    rows, done = [], {}
    if (OUT / "results.jsonl").exists():  # resume: a case already written under this tag is not run again
        for line in open(OUT / "results.jsonl"):
            d = json.loads(line)
            done[(d["tag"], d["scene"], d["code"])] = d
    for scene in a.scenes.split(","):
        for code, bump in CODES:
            if (a.tag, scene, f"{code}{bump}") in done:
                rows.append(done[(a.tag, scene, f"{code}{bump}")])
                print(f"{scene} {code}{bump}: already in results.jsonl (tag {a.tag!r})", flush=True)
                continue
            r = run_case(scene, code, bump, D, settings, default_settings, skip=set(filter(None, a.skip.split(","))))
            r["tag"] = a.tag
            rows.append(r)
            with open(OUT / "results.jsonl", "a") as fh:
                fh.write(json.dumps(r) + "\n")
            print(f"{scene:<10}{code}{bump:<3} b3 {r['psnr']['b3']:.2f} ({r['seconds']['b3']:.1f}s, gaptv "
                  f"{r['psnr']['b3'] - r['gaptv']:+.2f}) "
                  + " ".join(f"{k} {v:+.2f}/{r['ratio'][k]:.2f}x" for k, v in r["gain"].items() if k in r["ratio"] and k != "b3"),
                  flush=True)
    summarise(rows)


def summarise(rows):
    keys = [k for k in rows[0]["gain"] if k != "b3"]
    groups = (("tune", lambda s: s in TUNE), ("held", lambda s: s in HELD), ("other", lambda s: s not in TUNE + HELD))
    for name, sel in groups:
        g = [r for r in rows if sel(r["scene"])]
        if not g:
            continue
        b3 = np.mean([r["psnr"]["b3"] for r in g])
        print(f"{name} ({len(g)} cases, b3 {b3:.2f} dB, GAP-TV + {b3 - np.mean([r['gaptv'] for r in g]):.2f}, "
              f"b3 {np.mean([r['seconds']['b3'] for r in g]):.1f} s in-process):")
        for k in keys:
            gains = [r["gain"][k] for r in g if k in r["gain"]]
            if len(gains) < len(g):
                continue
            t = np.mean([r["seconds"][k] for r in g]) / np.mean([r["seconds"]["b3"] for r in g]) if k in g[0]["seconds"] else np.nan
            c = np.mean([r["cpu_seconds"][k] for r in g]) / np.mean([r["cpu_seconds"]["b3"] for r in g]) if k in g[0]["cpu_seconds"] else np.nan
            print(f"  {k:<7} mean {np.mean(gains):+.3f} dB (abs {np.mean([r['psnr'][k] for r in g]):.2f}), "
                  f"worst {min(gains):+.3f}, time {t:.2f}x (cpu {c:.2f}x)")


def main():
    ap = argparse.ArgumentParser()
    sub = ap.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("run")
    r.add_argument("--scenes", default=",".join(TUNE))
    r.add_argument("--tag", default="")
    r.add_argument("--skip", default="", help="candidates left out, comma separated")
    c = sub.add_parser("choose")
    c.add_argument("names")
    c.add_argument("--why", default="")
    s = sub.add_parser("summary")
    s.add_argument("tags", nargs="*")
    a = ap.parse_args()
    if a.cmd == "run":
        main_run(a)
    elif a.cmd == "choose":
        f = OUT / "choice.json"
        if f.exists():
            sys.exit(f"a choice is already recorded: {f.read_text()}")
        rows = [json.loads(line) for line in open(OUT / "results.jsonl")]
        if any(r["scene"] in HELD for r in rows):
            sys.exit("held-out rows already exist: the choice would not be blind")
        names = a.names.split(",")
        assert len(names) <= 2 and all(n in CANDIDATES for n in names), names
        f.write_text(json.dumps(dict(chosen=names, why=a.why, time=time.strftime("%Y-%m-%d %H:%M:%S"),
                                     tuning_rows=len(rows))) + "\n")
        print(f.read_text())
    else:
        rows = [json.loads(line) for line in open(OUT / "results.jsonl")]
        tags = a.tags or sorted({r["tag"] for r in rows})
        summarise([r for r in rows if r["tag"] in tags])


if __name__ == "__main__":
    main()
