"""Command line: ``codedvideo train | simulate | reconstruct | evaluate | run | codes``.

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
    t.add_argument("--kind", choices=("learned", "dct"), default="learned")
    t.add_argument("--seed", type=int, default=0)
    t.add_argument("--cache", default="cache")

    s = sub.add_parser("simulate", help="simulate a coded capture of a video")
    s.add_argument("video", help="synth:NAME or a video / frame-sequence path")
    s.add_argument("--frames", "-N", type=int, required=True)
    s.add_argument("--bump", "-L", type=int, default=2)
    s.add_argument("--code", default="hitomi", choices=("hitomi", "hitomi-tiled", "bernoulli", "global"))
    s.add_argument("--noise-sigma", type=float, default=0.0, help="read noise, grey levels")
    s.add_argument("--seed", type=int, default=0)
    s.add_argument("--size", type=int, nargs=2, metavar=("H", "W"), default=None, help="centre crop (synth: size)")
    s.add_argument("--start", type=int, default=0, help="first frame of a video file")
    s.add_argument("--output", "-o", required=True, help="output folder")

    r = sub.add_parser("reconstruct", help="recover the video from a coded image and its mask")
    r.add_argument("--coded", required=True, help="coded image: .npy, .tif, .exr or .png (H, W)")
    r.add_argument("--mask", required=True, help="mask: .npy (N, H, W) or a multi-page TIFF")
    r.add_argument("--dictionary", required=True, help="dictionary store (.zarr)")
    r.add_argument("--output", "-o", required=True, help=".npy, .zarr, .mp4/.mkv/.gif or a folder of frames")
    r.add_argument("--truth", default=None, help="ground truth (N, H, W) for PSNR/SSIM in the metrics")
    r.add_argument("--max-atoms", type=int, default=PipelineConfig().reconstruct.max_atoms)
    r.add_argument("--tol-rms", type=float, default=None, help="residual tolerance, RMS per pixel (default: from --noise-sigma)")
    r.add_argument("--noise-sigma", type=float, default=0.0, help="read noise of the capture, grey levels")
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
    e.add_argument("--recon", required=True)
    e.add_argument("--truth", required=True)
    e.add_argument("--data-range", type=float, default=255.0)
    e.add_argument("--output", "-o", default=None, help="write the JSON here too")

    u = sub.add_parser("run", help="run the stages a pipeline.yaml names")
    u.add_argument("config", help="pipeline.yaml")

    c = sub.add_parser("codes", help="shutter codes")
    csub = c.add_subparsers(dest="codes_command", required=True, metavar="ACTION")
    ck = csub.add_parser("check", help="report which hardware constraints a mask meets")
    ck.add_argument("mask")
    return p


def _cmd_train(a) -> int:
    from .pipeline import train_dictionary

    base = PipelineConfig()
    cfg = base.model_copy(update=dict(
        frames=a.frames, seed=a.seed, cache=a.cache,
        dictionary=base.dictionary.model_copy(update=dict(
            kind=a.kind, atoms=a.atoms, iterations=a.iterations, samples=a.samples, sparsity=a.sparsity,
            training=list(a.videos) or ["synth:train"])),
    ))
    path, meta = train_dictionary(cfg, output=a.output, progress=not a.quiet)
    print(json.dumps(dict(dictionary=str(path), atoms=meta["atoms"], frames=meta["frames"], method=meta.get("method"),
                          final_rmse=meta.get("final_rmse"), reused=meta["reused"], seconds=round(meta["seconds"], 2))))
    return 0


def _cmd_simulate(a) -> int:
    from .pipeline import load_video, simulate_capture, write_capture

    size = tuple(a.size) if a.size else ((256, 256) if a.video.startswith("synth:") else None)
    video = load_video(a.video, frames=a.frames, size=size, seed=a.seed, start=a.start)
    cap = simulate_capture(video, code=a.code, bump=a.bump, sigma=a.noise_sigma, seed=a.seed)
    paths = write_capture(cap, a.output)
    print(json.dumps({k: str(v) for k, v in paths.items()}))
    return 0


def _cmd_reconstruct(a) -> int:
    from .metrics import evaluate
    from .pipeline import (
        _check_dictionary, _write_json, metrics_path, read_coded, read_mask, read_volume,
        reconstruct_volume, trivial_estimate, write_volume,
    )
    from .reconstruct import OmpSettings
    from .store import load_dictionary

    t_all = time.perf_counter()
    t0 = time.perf_counter()
    coded = read_coded(a.coded)
    mask = read_mask(a.mask)
    from .physics import check_pair

    check_pair(coded.shape, mask.shape, where=f"mask {a.mask}")
    D, meta = load_dictionary(a.dictionary)
    _check_dictionary(meta, mask.shape[0], a.dictionary)
    truth = read_volume(a.truth) if a.truth else None
    if truth is not None and truth.shape != mask.shape:
        raise InputError(f"truth {a.truth}: shape {truth.shape} != mask shape {mask.shape}")
    t_read = time.perf_counter() - t0
    tol = a.tol_rms if a.tol_rms is not None else auto_tolerance(a.noise_sigma)
    settings = OmpSettings(max_atoms=a.max_atoms, tol_rms=tol, batch=a.batch, static_atoms=a.static_atoms)
    volume, info = reconstruct_volume(coded, mask, D, settings=settings, tile=a.tile, cache=a.cache,
                                      scheduler=a.scheduler, workers=a.workers, progress=not a.quiet,
                                      dictionary_key=meta["sha256"])
    t0 = time.perf_counter()
    write_volume(volume, a.output, data_range=a.data_range, fps=a.fps)
    info["seconds"] = dict(read=t_read, **info["seconds"], write=time.perf_counter() - t0)
    metrics = dict(
        output=str(a.output), inputs=dict(coded=a.coded, mask=a.mask, dictionary=a.dictionary, truth=a.truth),
        settings=dict(settings.__dict__, tile=a.tile, scheduler=a.scheduler, workers=a.workers, dictionary_atoms=D.shape[1]),
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


def _cmd_evaluate(a) -> int:
    from .metrics import evaluate
    from .pipeline import _write_json, read_volume

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


def _cmd_codes(a) -> int:
    from .codes import check_code
    from .pipeline import read_mask

    print(json.dumps(check_code(read_mask(a.mask)).as_dict()))
    return 0


COMMANDS = dict(train=_cmd_train, simulate=_cmd_simulate, reconstruct=_cmd_reconstruct, evaluate=_cmd_evaluate,
                run=_cmd_run, codes=_cmd_codes)


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
