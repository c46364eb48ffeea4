"""Stage: reconstruct the capture (trains and simulates first when their results are not cached)."""
import sys

from _common import config_args, guarded, load

from codedvideo.api import run_pipeline


def main(config: str) -> None:
    cfg = load(config)
    cfg = cfg.model_copy(update=dict(stages=["train", "simulate", "reconstruct", "evaluate"]))
    report = run_pipeline(cfg, config_path=config)
    print(f"video: {report['outputs']['video']}\nmetrics: {report['metrics_path']}")


if __name__ == "__main__":
    args = config_args(__doc__)
    sys.exit(guarded(lambda: main(args.config)))
