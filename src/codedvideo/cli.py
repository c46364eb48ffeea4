"""Command line: ``codedvideo train | simulate | reconstruct | evaluate | run | report | codes``.

Any :class:`~codedvideo.errors.CodedVideoError` becomes one line on stderr
(``codedvideo: error: ...``) and exit status 2; nothing half-written is left
behind because every writer goes through a temporary name.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import time
import warnings
from pathlib import Path

import numpy as np

from . import __version__
from .baselines import METHODS
from .codes import CODE_NAMES
from .config import PipelineConfig, auto_tolerance, load_config
from .errors import CodedVideoError, InputError

log = logging.getLogger("codedvideo")


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="codedvideo", description="Video from a single coded-exposure photograph (Hitomi et al. 2011).")
    p.add_argument("--version", action="version", version=f"codedvideo {__version__}")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bars")
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND")

    t = sub.add_parser("train", help="learn a K-SVD dictionary (or build a 3D DCT one)")
    t.add_argument("videos", nargs="*", metavar="VIDEO", help="training videos (default: the embedded synthetic set)")
    t.add_argument("--frames", "-N", type=int, required=True, help="sub-frames N per coded image")
    t.add_argument("--output", "-o", required=True, help="dictionary store (.zarr)")
    t.add_argument("--atoms", type=int, default=PipelineConfig().dictionary.atoms)
    t.add_argument("--iterations", type=int, default=PipelineConfig().dictionary.iterations)
    t.add_argument("--samples", type=int, default=PipelineConfig().dictionary.samples)
    t.add_argument("--sparsity", type=int, default=PipelineConfig().dictionary.sparsity)
    t.add_argument("--max-speed", type=float, default=PipelineConfig().dictionary.max_speed,
                   help="fastest synthetic training motion, pixels per sub-frame")
    t.add_argument("--kind", choices=("learned", "dct"), default="learned")
    t.add_argument("--seed", type=int, default=0)
    t.add_argument("--cache", default="cache")

    s = sub.add_parser("simulate", help="simulate a coded capture of a video")
    s.add_argument("video", help="synth:NAME or a video / frame-sequence path")
    s.add_argument("--frames", "-N", type=int, required=True)
    s.add_argument("--bump", "-L", type=int, default=2)
    s.add_argument("--code", default=None, choices=CODE_NAMES,
                   help="shutter code (default: hitomi, or file with --code-file); see README")
    s.add_argument("--code-file", default=None, metavar="PATH", help="mask of --code file: .npy (N, H, W) or multi-page TIFF")
    s.add_argument("--p", type=float, default=PipelineConfig().code.p, help="open probability of bernoulli / shifting")
    s.add_argument("--noise-sigma", type=float, default=0.0, help="read noise, grey levels")
    s.add_argument("--shot-noise", action="store_true", help="Poisson photon noise (see --full-well, --gain)")
    s.add_argument("--full-well", type=float, default=PipelineConfig().noise.full_well, help="full-well capacity, electrons")
    s.add_argument("--gain", type=float, default=PipelineConfig().noise.gain, help="electrons per grey level")
    s.add_argument("--bits", type=int, default=None, help="quantise the coded image to this bit depth")
    s.add_argument("--white-level", type=float, default=None, help="clip the coded image at this grey level (saturation)")
    s.add_argument("--seed", type=int, default=0)
    s.add_argument("--size", type=int, nargs=2, metavar=("H", "W"), default=None, help="centre crop (synth: size)")
    s.add_argument("--start", type=int, default=0, help="first frame of a video file")
    s.add_argument("--output", "-o", required=True, help="output folder")
    s.add_argument("--cacti-out", default=None, metavar="FILE.mat",
                   help="also write the capture as a CACTI benchmark .mat (orig, mask, meas; one measurement)")

    r = sub.add_parser("reconstruct", help="recover the video from a coded image and its mask")
    r.add_argument("--coded", default=None, help="coded image: .npy, .tif, .exr, .dpx or .png (H, W); required unless --cacti")
    r.add_argument("--mask", default=None, help="mask: .npy (N, H, W), a multi-page TIFF or frames; required unless --cacti")
    r.add_argument("--cacti", default=None, metavar="FILE.mat",
                   help="instead of --coded/--mask: a CACTI .mat (mask, meas, orig); every measurement is reconstructed")
    r.add_argument("--measurement", type=int, default=None, metavar="Q",
                   help="with --cacti: reconstruct only measurement Q (1-based)")
    r.add_argument("--color", choices=("luma", "channels"), default="luma",
                   help="colour coded image: its luma (default), or each channel with the same mask (colour output)")
    r.add_argument("--dictionary", default=None, help="dictionary store (.zarr); needed by --method omp only")
    r.add_argument("--method", choices=METHODS, default="omp",
                   help="omp: learned dictionary (default); dct: 3D DCT dictionary, same OMP; "
                        "thinout, interp, gaptv: baselines (see README)")
    r.add_argument("--output", "-o", required=True,
                   help=".npy, .zarr, .mat, .tif, .mp4/.mkv/.gif or a folder of frames (--cacti: all measurements, time-first)")
    r.add_argument("--truth", default=None, help="ground truth (N, H, W) for PSNR/SSIM in the metrics")
    r.add_argument("--max-atoms", type=int, default=PipelineConfig().reconstruct.max_atoms)
    r.add_argument("--tol-rms", type=float, default=None, help="residual tolerance, RMS per pixel (default: from --noise-sigma)")
    r.add_argument("--noise-sigma", type=float, default=0.0, help="read noise of the capture, grey levels")
    r.add_argument("--white-level", type=float, default=None,
                   help="saturation level of the coded image: pixels at or above it are treated as missing")
    r.add_argument("--trust-saturated", action="store_true", help="with --white-level: use saturated pixels anyway")
    r.add_argument("--stride", type=int, default=PipelineConfig().reconstruct.stride,
                   help="patch stride 1..7: 1 solves every overlapping patch (the paper), s about s*s times fewer")
    r.add_argument("--weighting", choices=("uniform", "fit"), default=PipelineConfig().reconstruct.weighting,
                   help="average of overlapping estimates: uniform (the paper) or weighted by each patch's misfit")
    r.add_argument("--static-atoms", type=int, default=PipelineConfig().reconstruct.static_atoms,
                   help="still-scene test: 2D DCT atoms before full OMP (0: off)")
    r.add_argument("--tile", type=int, default=PipelineConfig().reconstruct.tile)
    r.add_argument("--batch", type=int, default=PipelineConfig().reconstruct.batch)
    r.add_argument("--scheduler", default=None, help="dask.distributed scheduler address (default: local, both cores)")
    r.add_argument("--workers", type=int, default=None, help="local worker threads")
    r.add_argument("--data-range", type=float, default=255.0, help="peak value for PSNR and video scaling")
    r.add_argument("--fps", type=int, default=30)
    r.add_argument("--cache", default="cache")

    e = sub.add_parser("evaluate", help="per-frame and mean PSNR/SSIM as JSON")
    e.add_argument("--recon", required=True, help=".npy, .zarr, .mat, .tif, a video or frames")
    e.add_argument("--truth", required=True, help="as --recon; a .mat gives 'recon', else a CACTI file's 'orig'")
    e.add_argument("--data-range", type=float, default=255.0)
    e.add_argument("--output", "-o", default=None, help="write the JSON here too")

    u = sub.add_parser("run", help="run the stages a pipeline.yaml names")
    u.add_argument("config", help="pipeline.yaml")

    rp = sub.add_parser("report", help="the paper's experiments and error against run time, as HTML + CSV")
    rp.add_argument("config", help="pipeline.yaml (its report: section)")

    c = sub.add_parser("codes", help="shutter codes")
    csub = c.add_subparsers(dest="codes_command", required=True, metavar="ACTION")
    ck = csub.add_parser("check", help="report which hardware constraints a mask meets")
    ck.add_argument("mask")
    return p


def _cmd_train(a) -> int:
    from .io import check_writable
    from .pipeline import train_dictionary

    check_writable(a.output)  # before training
    base = PipelineConfig()
    cfg = base.model_copy(update=dict(
        frames=a.frames, seed=a.seed, cache=a.cache,
        dictionary=base.dictionary.model_copy(update=dict(
            kind=a.kind, atoms=a.atoms, iterations=a.iterations, samples=a.samples, sparsity=a.sparsity,
            max_speed=a.max_speed, training=list(a.videos) or ["synth:train"])),
    ))
    path, meta = train_dictionary(cfg, output=a.output, progress=not a.quiet)
    print(json.dumps(dict(dictionary=str(path), atoms=meta["atoms"], frames=meta["frames"], method=meta.get("method"),
                          final_rmse=meta.get("final_rmse"), reused=meta["reused"], seconds=round(meta["seconds"], 2))))
    return 0


def _cmd_simulate(a) -> int:
    from .io import check_writable
    from .pipeline import load_video, simulate_capture, write_capture

    check_writable(Path(a.output) / "coded.npy")  # before any work
    if a.cacti_out:
        check_writable(a.cacti_out)
    size = tuple(a.size) if a.size else ((256, 256) if a.video.startswith("synth:") else None)
    video = load_video(a.video, frames=a.frames, size=size, seed=a.seed, start=a.start)
    code = a.code or ("file" if a.code_file else "hitomi")
    if a.code_file and code != "file":
        raise InputError(f"--code-file {a.code_file}: only used with --code file (got --code {code})")
    sensor = None
    if a.shot_noise or a.bits is not None or a.white_level is not None:
        from .physics import SensorModel

        sensor = SensorModel(shot_noise=a.shot_noise, full_well=a.full_well, gain=a.gain, bits=a.bits,
                             white_level=a.white_level)
    cap = simulate_capture(video, code=code, bump=a.bump, sigma=a.noise_sigma, seed=a.seed, p=a.p,
                           code_path=a.code_file, sensor=sensor)
    paths = write_capture(cap, a.output)
    if a.cacti_out:
        from .cacti import write_cacti

        paths["cacti"] = write_cacti(a.cacti_out, mask=cap["mask"], meas=cap["coded"][None], orig=cap["truth"])
    print(json.dumps({k: str(v) for k, v in paths.items()}))
    return 0


def _omp_settings(a):
    """The sparse-coding settings that reconstruct's options give."""
    from .reconstruct import OmpSettings

    tol = a.tol_rms if a.tol_rms is not None else auto_tolerance(a.noise_sigma)
    return OmpSettings(max_atoms=a.max_atoms, tol_rms=tol, batch=a.batch, static_atoms=a.static_atoms,
                       stride=a.stride, weighting=a.weighting)


def _cmd_reconstruct(a) -> int:
    from .metrics import evaluate
    from .pipeline import (
        _check_dictionary, _write_json, check_output, check_size, metrics_path, read_coded, read_mask, read_volume,
        trivial_estimate, write_volume,
    )
    from .baselines import reconstruct_method

    if a.cacti or a.color == "channels":
        return _cmd_reconstruct_multi(a)
    if not (a.coded and a.mask):
        raise InputError("reconstruct: give --coded and --mask, or --cacti FILE.mat")
    if a.measurement is not None:
        raise InputError("reconstruct: --measurement applies to --cacti only")
    check_output(a.output)  # before any work: a known format in a writable place
    t_all = time.perf_counter()
    t0 = time.perf_counter()
    coded = read_coded(a.coded)
    check_size(coded.shape, a.coded)
    mask = read_mask(a.mask)
    from .physics import check_pair

    check_pair(coded.shape, mask.shape, where=f"mask {a.mask}")
    D, meta = _method_dictionary(a, mask.shape[0])
    truth = read_volume(a.truth) if a.truth else None
    if truth is not None and truth.shape != mask.shape:
        raise InputError(f"truth {a.truth}: shape {truth.shape} != mask shape {mask.shape}")
    t_read = time.perf_counter() - t0
    settings = _omp_settings(a)
    coded_used, mask_used, saturated = coded, mask, 0
    if a.white_level is not None and not a.trust_saturated:  # saturated pixels are missing measurements
        from .pipeline import drop_saturated

        coded_used, mask_used, saturated = drop_saturated(coded, mask, a.white_level)
        _check_not_all_saturated(mask_used, saturated, a.coded, a.white_level)
    volume, info = reconstruct_method(a.method, coded_used, mask_used, dictionary=D, settings=settings, tile=a.tile,
                                      cache=a.cache, scheduler=a.scheduler, workers=a.workers, progress=not a.quiet,
                                      dictionary_key=meta.get("sha256", ""))
    info["saturated_pixels"] = saturated
    t0 = time.perf_counter()
    write_volume(volume, a.output, data_range=a.data_range, fps=a.fps)
    info["seconds"] = dict(read=t_read, **info["seconds"], write=time.perf_counter() - t0)
    metrics = dict(
        output=str(a.output), inputs=dict(coded=a.coded, mask=a.mask, dictionary=a.dictionary, truth=a.truth),
        settings=dict(settings.__dict__, method=a.method, tile=a.tile, scheduler=a.scheduler, workers=a.workers,
                      dictionary_atoms=info.get("dictionary_atoms")),
        reconstruction=info,
    )
    if truth is not None:
        metrics["quality"] = evaluate(volume, truth, data_range=a.data_range)
        metrics["trivial"] = evaluate(trivial_estimate(coded, mask), truth, data_range=a.data_range)
    info["seconds"]["total"] = time.perf_counter() - t_all
    mpath = _write_json(metrics_path(a.output), metrics)
    summary = dict(output=str(a.output), metrics=str(mpath), seconds=round(info["seconds"]["total"], 2),
                   patches_per_second=round(info["patches_per_second"]))
    if truth is not None:
        summary.update(psnr=round(metrics["quality"]["psnr"], 2), ssim=round(metrics["quality"]["ssim"], 4))
    print(json.dumps(summary))
    return 0


def _method_dictionary(a, frames: int):
    """``(D, meta)`` of ``--dictionary`` for ``--method omp``; ``(None, {})`` for the other methods."""
    from .pipeline import _check_dictionary
    from .store import load_dictionary

    if a.method != "omp":
        return None, {}
    if not a.dictionary:
        raise InputError("reconstruct --method omp: give --dictionary DICT.zarr (or --method dct, thinout, interp, gaptv)")
    D, meta = load_dictionary(a.dictionary)
    _check_dictionary(meta, frames, a.dictionary)
    return D, meta


def _check_not_all_saturated(mask_used: np.ndarray, saturated: int, coded_path, white_level) -> None:
    if saturated and not mask_used.any():
        raise InputError(f"coded image {coded_path}: every measured pixel is at or above --white-level {white_level}; "
                         "nothing is left to reconstruct (--trust-saturated uses them anyway)")


def _cmd_reconstruct_multi(a) -> int:
    """Several coded images sharing one mask: a CACTI file's measurements, or the channels of a colour image.

    Output: measurements' volumes concatenated time-first (Q*N, H, W), or
    channels stacked first (C, N, H, W); one metrics JSON with an entry per
    measurement (channel) and the mean over all of them.
    """
    from .metrics import evaluate
    from .physics import check_pair
    from .pipeline import (
        _check_dictionary, _write_json, check_output, check_size, metrics_path, read_coded, read_mask, read_volume,
        trivial_estimate, write_volume,
    )
    from .baselines import reconstruct_method

    check_output(a.output)  # before any work: a known format in a writable place
    t_all = t0 = time.perf_counter()
    if a.cacti:
        from .cacti import read_cacti

        if a.coded or a.mask or a.truth:
            raise InputError(f"reconstruct --cacti {a.cacti}: takes coded images, mask and truth from the file "
                             "(drop --coded, --mask and --truth)")
        if a.color != "luma":
            raise InputError(f"reconstruct --cacti {a.cacti}: CACTI files are grey; --color channels does not apply")
        data = read_cacti(a.cacti)
        mask, kind = data.mask, "measurements"
        if a.measurement is not None and not 1 <= a.measurement <= data.measurements:
            raise InputError(f"--measurement {a.measurement}: {a.cacti} holds measurements 1..{data.measurements}")
        chosen = range(data.measurements) if a.measurement is None else [a.measurement - 1]
        labels = [dict(measurement=q + 1) for q in chosen]
        codeds = [data.meas[q] for q in chosen]
        truths = None if data.orig is None else [data.truth(q) for q in chosen]
        inputs = dict(cacti=a.cacti, dictionary=a.dictionary, measurements=[q + 1 for q in chosen])
    else:
        if not (a.coded and a.mask):
            raise InputError("reconstruct: give --coded and --mask, or --cacti FILE.mat")
        if a.measurement is not None:
            raise InputError("reconstruct: --measurement applies to --cacti only")
        coded = read_coded(a.coded, color="channels")
        check_size(coded.shape, a.coded)
        mask, kind = read_mask(a.mask), "channels"
        check_pair(coded.shape[1:], mask.shape, where=f"mask {a.mask}")
        codeds = list(coded)
        labels = [dict(channel=c) for c in range(len(codeds))]
        truths = None
        if a.truth:
            truth = read_volume(a.truth, color="channels")
            truth = truth[None] if truth.ndim == 3 else truth
            if truth.shape != (len(codeds), *mask.shape):
                raise InputError(f"truth {a.truth}: shape {truth.shape} != (channels, N, H, W) "
                                 f"{(len(codeds), *mask.shape)}")
            truths = list(truth)
        inputs = dict(coded=a.coded, mask=a.mask, dictionary=a.dictionary, truth=a.truth, color=a.color)
    D, meta = _method_dictionary(a, mask.shape[0])
    t_read = time.perf_counter() - t0
    settings = _omp_settings(a)
    volumes, entries = [], []
    for label, coded in zip(labels, codeds):
        coded_used, mask_used, saturated = coded, mask, 0
        if getattr(a, "white_level", None) is not None and not a.trust_saturated:
            from .pipeline import drop_saturated

            coded_used, mask_used, saturated = drop_saturated(coded, mask, a.white_level)
            _check_not_all_saturated(mask_used, saturated, a.cacti or a.coded, a.white_level)
        volume, info = reconstruct_method(a.method, coded_used, mask_used, dictionary=D, settings=settings,
                                          tile=a.tile, cache=a.cache, scheduler=a.scheduler, workers=a.workers,
                                          progress=not a.quiet, dictionary_key=meta.get("sha256", ""))
        info["saturated_pixels"] = saturated
        volumes.append(volume)
        entries.append(dict(label, reconstruction=info))
    volume = np.concatenate(volumes) if kind == "measurements" else np.stack(volumes)
    t0 = time.perf_counter()
    write_volume(volume, a.output, data_range=a.data_range, fps=a.fps)
    t_write = time.perf_counter() - t0
    patches = sum(e["reconstruction"]["patches"] for e in entries)
    t_rec = sum(e["reconstruction"]["seconds"]["reconstruct"] for e in entries)
    metrics = dict(
        output=str(a.output), inputs=inputs, layout="(Q*N, H, W)" if kind == "measurements" else "(C, N, H, W)",
        settings=dict(settings.__dict__, method=a.method, tile=a.tile, scheduler=a.scheduler, workers=a.workers,
                      dictionary_atoms=info.get("dictionary_atoms")),
        reconstruction=dict(patches=patches, patches_per_second=patches / max(t_rec, 1e-9),
                            seconds=dict(read=t_read, reconstruct=t_rec, write=t_write)),
    )
    summary = dict(output=str(a.output))
    if truths is not None:
        for entry, vol, coded, truth in zip(entries, volumes, codeds, truths):
            entry["quality"] = evaluate(vol, truth, data_range=a.data_range)
            entry["trivial"] = evaluate(trivial_estimate(coded, mask), truth, data_range=a.data_range)
        # every measurement (channel) has N frames: the mean over all frames is the mean of their means
        metrics["quality"] = evaluate(np.concatenate(volumes), np.concatenate(truths), data_range=a.data_range)
        metrics["trivial"] = evaluate(np.concatenate([trivial_estimate(c, mask) for c in codeds]),
                                      np.concatenate(truths), data_range=a.data_range)
        per = {f"psnr_per_{kind[:-1]}": [e["quality"]["psnr"] for e in entries],
               f"ssim_per_{kind[:-1]}": [e["quality"]["ssim"] for e in entries]}
        metrics["quality"].update(per)
        summary.update(psnr=round(metrics["quality"]["psnr"], 2), ssim=round(metrics["quality"]["ssim"], 4),
                       **{k: [round(v, 2 if k.startswith("psnr") else 4) for v in vals] for k, vals in per.items()})
    metrics[kind] = entries
    metrics["reconstruction"]["seconds"]["total"] = time.perf_counter() - t_all
    mpath = _write_json(metrics_path(a.output), metrics)
    summary.update(metrics=str(mpath), seconds=round(metrics["reconstruction"]["seconds"]["total"], 2),
                   patches_per_second=round(metrics["reconstruction"]["patches_per_second"]))
    print(json.dumps(summary))
    return 0


def _cmd_evaluate(a) -> int:
    from .metrics import evaluate
    from .io import check_writable
    from .pipeline import _write_json, read_volume

    if a.output:
        check_writable(a.output)
    result = evaluate(read_volume(a.recon), read_volume(a.truth), data_range=a.data_range)
    if a.output:
        _write_json(Path(a.output), result)
    print(json.dumps(result))
    return 0


def _cmd_run(a) -> int:
    from .pipeline import run_pipeline

    cfg = load_config(a.config)
    report = run_pipeline(cfg, progress=not a.quiet)
    lines = [f"metrics: {report['metrics_path']}"]
    if "outputs" in report:
        lines.insert(0, f"video: {report['outputs']['video']}")
        lines.insert(1, f"frames: {report['outputs'].get('frames', '-')}")
    if "quality" in report:
        q, tr = report["quality"], report["trivial"]
        lines.append(f"PSNR {q['psnr']:.2f} dB, SSIM {q['ssim']:.4f} (trivial estimate: {tr['psnr']:.2f} dB, {tr['ssim']:.4f})")
    secs = ", ".join(f"{k} {v:.1f} s" for k, v in report["seconds"].items())
    lines.append(f"time: {secs}")
    print("\n".join(lines))
    return 0


def _cmd_report(a) -> int:
    from .report import run_report

    result = run_report(load_config(a.config), progress=not a.quiet)
    lines = [f"report: {result['html']}", f"numbers: {result['csv']}", f"video: {result['video']}"]
    lines += [f"{'reproduced' if f['holds'] else 'NOT reproduced'}: {f['claim']} ({f['detail']})" for f in result["findings"]]
    lines.append(f"experiments: {result['computed']} computed, {result['reused']} reused; {result['seconds']:.0f} s")
    print("\n".join(lines))
    return 0


def _cmd_codes(a) -> int:
    from .codes import check_code
    from .pipeline import read_mask

    print(json.dumps(check_code(read_mask(a.mask)).as_dict()))
    return 0


COMMANDS = dict(train=_cmd_train, simulate=_cmd_simulate, reconstruct=_cmd_reconstruct, evaluate=_cmd_evaluate,
                run=_cmd_run, report=_cmd_report, codes=_cmd_codes)


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="codedvideo: %(message)s")
    warnings.simplefilter("default")
    try:
        return COMMANDS[args.command](args)
    except CodedVideoError as exc:
        print(f"codedvideo: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("codedvideo: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
