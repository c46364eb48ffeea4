"""Shared helpers of the stage scripts: read the config named on the command line."""
from __future__ import annotations

import sys

from codedvideo.config import load_config
from codedvideo.errors import CodedVideoError


def config_path(default: str = "pipeline.yaml") -> str:
    """The config named on the command line (default: pipeline.yaml)."""
    return sys.argv[1] if len(sys.argv) > 1 else default


def config_from_argv(default: str = "pipeline.yaml"):
    return load_config(config_path(default))


def guarded(fn) -> int:
    """Run a stage; a CodedVideoError becomes one line on stderr and exit 2."""
    try:
        fn()
    except CodedVideoError as exc:
        print(f"codedvideo: error: {exc}", file=sys.stderr)
        return 2
    return 0
