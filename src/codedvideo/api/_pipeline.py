"""A run of pipeline.yaml: the stages its config names (:func:`run_pipeline`), each a function of its settings,
its reconstruction the API's job (:class:`codedvideo.api.ReconstructionJob`) with the settings of its
``reconstruct:`` section, resolved and checked as the command line's options are.

The command line (``codedvideo run``) and the ``tasks/`` scripts call it.  Each result is cached under a key
that hashes its settings and inputs (:mod:`codedvideo.engine.cache`), so a rerun reuses a dictionary or
finished reconstruction tiles instead of recomputing them.  Every reconstruction writes a metrics JSON beside
its output: seconds per stage, patches per second, atoms used, and PSNR/SSIM when the truth is known.
"""

from __future__ import annotations

import time
from pathlib import Path

from codedvideo.model import doors
from codedvideo.api._job import Captures, ReconstructionJob
from codedvideo.api._record import job_record
from codedvideo.api._settings import ReconstructSettings, resolve
from codedvideo.model.doors import through
from codedvideo.data.scenes import load_video
from codedvideo.engine.config import PRESET_KEYS, PipelineConfig
from codedvideo.engine.simulation import sensor_model, simulate_capture
from codedvideo.engine.training import train_dictionary
from codedvideo.formats import io as cio
from codedvideo.formats.volumes import CAPTURE_FILES, metrics_path, write_capture, write_json, write_volume


def run_pipeline(cfg: PipelineConfig, *, progress: bool = True, config_path: str | Path | None = None) -> dict:
    """Run the stages the config names; return the metrics written.

    Every output is checked before any work (:func:`codedvideo.formats.outputs.check_outputs`):
    none may touch the config file, the scene, the code file, the dictionary,
    the training videos or the cache.  Its messages name the settings as pipeline.yaml does.
    """
    with through("config"):
        return _run_pipeline(cfg, progress=progress, config_path=config_path)


def _run_pipeline(cfg: PipelineConfig, *, progress: bool, config_path: str | Path | None) -> dict:
    from codedvideo.formats.outputs import mark_written

    out = Path(cfg.output.dir)
    _check_outputs(cfg, out, config_path)  # before any work
    from codedvideo.engine.config import check_scheduler

    cio.check_cache(cfg.cache)
    check_scheduler(cfg.reconstruct.scheduler)
    report: dict = dict(config=cfg.model_dump(mode="json"), seconds={})
    dict_path = capture = None
    if "simulate" in cfg.stages or "reconstruct" in cfg.stages:
        # the scene and the code read (and so checked) and the capture simulated before any training: a missing,
        # short or too small video, or a code file that does not fit, ends the run in a second, not after K-SVD
        t0 = time.perf_counter()
        video = load_video(cfg.scene.video, frames=cfg.frames, size=cfg.scene.size, seed=cfg.seed, start=cfg.scene.start)
        capture = simulate_capture(video, code=cfg.code, sigma=cfg.noise.sigma, seed=cfg.seed,
                                   sensor=sensor_model(cfg.noise))
        del video
        report["seconds"]["simulate"] = time.perf_counter() - t0
    if "train" in cfg.stages or "reconstruct" in cfg.stages:
        t0 = time.perf_counter()
        dict_path, dmeta = train_dictionary(cfg, progress=progress)
        report["seconds"]["train"] = time.perf_counter() - t0
        report["dictionary"] = dict(path=str(dict_path), reused=dmeta["reused"], atoms=dmeta["atoms"],
                                    method=dmeta.get("method"), final_rmse=dmeta.get("final_rmse"))
    # each output is recorded as codedvideo's as soon as it is in place, so that a run that fails or is
    # stopped later does not leave files that the next run must refuse as the user's
    if capture is not None:
        t0 = time.perf_counter()
        capture_paths = write_capture(capture, out / "capture")
        for path in capture_paths.values():
            mark_written(path)
        report["capture"] = {k: str(v) for k, v in capture_paths.items()}
        report["seconds"]["simulate"] += time.perf_counter() - t0
        if "reconstruct" in cfg.stages:
            # a simulate-only run's record beside the capture (checked as codedvideo's before any work) describes
            # the capture just replaced; this run's record is beside its reconstruction
            (out / "capture" / "metrics.json").unlink(missing_ok=True)
    if "reconstruct" in cfg.stages:
        _reconstruct(cfg, capture, dict_path, out, report, progress)
    report["seconds"]["total"] = sum(report["seconds"].values())
    # a run that reconstructs nothing (`make simulate`) keeps its record beside the capture: it replaced the last
    # reconstruction's record (and its PSNR), and says that reconstruction is not of this capture
    mpath = _metrics_of(cfg, out)
    if "simulate" in cfg.stages and "reconstruct" not in cfg.stages:
        earlier = [p for p in (out / cfg.output.video, out / "recon.npy", out / "frames") if p.exists()]
        if earlier:
            doors.warn(f"{', '.join(map(str, earlier))}: from an earlier run, not reconstructed from this capture "
                          "(run the reconstruct stage to replace them)")
    mark_written(write_json(mpath, report))
    report["metrics_path"] = str(mpath)
    return report


#: The record of a run that only trains (beside the folder's captures and reconstructions, which it does not touch).
TRAIN_METRICS = "train.metrics.json"


def _metrics_of(cfg: PipelineConfig, out: Path) -> Path:
    """Where the run's record goes: beside the reconstruction; a run that reconstructs nothing (`make simulate`)
    beside its capture (the last reconstruction's record left alone); a run that only trains, a record of its
    own (the capture's and the reconstruction's describe them, not it)."""
    if "reconstruct" in cfg.stages:
        return metrics_path(out / cfg.output.video)
    return out / "capture" / "metrics.json" if "simulate" in cfg.stages else out / TRAIN_METRICS


def _check_outputs(cfg: PipelineConfig, out: Path, config_path) -> None:
    """Every output of the run checked (:func:`codedvideo.formats.outputs.check_outputs`): none may touch the
    config file, the scene, the code file, the dictionary, the training videos or the cache."""
    from codedvideo.formats.outputs import Output, check_outputs

    outputs = [Output(out, "place", "output.dir"), Output(out / cfg.output.video, "file", "output.video"),
               Output(out / "recon.npy", "file"), Output(metrics_path(out / cfg.output.video), "file", "metrics"),
               Output(out / "capture", "place", "capture folder")]
    outputs += [Output(out / "capture" / name, "file") for name in (*CAPTURE_FILES, "metrics.json")]
    outputs.append(Output(out / TRAIN_METRICS, "file"))
    if cfg.output.frames != "none":
        outputs.append(Output(out / "frames", "folder", "frames folder"))
    check_outputs(outputs, dict(config=config_path, scene=cfg.scene.video, code=cfg.code.path,
                                dictionary=cfg.dictionary.path, training=list(cfg.dictionary.training), cache=cfg.cache),
                  overwrite=cfg.output.overwrite)


def _write_outputs(cfg: PipelineConfig, out: Path, volume, data_range: float) -> dict:
    """The reconstruction written: the video, the frames (unless ``output.frames`` is none) and recon.npy, each
    recorded as codedvideo's once it is in place; their paths."""
    from codedvideo.formats.outputs import mark_written

    video_path = write_volume(volume, out / cfg.output.video, fps=cfg.output.fps, data_range=data_range)
    mark_written(video_path)
    outputs = dict(video=str(video_path))
    if cfg.output.frames != "none":
        outputs["frames"] = str(out / "frames")
        cio.write_frames(out / "frames", volume, fmt=cfg.output.frames, data_range=data_range)
        mark_written(out / "frames")
    mark_written(cio.write_array(out / "recon.npy", volume))
    outputs["volume"] = str(out / "recon.npy")
    return outputs


def run_settings(cfg: PipelineConfig, dictionary, noise_sigma: float, progress: bool) -> ReconstructSettings:
    """The reconstruction settings of pipeline.yaml: its ``reconstruct:`` section (the preset and the keys given
    beside it, as the command line's options give them), the noise's sigma and white level, and the output's
    data range."""
    rc = cfg.reconstruct
    return ReconstructSettings(
        preset=rc.preset, **rc.given(), dictionary=dictionary, tol_rms=None if rc.tol_rms == "auto" else rc.tol_rms,
        noise_sigma=noise_sigma, data_range=cfg.output.data_range, white_level=cfg.noise.white_level,
        **{k: getattr(rc, k) for k in ("static_atoms", "weighting", "tile", "batch", "scheduler", "workers",
                                       "cache_budget") if k not in PRESET_KEYS},
        cache=cfg.cache, progress=progress)


def _reconstruct(cfg: PipelineConfig, capture: dict, dict_path, out: Path, report: dict, progress: bool) -> None:
    """The reconstruct stage: the API's job on the simulated capture, its outputs written, scored with the truth
    when the evaluate stage is named; the report gains its records and seconds."""
    sensor = sensor_model(cfg.noise)
    # with shot noise / quantisation: the RMS noise at the mean coded level
    sigma = sensor.noise_sigma(float(capture["coded"].mean())) if sensor else cfg.noise.sigma
    resolved = resolve(run_settings(cfg, dict_path, sigma, progress), door="config")
    job = ReconstructionJob(Captures(codeds=[capture["coded"]], masks=[capture["mask"]],
                                     truths=capture["truth"] if "evaluate" in cfg.stages else None,
                                     source="simulated capture"), resolved)
    started = time.perf_counter()
    (_, volume, _), = job.run(cfg.cache)
    report["seconds"]["reconstruct"] = time.perf_counter() - started - job.seconds_scored
    t0 = time.perf_counter()
    outputs = _write_outputs(cfg, out, volume, job.units.value)
    report["seconds"]["write"] = time.perf_counter() - t0
    # the record `codedvideo reconstruct` writes (the video as written scored too), the run's stages beside it
    report.update(job_record(job, output=outputs["video"], write=report["seconds"]["write"], started=started),
                  outputs=outputs)
    if "quality" in report:
        written = report["quality"].get("output_file", {})  # (the video read back and scored, when it was)
        report["seconds"]["evaluate"] = job.seconds_scored + written.get("seconds", 0.0)
