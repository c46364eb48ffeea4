"""What the command-line tests share: a small valid capture's files (the ``files`` fixture of conftest.py makes
them), the arguments of a reconstruction of them, and checks that a refusal is one line and changes nothing."""
import hashlib
import os
from pathlib import Path

import numpy as np

from codedvideo.app.cli import main
from codedvideo.data.synth import make_scene
from codedvideo.formats.store import save_dictionary
from codedvideo.model.codes import make_code
from codedvideo.model.physics import simulate
from codedvideo.solvers.dictionaries import dct_dictionary

N, H, W = 4, 24, 30


def capture_files(tmp_path: Path) -> Path:
    """A valid capture, mask, truth and DCT dictionary in tmp_path/in; outputs go to tmp_path/out."""
    d = tmp_path / "in"
    d.mkdir()
    video = make_scene("default", frames=N, size=(H, W))
    mask = make_code("hitomi", (H, W), frames=N, bump=2, rng=1)
    np.save(d / "coded.npy", simulate(video, mask))
    np.save(d / "mask.npy", mask)
    np.save(d / "truth.npy", video)
    save_dictionary(d / "d.zarr", dct_dictionary(N), dict(patch=7, frames=N))
    return d


def files_under(root: Path) -> set:
    return {p.relative_to(root) for p in root.rglob("*")} if root.exists() else set()


def fails(capsys, args, *names, root=None):
    """Run the CLI; it must exit 2 with one line naming every name, and write nothing under ``root``."""
    before = files_under(root) if root else None
    capsys.readouterr()
    rc = main(["-q", *map(str, args)])
    err = capsys.readouterr().err.strip()
    assert rc == 2, err
    lines = err.splitlines()
    assert len(lines) == 1 and lines[0].startswith("codedvideo: error: "), err
    for name in names:
        assert str(name) in err, err
    if root is not None:
        assert files_under(root) == before, files_under(root) - before
    return err


def reconstruct_args(files, tmp_path, **over):
    args = dict(coded=files / "coded.npy", mask=files / "mask.npy", dictionary=files / "d.zarr",
                output=tmp_path / "out" / "r.npy", cache=tmp_path / "cache")
    args.update(over)
    out = ["reconstruct"]
    for k, v in args.items():
        if v is not None:
            out += [f"--{k}", v]
    return out


def tree(root: Path) -> dict:
    """Every path under root with the sha256 of its bytes (folders: None) and its permission bits."""
    out = {}
    for p in sorted(root.rglob("*")):
        st = os.lstat(p)
        data = hashlib.sha256(p.read_bytes()).hexdigest() if p.is_file() and not p.is_symlink() else None
        out[str(p.relative_to(root))] = (data, st.st_mode)
    return out


def refused(capsys, args, *names, root: Path):
    """The CLI refuses with one line naming ``names``; nothing under ``root`` changed, byte for byte."""
    before = tree(root)
    err = fails(capsys, args, *names)
    assert tree(root) == before
    return err
