"""Stage: reconstruct the capture (trains and simulates first when their results are not cached)."""
import sys

from _common import config_from_argv, config_path, guarded

from codedvideo.api import run_pipeline


def main() -> None:
    cfg = config_from_argv()
    cfg = cfg.model_copy(update=dict(stages=["train", "simulate", "reconstruct", "evaluate"]))
    report = run_pipeline(cfg, config_path=config_path())
    print(f"video: {report['outputs']['video']}\nmetrics: {report['metrics_path']}")


if __name__ == "__main__":
    sys.exit(guarded(main))
