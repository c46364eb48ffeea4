"""Shared helpers of the stage scripts: read the config named on the command line."""
from __future__ import annotations

import sys

from codedvideo.engine.config import load_config


def config_path(default: str = "pipeline.yaml") -> str:
    """The config named on the command line (default: pipeline.yaml)."""
    return sys.argv[1] if len(sys.argv) > 1 else default


def config_from_argv(default: str = "pipeline.yaml"):
    return load_config(config_path(default))


def guarded(fn) -> int:
    """Run a stage as the command line runs a command (:func:`codedvideo.app.cli.guarded`): an error, Ctrl-C or
    SIGTERM is one line on stderr and its exit status (2, 130, 143)."""
    from codedvideo.app.cli import guarded as as_command

    return as_command(fn)
