"""A job's locks on its cache entries, and the open files they need.

A reconstruction job locks the working store of every capture of the windows it holds
(:func:`codedvideo.formats.store.entry_lock`), one lock a store however many captures use it, so that
two runs on the same entry take it in turn; each lock holds a file open (:func:`allow_open_files`).
"""

from __future__ import annotations

import contextlib
from pathlib import Path

from codedvideo.formats.store import entry_lock
from codedvideo.model.errors import OutputError


def allow_open_files(needed: int, cache) -> None:
    """Make room for ``needed`` open files (a job locks each working store of the windows it holds, 64
    kept for the rest): the soft limit raised toward the hard one (doubled, so that this is rare), or
    an OutputError, while planning and before any tile, where that is not allowed."""
    try:
        import resource
    except ImportError:  # not on this platform
        return
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    if soft == resource.RLIM_INFINITY or soft >= needed:
        return
    target = max(needed, 2 * soft) if hard == resource.RLIM_INFINITY else min(hard, max(needed, 2 * soft))
    try:
        if target < needed:
            raise ValueError(f"the hard limit is {hard}")
        resource.setrlimit(resource.RLIMIT_NOFILE, (target, hard))
    except (ValueError, OSError) as exc:
        raise OutputError(f"cache {cache}: this job locks a working store per capture of the windows it holds, "
                          f"{needed - 64} now, and cannot have more open files ({exc}; ulimit -n); raise the limit "
                          "or reconstruct fewer captures a job") from exc


class Busy(Exception):
    """A cache entry another run holds, asked for while the job holds others (:meth:`EntryLocks.take`)."""


class EntryLocks:
    """The cache entries a job holds (:func:`codedvideo.formats.store.entry_lock`), each locked once however many
    captures of its windows use it, and let go when the last window that uses it is done."""

    def __init__(self, cache):
        self.cache = cache
        self.held: dict[str, list] = {}  # entry -> [its lock, the windows using it (with repeats)]

    def take(self, entry: Path, window) -> None:
        """Lock ``entry`` for ``window``.  While the job holds other entries it never waits for one that
        another run holds (two runs taking each other's entries in turn would wait for ever): it raises
        :class:`Busy`, and the entry is asked for again once the job holds nothing."""
        name = str(entry)
        if name not in self.held:
            allow_open_files(len(self.held) + 65, self.cache)
            lock = contextlib.ExitStack()
            if not lock.enter_context(entry_lock(entry, blocking=not self.held)):
                lock.close()
                raise Busy(name)
            self.held[name] = [lock, []]
        self.held[name][1].append(id(window))

    def release(self, window) -> None:
        for name in list(self.held):
            lock, users = self.held[name]
            users[:] = [u for u in users if u != id(window)]
            if not users:
                lock.close()
                del self.held[name]

    def close(self) -> None:
        for lock, _ in self.held.values():
            lock.close()
        self.held.clear()
