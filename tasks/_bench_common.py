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
