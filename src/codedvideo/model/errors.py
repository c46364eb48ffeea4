"""Exception types shared by every layer of codedvideo.

The command line turns any :class:`CodedVideoError` into a one-line message on
stderr and a non-zero exit status, so messages must name the file (or the
setting) and the problem, e.g. ``"mask runs/mask.npy: shape (8, 64, 64) does
not match coded image (64, 80)"``.
"""

from __future__ import annotations


class CodedVideoError(Exception):
    """Base class of every error codedvideo reports to the user."""


class InputError(CodedVideoError, ValueError):
    """An input file, array or option is missing, malformed or inconsistent."""


class ConfigError(CodedVideoError, ValueError):
    """pipeline.yaml (or an option given on the command line) is invalid."""


class OutputError(CodedVideoError, OSError):
    """An output cannot be written."""


class SchedulerError(CodedVideoError, RuntimeError):
    """A dask.distributed scheduler cannot be reached, or was lost during a run."""
