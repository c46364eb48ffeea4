"""Rendering of ``codedvideo report``: figures (matplotlib, Agg), CSV, HTML and the video.

The HTML is self-contained (figures embedded as base64 PNG; the PNGs are also
written to ``figures/`` beside it); the side-by-side video is written beside it
with :func:`codedvideo.formats.io.write_video` and linked.  ``report.csv`` holds every
number: one row per experiment and scene, and one ``scene = mean`` row per
averaged cell.
"""

from __future__ import annotations

import base64
import csv
import html
import io
import platform
import os
from pathlib import Path

import numpy as np

from codedvideo.api.config import PRESETS, preset_options
from codedvideo.formats import io as cio

CSV_FIELDS = ("experiment", "label", "scene", "frames", "code", "bump", "sigma", "method", "max_atoms", "tol_rms",
              "dictionary_atoms", "psnr", "ssim", "seconds", "atoms_mean", "key")
ERROR_GAIN = 4.0  # the error panel shows |reconstruction - truth| times this


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


#: The figures' names (``figures/NAME.png``).
FIGURES = ("table1", "fig7", "speed", "fig4", "strips")


def _save(fig, folder: Path, name: str) -> str:
    """Write ``folder/name.png`` and return it base64-encoded."""
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110, bbox_inches="tight")
    _plt().close(fig)
    data = buf.getvalue()
    folder.mkdir(parents=True, exist_ok=True)
    with cio.atomic_output(folder / f"{name}.png") as tmp:
        Path(tmp).write_bytes(data)
    return base64.b64encode(data).decode()


def fig_table1(summary: dict, rc, folder: Path) -> str:
    plt = _plt()
    fig, ax = plt.subplots(figsize=(6, 4))
    for s in rc.table_sigmas:
        ax.plot(rc.table_bumps, [summary["table"][(b, s)] for b in rc.table_bumps], "o-", label=f"sigma = {s:g}")
    ax.set(xlabel="bump length L (sub-frames)", ylabel="PSNR (dB)", title=f"Table 1: PSNR against L, N = {rc.frames}")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    return _save(fig, folder, "table1")


def fig_fig7(summary: dict, folder: Path) -> str:
    plt = _plt()
    fig, ax = plt.subplots(figsize=(6, 4))
    labels = list(dict.fromkeys(label for label, _ in summary["fig7"]))
    for label in labels:
        ns = sorted(f for (lab, f) in summary["fig7"] if lab == label)
        ax.plot(ns, [summary["fig7"][(label, f)]["psnr"] for f in ns], "o-", label=label)
    ax.set(xlabel="N (sub-frames per coded image)", ylabel="PSNR (dB)", title="Fig. 7: PSNR against N")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    return _save(fig, folder, "fig7")


def fig_speed(summary: dict, folder: Path) -> str:
    plt = _plt()
    fig, axes = plt.subplots(1, 2, figsize=(12, 4.5))
    items = list(summary["speed"].items())
    for ax, metric, unit in ((axes[0], "psnr", "PSNR (dB)"), (axes[1], "ssim", "SSIM")):
        colours = plt.get_cmap("tab20")
        for i, (label, v) in enumerate(items):
            marker = "o" if label.startswith("OMP") else "*" if label.startswith("preset") else "s"
            ax.plot(v["seconds"], v[metric], marker, color=colours(i % 20), label=label, ms=11 if marker == "*" else 6)
        for label, v in items:  # a refined preset's PSNR after its passes and along its refinement, up to its point
            if metric == "psnr" and v.get("refine_trace"):
                ax.plot(*zip(*v["refine_trace"]), ":", color="0.4", lw=1.2,
                        label=f"{label}, along its passes and refinement")
        front = sorted((v["seconds"], v[metric]) for _, v in items if v[f"pareto_{metric}"])
        ax.step([t for t, _ in front], [q for _, q in front], "k--", where="post", lw=1, label="Pareto front")
        ax.set_xscale("log")
        ax.set(xlabel="wall time per coded image (s)", ylabel=unit, title=f"{unit} against run time")
        ax.grid(alpha=0.3, which="both")
    axes[1].legend(fontsize=7, loc="center left", bbox_to_anchor=(1.02, 0.5))
    return _save(fig, folder, "speed")


def _volume(runner, rec) -> np.ndarray:
    return np.load(runner.folder / f"{rec['key']}.npy")


def fig_fig4(runner, results: dict, rc, folder: Path) -> str:
    plt = _plt()
    recs = [r for r in results["fig4"] if r["scene"] == rc.video_scene]
    fig, axes = plt.subplots(len(recs), 3, figsize=(9, 3 * len(recs)), squeeze=False)
    for row, rec in zip(axes, recs):
        cap = runner.capture(rc.video_scene, rc.frames, rec["code"], rec["bump"], 0.0)
        vol = _volume(runner, rec)
        for ax, img, title, vmax in ((row[0], cap["mask"][0], f"{rec['code']}: exposure, sub-frame 1", 1),
                                     (row[1], cap["coded"], "coded image", rec["bump"] * 255.0),
                                     (row[2], vol[0], f"reconstruction, sub-frame 1 (video: {rec['psnr']:.2f} dB)", 255.0)):
            ax.imshow(img, cmap="gray", vmin=0, vmax=vmax)
            ax.set_title(title, fontsize=9)
            ax.axis("off")
    return _save(fig, folder, "fig4")


def fig_strips(runner, results: dict, rc, folder: Path) -> str:
    plt = _plt()
    recs = [r for r in results["fig7"] if r["scene"] == rc.video_scene and r["frames"] == rc.frames]
    recs += results.get("strips", [])  # the best preset's frames beside them
    truth = runner.video(rc.video_scene, rc.frames)
    idx = sorted({int(round(x)) for x in np.linspace(0, rc.frames - 1, min(rc.frames, 4))})
    rows = [("truth", truth)] + [(f"{r['label']}".replace(" (", "\n(") + f"\n{r['psnr']:.2f} dB", _volume(runner, r))
                                 for r in recs]
    fig, axes = plt.subplots(len(rows), len(idx), figsize=(2.2 * len(idx), 2.3 * len(rows)), squeeze=False)
    for ax_row, (label, vol) in zip(axes, rows):
        for ax, t in zip(ax_row, idx):
            ax.imshow(np.clip(vol[t], 0, 255), cmap="gray", vmin=0, vmax=255)
            ax.set_xticks([])
            ax.set_yticks([])
        ax_row[0].set_ylabel(label, fontsize=7)
    for ax, t in zip(axes[0], idx):
        ax.set_title(f"sub-frame {t + 1}", fontsize=8)
    return _save(fig, folder, "strips")


def side_by_side(runner, results: dict, rc, out: Path) -> Path:
    """truth | coded (/ L) | OMP reconstruction | |error| x ERROR_GAIN, as ``side_by_side.mp4``."""
    rec = next(r for r in results["fig7"]
               if r["scene"] == rc.video_scene and r["frames"] == rc.frames and r["method"] == "omp")
    truth = runner.video(rc.video_scene, rc.frames)
    cap = runner.capture(rc.video_scene, rc.frames, rec["code"], rec["bump"], 0.0)
    vol = np.clip(_volume(runner, rec), 0, 255)
    coded = np.broadcast_to(cap["coded"] / rec["bump"], truth.shape)
    err = np.clip(np.abs(vol - truth) * ERROR_GAIN, 0, 255)
    gap = np.full((truth.shape[0], truth.shape[1], 2), 255.0, np.float32)
    frames = np.concatenate([truth, gap, coded, gap, vol, gap, err], axis=2)
    return cio.write_video(out / "side_by_side.mp4", frames.astype(np.float32), fps=rc.fps)


def csv_rows(results: dict, summary: dict, rc) -> list[dict]:
    rows = []
    for exp in ("table1", "table1_frames", "fig7", "fig4", "speed"):
        for r in results.get(exp, []):  # (Table 1 at other N is Table 1 too: its rows name their N)
            rows.append(dict({k: r.get(k) for k in CSV_FIELDS}, experiment=exp.split("_")[0], label=r.get("label", "")))
    for (b, s), v in summary["table"].items():
        rows.append(dict(experiment="table1", label=f"L = {b}, sigma = {s:g}", scene="mean", frames=rc.frames,
                         code="hitomi", bump=b, sigma=s, method="omp", psnr=v))
    for (n, b, s), cell in summary["table_frames"].items():
        for method, v in cell.items():
            rows.append(dict(experiment="table1", label=f"N = {n}, L = {b}, sigma = {s:g}", scene="mean",
                             frames=n, code="hitomi", bump=b, sigma=s, method=method, psnr=v))
    for (label, f), v in summary["fig7"].items():
        rows.append(dict(experiment="fig7", label=label, scene="mean", frames=f, **v))
    for label, v in summary["fig4"].items():
        rows.append(dict(experiment="fig4", label=label, scene="mean", frames=rc.frames, **v))
    for label, v in summary["speed"].items():
        rows.append(dict(experiment="speed", label=label, scene="mean", frames=rc.frames,
                         psnr=v["psnr"], ssim=v["ssim"], seconds=v["seconds"]))
    return rows


def write_csv(path: Path, rows: list[dict]) -> Path:
    with cio.atomic_output(path) as tmp:
        with open(tmp, "w", newline="") as fh:
            w = csv.DictWriter(fh, fieldnames=CSV_FIELDS, extrasaction="ignore")
            w.writeheader()
            for row in rows:
                w.writerow({k: ("" if row.get(k) is None else row.get(k)) for k in CSV_FIELDS})
    return path


def _img(b64: str, alt: str) -> str:
    return f'<img alt="{html.escape(alt)}" src="data:image/png;base64,{b64}">'


def _table(header: list[str], rows: list[list[str]]) -> str:
    head = "".join(f"<th>{h}</th>" for h in header)
    body = "".join("<tr>" + "".join(f"<td>{c}</td>" for c in row) + "</tr>" for row in rows)
    return f"<table><tr>{head}</tr>{body}</table>"


def frames_table_html(table: dict, sigmas) -> str:
    """Table 1 at the other N of ``report.table_frames``: a row per (N, L), a cell per sigma holding the default,
    GAP-TV and the still estimate; the default in bold where it is below the better of the two by more than
    0.3 dB (empty: no such N)."""
    if not table:
        return ""
    rows = []
    for n, bump in dict.fromkeys((n, b) for n, b, _ in table):
        cells = []
        for s in sigmas:
            c = table[(n, bump, float(s))]
            low = c["omp"] < max(c["gaptv"], c["trivial"]) - 0.3
            default = f"<b>{c['omp']:.2f}</b>" if low else f"{c['omp']:.2f}"
            cells.append(f"{default} / {c['gaptv']:.2f} / {c['trivial']:.2f}")
        rows.append([f"N = {n}, L = {bump}"] + cells)
    return ("<h2>Table 1 at other N: the default / GAP-TV / the still estimate (dB)</h2>\n"
            "<p>hitomi code, the report's learned dictionary at each N; a default more than 0.3 dB below the "
            "better of the two simple answers in bold.</p>\n"
            + _table(["N, L \\ sigma"] + [f"{s:g}" for s in sigmas], rows))


def write_report(cfg, runner, results: dict, summary: dict, *, seconds: float) -> dict:
    """Write report.html, report.csv, figures/*.png and side_by_side.mp4 into ``cfg.report.dir``."""
    rc = cfg.report
    out = Path(rc.dir)
    figs = out / "figures"
    f_t1 = fig_table1(summary, rc, figs)
    f_7 = fig_fig7(summary, figs)
    f_4 = fig_fig4(runner, results, rc, figs)
    f_sp = fig_speed(summary, figs)
    f_st = fig_strips(runner, results, rc, figs)
    video = side_by_side(runner, results, rc, out)
    csv_path = write_csv(out / "report.csv", csv_rows(results, summary, rc))

    t1_rows = []
    for b in rc.table_bumps:
        cells = []
        for s in rc.table_sigmas:
            v = f"{summary['table'][(b, s)]:.2f}"
            cells.append(f"<b>{v}</b>" if summary["best"][s] == b else v)
        t1_rows.append([str(b)] + cells)
    ns = sorted({f for (_, f) in summary["fig7"]})
    labels = list(dict.fromkeys(label for label, _ in summary["fig7"]))
    f7_rows = [[html.escape(lab)] + [f"{summary['fig7'][(lab, f)]['psnr']:.2f}" for f in ns] for lab in labels]
    f4_rows = [[html.escape(k), f"{v['psnr']:.2f}", f"{v['ssim']:.4f}"] for k, v in summary["fig4"].items()]
    sp_rows = [[html.escape(k), f"{v['seconds']:.3f}", f"{v['psnr']:.2f}", f"{v['ssim']:.4f}",
                "yes" if v["pareto_psnr"] else "", "yes" if v["pareto_ssim"] else ""]
               for k, v in sorted(summary["speed"].items(), key=lambda kv: kv[1]["seconds"])]
    find = "".join(
        f"<li><b>{verdict(f['holds']).upper()}</b>: {html.escape(f['claim'])}. "
        f"{html.escape(f['detail'])}</li>" for f in summary["findings"])
    d = runner.dictionary_config(rc.frames)
    dict_desc = (f"K-SVD, {runner.main_atoms()} atoms, {d.dictionary.samples} samples, {d.dictionary.iterations} "
                 f"iterations, trained on synth:train (training photographs only), one per N")
    r = cfg.reconstruct
    presets = "; ".join(f"{name}: {preset_options(name) or 'the defaults'}" for name in PRESETS)
    t1_html = _table(["L \\ sigma"] + [f"{s:g}" for s in rc.table_sigmas], t1_rows)
    tn_html = frames_table_html(summary["table_frames"], rc.table_sigmas)
    page = f"""<!doctype html><html><head><meta charset="utf-8"><title>codedvideo report</title>
<style>body{{font-family:sans-serif;max-width:1100px;margin:2em auto;line-height:1.4}}
table{{border-collapse:collapse;margin:0.5em 0}}td,th{{border:1px solid #bbb;padding:2px 8px;text-align:right}}
td:first-child{{text-align:left}}img{{max-width:100%}}</style></head><body>
<h1>codedvideo report: Hitomi et al. (ICCV 2011) reproduced</h1>
<p>Test scenes {", ".join(rc.scenes)} (synthetic motion of test photographs; never training scenes), {rc.size[0]}x{rc.size[1]},
seed {cfg.seed}. PSNR per frame (peak 255) averaged over frames, then over scenes. Dictionary: {dict_desc}.
OMP: max_atoms {r.max_atoms}, tol_rms max(sigma, 2), still-scene test {r.static_atoms} atoms, tile {r.tile}.
Bump length outside Table 1: L = {rc.bump}. Noise: Gaussian read noise on the coded image (sum convention), grey levels.
Report run time {seconds:.0f} s ({runner.computed} experiments computed, {runner.reused} reused from the cache) on
{os.cpu_count()} cores (load average {os.getloadavg()[0]:.1f} at the end), {html.escape(platform.platform())}.
Wall times are for one coded image on this machine, the best of {rc.repeats} runs (a shared CPU still leaves noise of
tens of percent); OMP and DCT run through the Dask tile graph, the baselines in numpy.</p>
<h2>Findings of the paper</h2><ul>{find}</ul>
<h2>Table 1: PSNR (dB) against bump length and read noise, N = {rc.frames}</h2>
<p>hitomi code, learned dictionary; the best of each column in bold.</p>
{t1_html}
{_img(f_t1, "Table 1")}
{tn_html}
<h2>Fig. 7: PSNR (dB) against N</h2>
{_table(["method (code)"] + [f"N = {f}" for f in ns], f7_rows)}
{_img(f_7, "Fig. 7")}
<h2>Fig. 4: pixel-wise against row-wise sampling, N = {rc.frames}, same OMP</h2>
{_table(["code", "PSNR (dB)", "SSIM"], f4_rows)}
{_img(f_4, "Fig. 4")}
<h2>Error against run time, N = {rc.frames}</h2>
<p>Every method on its natural code (the baselines' points are the Fig. 7 runs at N = {rc.frames}), and OMP with
one setting changed at a time from max_atoms {r.max_atoms}, tol_rms 2, {runner.main_atoms()} atoms, hitomi (sliding)
code (patch stride {r.stride}); "preset NAME" is <code>--preset NAME</code> ({html.escape(presets)}). Dashed: the
Pareto front (no other point is both faster and better).</p>
{_table(["method / setting", "seconds", "PSNR (dB)", "SSIM", "Pareto (PSNR)", "Pareto (SSIM)"], sp_rows)}
{_img(f_sp, "error against run time")}
<h2>Frames: {rc.video_scene}, N = {rc.frames}</h2>
{_img(f_st, "frame strips")}
<p>Side-by-side video: <a href="{video.name}">{video.name}</a> (truth | coded image / L | learned + OMP |
|error| x {ERROR_GAIN:g}), {rc.fps} frames per second.</p>
<p>Every number: <a href="{csv_path.name}">{csv_path.name}</a>.</p>
</body></html>
"""
    html_path = out / "report.html"
    with cio.atomic_output(html_path) as tmp:
        Path(tmp).write_text(page)
    return dict(html=html_path, csv=csv_path, video=video, figures=figs)


def verdict(holds: bool | None) -> str:
    """How a finding reads: reproduced, NOT reproduced, or not tested."""
    return "not tested (this config cannot test it)" if holds is None else "reproduced" if holds else "NOT reproduced"
