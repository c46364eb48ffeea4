"""Nothing a user owns is ever lost: outputs that would touch an input, a folder or a file of the user's are refused
before any work, with every byte under the working folder unchanged; every bad option is a one-line error.
"""
import os
import socket

import numpy as np
import pytest

from codedvideo.app.cli import main
from codedvideo.formats.outputs import record_path, written_by_codedvideo
from cli_inputs import H, N, W, fails, reconstruct_args, refused, tree  # noqa: F401


# ----------------------------------------------------------------------------- an output that is an input
@pytest.mark.parametrize("which", ["coded", "mask", "truth", "dictionary", "coded-tif", "cache", "in-cache",
                                   "in-dictionary", "input-folder", "parent-of-inputs"])
def test_output_that_is_contains_or_lies_inside_an_input_is_refused(files, tmp_path, capsys, which):
    from codedvideo.formats import io as cio

    cio.write_image(files / "coded.tif", np.load(files / "coded.npy"))
    cache = tmp_path / "cache"
    cache.mkdir()
    (cache / "keep.txt").write_text("cached")
    over = dict(truth=files / "truth.npy", cache=cache)
    output = {"coded": files / "coded.npy", "mask": files / "mask.npy", "truth": files / "truth.npy",
              "dictionary": files / "d.zarr", "coded-tif": files / "coded.tif", "cache": cache,
              "in-cache": cache / "r.npy", "in-dictionary": files / "d.zarr" / "r.npy",
              "input-folder": files, "parent-of-inputs": tmp_path}[which]
    if which == "coded-tif":
        over["coded"] = files / "coded.tif"
    err = refused(capsys, reconstruct_args(files, tmp_path, output=output, **over), output.name, root=tmp_path)
    assert "input" in err or "folder" in err


@pytest.mark.parametrize("which", ["coded", "mask"])
def test_an_input_given_through_a_symbolic_link_is_still_that_input(files, tmp_path, capsys, which):
    """The link is what the run reads, but the file it points to is what an output there would replace."""
    link = tmp_path / f"link-{which}.npy"
    link.symlink_to(files / f"{which}.npy")
    args = reconstruct_args(files, tmp_path, output=files / f"{which}.npy", **{which: link})
    for overwrite in ([], ["--overwrite"]):
        err = refused(capsys, [*args, *overwrite], f"{which}.npy", root=tmp_path)
        assert "is the input" in err


def test_cacti_file_and_training_video_are_inputs_too(files, tmp_path, capsys):
    from codedvideo.formats.cacti import write_cacti

    mat = tmp_path / "scene.mat"
    write_cacti(mat, mask=np.load(files / "mask.npy"), meas=np.load(files / "coded.npy")[None],
                orig=np.load(files / "truth.npy"))
    refused(capsys, ["reconstruct", "--cacti", mat, "--method", "thinout", "--output", mat], "scene.mat", "input",
            root=tmp_path)
    refused(capsys, ["evaluate", "--recon", files / "truth.npy", "--truth", mat, "--output", mat], "scene.mat",
            root=tmp_path)
    video = tmp_path / "clip.npy"
    np.save(video, np.load(files / "truth.npy"))
    refused(capsys, ["simulate", video, "--frames", N, "--output", tmp_path / "cap", "--cacti-out", video], "clip.npy",
            root=tmp_path)


def test_pipeline_run_never_writes_over_its_config(tmp_path, capsys):
    cfg = tmp_path / "p.yaml"
    cfg.write_text(f"frames: {N}\ndictionary: {{kind: dct}}\nscene: {{size: [{H}, {W}]}}\n"
                   f"cache: {tmp_path / 'cache'}\noutput: {{dir: {tmp_path}, video: p.mp4, frames: none}}\n")
    (tmp_path / "p.mp4").write_text("my video")
    refused(capsys, ["run", cfg], "p.mp4", "--overwrite", root=tmp_path)
    cfg.write_text(cfg.read_text().replace(f"dir: {tmp_path}", f"dir: {tmp_path / 'cache'}"))
    refused(capsys, ["run", cfg], "cache", "input", root=tmp_path)


# ----------------------------------------------------------------------------- what exists at the output
def test_a_folder_of_the_users_is_never_replaced(files, tmp_path, capsys):
    for name in ("mine", "X.npy", "X.zarr"):
        folder = tmp_path / name
        folder.mkdir()
        (folder / "thesis.txt").write_text("years of work")
        refused(capsys, reconstruct_args(files, tmp_path, output=folder), name, "folder", root=tmp_path)
        refused(capsys, reconstruct_args(files, tmp_path, output=folder, overwrite=None) + ["--overwrite"], name,
                root=tmp_path)
    (tmp_path / "noext").write_text("a file without suffix")
    refused(capsys, reconstruct_args(files, tmp_path, output=tmp_path / "noext") + ["--overwrite"], "noext", "a file",
            root=tmp_path)
    refused(capsys, ["train", "--kind", "dct", "--frames", N, "--output", tmp_path / "mine"], "mine", root=tmp_path)


def test_not_a_regular_file_or_folder(files, tmp_path, capsys):
    fifo = tmp_path / "pipe.npy"
    os.mkfifo(fifo)
    refused(capsys, reconstruct_args(files, tmp_path, output=fifo) + ["--overwrite"], "pipe.npy", "FIFO", root=tmp_path)
    link = tmp_path / "link.npy"
    link.symlink_to(files / "truth.npy")
    refused(capsys, reconstruct_args(files, tmp_path, output=link) + ["--overwrite"], "link.npy", "symbolic link",
            root=tmp_path)
    sock = tmp_path / "s.npy"
    with socket.socket(socket.AF_UNIX) as s:
        s.bind(str(sock))
        refused(capsys, reconstruct_args(files, tmp_path, output=sock) + ["--overwrite"], "s.npy", "socket", root=tmp_path)


def test_a_users_file_is_replaced_only_with_overwrite_and_never_when_read_only(files, tmp_path, capsys):
    target = tmp_path / "out" / "r.npy"
    target.parent.mkdir()
    target.write_text("the user's")
    refused(capsys, reconstruct_args(files, tmp_path, output=target), "r.npy", "--overwrite", root=tmp_path)
    assert main(["-q", *map(str, reconstruct_args(files, tmp_path, output=target)), "--overwrite"]) == 0
    assert np.load(target).shape == (N, H, W) and written_by_codedvideo(target)
    target.chmod(0o444)
    refused(capsys, reconstruct_args(files, tmp_path, output=target) + ["--overwrite"], "r.npy", "read-only",
            root=tmp_path)


def test_codedvideo_replaces_its_own_unchanged_outputs_and_not_edited_ones(files, tmp_path, capsys):
    for output in (tmp_path / "o" / "r.npy", tmp_path / "o" / "frames", tmp_path / "o" / "v.zarr"):
        args = [str(x) for x in reconstruct_args(files, tmp_path, output=output)]
        assert main(["-q", *args]) == 0
        assert written_by_codedvideo(output)
        assert main(["-q", *args]) == 0  # a rerun replaces what it wrote
    own = tmp_path / "o" / "r.npy"
    assert record_path(own).is_file()
    own.write_bytes(own.read_bytes()[:-4] + b"edit")  # the user changed it since
    assert not written_by_codedvideo(own)
    refused(capsys, reconstruct_args(files, tmp_path, output=own), "r.npy", "--overwrite", root=tmp_path)


def test_simulate_writes_into_a_folder_but_not_over_the_users_files(tmp_path, capsys):
    cap = tmp_path / "cap"
    cap.mkdir()
    (cap / "notes.txt").write_text("keep")
    args = ["simulate", "synth:default", "--frames", N, "--size", H, W, "--output", cap]
    assert main(["-q", *map(str, args)]) == 0
    assert (cap / "notes.txt").read_text() == "keep" and (cap / "coded.npy").is_file()
    assert main(["-q", *map(str, args)]) == 0  # its own files: replaced
    np.save(cap / "mask.npy", np.zeros(3))  # now the user's
    refused(capsys, args, "mask.npy", "--overwrite", root=tmp_path)


def test_a_file_never_replaces_a_folder_inside_the_writer_either(tmp_path):
    """The last line of defence (io.atomic_output), whatever the caller checked."""
    from codedvideo.formats import io as cio
    from codedvideo.model.errors import OutputError

    folder = tmp_path / "v.npy"
    folder.mkdir()
    (folder / "x").write_text("x")
    with pytest.raises(OutputError, match="folder"):
        cio.write_array(folder, np.zeros(3))
    assert (folder / "x").read_text() == "x" and [p.name for p in tmp_path.iterdir()] == ["v.npy"]


# ----------------------------------------------------------------------------- every option checked before any work
BAD_RECONSTRUCT_OPTIONS = [
    ("--tol-rms", "inf"), ("--tol-rms", "nan"), ("--tol-rms", "-1"), ("--tol-rms", "1e30"), ("--noise-sigma", "inf"), ("--noise-sigma", "-1"),
    ("--noise-sigma", "nan"), ("--max-atoms", "0"), ("--max-atoms", "-1"), ("--static-atoms", "1000"),
    ("--stride", "0"), ("--stride", "9"), ("--batch", "0"), ("--batch", "-1"), ("--workers", "0"), ("--workers", "-1"),
    ("--data-range", "0"), ("--data-range", "-1"), ("--data-range", "nan"), ("--fps", "0"), ("--fps", "-1"),
    ("--tile", "0"), ("--tile", "100000"), ("--white-level", "-3"), ("--scheduler", "not an address"),
    ("--max-atoms", "eight"),
]


@pytest.mark.parametrize("option,value", BAD_RECONSTRUCT_OPTIONS)
def test_every_bad_reconstruct_option_is_one_line_exit_2_nothing_written(files, tmp_path, capsys, option, value):
    for output in ("r.npy", "r.mp4"):
        args = reconstruct_args(files, tmp_path, output=tmp_path / "out" / output) + [option, value]
        refused(capsys, args, option, root=tmp_path)
    assert not (tmp_path / "cache").exists()


@pytest.mark.parametrize("args,option", [
    (["train", "--frames", "0"], "--frames"), (["train", "--frames", N, "--atoms", "0"], "--atoms"),
    (["train", "--frames", N, "--samples", "0"], "--samples"), (["train", "--frames", "65"], "--frames"),
    (["simulate", "synth:default", "--frames", N, "--size", "-1", "64"], "--size"),
    (["simulate", "synth:default", "--frames", N, "--seed", "-1"], "--seed"),
    (["simulate", "synth:default", "--frames", N, "--noise-sigma", "inf"], "--noise-sigma"),
    (["simulate", "synth:default", "--frames", N, "--p", "0"], "--p"),
    (["evaluate", "--recon", "a.npy", "--truth", "b.npy", "--data-range", "0"], "--data-range"),
])
def test_bad_options_of_the_other_commands(tmp_path, capsys, args, option):
    if args[0] in ("train", "simulate"):
        args = args + ["--output", tmp_path / "o"]
    refused(capsys, args, option, root=tmp_path)


def test_unreachable_scheduler_fails_fast_before_any_work(files, tmp_path, capsys):
    with socket.socket() as s:  # a port nobody listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    refused(capsys, reconstruct_args(files, tmp_path) + ["--scheduler", f"tcp://127.0.0.1:{port}"], str(port),
            "cannot connect", root=tmp_path)


@pytest.mark.parametrize("text,names", [
    ("", ["empty"]),
    ("frames: 8\nframes: 4\n", ["duplicate key 'frames'", "line 2"]),
    ("reconstruct: {tile: 64, tile: 32}\n", ["duplicate key 'tile'"]),
    ('frames: "8"\n', ["frames", "integer"]),
    ("frames: true\n", ["frames", "integer"]),
    ("reconstruct: {tol_rms: .inf}\n", ["reconstruct.tol_rms", "finite"]),
    ("noise: {sigma: .nan}\n", ["noise.sigma", "finite"]),
    ("output: {fps: 0}\n", ["output.fps"]),
    ("output: {video: recon.yaml}\n", ["output.video"]),
    ("reconstruct: {scheduler: nowhere}\n", ["reconstruct.scheduler"]),
    ("scene: {size: [3, 64]}\n", ["scene.size"]),
])
def test_strict_pipeline_yaml(tmp_path, capsys, text, names):
    cfg = tmp_path / "p.yaml"
    cfg.write_text(text)
    refused(capsys, ["run", cfg], "p.yaml", *names, root=tmp_path)


def test_run_given_a_folder_or_non_utf8_yaml(tmp_path, capsys):
    refused(capsys, ["run", tmp_path], "not a file", root=tmp_path)
    cfg = tmp_path / "p.yaml"
    cfg.write_bytes(b"frames: 8\n# \xff\xfe\n")
    refused(capsys, ["run", cfg], "p.yaml", "UTF-8", root=tmp_path)


# ----------------------------------------------------------------------------- report, run and simulate
def test_report_refuses_the_users_files_in_its_folder_before_any_work(tmp_path, capsys):
    """`codedvideo report` writes report.html, report.csv, the video and figures into report.dir: a file
    there that codedvideo did not write is refused (with --overwrite: replaced), and a report.dir that is
    a file, or a cache that is a file, is a one-line error, all before any experiment runs."""
    import yaml

    own = tmp_path / "own"
    (own / "figures").mkdir(parents=True)
    (own / "report.html").write_text("my notes")
    (own / "figures" / "fig7.png").write_bytes(b"my figure")
    (tmp_path / "file.txt").write_text("mine")

    def config(name, **change):
        raw = dict(report=dict(dir=str(own), size=[32, 32]), cache=str(tmp_path / "cache"))
        raw["report"].update(change.pop("report", {}))
        raw.update(change)
        path = tmp_path / f"{name}.yaml"
        path.write_text(yaml.safe_dump(raw))
        return str(path)

    err = refused(capsys, ["report", config("a")], "report.html", "--overwrite", root=tmp_path)
    assert "not written by codedvideo" in err
    (own / "report.html").unlink()
    refused(capsys, ["report", config("b")], "fig7.png", root=tmp_path)
    refused(capsys, ["report", config("c", report=dict(dir=str(tmp_path / "file.txt")))], "file.txt", "a file",
            root=tmp_path)
    refused(capsys, ["report", config("d", report=dict(dir=str(tmp_path / "new")), cache=str(tmp_path / "file.txt"))],
            "cache", "file.txt", root=tmp_path)


def test_run_refuses_a_cache_that_is_a_file_before_any_work(tmp_path, capsys):
    """A failed run must not leave files that block the next one: the cache is checked before anything."""
    import yaml

    (tmp_path / "file.txt").write_text("mine")
    path = tmp_path / "p.yaml"
    path.write_text(yaml.safe_dump(dict(cache=str(tmp_path / "file.txt"), output=dict(dir=str(tmp_path / "out")))))
    refused(capsys, ["run", str(path)], "cache", "file.txt", root=tmp_path)


def test_simulate_refuses_an_extra_output_on_top_of_its_own(tmp_path, capsys):
    """--cacti-out where simulate writes its coded image (or any two outputs of one run in one place)."""
    (tmp_path / "d").mkdir()
    for name in ("coded.npy", "mask.npy"):
        refused(capsys, ["simulate", "synth:default", "--size", "16", "16", "--frames", "4", "--output",
                         str(tmp_path / "d"), "--cacti-out", str(tmp_path / "d" / name)], name, "--cacti-out",
                root=tmp_path)


def test_a_run_stopped_after_its_capture_is_written_does_not_block_the_next(tmp_path, capsys, monkeypatch):
    """Each output is codedvideo's as soon as it is in place: a run interrupted (or failing) after writing
    its capture files leaves files that the next run replaces, not the user's files to refuse."""
    import yaml

    from codedvideo.api import _pipeline as pipeline

    cfg = tmp_path / "p.yaml"
    cfg.write_text(yaml.safe_dump(dict(cache=str(tmp_path / "cache"), scene=dict(size=[32, 32]),
                                       output=dict(dir=str(tmp_path / "out"), frames="none"))))

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    with monkeypatch.context() as m:
        m.setattr(pipeline, "write_volume", interrupted)
        assert main(["-q", "run", str(cfg)]) == 130
    assert (tmp_path / "out" / "capture" / "coded.npy").exists()
    capsys.readouterr()
    assert main(["-q", "run", str(cfg)]) == 0, capsys.readouterr().err
    assert written_by_codedvideo(tmp_path / "out" / "recon.npy")


@pytest.mark.parametrize("stop", [KeyboardInterrupt, OSError])
def test_an_output_stopped_before_it_is_in_place_leaves_no_folder_it_made(tmp_path, monkeypatch, stop):
    """Reported: SIGTERM (unwound as Ctrl-C) left the empty folder made for the output behind; a folder that
    was there before stays, and so does one that holds something else."""
    from codedvideo.formats.atomic import atomic_output
    from codedvideo.formats.store import save_dictionary
    from codedvideo.solvers.dictionaries import dct_dictionary

    (tmp_path / "kept").mkdir()
    for target in (tmp_path / "new" / "deeper" / "r.npy", tmp_path / "kept" / "sub" / "r.npy"):
        with pytest.raises((stop, OSError)), atomic_output(target) as tmp:
            np.save(tmp, np.zeros(3))
            raise stop("stopped")
    assert not (tmp_path / "new").exists() and list((tmp_path / "kept").iterdir()) == []
    (tmp_path / "other").mkdir()
    with pytest.raises(KeyboardInterrupt), atomic_output(tmp_path / "other" / "a" / "r.npy"):
        (tmp_path / "other" / "note.txt").write_text("the user's")
        raise KeyboardInterrupt
    assert sorted(p.name for p in (tmp_path / "other").iterdir()) == ["note.txt"]

    def stopped(*args, **kwargs):
        raise KeyboardInterrupt

    import zarr
    monkeypatch.setattr(zarr, "open_group", stopped)
    with pytest.raises(KeyboardInterrupt):
        save_dictionary(tmp_path / "dicts" / "d.zarr", dct_dictionary(4), dict(patch=7, frames=4))
    assert not (tmp_path / "dicts").exists()
