"""Run pipeline.yaml with its reconstruction graph submitted to a dask.distributed scheduler.

    python tasks/submit.py pipeline.yaml tcp://scheduler:8786

On Slurm or PBS, start the scheduler and workers with dask-jobqueue (for
example ``SLURMCluster(...).scale(jobs=4)``) and pass its ``scheduler_address``;
the workers must see the same file system as this process (the Zarr working
store lives under ``cache``).
"""
import argparse
import sys

from _common import guarded

from codedvideo.engine.config import ReconstructConfig, load_config, validated
from codedvideo.api import run_pipeline


def main(config: str, scheduler: str) -> None:
    cfg = load_config(config)
    reconstruct = validated(ReconstructConfig, dict(cfg.reconstruct.model_dump(), scheduler=scheduler),
                            {"scheduler": "SCHEDULER_ADDRESS"})
    report = run_pipeline(cfg.model_copy(update=dict(reconstruct=reconstruct)), config_path=config)
    print(f"video: {report['outputs']['video']}\nmetrics: {report['metrics_path']}")


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("config", help="the pipeline config")
    ap.add_argument("scheduler", metavar="SCHEDULER_ADDRESS", help="the dask.distributed scheduler, e.g. tcp://host:8786")
    args = ap.parse_args()
    if not args.scheduler:
        ap.error("SCHEDULER_ADDRESS is empty")
    sys.exit(guarded(lambda: main(args.config, args.scheduler)))
