"""The door a call came through, and what each door calls a setting.

The same settings reach the engine through three doors: the command line (``--noise-sigma``), the Python API
(``noise_sigma``) and pipeline.yaml (``noise.sigma``).  A message names a setting with :func:`name`, which
spells it as the door of the call in progress says it (:func:`through` sets the door; the command line's is the
default), so no message is reworded after it is made.  :func:`warn` says a warning at the line of the caller's
own code, the first frame outside this package, as it happens.
"""

from __future__ import annotations

import contextlib
import contextvars
import sys
import warnings
from pathlib import Path

#: The doors a setting can be named through: the command line, the Python API, pipeline.yaml.
DOORS = ("cli", "api", "config")

#: pipeline.yaml's keys of the settings it holds outside ``reconstruct:``.
CONFIG_KEYS = {"noise_sigma": "noise.sigma", "white_level": "noise.white_level", "black_level": "noise.black_level",
               "bits": "noise.bits", "data_range": "output.data_range", "bayer": "bayer", "cache": "cache",
               "shot_noise": "noise.shot_noise", "full_well": "noise.full_well", "gain": "noise.gain",
               "seed": "seed", "frames": "frames"}

#: The door of the call in progress; None outside any (the engine called directly).
_door: contextvars.ContextVar[str | None] = contextvars.ContextVar("codedvideo_door", default=None)

_PACKAGE = str(Path(__file__).resolve().parents[1])


def current() -> str:
    """The door of the call in progress (``"cli"`` outside any: the engine's own messages name the options)."""
    return _door.get() or "cli"


@contextlib.contextmanager
def through(door: str):
    """Within the block, settings are named as ``door`` names them."""
    if door not in DOORS:
        raise ValueError(f"door {door!r}: one of {', '.join(DOORS)}")
    token = _door.set(door)
    try:
        yield
    finally:
        _door.reset(token)


def name(field: str, door: str | None = None) -> str:
    """What ``door`` (default: the current one) calls the setting ``field``: ``--noise-sigma`` on the command
    line, ``noise_sigma`` in Python, ``noise.sigma`` in pipeline.yaml."""
    through_door = door or current()
    if through_door == "cli":
        return "--" + field.replace("_", "-")
    if through_door == "config":
        return CONFIG_KEYS.get(field, f"reconstruct.{field}")
    return field


#: pipeline.yaml's keys whose setting the command line and the API name otherwise than by the key's last part.
_FIELDS_OF_KEYS = {"code.path": "code_file", "noise.sigma": "noise_sigma"}


def key(config_key: str) -> str:
    """A pipeline.yaml key (``code.bump``) as the door of the call names its setting: the key itself in
    pipeline.yaml (and outside any door: a config validated directly), ``--bump`` on the command line, ``bump``
    in Python."""
    if _door.get() in (None, "config"):
        return config_key
    return name(_FIELDS_OF_KEYS.get(config_key, config_key.rsplit(".", 1)[-1]))


#: Parts of messages the call in progress keeps to itself (:func:`muted`; empty: none).
_muted: contextvars.ContextVar[tuple[str, ...]] = contextvars.ContextVar("codedvideo_muted", default=())


@contextlib.contextmanager
def muted(matching: str = ""):
    """Within the block, :func:`warn` drops the messages that contain ``matching`` (every message when empty), for
    this call only: other threads and other calls keep theirs, where ``warnings.catch_warnings`` would change the
    filters of the whole process.  (A job's first passes are muted: its last job says the same warnings.)"""
    token = _muted.set(_muted.get() + (matching,))
    try:
        yield
    finally:
        _muted.reset(token)


def warn(message: str, category: type[Warning] = UserWarning) -> None:
    """``warnings.warn`` at the first frame outside codedvideo: the line of the caller's code that led to it
    (unless the call in progress muted it: :func:`muted`)."""
    if any(part in message for part in _muted.get()):
        return
    frame, level = sys._getframe(1), 2
    while frame is not None and frame.f_code.co_filename.startswith(_PACKAGE):
        frame, level = frame.f_back, level + 1
    warnings.warn(message, category, stacklevel=level)
