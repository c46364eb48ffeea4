"""What a reconstruction job says once it has run, apart from the job that runs it: each capture's frames
scored against the truth as they come (:class:`Scores`) and the metrics record (:func:`job_record`, the
command line's ``.metrics.json`` and the API's ``Reconstruction.record``)."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from codedvideo.model.metrics import evaluate, mean_psnr
from codedvideo.model.sequence import StepErrors


class Scores:
    """The per-frame PSNR and SSIM of a job's results and of the trivial estimate against the truth, capture
    after capture, and the errors of consecutive frames across the boundaries of a stream."""

    def __init__(self):
        self.frames: dict[str, list] = dict(psnr=[], ssim=[])
        self.trivial: dict[str, list] = dict(psnr=[], ssim=[])
        self.steps = StepErrors()

    def add(self, entry: dict, volume, truth, trivial: np.ndarray, *, data_range: float, stream: bool) -> float:
        """Score a capture's ``volume`` and its ``trivial`` estimate against ``truth`` into its record ``entry``
        (``quality``, ``trivial``), its refinement's trace ended at its own PSNR; the seconds it took."""
        t0 = time.perf_counter()
        h, w = np.shape(truth)[-2:]
        frames = np.asarray(volume)  # (a capture kept on disk read whole to be scored)
        entry["quality"] = evaluate(frames.reshape(-1, h, w), truth.reshape(-1, h, w), data_range=data_range)
        entry["trivial"] = evaluate(trivial.reshape(-1, h, w), truth.reshape(-1, h, w), data_range=data_range)
        trace = entry["reconstruction"].get("refine_trace")
        if trace and abs(trace[-1]["psnr"] - entry["quality"]["psnr"]) > 1e-6:
            # the result after the refinement's last point: joined with its neighbours, raised to the white
            # level: the trace ends at the capture's own PSNR
            trace.append(dict(stage="result", seconds=trace[-1]["seconds"], psnr=entry["quality"]["psnr"]))
        for key in ("psnr", "ssim"):
            self.frames[key] += entry["quality"][f"{key}_per_frame"]
            self.trivial[key] += entry["trivial"][f"{key}_per_frame"]
        if stream:
            self.steps.add(frames, truth)
        return time.perf_counter() - t0


def job_record(job, *, output=None, read: float = 0.0, write: float = 0.0, started: float | None = None) -> dict:
    """The metrics record of a :class:`~codedvideo.api._job.ReconstructionJob` after its run: settings, data
    range, preset, each capture's entry and the totals, and the quality when a truth was given.  ``read``,
    ``write``: the seconds the door spent reading the inputs and writing the outputs; ``started``: when it
    started (``time.perf_counter``).  With a truth and an ``output`` that holds the frames less exactly than
    float32 (:func:`quantised`: a video, a folder of 16-bit frames), the file as written is read back and scored
    too (``quality.output_file``, :func:`written_quality`).  ``codedvideo reconstruct`` and ``codedvideo run``
    both write this record (``run`` with its stages beside it)."""
    r, captures, units, omp = job.r, job.captures, job.units, job.omp
    metrics = dict(({"output": str(output)} if output is not None else {}), inputs=captures.inputs,
                   settings=dict(omp.__dict__, tol_rms=omp.tol_rms / units.scale, method=r.method,
                                 adapt=r.rc.adapt, adapt_rounds=r.rc.adapt_rounds, refine=r.rc.refine,
                                 tile=r.rc.tile, scheduler=r.rc.scheduler, workers=r.rc.workers,
                                 dictionary_atoms=job.entries[0]["reconstruction"].get("dictionary_atoms")),
                   data_range=units.as_dict(), preset=r.preset)
    if job.cuts is not None:  # the boundaries not joined, and why (each was asked by the join already)
        cut = job.cuts
        metrics["cuts"] = [dict(c, captures=[captures.labels[c["boundary"] + d].get("capture", c["boundary"] + d + 1)
                                             for d in (0, 1)])
                           for c in (cut(i) and dict(boundary=i, **cut(i)) for i in range(job.count - 1)) if c]
    read_all = read + job.seconds_prepared
    total = time.perf_counter() - started if started is not None else None
    if captures.kind in ("single", "bayer"):
        info = job.entries[0]["reconstruction"]
        info["seconds"] = dict(read=read_all, **info["seconds"], write=write,
                               total=total if total is not None else read_all + sum(info["seconds"].values()))
        metrics["reconstruction"] = info
        if captures.kind == "bayer":
            metrics.update(layout="(C, N, H, W)", bayer=dict(info.get("bayer", {}), pattern=r.bayer))
            metrics["settings"]["bayer"] = r.bayer
    else:
        metrics.update(_stream_totals(job.entries, captures.kind, read_all, write, total))
    if job.scores.frames["psnr"]:
        metrics["quality"], metrics["trivial"] = _quality(job, output)
        if output is not None and captures.kind in ("single", "captures", "measurements") and quantised(output):
            metrics["quality"]["output_file"] = written_quality(output, job)  # the file as written, decoded
    return metrics


def _share_solving(entries: list[dict]) -> None:
    """Each capture's ``seconds.reconstruct`` as its share of the stream's: the stream solves a window of
    captures' tiles in one graph, so the first capture's wait held the others' work; the waits' sum is
    shared in proportion to the seconds spent on each capture's own tiles in this run (none for tiles
    reused from the cache)."""
    infos = [e["reconstruction"] for e in entries]
    work = [float(info.get("seconds_total", 0.0)) for info in infos]
    if len(infos) < 2 or sum(work) <= 0:
        return
    waited = sum(info["seconds"].get("reconstruct", 0.0) for info in infos)
    for info, w in zip(infos, work):
        info["seconds"]["reconstruct"] = waited * w / sum(work)


def _stream_totals(entries: list[dict], kind: str, read: float, write: float, total: float | None) -> dict:
    """A stream's totals: its patches, the patches a second of the tiles solved in this run, the seconds."""
    _share_solving(entries)
    t_rec = sum(sum(e["reconstruction"]["seconds"].get(k, 0.0) for k in ("first_pass", "adapt", "reconstruct"))
                for e in entries)
    # the patches of the tiles computed in this run (a rerun from the cache counted every patch: 1.3 M/s)
    solved = sum(r.get("patches_computed", 0.0) for r in (e["reconstruction"] for e in entries))
    return {"layout": "(C, N, H, W)" if kind == "channels" else "(T*N, H, W)",
            "reconstruction": dict(patches=sum(e["reconstruction"]["patches"] for e in entries),
                                   patches_per_second=solved / max(t_rec, 1e-9),
                                   seconds=dict(read=read, reconstruct=t_rec, write=write,
                                                total=total if total is not None else read + t_rec + write)),
            kind: entries}


def _quality(job, output) -> tuple[dict, dict]:
    """The mean quality over all frames (every coded image has N frames: the mean of their means), and the
    trivial estimate's."""
    scores, units, kind, n = job.scores, job.units, job.captures.kind, job.n
    per_frame = scores.frames
    quality = dict(psnr=mean_psnr(per_frame["psnr"]), ssim=float(np.mean(per_frame["ssim"])),
                   exact_frames=int(np.sum(np.isposinf(per_frame["psnr"]))),
                   psnr_per_frame=per_frame["psnr"], ssim_per_frame=per_frame["ssim"], data_range=units.value,
                   psnr_peak=dict(value=units.value, source=units.source))
    trivial = dict(psnr=mean_psnr(scores.trivial["psnr"]), ssim=float(np.mean(scores.trivial["ssim"])),
                   psnr_per_frame=scores.trivial["psnr"], ssim_per_frame=scores.trivial["ssim"],
                   data_range=units.value)
    if kind == "bayer":  # frames are channel-major: R's N, G's N, B's N
        for key in ("psnr", "ssim"):
            quality[f"{key}_per_channel"] = [float(np.mean(per_frame[key][c * n : (c + 1) * n])) for c in range(3)]
    elif kind != "single":
        name = kind[:-1]
        scored = [e for e in job.entries if "quality" in e]  # (a stream's truth may end before its last)
        quality.update({f"psnr_per_{name}": [e["quality"]["psnr"] for e in scored],
                        f"ssim_per_{name}": [e["quality"]["ssim"] for e in scored]})
        if len(scored) < len(job.entries):
            quality["scored"] = [e.get(name, i + 1) for i, e in enumerate(scored)]
        if kind in ("captures", "measurements") and len(scored) > 1:
            pairs = [dict(last=per_frame["psnr"][(i + 1) * n - 1], first_next=per_frame["psnr"][(i + 1) * n])
                     for i in range(len(scored) - 1)]  # flicker at the boundaries
            quality["boundaries"] = dict(dict(pairs=pairs), **scores.steps.summary())
    # of the volume as reconstructed (float32); a lossy output file holds it less exactly (evaluate the file)
    suffix = Path(str(output)).suffix.lower() if output is not None else ""
    lossy = "H.264" if suffix in (".mp4", ".mov") else \
        "GIF palette (3-3-2)" if suffix == ".gif" and len(job.shape) == 4 else None
    quality["measured_on"] = "volume before encoding" + (f"; the output is lossy ({lossy})" if lossy else "")
    return quality, trivial


def quantised(output) -> bool:
    """Whether an output holds the reconstruction less exactly than float32: a video (8-bit, H.264 or a GIF's
    palette) or a folder of 16-bit frames."""
    from codedvideo.formats.io import VIDEO_SUFFIXES

    return Path(output).suffix.lower() in (*VIDEO_SUFFIXES, "", ".d")


def written_quality(output, job) -> dict:
    """PSNR/SSIM of the output file as written, decoded and read back in the run's units (a video's 8-bit frames
    times the data range / 255), against the frames the truth of ``job`` covers."""
    from codedvideo.formats.io import VIDEO_SUFFIXES
    from codedvideo.formats.volumes import read_scored

    t0 = time.perf_counter()
    written = read_scored(str(output), "reconstruction")
    truths = []
    for i in range(job.count):
        truth = job.captures.truth(i)
        if truth is None:  # (a benchmark file's truth covers its first measurements only)
            break
        truths.append(np.asarray(truth, np.float32).reshape(-1, *job.shape[-2:]))
    truth = np.concatenate(truths)
    frames = np.asarray(written[: truth.shape[0]], np.float32)
    if Path(output).suffix.lower() in VIDEO_SUFFIXES:
        frames *= np.float32(job.units.value / 255.0)
    scored = evaluate(frames, truth, data_range=job.units.value)
    return dict(psnr=scored["psnr"], ssim=scored["ssim"], psnr_per_frame=scored["psnr_per_frame"],
                ssim_per_frame=scored["ssim_per_frame"], measured_on=f"{output} as written, decoded",
                seconds=time.perf_counter() - t0)
