"""Stage: train (or reuse) the dictionary that pipeline.yaml describes."""
import sys

from _common import config_from_argv, guarded

from codedvideo.pipeline import train_dictionary


def main() -> None:
    path, meta = train_dictionary(config_from_argv())
    print(f"dictionary: {path} ({meta['atoms']} atoms, {'reused' if meta['reused'] else 'trained'} in {meta['seconds']:.1f} s)")


if __name__ == "__main__":
    sys.exit(guarded(main))
