"""Where results go: an output never touches what the user owns.

Every command names its outputs and its inputs before any work is done, and
:func:`check_outputs` refuses, with one line naming both:

- an output that is, contains or lies inside one of the run's inputs (the
  coded image, mask, truth, dictionary, CACTI file, training videos, the cache),
  or is another output of the same run;
- an existing output that is not a regular file or folder (a device node, a
  FIFO, a socket, a symbolic link), or is read-only;
- an existing output of the other kind (a file where a folder is written, or
  the reverse);
- an existing folder that codedvideo did not write, ``overwrite`` or not.  A
  folder is codedvideo's only when its record (``.NAME.codedvideo`` beside it)
  names every file and folder codedvideo wrote in it (relative path; size,
  modification time, change time and inode of each file) and the folder holds nothing else,
  each file unchanged.  A file or folder put inside by the user, a file the
  user changed, or a folder with no record (a marker file such as
  ``codedvideo-frames.json`` proves nothing) is named in the refusal; a file
  the user removed loses nothing of theirs;
- an existing file that codedvideo did not write, unless ``overwrite`` is
  given.  A file codedvideo wrote has a hidden record beside it
  (``.NAME.codedvideo``: size, modification time, change time and inode at
  writing), so a rerun replaces its own unchanged results and nothing else.
  The change time (``st_ctime``) is what an edit in place cannot hide: one
  that keeps the size and sets the modification time back (``touch -r``,
  ``os.utime``) still moves it.  A record written before it was kept (no
  ``ctime_ns``) is checked on the rest.

Writers replace an output by renaming a finished temporary onto it
(:func:`codedvideo.formats.atomic.atomic_output`), so the old output stays whole until the
new one is complete.  Call :func:`mark_written` after writing a file or folder
output (the record is itself written atomically).
"""

from __future__ import annotations

import json
import os
import stat
from dataclasses import dataclass
from pathlib import Path

from codedvideo.model.errors import OutputError

#: Suffix of the hidden record written beside every file output.
OWNED_SUFFIX = ".codedvideo"


@dataclass(frozen=True)
class Output:
    """One output of a run.

    kind
        ``"file"`` (replaced as a whole), ``"folder"`` (a folder replaced as a
        whole: frames, Zarr) or ``"place"`` (a folder that outputs are written
        into; it is created when missing and never replaced).
    """

    path: Path
    kind: str = "file"
    label: str = "output"


def _real(path: Path) -> Path:
    """Absolute path with symbolic links of its folders resolved (the last part is kept as named)."""
    absolute = Path(path).absolute()
    return Path(os.path.realpath(absolute.parent)) / absolute.name


def _inside(child: Path, parent: Path) -> bool:
    return child != parent and child.is_relative_to(parent)


def record_path(path: str | os.PathLike) -> Path:
    """The hidden record beside a file or folder output."""
    target = Path(path)
    return target.with_name(f".{target.name}{OWNED_SUFFIX}")


def _fingerprint(st: os.stat_result) -> dict:
    """What a record holds of a file: an edit in place that keeps the size and sets the modification time back
    still moves the change time, which no user can set."""
    return dict(size=st.st_size, mtime_ns=st.st_mtime_ns, ctime_ns=st.st_ctime_ns, inode=st.st_ino)


def _unchanged(recorded, now: dict | None) -> bool:
    """True when the record ``recorded`` of a file holds its fingerprint as it is now (``now``; None, a folder:
    recorded as one); a record written before change times were kept (no ``ctime_ns``) is checked on the rest."""
    if now is None or recorded is None:
        return now is recorded
    if not isinstance(recorded, dict) or "kind" in now:  # (a link, a FIFO...: never codedvideo's)
        return False
    return all(recorded.get(k) == v for k, v in now.items() if k != "ctime_ns" or "ctime_ns" in recorded)


def _folder_entries(path: Path) -> dict[str, dict | None]:
    """Everything under the folder ``path``, by path relative to it (sorted): a file's fingerprint, or None for a
    folder; anything else (a link, a FIFO...) as ``{"kind": ...}``, which no record of codedvideo's holds."""
    entries: dict[str, dict | None] = {}
    for top, dirs, names in os.walk(path, onerror=_raise):
        dirs.sort()
        for name in sorted([*dirs, *names]):
            full = os.path.join(top, name)
            rel = os.path.relpath(full, path)
            st = os.lstat(full)
            if stat.S_ISDIR(st.st_mode):
                entries[rel] = None
            elif stat.S_ISREG(st.st_mode):
                entries[rel] = _fingerprint(st)
            else:
                entries[rel] = dict(kind=_kind_of(st) or "not a regular file")
    return dict(sorted(entries.items()))


def _raise(exc: OSError) -> None:
    raise exc


def mark_written(path: str | os.PathLike) -> None:
    """Record that codedvideo wrote the file or folder ``path`` as it is now (see the module docstring)."""
    from codedvideo.formats.atomic import atomic_output

    target = Path(path)
    try:
        st = os.lstat(target)
        if stat.S_ISDIR(st.st_mode):
            record = dict(name=target.name, kind="folder", inode=st.st_ino, files=_folder_entries(target))
        elif stat.S_ISREG(st.st_mode):
            record = dict(_fingerprint(st), name=target.name)
        else:
            return
    except OSError:
        return
    with atomic_output(record_path(target)) as tmp:
        Path(tmp).write_text(json.dumps(record) + "\n")


def folder_problem(path: str | os.PathLike) -> str | None:
    """Why the folder ``path`` is not codedvideo's to replace (None: it is; see the module docstring).

    One phrase naming the first file or folder (in sorted order) that codedvideo did not write there, or that
    changed since: "holds PATH, which codedvideo did not write", "PATH changed since codedvideo wrote it".
    """
    folder = Path(path)
    try:
        st = os.lstat(folder)
        found = _folder_entries(folder)
    except OSError as exc:
        return f"cannot read it ({exc.strerror or exc})"
    record = record_path(folder)
    try:
        recorded = json.loads(record.read_text())
    except FileNotFoundError:
        recorded = None
    except (OSError, ValueError):
        recorded = {}
    if not isinstance(recorded, dict) or recorded.get("kind") != "folder" or recorded.get("inode") != st.st_ino \
            or not isinstance(recorded.get("files"), dict):
        why = f"no record {record.name} beside it" if recorded is None else \
            f"its record {record.name} does not describe this folder"
        first = next(iter(found), None)
        return f"is a folder codedvideo did not write ({why}; " + \
            (f"the first file in it: {folder / first})" if first else "it is empty)")
    files = recorded["files"]
    for rel, fingerprint in found.items():
        if rel not in files:
            return f"holds {folder / rel}, which codedvideo did not write"
        if not _unchanged(files[rel], fingerprint):
            return f"{folder / rel} changed since codedvideo wrote it"
    return None


def written_by_codedvideo(path: str | os.PathLike) -> bool:
    """True when ``path`` is a file or folder that codedvideo wrote and nobody changed since."""
    target = Path(path)
    try:
        st = os.lstat(target)
    except OSError:
        return False
    if stat.S_ISDIR(st.st_mode):
        return folder_problem(target) is None
    if not stat.S_ISREG(st.st_mode):
        return False
    try:
        recorded = json.loads(record_path(target).read_text())
    except (OSError, ValueError):
        return False
    return _unchanged(recorded, _fingerprint(st))


def _kind_of(st: os.stat_result) -> str | None:
    if stat.S_ISLNK(st.st_mode):
        return "a symbolic link"
    if stat.S_ISCHR(st.st_mode) or stat.S_ISBLK(st.st_mode):
        return "a device"
    if stat.S_ISFIFO(st.st_mode):
        return "a FIFO"
    if stat.S_ISSOCK(st.st_mode):
        return "a socket"
    return None


def check_outputs(outputs: list[Output], inputs: dict[str, object], *, overwrite: bool = False) -> None:
    """Refuse, before any work, outputs that would touch what the user owns (module docstring).

    Parameters
    ----------
    outputs : the run's outputs
    inputs : label -> path (or a list of paths, or None) of everything the run reads
    overwrite : replace existing files that codedvideo did not write

    Raises :class:`OutputError` naming the output, the problem and, for a
    clash, the input.  Creates nothing.
    """
    from codedvideo.formats.atomic import check_writable

    named: dict[Path, Output] = {}
    for out in outputs:  # two outputs of one run in one place: the second would replace the first
        first = named.setdefault(_real(out.path), out)
        if first is not out and "place" not in (first.kind, out.kind):
            raise OutputError(f"{out.label} {out.path}: is also where the {first.label} goes; choose another output")
    ins: list[tuple[str, Path]] = []
    for label, value in inputs.items():
        for p in value if isinstance(value, (list, tuple)) else [value]:
            if p and not str(p).startswith(("synth:", "footage:", "manifest:", "skimage:")):
                # an input is what it points to: a link to a file is that file (replacing that file loses
                # the input the link gave), whereas an output named by a link is refused as a link below
                ins.append((label, Path(os.path.realpath(Path(str(p)).absolute()))))
    for out in outputs:
        real = _real(out.path)
        for label, inp in ins:
            if real == inp:
                raise OutputError(f"{out.label} {out.path}: is the input {label} {inp}; choose another output")
            if out.kind != "place" and _inside(inp, real):
                raise OutputError(f"{out.label} {out.path}: contains the input {label} {inp}; choose another output")
            if _inside(real, inp):
                raise OutputError(f"{out.label} {out.path}: lies inside the input {label} {inp}; choose another output")
        try:
            st = os.lstat(out.path)
        except FileNotFoundError:
            check_writable(out.path)
            continue
        except OSError as exc:
            raise OutputError(f"{out.label} {out.path}: cannot inspect it ({exc.strerror or exc})") from exc
        odd = _kind_of(st)
        if odd:
            raise OutputError(f"{out.label} {out.path}: exists and is {odd}, not a regular file or folder; "
                              "codedvideo will not replace it")
        is_dir = stat.S_ISDIR(st.st_mode)
        if out.kind == "place":
            if not is_dir:
                raise OutputError(f"{out.label} {out.path}: exists and is a file; a folder is needed here")
            check_writable(out.path / "x")
            continue
        if is_dir != (out.kind == "folder"):
            have, want = ("a folder", "a file") if is_dir else ("a file", "a folder")
            raise OutputError(f"{out.label} {out.path}: exists and is {have}, but codedvideo writes {want} there; "
                              "choose another output")
        if not st.st_mode & 0o222:
            raise OutputError(f"{out.label} {out.path}: exists and is read-only; codedvideo will not replace it")
        if is_dir:
            problem = folder_problem(out.path)
            if problem:
                raise OutputError(f"{out.label} {out.path}: {problem}; a folder is replaced only when it holds "
                                  "nothing but what codedvideo wrote there, --overwrite or not (move that out, or "
                                  "choose another output)")
            check_writable(out.path)
            continue
        if written_by_codedvideo(out.path):
            check_writable(out.path)
            continue
        if not overwrite:
            raise OutputError(f"{out.label} {out.path}: exists and was not written by codedvideo; "
                              "give --overwrite to replace it")
        check_writable(out.path)
