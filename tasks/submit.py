"""Run pipeline.yaml with its reconstruction graph submitted to a dask.distributed scheduler.

    python tasks/submit.py pipeline.yaml tcp://scheduler:8786

On Slurm or PBS, start the scheduler and workers with dask-jobqueue (for
example ``SLURMCluster(...).scale(jobs=4)``) and pass its ``scheduler_address``;
the workers must see the same file system as this process (the Zarr working
store lives under ``cache``).
"""
import sys

from _common import guarded

from codedvideo.engine.config import ReconstructConfig, load_config, validated
from codedvideo.api import run_pipeline


def main() -> None:
    if len(sys.argv) < 3 or not sys.argv[2]:
        raise SystemExit("usage: tasks/submit.py pipeline.yaml SCHEDULER_ADDRESS")
    cfg = load_config(sys.argv[1])
    reconstruct = validated(ReconstructConfig, dict(cfg.reconstruct.model_dump(), scheduler=sys.argv[2]),
                            {"scheduler": "SCHEDULER_ADDRESS"})
    report = run_pipeline(cfg.model_copy(update=dict(reconstruct=reconstruct)), config_path=sys.argv[1])
    print(f"video: {report['outputs']['video']}\nmetrics: {report['metrics_path']}")


if __name__ == "__main__":
    sys.exit(guarded(main))
