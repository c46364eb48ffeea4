"""Stage: simulate the coded capture of the scene pipeline.yaml names (the `simulate` stage of `codedvideo run`)."""
import sys

from _common import config_args, guarded, load

from codedvideo.api import run_pipeline


def main(config: str) -> None:
    cfg = load(config)
    report = run_pipeline(cfg.model_copy(update=dict(stages=["simulate"])), config_path=config)
    for name, path in report["capture"].items():
        print(f"{name}: {path}")


if __name__ == "__main__":
    args = config_args(__doc__)
    sys.exit(guarded(lambda: main(args.config)))
