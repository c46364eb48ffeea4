"""Stage: train (or reuse) the dictionary that pipeline.yaml describes, or regenerate the shipped ones.

    python tasks/train.py [pipeline.yaml]     # the dictionary: section (reused when shipped or cached)
    python tasks/train.py --shipped [N ...]   # `make train`: retrain codedvideo/data/dict-N*.zarr with the
                                              # defaults and rewrite both manifests with their checksums
"""
import sys

from _common import guarded, load, parser

from codedvideo.data import shipped
from codedvideo.engine.config import PipelineConfig
from codedvideo.engine.training import train_dictionary


def _shipped(frames: list[int]) -> None:
    for n in frames:
        path, meta = train_dictionary(PipelineConfig(frames=n), output=shipped.path_for(n), retrain=True)
        print(f"dictionary N = {n}: {path} (final RMSE {meta.get('final_rmse'):.4f}, {meta['seconds']:.0f} s)")
    print(f"manifests: {', '.join(map(str, shipped.write_manifests()))}")


def main(args) -> None:
    if args.shipped is not None:
        _shipped(args.shipped or shipped.available())
        return
    path, meta = train_dictionary(load(args.config))
    state = "shipped" if meta.get("shipped") else "reused" if meta["reused"] else "trained"
    print(f"dictionary: {path} ({meta['atoms']} atoms, {state} in {meta['seconds']:.1f} s)")


if __name__ == "__main__":
    ap = parser(__doc__)
    ap.add_argument("--shipped", nargs="*", type=int, metavar="N",
                    help="retrain the shipped dictionaries (all, or those of N frames) and rewrite both manifests")
    args = ap.parse_args()
    sys.exit(guarded(lambda: main(args)))
