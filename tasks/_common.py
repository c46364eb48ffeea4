"""Shared helpers of the stage scripts: their command line (argparse: `--help` answers without doing work) and
the config it names."""
from __future__ import annotations

import argparse

from codedvideo.engine.config import load_config


def parser(doc: str | None) -> argparse.ArgumentParser:
    """A stage script's parser: its docstring as the description, and the config as the first argument."""
    ap = argparse.ArgumentParser(description=doc, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("config", nargs="?", default="pipeline.yaml", help="the pipeline config (default: pipeline.yaml)")
    return ap


def config_args(doc: str | None, argv: list[str] | None = None) -> argparse.Namespace:
    """The command line of a stage that reads only a config: ``args.config``."""
    return parser(doc).parse_args(argv)


def load(path: str):
    return load_config(path)


def guarded(fn) -> int:
    """Run a stage as the command line runs a command (:func:`codedvideo.app.cli.guarded`): an error, Ctrl-C or
    SIGTERM is one line on stderr and its exit status (2, 130, 143)."""
    from codedvideo.app.cli import guarded as as_command

    return as_command(fn)


if __name__ == "__main__":  # a helper module of the scripts beside it, not a script: it says what it is
    print(__doc__)
