"""Run pipeline.yaml with its reconstruction graph submitted to a dask.distributed scheduler.

    python tasks/submit.py pipeline.yaml tcp://scheduler:8786

On Slurm or PBS, start the scheduler and workers with dask-jobqueue (for
example ``SLURMCluster(...).scale(jobs=4)``) and pass its ``scheduler_address``;
the workers must see the same file system as this process (the Zarr working
store lives under ``cache``).
"""
import sys

from _common import guarded

from codedvideo.config import load_config
from codedvideo.pipeline import run_pipeline


def main() -> None:
    if len(sys.argv) < 3 or not sys.argv[2]:
        raise SystemExit("usage: tasks/submit.py pipeline.yaml SCHEDULER_ADDRESS")
    cfg = load_config(sys.argv[1])
    cfg = cfg.model_copy(update=dict(reconstruct=cfg.reconstruct.model_copy(update=dict(scheduler=sys.argv[2]))))
    report = run_pipeline(cfg)
    print(f"video: {report['outputs']['video']}\nmetrics: {report['metrics_path']}")


if __name__ == "__main__":
    sys.exit(guarded(main))
