"""The table ``tasks/bench.py`` prints from its results: a line for each timed run, and the lines of each case
that has its own (the sequence's ratios, the presets' front, the footage's units)."""
from __future__ import annotations

import numpy as np


def quality_table(r: dict) -> list[str]:
    out = [f"{'scene':<24}{'code':<12}{'sigma':>6}  {'default dB/SSIM/s':>22}  {'gap-tv':>22}  {'dct (16 atoms)':>22}"]
    cell = lambda v: f"{v['psnr']:6.2f} {v['ssim']:.3f} {v['seconds']:5.2f}s"
    for x in r["rows"]:
        out.append(f"{x['scene']:<24}{x['code'] + ' L=' + str(x['bump']):<12}{x['sigma']:>6.0f}  {cell(x['default']):>22}  "
                   f"{cell(x['gaptv']):>22}  {cell(x['dct']):>22}")
    for kind in ("real", "synthetic"):
        sel = [x for x in r["rows"] if x["kind"] == kind]
        if sel:
            m = {k: np.mean([x[k]["psnr"] for x in sel]) for k in ("default", "gaptv", "dct")}
            wins = sum(x["default"]["psnr"] > x["gaptv"]["psnr"] for x in sel)
            out.append(f"mean over {kind} scenes: default {m['default']:.2f} dB, gap-tv {m['gaptv']:.2f} dB, "
                       f"dct {m['dct']:.2f} dB; default beats gap-tv in {wins}/{len(sel)}")
    return out


def _lines_units(r: dict) -> list[str]:
    """The table's lines of the units case."""
    rows: list[str] = []
    rows.append("  units: " + ", ".join(f"{k} {v['psnr']:.2f} dB (range {v['data_range']:g}) {v['seconds']:.1f} s"
                                        for k, v in r.items() if isinstance(v, dict)))
    return rows


def _lines_adapt(r: dict) -> list[str]:
    """The table's lines of the adapt case."""
    rows: list[str] = []
    for x in r["rows"]:
        base = x["default"]["seconds"]
        rows.append(f"  --adapt, {x['scene']} {x['code']} ({x['units']}): " + ", ".join(
            f"{k} {x[k]['psnr']:.2f} dB {x[k]['seconds']:.2f} s ({x[k]['seconds'] / base:.2f}x)"
            for k in ("default", "omp --adapt", "nonlocal", "nonlocal --adapt")))
    return rows


def _lines_presets(r: dict) -> list[str]:
    """The table's lines of the presets case."""
    rows: list[str] = []
    import bench_presets

    rows.extend("  " + line for line in bench_presets.table(r).splitlines())
    return rows


def _lines_startup(r: dict) -> list[str]:
    """The table's lines of the startup case."""
    rows: list[str] = []
    rows.append(f"  start-up: reconstruct {r['size']} as a whole process {r['process_seconds']:.2f} s, in-process "
                f"{r['in_process_seconds']:.2f} s: {r['ratio']:.2f}x (target 1.5x)")
    return rows


def _lines_calibrated(r: dict) -> list[str]:
    """The table's lines of the calibrated case."""
    rows: list[str] = []
    for key, row in r.items():
        if isinstance(row, dict) and "nominal" in row:
            rows.append(f"  misregistered code ({key}): nominal mask {row['nominal']['psnr']:.2f} dB "
                        f"{row['nominal']['seconds']:.2f} s, measured mask {row['measured']['psnr']:.2f} dB "
                        f"{row['measured']['seconds']:.2f} s")
    return rows


def _lines_sequence(r: dict) -> list[str]:
    """The table's lines of the sequence case."""
    rows: list[str] = []
    for scene in ("static70", "still", "moving"):
        q, i = r[scene]["sequence"], r[scene]["independent"]
        moving = (f", moving part {q['psnr_moving']:.2f} vs {i['psnr_moving']:.2f} dB"
                  if "psnr_moving" in q else "")
        rows.append(f"  {r['captures']} captures {scene}: one job {q['seconds']:.1f} s {q['psnr']:.2f} dB, "
                    f"capture by capture {i['seconds']:.1f} s {i['psnr']:.2f} dB{moving}")
    rows.append(f"  70 %-still / moving: {100 * r['moving_vs_still70_time']:.1f} % of the time; still / moving: "
                f"{100 * r['still_vs_moving_time']:.1f} %; moving, one job / capture by capture: "
                f"{100 * r['moving']['time_ratio']:.1f} % (medians of {len(r['moving']['sequence'].get('seconds_runs', [0]))} whole processes)")
    if "moving_vs_still70_pipeline_time" in r:
        rows.append(f"  70 %-still / moving, the pipeline's own time (metrics JSON, no start-up): "
                    f"{100 * r['moving_vs_still70_pipeline_time']:.1f} %")
    if "longer" in r:
        lg = r["longer"]
        rows.append(f"  70 %-still / moving at {lg['captures']} captures (whole processes): "
                    f"{100 * lg['moving_vs_still70_time']:.1f} % ({lg['seconds']['static70']:.1f} s against "
                    f"{lg['seconds']['moving']:.1f} s)")
    rows.append("  boundary step / inside step: " + ", ".join(
        f"{scene} {r[scene]['sequence'].get('boundary_to_inside') or 0:.2f} joined, "
        f"{r[scene]['independent'].get('boundary_to_inside') or 0:.2f} alone" for scene in ("static70", "moving")))
    rows.append("  peak RSS by T: " + ", ".join(f"T = {t}: {m['peak_rss_mb']:.0f} MB ({m['seconds']:.1f} s)"
                                               for t, m in r["memory"].items()))
    for sigma, v in r.get("noisy", {}).items():
        q, i = v["sequence"], v["independent"]
        rows.append(f"  70 %-still, read noise {sigma}: one job {q['seconds']:.1f} s {q['psnr']:.2f} dB (moving part "
                    f"{q['psnr_moving']:.2f}), capture by capture {i['seconds']:.1f} s {i['psnr']:.2f} dB "
                    f"({i['psnr_moving']:.2f})")
    return rows


def _lines_video(r: dict) -> list[str]:
    """The table's lines of the video case."""
    rows: list[str] = []
    for key, v in r.items():
        if isinstance(v, dict) and "captures" in v:
            rows.append(f"  video {key} N = 18: {v['seconds']:.0f} s ({v['seconds_per_capture']:.1f} s a capture), "
                        f"peak {v['peak_rss_mb']:.0f} MB, {v['psnr']:.2f} dB")
    return rows


def _lines_outputs(r: dict) -> list[str]:
    """The table's lines of the outputs case."""
    rows: list[str] = []
    rows.append(f"  outputs {r['size'][1]}x{r['size'][0]} N = 18, peak RSS of whole processes (fresh caches): " +
                ", ".join(f"{k} {v['peak_rss_mb']:.0f} MB ({v['of_npy']:.2f}x)" for k, v in r["peaks"].items()))
    return rows


def _lines_outputs_4k(r: dict) -> list[str]:
    """The table's lines of the outputs4k case."""
    rows: list[str] = []
    rows.append(f"  outputs {r['size'][1]}x{r['size'][0]} N = 18, peak RSS of whole processes (fresh caches): " +
                ", ".join(f"{k} {v['peak_rss_mb']:.0f} MB ({v['of_npy']:.2f}x, {v['seconds']:.0f} s)"
                          for k, v in r["peaks"].items()))
    stream = [v for v in r["peaks"].values() if v["captures"] > 1]
    rows.append("  a stream as one job, peak by captures: " + ", ".join(
        f"{v['captures']}: {v['peak_rss_mb']:.0f} MB" for v in stream) +
        f" (target 2 GB, {r['target_mb']:.0f} MB as counted here: {'met' if all(v['peak_rss_mb'] <= r['target_mb'] for v in stream) else 'NOT met'})")
    return rows


def _lines_footage(r: dict) -> list[str]:
    """The table's lines of the footage case."""
    rows: list[str] = []
    for clip, v in r.items():
        if isinstance(v, dict) and "sequence" in v:
            q, i, u = v["sequence"], v["independent"], v["sequence [0, 1]"]
            rows.append(f"  footage {clip} ({v['captures']} captures of {v['size'][0]}x{v['size'][1]}, N = 8, "
                        f"noise {r['noise_sigma']:g}): one job {q['seconds']:.1f} s {q['psnr']:.2f} dB SSIM "
                        f"{q['ssim']:.4f}, boundary step {q['boundary_to_inside']:.2f} of the inside step, "
                        f"{100 * q['patches_still']:.0f} % of patches still; capture by capture {i['seconds']:.1f} s "
                        f"{i['psnr']:.2f} dB SSIM {i['ssim']:.4f}, boundary {i['boundary_to_inside']:.2f} "
                        f"({100 * v['time_ratio']:.1f} % of the time, medians of {len(q['seconds_runs'])})")
            rows.append(f"    [0, 1] floats {u['psnr']:.2f} dB {u['seconds']:.1f} s: largest difference "
                        f"{v['unit_max_diff_grey']:.2g} grey levels, {100 * v['unit_share_over_0.01']:.3f} % of "
                        f"values over 0.01; the 8-bit capture one float step up: {v['nudged_max_diff_grey']:.2g}, "
                        f"{100 * v['nudged_share_over_0.01']:.3f} %")
    return rows


def _lines_bayer(r: dict) -> list[str]:
    """The table's lines of the bayer case."""
    rows: list[str] = []
    rows.append(f"  bayer {r['pattern']}: colour result {r['omp']['psnr']:.2f} dB, demosaicked static estimate "
                f"{r['static']['psnr']:.2f} dB")
    return rows


def _lines_robust(r: dict) -> list[str]:
    """The robust sweep's targets: the default's worst margin over the better simple answer, best's over the
    default, frames beyond [-0.25, 1.25]."""
    s = r["summary"]
    lines = [f"  {s['cases']} cases: default - max(trivial, GAP-TV) worst {s['default_worst_margin']:+.2f} dB "
             f"({s['default_below_floor_0_3']} more than 0.3 below); 8-bit against [0, 1] worst "
             f"{s['default_8bit_worst_gap']:+.2f} dB; {s['out_of_range']} with frames beyond [-0.25, 1.25]"]
    if "best_worst_lead" in s:
        lines.append(f"  best - default worst {s['best_worst_lead']:+.2f} dB ({s['best_below_default_0_05']} "
                     "more than 0.05 below)")
    return lines


def _crop_lines(r: dict, label: str) -> list[str]:
    """A sweep over crops (tasks/bench_robust.py): best - the default and the default's margin, each ``label``
    (the read noise, or the sub-frames) in its summary."""
    return [f"  {label + ' ' if label else ''}{value}: best - default worst {s['best_lead_worst']:+.2f} / median "
            f"{s['best_lead_median']:+.2f} dB; default - max(trivial, GAP-TV) worst {s['default_margin_worst']:+.2f} dB "
            f"({s['cases']} captures)" for value, s in r["summary"].items()]


def _lines_robust_noise(r: dict) -> list[str]:
    """The read-noise sweep off the centre crops, each noise level."""
    return _crop_lines(r, "read noise")


def _lines_robust_crops(r: dict) -> list[str]:
    """The codes off the centre crops, each N and code."""
    return _crop_lines(r, "")


#: The table's lines of each case that has its own.
_CASE_LINES = {
    "robust": _lines_robust,
    "robust-noise": _lines_robust_noise,
    "robust-crops": _lines_robust_crops,
    "units": _lines_units,
    "adapt": _lines_adapt,
    "presets": _lines_presets,
    "front": _lines_presets,
    "startup": _lines_startup,
    "calibrated": _lines_calibrated,
    "sequence": _lines_sequence,
    "video": _lines_video,
    "outputs": _lines_outputs,
    "outputs4k": _lines_outputs_4k,
    "footage": _lines_footage,
    "bayer": _lines_bayer,
}


def table(results: dict) -> str:
    rows = []
    fmt = "{:<34} {:>9} {:>9} {:>8} {:>12} {:>9}"
    rows.append(fmt.format("case", "seconds", "PSNR dB", "SSIM", "patches/s", "peak MB"))
    for name, r in results["cases"].items():
        if "error" in r:
            rows.append(f"{name:<34} error: {r['error']}")
            continue
        peak = f"{r['peak_rss_mb']:.0f}" if "peak_rss_mb" in r else ""
        for key, label in (("omp", "omp sliding"), ("gaptv", "gap-tv sliding"), ("hitomi", "omp sliding"),
                           ("hitomi-tiled", "omp tiled"), ("gaptv-tiled", "gap-tv tiled"),
                           ("omp-stride2", "omp sliding, stride 2")):
            if key in r:
                v = r[key]
                rows.append(fmt.format(f"{name} {r.get('size')} N={r.get('frames')} {label}", f"{v['seconds']:.2f}",
                                       f"{v['psnr']:.2f}", f"{v['ssim']:.3f}",
                                       f"{v['patches_per_second']:.0f}" if "patches_per_second" in v else "", peak))
        if "naive" in r:
            nv = r["naive"]
            rows.append(f"  naive OMP on a {nv['crop']}x{nv['crop']} crop: {nv['naive_seconds']:.1f} s, {nv['naive_psnr']:.2f} dB "
                        f"(fast: {nv['fast_seconds']:.2f} s, {nv['fast_psnr']:.2f} dB); full image extrapolated "
                        f"{nv['extrapolated_full_seconds']:.0f} s")
            if "kernel_load_seconds" in r:
                rows.append(f"  compiled OMP kernel: loaded once per process in {r['kernel_load_seconds']:.2f} s, "
                            "before the timings above")
        if name in _CASE_LINES:
            rows.extend(_CASE_LINES[name](r))
        for scene in ("default", "default-static70"):
            if scene in r:
                s = r[scene]
                rows.append(f"  {scene}: still-scene test {s['skip']['seconds']:.2f} s {s['skip']['psnr']:.2f} dB "
                            f"({100 * s['skip']['static_fraction']:.0f}% patches still) vs off {s['no_skip']['seconds']:.2f} s "
                            f"{s['no_skip']['psnr']:.2f} dB")
    if "nonlocal" in results["cases"] and "error" not in results["cases"]["nonlocal"]:
        from bench_nonlocal import nonlocal_table

        rows.extend(nonlocal_table(results["cases"]["nonlocal"]))
    if "quality" in results["cases"] and "error" not in results["cases"]["quality"]:
        rows.extend(quality_table(results["cases"]["quality"]))
    c = results["cases"]
    if "b" in c and "b1" in c and "error" not in c["b"] and "error" not in c["b1"]:
        rows.append(f"two workers vs one on b: {c['b1']['omp']['seconds'] / c['b']['omp']['seconds']:.2f}x")
    return "\n".join(rows)


if __name__ == "__main__":  # a helper module of the scripts beside it, not a script: it says what it is
    print(__doc__)
