"""Command line: ``codedvideo train | simulate | reconstruct | evaluate | run | report | codes``.

Any :class:`~codedvideo.model.errors.CodedVideoError` becomes one line on stderr
(``codedvideo: error: ...``) and exit status 2; nothing half-written is left
behind because every writer goes through a temporary name.
"""

from __future__ import annotations

import argparse
import atexit
import contextlib
import dataclasses
import json
import logging
import os
import re
import signal
import sys
import threading
import time
import warnings
from pathlib import Path

import numpy as np

from codedvideo import __version__, api
from codedvideo.api.config import (DEFAULT_CACHE, PRESETS, OutputConfig, PipelineConfig, default_config_path, load_config,
                                   preset_options, validated)
from codedvideo.model import doors
from codedvideo.model.codes import CODE_NAMES, short_of_the_truth
from codedvideo.model.errors import CodedVideoError, ConfigError, InputError
from codedvideo.formats.outputs import Output, check_outputs, mark_written
from codedvideo.model.metrics import json_safe

log = logging.getLogger("codedvideo")

#: '-' then a digit, '.digit', or inf / infinity / nan: no option of codedvideo's starts so.
_NEGATIVE_NUMBER = re.compile(r"^-(\d|\.\d|(inf|infinity|nan)$)", re.IGNORECASE)


class _Help(argparse.ArgumentDefaultsHelpFormatter):
    """Help with each option's default as the parser holds it, ``(default: X)``; none shown for a flag, an
    option whose default is found at run time (None), or one whose help says its default itself."""

    def _get_help_string(self, action: argparse.Action) -> str:
        text = action.help or ""
        if action.default is None or action.default is False or action.default == argparse.SUPPRESS \
                or "default" in text \
                or not (action.option_strings or action.nargs in ("?", "*")):
            return text
        return text + " (default: %(default)s)"


class _Parser(argparse.ArgumentParser):
    """argparse with the project's error form: one line, ``codedvideo: error: ...``, exit status 2.

    A value that starts with '-' and reads as a number (``-inf``, ``-1e3``, ``-nan``, a size ``-5M``) is a value,
    not an option (argparse's own rule takes only ``-5`` and ``-.5``), so that the option's range check names it."""

    def __init__(self, *args, **kwargs):
        kwargs.setdefault("formatter_class", _Help)
        super().__init__(*args, **kwargs)
        self._negative_number_matcher = _NEGATIVE_NUMBER

    def error(self, message: str):
        command = self.prog.removeprefix("codedvideo").strip()  # a subcommand's parser names it; the top one does not
        misplaced = message.startswith("unrecognized arguments:") and \
            bool({"-q", "--quiet"} & set(message.split(":", 1)[1].split()))
        hint = " (-q goes before the command: codedvideo -q COMMAND ...)" if misplaced else ""
        self.exit(2, f"codedvideo: error: {command + ': ' if command else ''}{message}{hint}\n")


def _parser() -> argparse.ArgumentParser:
    p = _Parser(prog="codedvideo", description="Video from a single coded-exposure photograph (Hitomi et al. 2011).",
                epilog="Each command's options: codedvideo COMMAND --help.  Guides and the full reference (every "
                       "option and pipeline.yaml key): the docs/ folder of the source, or `make docs`.  Start a run "
                       "of your own with `codedvideo config > pipeline.yaml`.")
    p.add_argument("--version", action="version", version=f"codedvideo {__version__}")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bars")
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND")

    t = sub.add_parser("train", help="learn a K-SVD dictionary (or build a 3D DCT one)")
    ti = t.add_argument_group("input")
    tk = t.add_argument_group("K-SVD", "the learned dictionary's settings")
    to = t.add_argument_group("output")
    ti.add_argument("videos", nargs="*", metavar="VIDEO", help="training videos (default: the embedded synthetic set)")
    ti.add_argument("--frames", "-N", type=int, required=True, help="sub-frames N per coded image")
    to.add_argument("--output", "-o", required=True, help="dictionary store (.zarr)")
    learned = PipelineConfig().dictionary  # (None: the default, so that --kind dct can tell a value given)
    tk.add_argument("--atoms", type=int, default=None, help=f"atoms K of the dictionary (default: {learned.atoms})")
    tk.add_argument("--iterations", type=int, default=None, help=f"K-SVD iterations (default: {learned.iterations})")
    tk.add_argument("--samples", type=int, default=None, help=f"training patches (default: {learned.samples})")
    tk.add_argument("--sparsity", type=int, default=None, help=f"atoms per training patch (default: {learned.sparsity})")
    ti.add_argument("--max-speed", type=float, default=None,
                    help=f"fastest synthetic training motion, pixels per sub-frame (default: {learned.max_speed:g})")
    ti.add_argument("--init", default=None, metavar="DICT",
                    help="start K-SVD from this dictionary store ('shipped': the one shipped for N) and keep its atoms: "
                         "adapt it to your scene, e.g. with --no-augment --iterations 1 on a reconstruction (docs/cli.md, train)")
    ti.add_argument("--no-augment", dest="augment", action="store_false",
                    help="take the training patches as they are (default: rotated, flipped and reversed at random)")
    ti.add_argument("--kind", choices=("learned", "dct"), default="learned",
                    help="learned: K-SVD on training videos; dct: the complete 3D DCT (N x 49 atoms, not trained)")
    ti.add_argument("--seed", type=int, default=0, help="seed of the training patches' draw and of K-SVD")
    to.add_argument("--cache", default=DEFAULT_CACHE, help="where a trained dictionary is kept for later runs")
    to.add_argument("--overwrite", action="store_true", help="replace an existing OUTPUT that codedvideo did not write")
    to.add_argument("--retrain", action="store_true",
                    help="train even when a shipped dictionary was made with these settings (make train)")

    s = sub.add_parser("simulate", help="simulate a coded capture of a video")
    si = s.add_argument_group("input", "the video filmed")
    sc = s.add_argument_group("code", "the shutter code")
    ss = s.add_argument_group("sensor", "the camera's noise and units")
    so = s.add_argument_group("output")
    si.add_argument("video", help="synth:NAME or a video / frame-sequence path")
    si.add_argument("--frames", "-N", type=int, required=True, help="sub-frames N per coded image")
    sc.add_argument("--bump", "-L", type=int, default=None,
                    help=f"bump length of hitomi, hitomi-tiled and rowwise (default: {PipelineConfig().code.bump})")
    sc.add_argument("--code", default=None, choices=CODE_NAMES,
                    help="shutter code (default: hitomi, or file with --code-file; the codes: docs/sampling.md)")
    sc.add_argument("--code-file", default=None, metavar="PATH",
                    help="mask of --code file: .npy (N, H, W) or multi-page TIFF; or .npy (K, N, H, W), one code per "
                         "capture in turn")
    sc.add_argument("--p", type=float, default=None,
                    help=f"open probability of bernoulli / shifting (default: {PipelineConfig().code.p:g})")
    ss.add_argument("--noise-sigma", type=float, default=0.0, help="read noise, grey levels")
    ss.add_argument("--shot-noise", action="store_true", help="Poisson photon noise (see --full-well, --gain)")
    ss.add_argument("--full-well", type=float, default=None,
                    help=f"full-well capacity, electrons, with --shot-noise (default: {PipelineConfig().noise.full_well:g})")
    ss.add_argument("--gain", type=float, default=None,
                    help=f"electrons per grey level, with --shot-noise (default: {PipelineConfig().noise.gain:g})")
    ss.add_argument("--bits", type=int, default=None,
                    help="quantise the coded image to this bit depth (with --white-level W, the levels span [0, W] "
                         "in the video's units: not raw counts)")
    ss.add_argument("--white-level", type=float, default=None, help="clip the coded image at this grey level (saturation)")
    ss.add_argument("--black-level", type=float, default=0.0,
                    help="raw output: add this offset once per read-out (then clipping and quantisation)")
    ss.add_argument("--bayer", type=str.upper, choices=api.BAYER_PATTERNS, default=None, metavar="PATTERN",
                    help="film the video's colours through a Bayer filter (RGGB, BGGR, GRBG, GBRG): coded.npy is the "
                         "single-channel mosaic, truth.npy the colour video (3, N, H, W)")
    ss.add_argument("--seed", type=int, default=0, help="seed of the code and of the noise (and of a synthetic scene)")
    si.add_argument("--size", type=int, nargs=2, metavar=("H", "W"), default=None, help="centre crop (synth: size)")
    si.add_argument("--start", type=int, default=0, help="first frame of a video file")
    si.add_argument("--captures", default="1", metavar="T",
                    help="T consecutive coded images of N sub-frames each (a coded camera's stream), or 'all' that "
                         "a video file holds; coded.npy is then (T, H, W) and truth.npy (T*N, H, W)")
    sc.add_argument("--new-code-per-capture", action="store_true",
                    help="a new shutter code for every capture (mask.npy (T, N, H, W)); default: the code repeats")
    so.add_argument("--output", "-o", required=True, help="output folder")
    so.add_argument("--cacti-out", default=None, metavar="FILE.mat",
                    help="also write the capture as a CACTI benchmark .mat (orig, mask, meas; one measurement)")
    so.add_argument("--overwrite", action="store_true", help="replace existing output files that codedvideo did not write")

    r = sub.add_parser("reconstruct", help="recover the video from a coded image and its mask")
    ri = r.add_argument_group("input", "the capture and its code")
    rs = r.add_argument_group("sensor", "the camera's units, noise and defects")
    rm = r.add_argument_group("method", "how the video is recovered")
    ro = r.add_argument_group("output")
    rp = r.add_argument_group("performance", "where and how the work runs; none changes the result")
    ri.add_argument("--coded", default=None,
                    help="coded image (H, W) or a stream of them: .npy (T, H, W), .tif (multi-page), .exr, .dpx, .png, "
                         "a folder or printf pattern of images, a lossless video; required unless --cacti")
    ri.add_argument("--mask", default=None,
                    help="mask: .npy (N, H, W) or one per capture (T, N, H, W), a multi-page TIFF or frames; "
                         "required unless --cacti")
    ri.add_argument("--cacti", default=None, metavar="FILE.mat",
                    help="instead of --coded/--mask: a CACTI .mat (mask, meas, orig); every measurement is reconstructed")
    ri.add_argument("--measurement", type=int, default=None, metavar="Q",
                    help="with --cacti: reconstruct only measurement Q (1-based)")
    ri.add_argument("--color", choices=("luma", "channels"), default="luma",
                    help="colour coded image: its luma (default), or each channel with the same mask (colour output)")
    ri.add_argument("--bayer", type=str.upper, choices=api.BAYER_PATTERNS, default=None, metavar="PATTERN",
                    help="the coded image is a Bayer mosaic (RGGB, BGGR, GRBG, GBRG): write the colour video (3, N, H, W)")
    rm.add_argument("--dictionary", default=None,
                    help="dictionary store (.zarr) for --method omp (default: the one shipped for the mask's N)")
    rm.add_argument("--preset", choices=tuple(PRESETS), default=None,
                    help="named settings: fast (" + preset_options("fast") + "), default (the paper's method), best ("
                         + preset_options("best") + "); an option given beside it wins (docs/quality.md, Presets)")
    rm.add_argument("--method", choices=api.METHOD_NAMES, default=None,
                    help="omp: learned dictionary, every patch on its own (default); nonlocal: then groups of "
                         "similar patches solved together under their own codes (better, about 4x the time); "
                         "dct: 3D DCT dictionary, same OMP; thinout, interp, gaptv: baselines (docs/baselines.md)")
    rm.add_argument("--adapt", action=argparse.BooleanOptionalAction, default=None,
                    help="adapt the dictionary to each capture: reconstruct, K-SVD (4 iterations) on that result, "
                         "reconstruct again with it (omp, nonlocal, dct; omp: about twice the time; nonlocal: a sparse survey "
                         "first, about 1.2x nonlocal's time, +0.6 dB on real footage); --no-adapt: not (over --preset best)")
    rm.add_argument("--adapt-rounds", type=int, choices=(1, 2), default=None,
                    help="with --adapt: 2 adapts again to the second pass's result and reconstructs a third time "
                         "(--preset best; +0.5 dB on real footage, 1.8x the time of one round)")
    rm.add_argument("--refine", type=int, default=None, metavar="ITERATIONS",
                    help="after the method's result: ITERATIONS of GAP with a low-rank prior on groups of similar "
                         "8x8 patches followed across sub-frames, the noise level annealed from 6 to 1 grey level; "
                         "with --noise-sigma the steps to the measurements are relaxed (0: none, the default; "
                         "--preset best: 32, +0.9 dB on held-out real footage, about 0.8x the time of the passes "
                         "before it)")
    ro.add_argument("--output", "-o", required=True,
                    help=".npy, .zarr, .mat, .tif/.tiff, .mp4/.mov (H.264), .mkv/.avi (FFV1), .gif, or a name without "
                         "suffix (or ending .d): a folder of 16-bit TIFF frames (--cacti: all measurements, time-first)")
    ri.add_argument("--truth", default=None,
                    help="ground truth for PSNR/SSIM in the metrics: (T*N, H, W) frames, (3, N, H, W) for colour")
    rm.add_argument("--max-atoms", type=int, default=None,
                    help=f"OMP's atoms per patch at most (default: {PipelineConfig().reconstruct.max_atoms})")
    rm.add_argument("--tol-rms", type=float, default=None, help="residual tolerance, RMS per pixel (default: from --noise-sigma)")
    rs.add_argument("--noise-sigma", type=float, default=0.0, help="read noise of the capture, grey levels")
    rs.add_argument("--white-level", type=float, default=None,
                    help="saturation level of the coded image: pixels at or above it recorded at least it (kept as "
                         "measurements, their frames raised to it)")
    rs.add_argument("--trust-saturated", action="store_true", help="with --white-level: take saturated pixels as exact (no raise; "
                    "with --bits or --black-level: keep them at all)")
    rs.add_argument("--black-level", type=float, default=0.0,
                    help="raw frames: the offset of every read-out, subtracted first (coded units)")
    rs.add_argument("--bits", type=int, default=None,
                    help="raw frames: ADC bit depth; values at 2**bits - 1 are saturated (missing), above it an error")
    rs.add_argument("--bad-pixels", default=None, metavar="FILE",
                    help="defective pixels, missing measurements: text rows 'y x', or .npy (K, 2) or an (H, W) map")
    rs.add_argument("--detect-bad-pixels", action="store_true",
                    help="find hot or dead pixels as outliers against their neighbourhood (across all captures)")
    rm.add_argument("--stride", type=int, default=None,
                    help="patch stride 1..7: 1 solves every overlapping patch (the paper, the default), s about s*s "
                         "times fewer")
    rm.add_argument("--weighting", choices=("uniform", "fit"), default=PipelineConfig().reconstruct.weighting,
                    help="average of overlapping estimates: uniform (the paper) or weighted by each patch's misfit")
    rm.add_argument("--static-atoms", type=int, default=PipelineConfig().reconstruct.static_atoms,
                    help="still-scene test: 2D DCT atoms before full OMP (0: off)")
    rp.add_argument("--tile", type=int, default=PipelineConfig().reconstruct.tile,
                    help="tile side in pixels, a task each")
    rp.add_argument("--batch", type=int, default=PipelineConfig().reconstruct.batch,
                    help="patches solved together in a tile")
    rp.add_argument("--scheduler", default=None, help="dask.distributed scheduler address (default: local, both cores)")
    rp.add_argument("--workers", type=int, default=None, help="local worker threads")
    rs.add_argument("--data-range", type=float, default=None,
                    help="peak value of the frames: the PSNR peak, the full scale of videos, and the working "
                         "scale, so the default tolerance is 2/255 of it (default: found from the capture; "
                         "docs/formats.md, Units)")
    ro.add_argument("--fps", type=int, default=OutputConfig.model_fields["fps"].default,
                    help="frame rate of a video output")
    rp.add_argument("--cache", default=DEFAULT_CACHE,
                    help="working stores and dictionaries, reused by later runs (in the user's cache folder, the working "
                         "stores are kept within 20 GiB)")
    rp.add_argument("--cache-budget", default=None, metavar="SIZE",
                    help="keep the cache's working stores within SIZE (e.g. 20G) as a long job goes, removing the "
                         "least recently used (a rerun computes their tiles again; default: 20G in the user's cache folder, no "
                         "limit in a folder given with --cache)")
    ro.add_argument("--overwrite", action="store_true",
                    help="replace an existing output file that codedvideo did not write (folders: never)")
    rm.add_argument("--independent-captures", action="store_true",
                    help="a stack of coded images (or a CACTI file's measurements): reconstruct each on its own "
                         "(default: regions still from one capture to the next take coded / open count, without "
                         "sparse coding, and the step from one capture to the next is smoothed along the motion)")

    e = sub.add_parser("evaluate", help="per-frame and mean PSNR/SSIM as JSON")
    e.add_argument("--recon", required=True, help=".npy, .zarr, .mat, .tif, a video or frames")
    e.add_argument("--truth", required=True, help="as --recon; a .mat gives 'recon', else a CACTI file's 'orig'")
    e.add_argument("--data-range", type=float, default=None,
                   help="peak value of the frames (default: from the truth's values: 1, 255, 4095 or 65535)")
    e.add_argument("--output", "-o", default=None, help="write the JSON here too")
    e.add_argument("--overwrite", action="store_true", help="replace an existing --output that codedvideo did not write")

    u = sub.add_parser("run", help="run the stages a pipeline.yaml names")
    u.add_argument("config", nargs="?", default=None,
                   help="pipeline.yaml (default: the built-in one that `codedvideo config` prints)")
    u.add_argument("--overwrite", action="store_true",
                   help="replace existing output files that codedvideo did not write (as output.overwrite: true)")

    rp = sub.add_parser("report", help="the paper's experiments and error against run time, as HTML + CSV")
    rp.add_argument("config", help="pipeline.yaml (its report: section)")
    rp.add_argument("--overwrite", action="store_true",
                    help="replace existing files in report.dir that codedvideo did not write (as output.overwrite: true)")

    cf = sub.add_parser("config", help="print the built-in pipeline.yaml: every key, its default and what it does")
    cf.add_argument("--output", "-o", default=None, help="write it to this file instead (a new file)")
    cf.add_argument("--overwrite", action="store_true", help="replace an existing --output that codedvideo did not write")

    ca = sub.add_parser("cache", help="check or clean a cache folder (--cache, cache: in pipeline.yaml)")
    casub = ca.add_subparsers(dest="cache_command", required=True, metavar="ACTION")
    cv = casub.add_parser("verify", help="check every entry; exit 1 when one is broken")
    cv.add_argument("cache", nargs="?", default=DEFAULT_CACHE, help="the cache folder")
    cc = casub.add_parser("clean", help="remove cache entries (only codedvideo's own; entries in use are left)")
    cc.add_argument("cache", nargs="?", default=DEFAULT_CACHE, help="the cache folder")
    cc.add_argument("--broken", action="store_true", help="remove only broken, stale and leftover entries")

    c = sub.add_parser("codes", help="shutter codes")
    csub = c.add_subparsers(dest="codes_command", required=True, metavar="ACTION")
    ck = csub.add_parser("check", help="report which hardware constraints a mask meets")
    ck.add_argument("mask")
    return p


def _given(**options) -> dict:
    """The options given on the command line (None: not given, so the config model's default applies)."""
    return {k: v for k, v in options.items() if v is not None}


def _cmd_train(a) -> int:
    """Learn (or reuse) a dictionary with the API's training job and store it at ``--output``."""
    cfg = api.plan_training(frames=a.frames, dictionary={k: getattr(a, k) for k in api.TRAINING_KEYS}, seed=a.seed,
                            cache=a.cache, output=a.output, door="cli")
    kind = "file" if Path(a.output).suffix.lower() == ".zip" else "folder"  # a zipped store is one file
    check_outputs([Output(Path(a.output), kind, "dictionary")],  # before training
                  dict(video=list(a.videos), cache=a.cache, init=a.init if a.init != "shipped" else None),
                  overwrite=a.overwrite)
    path, meta = api.train_dictionary(cfg, output=a.output, progress=not a.quiet, retrain=a.retrain)
    mark_written(path)
    print(json.dumps(dict(dictionary=str(path), atoms=meta["atoms"], frames=meta["frames"], method=meta.get("method"),
                          final_rmse=meta.get("final_rmse"), reused=meta["reused"], seconds=round(meta["seconds"], 2))))
    return 0


def _cmd_simulate(a) -> int:
    """A video seen through a code and a sensor: the API's simulation, written as coded.npy, mask.npy and
    truth.npy (a video file's captures written as they are made)."""
    from codedvideo.formats.volumes import CAPTURE_FILES, write_capture

    if a.cacti_out and a.new_code_per_capture:
        raise ConfigError("option --cacti-out: a CACTI file has one mask; it does not go with --new-code-per-capture")
    if a.cacti_out and a.black_level:  # (a CACTI file's meas is the plain sum of the masked frames)
        raise ConfigError(f"option --black-level {a.black_level:g}: a CACTI file's meas is the plain sum of the "
                          "masked frames, with no offset; --cacti-out does not take a black level")
    if a.cacti_out and a.bayer:
        raise ConfigError(f"option --bayer {a.bayer}: makes one capture with a colour truth; --cacti-out (CACTI "
                          "files are grey) does not apply")
    settings = api.SimulateSettings(**{f.name: getattr(a, f.name) for f in dataclasses.fields(api.SimulateSettings)})
    plan = api.plan_simulation(settings, door="cli", clashes={"--cacti-out": a.cacti_out})
    if a.cacti_out and not plan.binary:  # a CACTI file holds a binary mask: a calibrated one is refused before any work
        raise ConfigError(f"option --cacti-out {a.cacti_out}: a CACTI file holds a binary mask, and the code "
                          f"file {a.code_file} is calibrated (values other than 0 and 1)")
    out = Path(a.output)
    outputs = [Output(out, "place", "output folder")] + [Output(out / f, "file") for f in CAPTURE_FILES]
    if a.cacti_out:
        outputs.append(Output(Path(a.cacti_out), "file", "--cacti-out"))
    check_outputs(outputs, dict(video=a.video, code_file=a.code_file), overwrite=a.overwrite)  # before any work
    captures = api.captures_of(plan)
    if a.new_code_per_capture and captures == 1:  # (a value the run would ignore)
        raise ConfigError("option --new-code-per-capture: one capture is made (--captures 1), so there is one code; "
                          "give --captures T or drop it")
    if plan.streamed and not a.cacti_out:
        paths = _simulate_video_file(a, plan, captures)
    else:
        cap = api.simulate_whole(plan, captures)
        paths = write_capture(cap, a.output)
    if a.cacti_out:
        from codedvideo.formats.cacti import write_cacti

        meas = cap["coded"] if cap["coded"].ndim == 3 else cap["coded"][None]
        paths["cacti"] = write_cacti(a.cacti_out, mask=cap["mask"], meas=meas, orig=cap["truth"])
    for path in paths.values():
        mark_written(path)
    print(json.dumps({k: str(v) for k, v in paths.items()}))
    return 0


def _reconstruct_settings(a):
    """Reconstruct's options as the API's settings, checked (with the preset resolved) before any work, and the
    outputs checked: the :class:`codedvideo.api.Resolved` settings."""
    from codedvideo.data import shipped
    from codedvideo.formats.io import VIDEO_SUFFIXES, gif_rate_problem
    from codedvideo.formats.volumes import metrics_path, output_kind

    if not a.cacti and not (a.coded and a.mask):
        raise InputError("reconstruct: give --coded and --mask, or --cacti FILE.mat")
    if a.measurement is not None and not a.cacti:
        raise InputError("reconstruct: --measurement applies to --cacti only")
    settings = api.ReconstructSettings(**{f.name: getattr(a, f.name) for f in dataclasses.fields(api.ReconstructSettings)
                                          if f.name != "progress"}, progress=not a.quiet)
    resolved = api.resolve_settings(settings, door="cli")
    if a.cacti and (a.coded or a.mask or a.truth):
        raise InputError(f"reconstruct --cacti {a.cacti}: takes coded images, mask and truth from the file "
                         "(drop --coded, --mask and --truth)")
    if a.cacti and a.color != "luma":
        raise InputError(f"reconstruct --cacti {a.cacti}: CACTI files are grey; --color channels does not apply")
    if a.bayer and (a.cacti or a.color != "luma"):
        raise InputError(f"reconstruct --bayer {a.bayer}: reads one single-channel mosaic (--coded); "
                         f"{'--cacti' if a.cacti else '--color channels'} does not apply")
    fps = validated(OutputConfig, dict(fps=a.fps)).fps
    output = Path(a.output)
    if output.suffix.lower() == ".gif" and gif_rate_problem(fps):
        raise ConfigError(f"reconstruct --fps {fps} with --output {output}: {gif_rate_problem(fps)}")
    if fps != OutputConfig.model_fields["fps"].default and output.suffix.lower() not in VIDEO_SUFFIXES:
        raise ConfigError(f"reconstruct --fps {fps} with --output {output}: the frame rate is a video's; "
                          f"the output is not one ({', '.join(VIDEO_SUFFIXES)})")
    check_outputs([Output(output, output_kind(output)), Output(metrics_path(output), "file", "metrics")],
                  dict(coded=a.coded, mask=a.mask, truth=a.truth, dictionary=a.dictionary, cacti=a.cacti, cache=a.cache,
                       bad_pixels=a.bad_pixels, shipped_dictionaries=shipped.DATA),
                  overwrite=a.overwrite)
    return resolved


def _read_captures(a) -> api.Captures:
    from codedvideo.formats.io import stored_dtype
    from codedvideo.model.physics import check_pair
    from codedvideo.formats.volumes import check_size, read_coded, read_coded_stack, read_masks, read_truth_stack, read_volume

    if a.cacti:
        from codedvideo.formats.cacti import read_cacti

        data = read_cacti(a.cacti)
        if a.measurement is not None and not 1 <= a.measurement <= data.measurements:
            raise InputError(f"--measurement {a.measurement}: {a.cacti} holds measurements 1..{data.measurements}")
        chosen = range(data.measurements) if a.measurement is None else [a.measurement - 1]
        covered = [data.truth(q) for q in chosen if data.truth(q) is not None]  # (the first of them)
        truths = np.concatenate(covered) if covered else None
        if data.orig is not None and len(covered) < len(chosen):
            warnings.warn(f"CACTI file {a.cacti}: orig holds the truth of measurement"
                          f"{'s 1 to ' if data.scored > 1 else ' '}{data.scored} of {data.measurements}; "
                          + ("the one chosen is reconstructed without a score" if not covered else
                             f"{len(covered)} of the {len(chosen)} reconstructed are scored (quality.scored)"))
        return api.Captures(
            codeds=[data.meas[q] for q in chosen], masks=[data.mask], truths=truths,
            labels=[dict(measurement=q + 1) for q in chosen], kind="measurements",
            inputs=dict(cacti=a.cacti, dictionary=a.dictionary, measurements=[q + 1 for q in chosen]),
            dtype=None, source=f"CACTI file {a.cacti}")
    if a.bayer:  # one single-channel mosaic, whole 2x2 cells (checked by the job); a colour truth (3, N, H, W)
        coded = read_coded(a.coded, color="error")
        check_size(coded.shape, a.coded)
        mask = read_masks(a.mask)
        check_pair(coded.shape, mask.shape, where=f"mask {a.mask}")
        truths = None
        if a.truth:
            truths = read_volume(a.truth, color="channels")
            if truths.shape != (3, *mask.shape):
                raise InputError(f"truth {a.truth}: shape {truths.shape} != (3, N, H, W) {(3, *mask.shape)} "
                                 f"(the colour video, under --bayer)")
        return api.Captures(codeds=coded[None], masks=[mask], truths=truths, labels=[{}], kind="bayer",
                         inputs=dict(coded=a.coded, mask=a.mask, dictionary=a.dictionary, truth=a.truth, bayer=a.bayer),
                         dtype=stored_dtype(a.coded), source=f"coded image {a.coded}")
    color = a.color == "channels"
    coded = read_coded(a.coded, color="channels") if color else read_coded_stack(a.coded)
    if color and coded.shape[0] == 1:  # a grey image: a "colour" result of one channel would mislead
        raise InputError(f"coded image {a.coded}: has one channel; --color channels is for a colour coded image "
                         "(leave it out for a grey one)")
    check_size(coded.shape, a.coded)
    mask = read_masks(a.mask)
    masks = list(mask) if mask.ndim == 4 else [mask]
    if len(masks) > 1 and (color or len(masks) != coded.shape[0]):
        raise InputError(f"mask {a.mask}: {len(masks)} masks (T, N, H, W) for {coded.shape[0]} coded images")
    for m in masks:
        check_pair(coded.shape[-2:], m.shape, where=f"mask {a.mask}")
    kind = "channels" if color else "single" if coded.shape[0] == 1 else "captures"
    n = masks[0].shape[0]
    truths = None
    if a.truth:  # a stream's truth (.npy) is read capture by capture, as its coded images
        truth = read_volume(a.truth, color="channels") if color else read_truth_stack(a.truth, n)
        truth = truth[None] if color and truth.ndim == 3 else truth
        want = (coded.shape[0], n, *coded.shape[-2:]) if color else (coded.shape[0] * n, *coded.shape[-2:])
        if truth.shape != want:
            what = "(channels, N, H, W)" if color else "(T*N, H, W) for T coded images of N sub-frames"
            given = truth.shape[1] if color else truth.shape[0] // coded.shape[0] * (truth.shape[0] % coded.shape[0] == 0)
            raise InputError(f"truth {a.truth}: shape {truth.shape} != {what} {want}"
                             + short_of_the_truth(n, given, f"mask {a.mask}"))
        truths = truth
    labels = ([dict(channel=c) for c in range(coded.shape[0])] if color else
              [{}] if kind == "single" else [dict(capture=t + 1) for t in range(coded.shape[0])])
    return api.Captures(
        codeds=coded, masks=masks, truths=truths, labels=labels, kind=kind,
        inputs=dict(coded=a.coded, mask=a.mask, dictionary=a.dictionary, truth=a.truth, color=a.color),
        dtype=stored_dtype(a.coded), source=f"coded image {a.coded}")


def _simulate_video_file(a, plan, captures: int) -> dict:
    """``simulate`` of a video file or a folder of frames: read, coded and written capture by capture (the same
    files as the API's whole simulation of the clip); their paths."""
    from codedvideo.formats.volumes import capture_paths, capture_writer

    out = Path(a.output)
    masks = captures if a.new_code_per_capture or plan.file_codes > 1 else 1  # a mask per capture, or one
    made = not out.exists()
    first, stream = api.simulate_captures(plan, captures)
    h, w = first.shape[1:]
    try:
        with capture_writer(out, coded_shape=(captures, h, w) if captures > 1 else (h, w),
                            mask_shape=(masks, a.frames, h, w) if masks > 1 else (a.frames, h, w),
                            truth_shape=(captures * a.frames, h, w)) as put:
            for t, (coded, mask, clip) in enumerate(stream):
                put(coded, mask if t < masks else None, clip)
    except BaseException:  # a video cut short found on the way: no file was renamed into place
        if made and out.is_dir() and not any(out.iterdir()):
            out.rmdir()
        raise
    return capture_paths(out)


def _cmd_reconstruct(a) -> int:
    """Coded images -> their video: one coded image, a stack of them (a coded camera's stream, (T, H, W)),
    a CACTI file's measurements (concatenated time-first, (T*N, H, W)) or a colour image's channels
    (stacked first, (C, N, H, W)): read the files, run the API's job, write each result as soon as it is
    done (streamed for .npy) and the job's record as the metrics JSON."""
    from codedvideo.formats.volumes import metrics_path, volume_writer, write_json

    resolved = _reconstruct_settings(a)  # before any work
    t_all = time.perf_counter()
    job = api.ReconstructionJob(_read_captures(a), resolved)
    if Path(a.output).suffix.lower() == ".mat":  # a v5 .mat file's 4 GiB: known before any work
        from codedvideo.formats.cacti import check_mat_size

        check_mat_size(a.output, job.shape)
    t_read, t_write, kind, n = time.perf_counter() - t_all - job.seconds_prepared, 0.0, job.captures.kind, job.n
    with contextlib.ExitStack() as stack:
        put = None  # the output is opened once the first result exists: a failure before leaves nothing
        for i, volume, _ in job.run(a.cache):
            t1 = time.perf_counter()
            if put is None:
                put = stack.enter_context(volume_writer(a.output, job.shape, data_range=job.units.value, fps=a.fps,
                                                        part=n))
            put(i if kind == "channels" else slice(None) if kind == "bayer" else slice(i * n, (i + 1) * n), volume)
            t_write += time.perf_counter() - t1
            del volume
        t1 = time.perf_counter()
    t_write += time.perf_counter() - t1
    mark_written(a.output)
    metrics = api.job_record(job, output=a.output, read=t_read, write=t_write, started=t_all)
    _warn_replaced_record(metrics_path(a.output), a.output)
    mpath = write_json(metrics_path(a.output), metrics)
    mark_written(mpath)
    print(json.dumps(_summary(metrics, mpath, kind), allow_nan=False))  # strict JSON: an exact PSNR is null
    return 0


def _summary(metrics: dict, mpath, kind: str) -> dict:
    """The line reconstruct prints: the output, its quality when scored, and the metrics file's figures."""
    summary = dict(output=metrics["output"])
    quality = metrics.get("quality")
    if quality:
        summary.update(psnr=round(quality["psnr"], 2), ssim=round(quality["ssim"], 4))
        if "output_file" in quality:  # (the reconstruction's figures above; the file's, quantised or lossy, here)
            summary.update(output_file_psnr=round(quality["output_file"]["psnr"], 2),
                           output_file_ssim=round(quality["output_file"]["ssim"], 4))
        if kind == "bayer":
            summary.update(trivial_psnr=round(metrics["trivial"]["psnr"], 2))
        elif kind != "single":
            name = kind[:-1]
            summary.update({k: [round(v, 2 if k.startswith("psnr") else 4) for v in quality[k]]
                            for k in (f"psnr_per_{name}", f"ssim_per_{name}")})
    info = metrics["reconstruction"]
    summary.update(metrics=str(mpath), seconds=round(info["seconds"]["total"], 2),
                   patches_per_second=round(info["patches_per_second"]), data_range=metrics["data_range"]["value"])
    return json_safe(summary)


def _warn_replaced_record(mpath: Path, output) -> None:
    """Say so when a metrics file about to be written holds the record of another output of the same stem that
    is still there (``rec.npy`` and ``rec.mp4`` share ``rec.metrics.json``): its figures are replaced."""
    try:
        earlier = json.loads(Path(mpath).read_text()).get("output")
    except (OSError, ValueError, AttributeError):
        return
    if earlier and Path(earlier).exists() and not _same_path(earlier, output):
        warnings.warn(f"{mpath}: held the record of {earlier}, which shares its name; it now describes {output} "
                      "(give the outputs different names to keep both)")


def _same_path(a, b) -> bool:
    """One file, however named (relative and absolute, through a link): the file itself when both exist."""
    try:
        return os.path.samefile(a, b)
    except OSError:
        return Path(a).resolve() == Path(b).resolve()


def _written_range(path) -> float | None:
    """The data range a reconstruction was written with, from the metrics JSON beside it (None: none).

    Outputs of one stem share that file (``v.mkv`` and ``v.npy`` both write ``v.metrics.json``), so it
    counts only when it names ``path`` as its output (``reconstruct``) or one of its outputs (``run``);
    one that describes another file is said in a warning and left out.
    """
    from codedvideo.formats.volumes import metrics_path

    where = metrics_path(Path(path))
    try:
        metrics = json.loads(where.read_text())
        named = [metrics.get("output"), *(metrics.get("outputs") or {}).values()]
        value = float(metrics["data_range"]["value"])
    except (OSError, ValueError, KeyError, TypeError, AttributeError):
        return None
    if Path(path).name not in {Path(str(p)).name for p in named if p}:
        warnings.warn(f"{where} describes {' and '.join(str(p) for p in named if p)}, not {path}: the data range "
                      f"{Path(path).name} was written with is not known; taken as the truth's (--data-range sets it)")
        return None
    return value


def _cmd_evaluate(a) -> int:
    """Per-frame and mean PSNR/SSIM of a reconstruction file against a truth file: read both (a long .npy a
    block of frames at a time), score them with the API's evaluate, print (and write) the JSON."""
    from codedvideo.formats.io import VIDEO_SUFFIXES
    from codedvideo.formats.volumes import write_json

    out = validated(OutputConfig, dict(data_range=a.data_range))
    if a.output:
        check_outputs([Output(Path(a.output), "file")], dict(recon=a.recon, truth=a.truth), overwrite=a.overwrite)
        if Path(a.output).suffix.lower() != ".json":
            raise ConfigError(f"evaluate --output {a.output}: the scores are written as JSON; name it .json")
    recon = api.read_scored(a.recon, "reconstruction")
    truth = api.read_scored(a.truth, "truth")
    recon, truth = api.as_scored(recon, truth, names=(str(a.recon), str(a.truth)))
    extra = {}
    if Path(a.truth).suffix.lower() == ".mat" and len(truth.shape) == len(recon.shape) == 3 \
            and 0 < truth.shape[0] < recon.shape[0] and tuple(truth.shape[1:]) == tuple(recon.shape[1:]):
        # a CACTI file's orig holds the truth of its first measurements only: those frames are scored
        warnings.warn(f"evaluate: truth {a.truth} holds {truth.shape[0]} frames of the reconstruction's "
                      f"{recon.shape[0]}; the first {truth.shape[0]} are scored", stacklevel=2)
        recon = np.asarray(recon[: truth.shape[0]])
        extra["scored_frames"] = int(truth.shape[0])
    if Path(a.recon).suffix.lower() in VIDEO_SUFFIXES:  # 8-bit frames: 255 was the data range they were written with
        written = _written_range(a.recon) or api.truth_data_range(truth, data_range=out.data_range,
                                                                  where=f"truth {a.truth}").value
        if written != 255.0:
            recon = np.asarray(recon, np.float32) * np.float32(written / 255.0)
            extra["reconstruction_scaled"] = f"video frames x {written:g} / 255 (the data range they were written with)"
    result = api.scores(recon, truth, data_range=out.data_range, names=(str(a.recon), f"truth {a.truth}"),
                        **extra)
    if a.output:
        mark_written(write_json(Path(a.output), result))
    print(json.dumps(result, allow_nan=False))
    return 0


def _config(a, use: str = "run"):
    """The config file of ``run`` and ``report`` (``run`` without one: the built-in pipeline.yaml), ``--overwrite``
    as ``output.overwrite: true``."""
    cfg = load_config(a.config or default_config_path(), use=use)
    if a.overwrite:
        cfg = cfg.model_copy(update=dict(output=cfg.output.model_copy(update=dict(overwrite=True))))
    return cfg


def _cmd_run(a) -> int:
    from codedvideo.api import run_pipeline

    report = run_pipeline(_config(a), progress=not a.quiet, config_path=a.config or default_config_path())
    lines = [f"metrics: {report['metrics_path']}"]
    if "outputs" in report:
        lines.insert(0, f"video: {report['outputs']['video']}")
        lines.insert(1, f"frames: {report['outputs'].get('frames', '-')}")
    if "quality" in report:
        q, tr = report["quality"], report["trivial"]
        lines.append(f"PSNR {q['psnr']:.2f} dB, SSIM {q['ssim']:.4f} (trivial estimate: {tr['psnr']:.2f} dB, {tr['ssim']:.4f})")
        if "output_file" in q:  # the video as written (8-bit, lossy), decoded
            lines.append(f"PSNR of {report['outputs']['video']} as written: {q['output_file']['psnr']:.2f} dB, SSIM "
                         f"{q['output_file']['ssim']:.4f}")
    secs = ", ".join(f"{k} {v:.1f} s" for k, v in report["seconds"].items())
    lines.append(f"time: {secs}")
    print("\n".join(lines))
    return 0


def _cmd_config(a) -> int:
    """The built-in pipeline.yaml, printed or written to a new file (a starting point for a run of one's own)."""
    text = default_config_path().read_text(encoding="utf-8")
    if a.output is None:
        sys.stdout.write(text)
        return 0
    from codedvideo.formats.atomic import atomic_output

    output = Path(a.output)
    if output.suffix.lower() not in (".yaml", ".yml"):
        raise ConfigError(f"config --output {output}: a pipeline file; name it .yaml")
    check_outputs([Output(output, "file")], {}, overwrite=a.overwrite)
    with atomic_output(output) as tmp:
        Path(tmp).write_text(text, encoding="utf-8")
    mark_written(output)
    print(output)
    return 0


def _cmd_report(a) -> int:
    from codedvideo.app.report import run_report
    from codedvideo.app.report_html import verdict

    result = run_report(_config(a, "report"), progress=not a.quiet, config_path=a.config)
    lines = [f"report: {result['html']}", f"numbers: {result['csv']}", f"video: {result['video']}"]
    lines += [f"{verdict(f['holds'])}: {f['claim']} ({f['detail']})" for f in result["findings"]]
    lines.append(f"experiments: {result['computed']} computed, {result['reused']} reused; {result['seconds']:.0f} s")
    print("\n".join(lines))
    return 0


def _cmd_cache(a) -> int:
    from codedvideo.api.cache import clean_cache, verify_cache

    if not str(a.cache).strip():  # (Path("") is the current folder)
        raise ConfigError(f"cache '': name the cache folder (default: {DEFAULT_CACHE})")
    if a.cache_command == "verify":
        records = verify_cache(a.cache)
        for r in records:
            print(json.dumps(dict(r, entry=str(r["entry"]))))
        broken = [r for r in records if r["status"] == "broken"]
        print(f"cache {a.cache}: {len(records)} entries, {len(broken)} broken", file=sys.stderr)
        return 1 if broken else 0
    removed = clean_cache(a.cache, broken_only=a.broken)
    print(json.dumps(dict(cache=str(a.cache), removed=[str(p) for p in removed])))
    return 0


def _cmd_codes(a) -> int:
    from codedvideo.model.codes import check_code
    from codedvideo.formats.volumes import read_masks

    masks = read_masks(a.mask)
    n = masks.shape[-3]
    shipped = api.shipped_frames()
    if n not in shipped:  # (a mask folder missing an image reads as a code of fewer sub-frames)
        ask, need = api.missing_frame_question(n), f"reconstructing it needs a dictionary trained for N = {n}"
        warnings.warn(f"mask {a.mask}: N = {n} sub-frames, for which no dictionary is shipped (shipped: N = "
                      f"{', '.join(map(str, shipped))}); " + (f"{ask} Otherwise, {need}" if ask else need),
                      stacklevel=2)
    if masks.ndim == 3:
        print(json.dumps(dict(check_code(masks).as_dict(), dictionary_shipped=n in shipped)))
        return 0
    # one code per capture (simulate --new-code-per-capture): each capture's report, and whether all meet each rule
    reports = [check_code(m).as_dict() for m in masks]
    met = {k: all(r[k] for r in reports) for k in ("binary", "single_bump", "fixed_bump")}
    lengths = {r["bump_length"] for r in reports}
    met["fixed_bump"] = met["fixed_bump"] and len(lengths) == 1  # one bump length for every pixel of every capture
    met["bump_length"] = lengths.pop() if met["fixed_bump"] else None
    coverage = [r["window_coverage"] for r in reports]
    met["window_coverage"] = None if None in coverage else all(coverage)
    print(json.dumps(dict(met, frames=n, dictionary_shipped=n in shipped, captures=len(reports), per_capture=reports)))
    return 0


COMMANDS = dict(train=_cmd_train, simulate=_cmd_simulate, reconstruct=_cmd_reconstruct, evaluate=_cmd_evaluate,
                run=_cmd_run, report=_cmd_report, codes=_cmd_codes, cache=_cmd_cache,
                config=_cmd_config)


def _one_line(message, category, filename, lineno, line=None) -> str:
    """A warning as the command line says it: one line, like its errors (not a path and a source line)."""
    return f"codedvideo: warning: {message}\n"


class _LogLine(logging.Formatter):
    """A log record as the command line says a warning or an error: ``codedvideo: warning: MESSAGE``."""

    def format(self, record: logging.LogRecord) -> str:
        return f"codedvideo: {record.levelname.lower()}: {record.getMessage()}"


class Terminated(KeyboardInterrupt):
    """SIGTERM (``kill``, ``timeout``, a batch scheduler ending a job), unwound as Ctrl-C is: every
    temporary removed, every lock released, one line, exit status 143."""


def _terminate(signum, frame):
    raise Terminated()


def main(argv: list[str] | None = None) -> int:
    try:
        args = _parser().parse_args(argv)
    except SystemExit as exc:  # --help, --version, or a bad option (one line already printed)
        return exc.code if isinstance(exc.code, int) else 2
    with doors.through("cli"):  # (a setting named as the command line names it, a rule between keys too)
        return guarded(lambda: COMMANDS[args.command](args))


def guarded(fn) -> int:
    """Run ``fn()`` as a command: its exit status, or an error, Ctrl-C or SIGTERM as one line and its status.

    Warnings are one line each (their format only: a caller that records them,
    as pytest.warns does, still gets them); SIGTERM unwinds as Ctrl-C does.
    The filters, the format and the SIGTERM handler are restored on return.
    The stage scripts of ``tasks/`` run through it too.
    """
    handler = logging.StreamHandler()  # log lines said as warnings are ("codedvideo: warning: ...")
    handler.setFormatter(_LogLine())
    logging.basicConfig(level=logging.WARNING, handlers=[handler])
    previous, warnings.formatwarning = warnings.formatwarning, _one_line
    # SIGTERM's default ends the process where it stands, leaving partial outputs behind
    on_term = signal.signal(signal.SIGTERM, _terminate) if threading.current_thread() is threading.main_thread() \
        else None
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("default")
            return fn() or 0
    except CodedVideoError as exc:
        print(f"codedvideo: error: {exc}", file=sys.stderr)
        return 2
    except MemoryError as exc:  # an allocation no check foresaw: one line, the temporaries already unwound
        print(f"codedvideo: error: out of memory ({exc or 'an allocation failed'}); give smaller settings "
              "(--samples, --tile, --captures) or free memory", file=sys.stderr)
        return 2
    except Terminated:
        print("codedvideo: terminated", file=sys.stderr)
        return 128 + signal.SIGTERM
    except KeyboardInterrupt:
        print("codedvideo: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:  # the reader of the output went away (`| head`): nothing more to say, no traceback
        _silence_stdout()
        return BROKEN_PIPE
    finally:
        warnings.formatwarning = previous
        if on_term is not None:
            signal.signal(signal.SIGTERM, on_term)


#: Blocks of at least this many bytes are mapped on their own and go back to the system when freed (glibc's
#: ``M_MMAP_THRESHOLD``, which otherwise rises to 32 MB as blocks are freed).
OWN_MAPPING_BYTES = 1 << 20


def _return_freed_blocks() -> None:
    """The command's process (not a library user's): with glibc, large blocks in their own mappings.

    The tile threads' arrays of a few MB each were otherwise carved from per-thread arenas that freed memory
    does not leave, so resident memory grew with every capture (docs/research.md, "Memory").  Elsewhere
    (another C library, another system) nothing is changed.
    """
    if not sys.platform.startswith("linux"):
        return
    import ctypes

    try:
        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError):  # not glibc
        return
    mallopt(-3, OWN_MAPPING_BYTES)  # M_MMAP_THRESHOLD (malloc.h); also turns off its dynamic rise


def console_main() -> None:
    """The ``codedvideo`` command: :func:`main`, then leave without finalising the interpreter.

    Freeing the modules a run loaded (numba, scipy, zarr, dask) takes a
    noticeable share of a short run after the work is done and every output is
    closed (docs/research.md, "Streams: where the start-up goes").  So
    the exit handlers run (log handlers, zarr's event loop), the standard
    streams are flushed, and the process ends with the command's exit code.
    An exception that escapes :func:`main` exits the usual way, traceback and all.
    """
    _return_freed_blocks()
    code = main()
    atexit._run_exitfuncs()  # what interpreter shutdown would run
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except BrokenPipeError:  # the reader went away before the last of the output: it was not all said
            code = code or BROKEN_PIPE
        except (OSError, ValueError):  # a closed stream: nothing more to say
            pass
    os._exit(code)


#: The exit status when the reader of the standard output goes away before the output ends, a shell's for a
#: command ended by SIGPIPE (128 + 13).
BROKEN_PIPE = 128 + 13


def _silence_stdout() -> None:
    """Point the standard output at the null device, so that what is still buffered for a reader that went away
    is not written (and raises nothing) when the streams are flushed."""
    try:
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
    except (OSError, ValueError, AttributeError):  # a stream with no descriptor (a test's capture): nothing to point
        pass


if __name__ == "__main__":  # pragma: no cover
    console_main()
