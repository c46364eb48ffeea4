"""Stage: simulate the coded capture of the scene pipeline.yaml names."""
import sys
from pathlib import Path

from _common import config_from_argv, guarded

from codedvideo.pipeline import load_video, simulate_capture, write_capture


def main() -> None:
    cfg = config_from_argv()
    video = load_video(cfg.scene.video, frames=cfg.frames, size=cfg.scene.size, seed=cfg.seed, start=cfg.scene.start)
    cap = simulate_capture(video, code=cfg.code.name, bump=cfg.code.bump, sigma=cfg.noise.sigma, seed=cfg.seed, p=cfg.code.p)
    for name, path in write_capture(cap, Path(cfg.output.dir) / "capture").items():
        print(f"{name}: {path}")


if __name__ == "__main__":
    sys.exit(guarded(main))
