"""Atomic writes: every file or folder the package writes is made under a temporary name beside its target
and renamed onto the target only when writing succeeded, so no reader ever sees it half-written.

One spelling of the temporary name (:func:`temporary_name`): ``.STEM.tmp-PID-HEX.SUFFIX`` (the target's
suffix kept, so writers that choose a format by extension still work) or ``.NAME.tmp-PID-HEX`` (Zarr stores
and cache entries); ``PID`` is the writing process, so a temporary whose process no longer runs is known to
be a killed run's and removed (:func:`remove_dead_temporaries`).
"""
from __future__ import annotations

import contextlib
import errno
import os
import re
import shutil
import time
import uuid
from pathlib import Path

from codedvideo.model.errors import OutputError

#: What follows the target's name in a temporary's name: the writing process and 8 hex digits.
_MARK = r"\.tmp-(\d+)-[0-9a-f]{8}"


def one_line(msg) -> str:
    """Library error text (often several lines) as one line."""
    return "; ".join(part.strip() for part in str(msg).splitlines() if part.strip()) or "unknown error"


def temporary_name(path: str | os.PathLike, *, keep_suffix: bool = True) -> Path:
    """A new temporary sibling of ``path``, hidden, naming this process: ``.STEM.tmp-PID-HEX.SUFFIX``, or
    with ``keep_suffix=False`` ``.NAME.tmp-PID-HEX``."""
    target = Path(path)
    mark = f".tmp-{os.getpid()}-{uuid.uuid4().hex[:8]}"
    if keep_suffix:
        return target.with_name(f".{target.stem}{mark}{target.suffix}")
    return target.with_name(f".{target.name}{mark}")


def temporary_pattern(name: str) -> str:
    """A regular expression matching the ``keep_suffix=False`` temporaries of the names ``name`` (a regular
    expression, group 1): ``.NAME.tmp-PID-HEX``."""
    return rf"^\.({name}){_MARK}$"


def temporaries_of(path: str | os.PathLike) -> list[Path]:
    """The ``keep_suffix=False`` temporaries of ``path`` there are (any process's)."""
    target = Path(path)
    pattern = re.compile(temporary_pattern(re.escape(target.name)))
    try:
        return sorted(p for p in target.parent.iterdir() if pattern.match(p.name))
    except OSError:
        return []


def discard(path: Path) -> None:
    """Remove a folder or a file, as far as possible."""
    if os.path.isdir(path) and not os.path.islink(path):
        shutil.rmtree(path, ignore_errors=True)
    else:
        with contextlib.suppress(OSError):
            os.unlink(path)


@contextlib.contextmanager
def atomic_output(path: str | os.PathLike):
    """Yield a temporary sibling of ``path``; rename it onto ``path`` on success.

    The temporary keeps ``path``'s suffix, so writers that choose a format by
    extension still work.  On an exception the temporary (file or folder) is
    removed and the exception re-raised; an existing ``path`` is untouched.
    """
    target = Path(path)
    made = make_parents(target)
    if not os.access(target.parent, os.W_OK):
        raise OutputError(f"{target}: folder {target.parent} is not writable")
    remove_dead_temporaries(target)
    tmp = temporary_name(target)
    try:
        try:
            yield tmp
        except OSError as exc:  # disk full, permissions...: one line naming the output
            if isinstance(exc, OutputError):
                raise
            raise OutputError(f"{target}: cannot write ({exc.strerror or one_line(exc)})") from exc
        rename_into_place(tmp, target)
    except BaseException:
        if tmp.is_dir():
            # a chunk write of zarr's I/O thread still in flight when Ctrl-C came can land after the removal
            for _ in range(5):
                shutil.rmtree(tmp, ignore_errors=True)
                if not tmp.exists():
                    break
                time.sleep(0.02)
        else:
            tmp.unlink(missing_ok=True)
        remove_made(made)
        raise


def make_parents(target: Path) -> list[Path]:
    """Create the folders ``target`` is to go into; those this made, deepest first (for :func:`remove_made`)."""
    made = [folder for folder in target.parents if not folder.exists()]
    try:
        target.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise OutputError(f"{target}: cannot create folder {target.parent} ({exc.strerror or exc})") from exc
    return made


def remove_made(made: list[Path]) -> None:
    """Remove the folders :func:`make_parents` made that are still empty (an output stopped before it was in
    place leaves no empty folder behind)."""
    for folder in made:  # (deepest first: each parent is empty once its child is gone)
        with contextlib.suppress(OSError):
            folder.rmdir()


def remove_dead_temporaries(path: Path) -> None:
    """Remove temporaries of ``path`` (both spellings of :func:`temporary_name`) that a killed process left
    (its pid, in the name, no longer runs)."""
    target = Path(path)
    pattern = re.compile(rf"^\.(?:{re.escape(target.stem)}{_MARK}{re.escape(target.suffix)}|"
                         rf"{re.escape(target.name)}{_MARK})$")
    try:
        siblings = list(target.parent.iterdir())
    except OSError:
        return
    for sib in siblings:
        m = pattern.match(sib.name)
        pid = int(m.group(1) or m.group(2)) if m else None
        if pid is None or pid == os.getpid():
            continue
        try:
            os.kill(pid, 0)
            continue  # still running: its own temporary
        except ProcessLookupError:
            pass
        except OSError:
            continue
        shutil.rmtree(sib, ignore_errors=True) if sib.is_dir() else sib.unlink(missing_ok=True)


def rename_into_place(tmp: Path, path: Path) -> None:
    """Rename a finished temporary file or folder onto ``path`` (replacing what is there)."""
    # a file never replaces a folder, nor a folder a file (codedvideo.formats.outputs refuses both before
    # any work; this keeps the rule for every writer)
    if path.is_dir() != tmp.is_dir() and (path.exists() or path.is_symlink()):
        have = "a folder" if path.is_dir() else "a file"
        raise OutputError(f"{path}: exists and is {have}; codedvideo does not replace it with "
                          f"{'a folder' if tmp.is_dir() else 'a file'}")
    try:
        if tmp.is_dir():  # the old folder stays whole until the new one is in place
            replace_dir(tmp, path)
        else:
            os.replace(tmp, path)  # atomic for a file
    except OSError as exc:
        raise OutputError(f"{path}: cannot rename the finished output into place ({exc.strerror or exc})") from exc


def replace_dir(tmp: Path, path: Path) -> None:
    """Rename the finished folder ``tmp`` to ``path``, replacing what is there.

    An existing ``path`` is first moved aside (and removed once ``tmp`` is in
    place; put back when the final rename fails).  Another process putting
    its own ``path`` in place between the two renames is moved aside too.
    """
    for attempt in range(8):
        old = None
        if os.path.lexists(path):
            old = temporary_name(path, keep_suffix=False)
            try:
                os.replace(path, old)
            except FileNotFoundError:  # someone else moved it meanwhile
                old = None
        try:
            os.replace(tmp, path)
        except OSError as exc:
            if old is not None and not os.path.lexists(path):
                try:
                    os.replace(old, path)  # keep the old one rather than nothing
                    old = None
                except OSError:
                    pass  # left as the hidden sibling, not removed
            elif old is not None:  # a concurrent writer's folder took its place
                discard(old)
            if exc.errno in (errno.ENOTEMPTY, errno.EEXIST) and attempt < 7:
                continue  # move that folder aside too
            raise
        if old is not None:
            discard(old)
        return


def check_writable(path: str | os.PathLike, *, what: str = "") -> Path:
    """Raise :class:`OutputError` unless ``path`` could be written (checked before any work is done).

    The nearest existing folder above ``path`` must be a writable folder
    (missing folders are created by the writer).  Nothing is created here.
    ``what`` names the path in the message (default: the path itself).
    """
    target = Path(path)
    name = f"{what} {target.parent}" if what else str(target)
    parent = target.absolute().parent
    while not parent.exists():
        parent = parent.parent
    if not parent.is_dir():
        raise OutputError(f"{name}: cannot create it, {parent} is a file, not a folder")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise OutputError(f"{name}: folder {parent} is not writable")
    return target


def check_cache(cache: str | os.PathLike) -> None:
    """Raise :class:`OutputError` unless the cache folder could hold a new entry (before any work)."""
    check_writable(Path(cache) / "entry", what="cache")
