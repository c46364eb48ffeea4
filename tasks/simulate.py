"""Stage: simulate the coded capture of the scene pipeline.yaml names (the `simulate` stage of `codedvideo run`)."""
import sys

from _common import config_from_argv, config_path, guarded

from codedvideo.api import run_pipeline


def main() -> None:
    cfg = config_from_argv()
    report = run_pipeline(cfg.model_copy(update=dict(stages=["simulate"])), config_path=config_path())
    for name, path in report["capture"].items():
        print(f"{name}: {path}")


if __name__ == "__main__":
    sys.exit(guarded(main))
