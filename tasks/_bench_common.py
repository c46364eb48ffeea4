"""What the bench scripts share (tasks/bench.py, bench_nonlocal.py, bench_presets.py): the quality cases' scenes
and codes, the metrics a quality table keeps, a matrix-multiply reference and a timed CLI run.  Kept here so that
bench.py imports its sub-benches and none of them imports bench.py back (no import cycle in tasks/)."""
from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "bench" / "results"

QUALITY_SCENES = ("footage:bikes-a", "footage:bikes-b", "footage:carphone", "footage:bunny",
                  "synth:default", "synth:coins-translate", "synth:camera-rotate")
QUALITY_CODES = (("bernoulli", 2), ("hitomi", 2), ("hitomi", 3))


def sgemm_gflops(n: int = 2048, repeats: int = 5) -> float:
    a = np.random.default_rng(0).random((n, n), dtype=np.float32)
    b = a.T.copy()
    a @ b
    t = time.perf_counter()
    for _ in range(repeats):
        a @ b
    return 2 * n**3 * repeats / (time.perf_counter() - t) / 1e9


def _q(metrics: dict) -> dict:
    return dict(psnr=metrics["psnr"], ssim=metrics["ssim"])


def _cli(*args, cwd) -> tuple[float, float]:
    """Run the codedvideo CLI as a user would; its wall time (whole process) and peak resident MB."""
    cmd = ["/usr/bin/time", "-f", "%M", sys.executable, "-m", "codedvideo.app.cli", "-q", *map(str, args)]
    t = time.perf_counter()
    proc = subprocess.run(cmd, capture_output=True, text=True, cwd=cwd)
    seconds = time.perf_counter() - t
    if proc.returncode != 0:
        raise RuntimeError(proc.stderr.strip().splitlines()[-1])
    return seconds, float(proc.stderr.strip().splitlines()[-1]) / 1024.0


def quality_captures(scenes, size):
    """The quality cases' captures: each scene of ``scenes`` at ``size`` under each of :data:`QUALITY_CODES`,
    without noise and with read noise sigma 4 (seed 0); yields ``(video, capture, row)``, ``row`` the case's
    record (scene, kind, code, bump, sigma) that the bench fills with each method's figures."""
    from codedvideo.data.scenes import load_video
    from codedvideo.engine.simulation import simulate_capture
    from codedvideo.model.codes import CodeSpec

    for scene in scenes:
        video = load_video(scene, frames=8, size=size)
        for code, bump in QUALITY_CODES:
            for sigma in (0.0, 4.0):
                cap = simulate_capture(video, code=CodeSpec(code, bump=bump), sigma=sigma, seed=0)
                yield video, cap, dict(scene=scene, kind="real" if scene.startswith("footage:") else "synthetic",
                                       code=code, bump=bump, sigma=sigma)


def default_and_dct(row: dict, video, cap, D, rc, cache: Path):
    """The default (dictionary ``D``, ``rc``'s atoms) and the 3D DCT (the same OMP, up to 16 atoms) on one quality
    capture through the tile graph, each in a fresh cache under ``cache``: seconds, PSNR and SSIM into ``row``
    (``default``, ``dct``); returns the default's volume."""
    import tempfile

    from codedvideo.engine.config import omp_settings
    from codedvideo.engine.windows import Execution, reconstruct_volume
    from codedvideo.model.metrics import evaluate
    from codedvideo.solvers.dictionaries import dct_dictionary

    first = None
    for label, dic, atoms in (("default", D, rc.max_atoms), ("dct", dct_dictionary(8), 16)):
        s = omp_settings(rc.model_copy(update=dict(max_atoms=atoms)), row["sigma"])
        with tempfile.TemporaryDirectory(dir=cache) as tmp:
            t = time.perf_counter()
            vol, _ = reconstruct_volume(cap["coded"], cap["mask"], dic, settings=s,
                                        run=Execution(cache=tmp, progress=False))
            row[label] = dict(seconds=time.perf_counter() - t, **_q(evaluate(vol, video, data_range=255.0)))
        first = vol if first is None else first
    return first


if __name__ == "__main__":  # a helper module of the scripts beside it, not a script: it says what it is
    print(__doc__)
