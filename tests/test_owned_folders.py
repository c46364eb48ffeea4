"""A folder is codedvideo's only when its record names every file codedvideo wrote there and the folder holds
nothing else, unchanged (issue 29): a user's file put inside a frame folder, a Zarr output or a dictionary, or a
marker file copied into a folder of the user's, makes a rerun refuse, --overwrite included, before any work.
"""
import json
import os
import time

import pytest

from codedvideo.app.cli import main
from codedvideo.formats.outputs import record_path, written_by_codedvideo
from cli_inputs import N, reconstruct_args, refused, tree


def run(args) -> int:
    return main(["-q", *map(str, args)])


@pytest.mark.parametrize("name", ["frames", "o.zarr"])
def test_a_users_file_put_inside_an_output_folder_is_never_deleted(files, tmp_path, capsys, name):
    output = tmp_path / "o" / name
    args = reconstruct_args(files, tmp_path, output=output)
    assert run(args) == 0 and written_by_codedvideo(output)
    assert run(args) == 0 and written_by_codedvideo(output)  # its own unchanged folder: replaced
    (output / "MYNOTES.txt").write_text("notes")
    for overwrite in ([], ["--overwrite"]):
        err = refused(capsys, [*args, *overwrite], "MYNOTES.txt", "did not write", root=tmp_path)
        assert name in err
    assert (output / "MYNOTES.txt").read_text() == "notes"


@pytest.mark.parametrize("name", ["frames", "o.zarr"])
def test_a_users_folder_or_a_changed_file_inside_is_refused_too(files, tmp_path, capsys, name):
    output = tmp_path / "o" / name
    args = reconstruct_args(files, tmp_path, output=output)
    assert run(args) == 0
    (output / "mine").mkdir()  # an empty folder of the user's
    refused(capsys, args, "mine", root=tmp_path)
    (output / "mine").rmdir()
    assert written_by_codedvideo(output)
    first = sorted(p for p in output.rglob("*") if p.is_file())[0]
    first.write_bytes(first.read_bytes() + b"the user's edit")
    assert not written_by_codedvideo(output)
    err = refused(capsys, [*args, "--overwrite"], first.name, "changed", root=tmp_path)
    assert name in err


def test_a_marker_file_alone_does_not_make_a_folder_codedvideos(files, tmp_path, capsys):
    fake = tmp_path / "fake"
    fake.mkdir()
    (fake / "codedvideo-frames.json").write_text("{}")
    (fake / "precious.txt").write_text("precious")
    for overwrite in ([], ["--overwrite"]):
        refused(capsys, [*reconstruct_args(files, tmp_path, output=fake), *overwrite], "fake", "codedvideo-frames.json",
                root=tmp_path)
    zfake = tmp_path / "z.zarr"  # a Zarr store of the user's whose attributes name a codedvideo kind
    zfake.mkdir()
    (zfake / "zarr.json").write_text(json.dumps(dict(zarr_format=3, node_type="group",
                                                     attributes=dict(kind="codedvideo-volume"))))
    (zfake / "precious.txt").write_text("precious")
    refused(capsys, [*reconstruct_args(files, tmp_path, output=zfake), "--overwrite"], "z.zarr", root=tmp_path)
    assert (fake / "precious.txt").read_text() == "precious" and (zfake / "precious.txt").read_text() == "precious"


def test_a_record_copied_or_forged_beside_a_users_folder_does_not_make_it_codedvideos(files, tmp_path, capsys):
    own = tmp_path / "own"
    args = reconstruct_args(files, tmp_path, output=own)
    assert run(args) == 0
    mine = tmp_path / "mine"
    mine.mkdir()
    for p in sorted(own.iterdir()):  # the same names and sizes, other files
        (mine / p.name).write_bytes(p.read_bytes())
    record_path(mine).write_bytes(record_path(own).read_bytes())
    refused(capsys, [*reconstruct_args(files, tmp_path, output=mine), "--overwrite"], "mine", root=tmp_path)
    record_path(mine).write_text("not json")
    refused(capsys, [*reconstruct_args(files, tmp_path, output=mine), "--overwrite"], "mine", root=tmp_path)


def test_a_frame_deleted_by_the_user_loses_nothing_of_theirs(files, tmp_path, capsys):
    output = tmp_path / "frames"
    args = reconstruct_args(files, tmp_path, output=output)
    assert run(args) == 0
    frames = sorted(output.glob("frame_*"))
    frames[0].unlink()
    assert written_by_codedvideo(output)
    assert run(args) == 0 and len(sorted(output.glob("frame_*"))) == len(frames) == N


def test_a_trained_dictionary_folder_holding_a_users_file_is_refused(tmp_path, capsys):
    out = tmp_path / "d.zarr"
    args = ["train", "--kind", "dct", "--frames", N, "--output", out, "--cache", tmp_path / "cache"]
    assert run(args) == 0 and written_by_codedvideo(out)
    assert run(args) == 0  # its own: replaced
    (out / "notes.txt").write_text("mine")
    refused(capsys, [*args, "--overwrite"], "notes.txt", root=tmp_path)


def test_pipeline_frames_folder_holding_a_users_file_is_refused_before_any_work(tmp_path, capsys):
    cfg = tmp_path / "p.yaml"
    cfg.write_text(f"frames: {N}\ndictionary: {{kind: dct}}\nscene: {{size: [24, 30]}}\n"
                   f"cache: {tmp_path / 'cache'}\noutput: {{dir: {tmp_path / 'out'}, video: p.mkv, frames: tiff16}}\n")
    assert run(["run", cfg]) == 0
    frames = tmp_path / "out" / "frames"
    assert written_by_codedvideo(frames)
    assert run(["run", cfg]) == 0
    (frames / "MYNOTES.txt").write_text("notes")
    before = tree(tmp_path)
    refused(capsys, ["run", cfg], "MYNOTES.txt", root=tmp_path)
    assert tree(tmp_path) == before and os.path.exists(frames / "MYNOTES.txt")


def _edit_in_place_keeping_size_and_mtime(path):
    """The user's edit that size and modification time cannot see: bytes changed in place, the time set back."""
    st = os.stat(path)
    time.sleep(0.05)  # (a real edit comes later than the coarse clock's tick after the write)
    with open(path, "r+b") as f:
        f.seek(st.st_size // 2)
        byte = f.read(1)
        f.seek(st.st_size // 2)
        f.write(bytes([byte[0] ^ 0xFF]))
    os.utime(path, ns=(st.st_atime_ns, st.st_mtime_ns))
    after = os.stat(path)
    assert (after.st_size, after.st_mtime_ns, after.st_ino) == (st.st_size, st.st_mtime_ns, st.st_ino)
    return path.read_bytes()


def test_a_frame_edited_in_place_with_its_size_and_mtime_kept_is_the_users(files, tmp_path, capsys):
    output = tmp_path / "o" / "frames"
    args = reconstruct_args(files, tmp_path, output=output)
    assert run(args) == 0 and written_by_codedvideo(output)
    frame = sorted(output.glob("frame_*"))[1]
    edited = _edit_in_place_keeping_size_and_mtime(frame)
    assert not written_by_codedvideo(output)
    for overwrite in ([], ["--overwrite"]):
        refused(capsys, [*args, *overwrite], frame.name, "changed", root=tmp_path)
    assert frame.read_bytes() == edited


def test_a_file_output_edited_in_place_with_its_size_and_mtime_kept_is_the_users(files, tmp_path, capsys):
    output = tmp_path / "o" / "r.npy"
    args = reconstruct_args(files, tmp_path, output=output)
    assert run(args) == 0 and written_by_codedvideo(output)
    edited = _edit_in_place_keeping_size_and_mtime(output)
    assert not written_by_codedvideo(output)
    refused(capsys, args, "r.npy", "not written by codedvideo", root=tmp_path)
    assert output.read_bytes() == edited


def test_a_record_written_before_change_times_were_kept_still_counts(files, tmp_path, capsys):
    output = tmp_path / "o" / "frames"
    args = reconstruct_args(files, tmp_path, output=output)
    assert run(args) == 0
    record = json.loads(record_path(output).read_text())
    for fingerprint in record["files"].values():
        if fingerprint is not None:
            del fingerprint["ctime_ns"]
    record_path(output).write_text(json.dumps(record))
    assert written_by_codedvideo(output)
    assert run(args) == 0 and written_by_codedvideo(output)
