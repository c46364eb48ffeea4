"""Bad input: one line on stderr naming the file and the problem, exit status 2, nothing written.

tests/test_io.py and tests/test_cacti.py already cover the readers of every format; this file covers what
they do not: the command line end to end (exit status, one line, no output left), the dictionary store,
the remaining formats (JPEG, multi-part EXR, AVI, a folder with one broken frame), pipeline.yaml, missing
inputs and outputs that cannot be written.
"""
import os
from pathlib import Path

import numpy as np
import pytest

import codedvideo as cv
from codedvideo.formats import io as cio
from codedvideo.app.cli import main
from codedvideo.solvers.dictionaries import dct_dictionary
from codedvideo.model.errors import InputError
from codedvideo.model.physics import simulate
from codedvideo.formats.volumes import read_volume, write_volume
from codedvideo.formats.store import load_dictionary, save_dictionary

from cli_inputs import N, H, W, fails, files_under, reconstruct_args  # noqa: F401  (files: conftest.py)


def test_the_valid_inputs_work(files, tmp_path, capsys):
    assert main(["-q", *map(str, reconstruct_args(files, tmp_path, truth=files / "truth.npy"))]) == 0
    assert (tmp_path / "out" / "r.npy").exists() and (tmp_path / "out" / "r.metrics.json").exists()


# ----------------------------------------------------------------------------- NaN / Inf in the coded image
@pytest.mark.parametrize("name,bad", [("c.npy", np.inf), ("c.npy", -np.inf), ("c.tif", np.nan), ("c.exr", np.inf)])
def test_nan_or_inf_in_the_coded_image(files, tmp_path, capsys, name, bad):
    coded = np.load(files / "coded.npy")
    coded[3, 4] = bad
    path = files / name
    np.save(path, coded) if name.endswith(".npy") else cio.write_image(path, coded, dtype=np.float32)
    err = fails(capsys, reconstruct_args(files, tmp_path, coded=path), name, "NaN or Inf", root=tmp_path)
    assert not (tmp_path / "cache").exists()  # refused before any work


# ----------------------------------------------------------------------------- mask / image disagreements
@pytest.mark.parametrize("kind", ["transposed", "channels-last", "other-size", "2d", "4d"])
def test_mask_and_image_shapes_disagree(files, tmp_path, capsys, kind):
    mask = np.load(files / "mask.npy")
    bad = dict(transposed=mask.transpose(0, 2, 1), **{"channels-last": np.moveaxis(mask, 0, -1)},
               **{"other-size": mask[:, :-1]}, **{"2d": mask[0]}, **{"4d": np.stack([mask, mask])})[kind]  # 4d: two masks, one image
    np.save(files / "bad_mask.npy", bad)
    fails(capsys, reconstruct_args(files, tmp_path, mask=files / "bad_mask.npy"), "bad_mask.npy", root=tmp_path)


@pytest.mark.parametrize("scale,what", [(255, "[255"), (1.5, "1.5"), (-1, "-1")])  # 0.5: a calibrated mask
def test_non_binary_mask(files, tmp_path, capsys, scale, what):
    mask = np.load(files / "mask.npy").astype(np.float32) * scale
    np.save(files / "grey.npy", mask)
    err = fails(capsys, reconstruct_args(files, tmp_path, mask=files / "grey.npy"), "grey.npy", "outside [0, 1]",
                root=tmp_path)
    assert what in err  # names an offending value


def test_a_mask_tiff_of_0_and_255_is_the_binary_code(files, tmp_path, capsys):
    """Mask images are read as a fraction of full scale (as scikit-image reads images): 255 is an open shutter."""
    cio.write_multipage_tiff(files / "m255.tif", np.load(files / "mask.npy") * 255)
    runs = {}
    for name, mask in (("npy", files / "mask.npy"), ("tif", files / "m255.tif")):
        args = reconstruct_args(files, tmp_path / name, mask=mask)
        capsys.readouterr()
        assert main(["-q", *map(str, args)]) == 0, capsys.readouterr().err
        runs[name] = np.load(tmp_path / name / "out" / "r.npy")
    assert np.array_equal(runs["npy"], runs["tif"])


def test_a_mask_tiff_of_0_and_1_is_refused_naming_its_full_scale(files, tmp_path, capsys):
    cio.write_multipage_tiff(files / "m01.tif", np.load(files / "mask.npy"))
    fails(capsys, reconstruct_args(files, tmp_path, mask=files / "m01.tif"), "m01.tif", "full scale 255",
          root=tmp_path)


def test_a_16_bit_mask_image_of_0_and_255_is_refused_naming_its_peak(files, tmp_path, capsys):
    """An 8-bit binary mask saved into 16-bit images holds 0 and 255 of 65535: every shutter would read as open
    0.4 %, and the result was noise (-35 dB) with no word."""
    cio.write_multipage_tiff(files / "m255_16.tif", (np.load(files / "mask.npy") * 255).astype(np.uint16))
    err = fails(capsys, reconstruct_args(files, tmp_path, mask=files / "m255_16.tif"), "m255_16.tif",
                "reach only 255 of the image's full scale 65535", root=tmp_path)
    assert "0 and 65535" in err


def test_mask_never_open_anywhere(files, tmp_path, capsys):
    np.save(files / "zeros.npy", np.zeros((N, H, W), np.uint8))
    fails(capsys, reconstruct_args(files, tmp_path, mask=files / "zeros.npy"), "zeros.npy", "ever open", root=tmp_path)


def test_every_pixel_saturated(files, tmp_path, capsys):
    fails(capsys, [*reconstruct_args(files, tmp_path), "--white-level", "0.001"], "coded.npy", "white-level",
          root=tmp_path)


@pytest.mark.parametrize("shape", [(1, W), (H, 1), (6, 6)])
def test_coded_image_smaller_than_a_patch_names_the_file(files, tmp_path, capsys, shape):
    """One-pixel strips and anything under 7x7 are refused: no patch fits (see README, Guarantees)."""
    np.save(files / "tiny.npy", np.ones(shape, np.float32))
    mask = np.zeros((N, *shape), np.uint8)
    mask[0] = 1
    np.save(files / "tiny_mask.npy", mask)
    fails(capsys, reconstruct_args(files, tmp_path, coded=files / "tiny.npy", mask=files / "tiny_mask.npy"),
          "tiny.npy", "smaller than one 7x7 patch", root=tmp_path)


# ----------------------------------------------------------------------------- dictionaries
def test_dictionary_for_another_n(files, tmp_path, capsys):
    save_dictionary(files / "d8.zarr", dct_dictionary(8), dict(patch=7, frames=8))
    fails(capsys, reconstruct_args(files, tmp_path, dictionary=files / "d8.zarr"), "d8.zarr", "N = 8", root=tmp_path)


def test_dictionary_for_another_patch_size(files, tmp_path, capsys):
    save_dictionary(files / "p5.zarr", np.eye(N * 25, dtype=np.float32), dict(patch=5, frames=N))
    fails(capsys, reconstruct_args(files, tmp_path, dictionary=files / "p5.zarr"), "p5.zarr", "patch size 5",
          root=tmp_path)


def _atoms_chunk(store: Path) -> Path:
    return next(p for p in (store / "atoms").rglob("*") if p.is_file() and p.name != "zarr.json")


@pytest.mark.parametrize("damage", ["truncated-chunk", "flipped-bytes", "no-chunk", "bad-metadata", "not-a-dictionary"])
def test_corrupt_dictionary_store(files, tmp_path, capsys, damage):
    store = files / "d.zarr"
    if damage == "truncated-chunk":
        chunk = _atoms_chunk(store)
        chunk.write_bytes(chunk.read_bytes()[: chunk.stat().st_size // 2])
    elif damage == "flipped-bytes":
        chunk = _atoms_chunk(store)
        data = bytearray(chunk.read_bytes())
        data[len(data) // 2 : len(data) // 2 + 8] = bytes(8)
        chunk.write_bytes(bytes(data))
    elif damage == "no-chunk":
        _atoms_chunk(store).unlink()
    elif damage == "bad-metadata":
        (store / "zarr.json").write_text("{ not json")
    else:
        write_volume(np.zeros((N, 8, 8), np.float32), files / "plain.zarr")
        store = files / "plain.zarr"
    with pytest.raises(InputError) as info:
        load_dictionary(store)
    assert store.name in str(info.value) and "\n" not in str(info.value)
    fails(capsys, reconstruct_args(files, tmp_path, dictionary=store), store.name, root=tmp_path)


def test_dictionary_with_nan_atoms(files, tmp_path, capsys):
    D = dct_dictionary(N)
    D[:, 5] = np.nan
    save_dictionary(files / "nan.zarr", D, dict(patch=7, frames=N))
    fails(capsys, reconstruct_args(files, tmp_path, dictionary=files / "nan.zarr"), "nan.zarr", "NaN", root=tmp_path)


# ----------------------------------------------------------------------------- formats test_io does not cut
def _cut(path: Path, frac: float) -> Path:
    data = path.read_bytes()
    out = path.with_name(f"cut_{path.name}")
    out.write_bytes(data[: max(int(len(data) * frac), 1)])
    return out


@pytest.mark.parametrize("frac", [0.02, 0.5, 0.9])
def test_truncated_jpeg_multipart_exr_and_avi(tmp_path, frac):
    import OpenImageIO as oiio

    yy, xx = np.mgrid[0:21, 0:31]
    frames = np.stack([128 + 60 * np.sin((xx + 2 * t) / 5.0) * np.cos(yy / 7.0) for t in range(5)]).astype(np.float32)
    jpg = tmp_path / "i.jpg"
    out = oiio.ImageOutput.create(str(jpg))
    out.open(str(jpg), oiio.ImageSpec(31, 21, 1, "uint8"))
    out.write_image(np.rint(frames[0]).astype(np.uint8)[..., None])
    out.close()
    cio.write_stack(tmp_path / "s.exr", frames)
    write_volume(frames, tmp_path / "v.avi")
    for path, read in ((jpg, cio.read_image), (tmp_path / "s.exr", cio.read_stack), (tmp_path / "v.avi", read_volume)):
        cut = _cut(path, frac)
        with pytest.raises(InputError) as info:
            read(cut)
        assert cut.name in str(info.value) and "\n" not in str(info.value)


def test_folder_of_frames_with_one_truncated_frame(files, tmp_path, capsys):
    mask = np.load(files / "mask.npy")
    (files / "maskframes").mkdir()
    for t, frame in enumerate(mask):
        cio.write_image(files / "maskframes" / f"m_{t}.png", frame)
    broken = files / "maskframes" / "m_2.png"
    broken.write_bytes(broken.read_bytes()[:40])
    fails(capsys, reconstruct_args(files, tmp_path, mask=files / "maskframes"), "m_2.png", root=tmp_path)


@pytest.mark.parametrize("frac", [0.3, 0.5, 0.7, 0.9])
def test_truncated_mask_tiff_through_the_cli(files, tmp_path, capsys, frac):
    """A multi-page TIFF cut between pages used to read as a shorter stack (then blamed on the dictionary's N)."""
    cio.write_multipage_tiff(files / "m.tif", np.load(files / "mask.npy"))
    cut = _cut(files / "m.tif", frac)
    fails(capsys, reconstruct_args(files, tmp_path, mask=cut), cut.name, "truncated", root=tmp_path)


# ----------------------------------------------------------------------------- pipeline.yaml
@pytest.mark.parametrize("text,names", [
    ("frame: 8\n", ["frame", "unknown key"]),                                    # mistyped top-level key
    ("noise: {sgima: 3}\n", ["noise.sgima", "unknown key"]),                     # mistyped nested key
    ("reconstruct: {max_atom: 8}\n", ["reconstruct.max_atom", "unknown key"]),
    ("frames: eight\n", ["frames", "integer"]),                                 # wrong type
    ("frames: 65\n", ["frames", "64"]),                                         # out of range
    ("code: {name: hitomy}\n", ["code.name", "hitomi"]),                        # not one of the choices
    ("code: {name: file}\n", ["code", "path"]),                                 # a rule between keys
    ("stages: [train, recontruct]\n", ["stages", "reconstruct"]),
    ("frames: [8\n", ["not valid YAML"]),                                       # broken YAML
    ("- frames\n- 8\n", ["mapping"]),                                           # not a mapping
    ("stages: [simulate, evaluate]\n", ["stages", "add reconstruct"]),          # evaluate without a reconstruction
    ("cache: ''\n", ["cache", "name a folder"]),                                 # entries among the user's files
    ("dictionary: {atoms: 1000, samples: 500}\n", ["atoms 1000", "samples 500", "608"]),
    ("report: {speed_atoms: [5000], dictionary: {samples: 2000}}\n", ["report.speed_atoms", "4608", "2000"]),
])
def test_bad_pipeline_yaml(tmp_path, capsys, text, names):
    cfg = tmp_path / "p.yaml"
    cfg.write_text(text + "output: {dir: " + str(tmp_path / "runout") + "}\n" if not text.startswith("-") else text)
    fails(capsys, ["run", cfg], "p.yaml", *names, root=tmp_path)
    assert not (tmp_path / "runout").exists()


# ----------------------------------------------------------------------------- missing inputs
@pytest.mark.parametrize("which", ["coded", "mask", "dictionary", "truth"])
def test_missing_reconstruct_inputs(files, tmp_path, capsys, which):
    missing = files / f"absent_{which}.npy"
    if which == "dictionary":
        missing = files / "absent.zarr"
    err = fails(capsys, reconstruct_args(files, tmp_path, **{which: missing}), missing.name, root=tmp_path)
    assert "no such file" in err


def test_missing_config_video_and_training_video(tmp_path, capsys):
    fails(capsys, ["run", tmp_path / "absent.yaml"], "absent.yaml", "no such file", root=tmp_path)
    fails(capsys, ["simulate", tmp_path / "absent.mkv", "--frames", N, "--output", tmp_path / "cap"], "absent.mkv",
          root=tmp_path)
    fails(capsys, ["train", tmp_path / "absent.mp4", "--frames", N, "--output", tmp_path / "d.zarr", "--iterations", 1,
                   "--cache", tmp_path / "cache"], "absent.mp4", root=tmp_path)
    fails(capsys, ["evaluate", "--recon", tmp_path / "absent.npy", "--truth", tmp_path / "absent2.npy"], "absent.npy",
          root=tmp_path)


# ----------------------------------------------------------------------------- outputs that cannot be written
def test_output_under_a_file(files, tmp_path, capsys):
    (tmp_path / "afile").write_text("x")
    for output in ("afile/r.npy", "afile/deeper/r.mkv", "afile/frames"):
        fails(capsys, reconstruct_args(files, tmp_path, output=tmp_path / output), output.split("/")[0], root=tmp_path)
    assert not (tmp_path / "cache").exists()  # refused before any work, not after the reconstruction
    fails(capsys, reconstruct_args(files, tmp_path, cache=tmp_path / "afile" / "cache"), "afile", root=tmp_path)
    fails(capsys, ["train", "--kind", "dct", "--frames", N, "--output", tmp_path / "afile" / "d.zarr"], "afile",
          root=tmp_path)
    fails(capsys, ["simulate", "synth:default", "--frames", N, "--size", H, W, "--output", tmp_path / "afile" / "cap"],
          "afile", root=tmp_path)
    fails(capsys, ["evaluate", "--recon", files / "truth.npy", "--truth", files / "truth.npy", "--output",
                   tmp_path / "afile" / "e.json"], "afile", root=tmp_path)
    cfg = tmp_path / "p.yaml"
    cfg.write_text(f"frames: {N}\ndictionary: {{kind: dct}}\nscene: {{size: [{H}, {W}]}}\n"
                   f"cache: {tmp_path / 'cache'}\noutput: {{dir: {tmp_path / 'afile' / 'run'}}}\n")
    fails(capsys, ["run", cfg], "afile", root=tmp_path)


def test_unknown_output_format_is_refused_before_the_work(files, tmp_path, capsys):
    fails(capsys, reconstruct_args(files, tmp_path, output=tmp_path / "out" / "r.xyz"), "r.xyz", "unknown format",
          root=tmp_path)
    assert not (tmp_path / "cache").exists()


def test_read_only_output_folder(files, tmp_path, capsys):
    """Root writes into read-only folders, and CI runs as root: there the CLI runs in a process without the
    capability to override file permissions (util-linux setpriv), as any other user would be."""
    import shutil
    import subprocess
    import sys

    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o555)
    args = reconstruct_args(files, tmp_path, output=ro / "r.npy")
    try:
        if os.geteuid() != 0:
            fails(capsys, args, "ro", "not writable", root=tmp_path)
            return
        assert shutil.which("setpriv"), "setpriv (util-linux) is needed to test permissions as root"
        before = files_under(tmp_path)
        done = subprocess.run(["setpriv", "--bounding-set=-dac_override,-dac_read_search", "--inh-caps=-all", "--",
                               sys.executable, "-m", "codedvideo.app.cli", "-q", *map(str, args)],
                              capture_output=True, text=True)
        err = done.stderr.strip()
        assert done.returncode == 2 and len(err.splitlines()) == 1, err
        assert str(ro) in err and "not writable" in err, err
        assert files_under(tmp_path) == before
    finally:
        ro.chmod(0o755)


def test_read_only_folder_through_os_access(files, tmp_path, capsys, monkeypatch):
    """The same check as a read-only folder, also where the tests run as root (os.access is what is asked)."""
    ro = tmp_path / "ro"
    ro.mkdir()
    real = os.access
    monkeypatch.setattr(os, "access", lambda p, mode, **kw: False if Path(p) == ro else real(p, mode, **kw))
    fails(capsys, reconstruct_args(files, tmp_path, output=ro / "r.npy"), "ro", "not writable", root=tmp_path)


def test_write_failure_midway_leaves_the_old_output_and_no_temporary(files, tmp_path, monkeypatch):
    """A disk-full style OSError inside a writer: a one-line OutputError, the old file intact, no temporary."""
    from codedvideo.model.errors import OutputError

    target = tmp_path / "out" / "r.npy"
    cio.write_array(target, np.arange(3))

    def full(fh, arr, **kw):
        fh.write(b"partial")
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(np, "save", full)
    with pytest.raises(OutputError, match="No space left on device") as info:
        cio.write_array(target, np.zeros(5))
    assert "r.npy" in str(info.value)
    monkeypatch.undo()
    np.testing.assert_array_equal(np.load(target), np.arange(3))
    assert sorted(p.name for p in target.parent.iterdir()) == ["r.npy"]


def test_an_npz_archive_named_npy(files, tmp_path, capsys):
    np.savez(tmp_path / "coded.npz", coded=np.load(files / "coded.npy"))
    os.replace(tmp_path / "coded.npz", tmp_path / "coded.npy")
    fails(capsys, reconstruct_args(files, tmp_path, coded=tmp_path / "coded.npy"), "coded.npy", ".npz", root=tmp_path)


@pytest.mark.parametrize("which,shape", [("coded", (0, H, W)), ("coded", (H, 0)), ("coded", (3, 0, W)),
                                         ("mask", (N, H, 0)), ("truth", (0, H, W))])
def test_an_empty_array_is_one_line_naming_it(files, tmp_path, capsys, which, shape):
    empty = tmp_path / f"empty-{which}.npy"
    np.save(empty, np.zeros(shape, np.uint8 if which == "mask" else np.float32))
    fails(capsys, reconstruct_args(files, tmp_path, **{which: empty}), empty.name, "holds no values", root=tmp_path)
    if which == "truth":
        fails(capsys, ["evaluate", "--recon", empty, "--truth", empty], empty.name, "holds no values", root=tmp_path)


def test_a_gif_faster_than_its_hundredths_of_a_second_is_refused_before_any_work(files, tmp_path, capsys):
    fails(capsys, [*reconstruct_args(files, tmp_path, output=tmp_path / "v.gif"), "--fps", 200], "--fps 200",
          "v.gif", "hundredths", root=tmp_path)
    cfg = tmp_path / "p.yaml"
    cfg.write_text(f"cache: {tmp_path / 'cache'}\noutput: {{dir: {tmp_path / 'out'}, video: r.gif, fps: 120}}\n")
    fails(capsys, ["run", cfg], "p.yaml", "fps 120", "hundredths", root=tmp_path)


def test_a_dictionary_with_more_atoms_than_its_samples_can_give_is_refused_before_training(tmp_path, capsys):
    fails(capsys, ["train", "--frames", 8, "--atoms", 1000, "--samples", 500, "--output", tmp_path / "d.zarr",
                   "--cache", tmp_path / "cache"], "atoms 1000", "samples 500", root=tmp_path)
    fails(capsys, ["train", "--kind", "dct", "--frames", 8, "--output", tmp_path / "d.zarr", "--cache", ""], "--cache",
          root=tmp_path)


def test_training_options_given_to_a_dct_dictionary_are_refused_not_ignored(tmp_path, capsys):
    fails(capsys, ["train", "--kind", "dct", "--frames", 8, "--atoms", 5, "--output", tmp_path / "d.zarr"],
          "--kind dct", "--atoms is for learned", root=tmp_path)
    assert main(["-q", "train", "--kind", "dct", "--frames", "4", "--output", str(tmp_path / "d.zarr"), "--cache",
                 str(tmp_path / "cache")]) == 0


def test_learning_more_atoms_than_its_samples_can_give_is_one_line_from_the_api_too():
    """(The report's dictionaries, and any caller that builds its settings without the config model.)"""
    from codedvideo.solvers.dictionaries import KsvdSettings, learn_dictionary
    from codedvideo.model.errors import InputError

    video = np.random.default_rng(0).uniform(0, 255, (4, 16, 16)).astype(np.float32)
    with pytest.raises(InputError, match="other 300 among the training patches, but only 200 were drawn"):
        learn_dictionary([video], frames=4, settings=KsvdSettings(atoms=4 * 49 + 300, samples=200, iterations=1))


def test_a_calibrated_code_for_a_cacti_file_is_refused_before_anything_is_written(tmp_path, capsys):
    """(The capture files were written, then the CACTI file refused the mask.)"""
    np.save(tmp_path / "cal.npy", np.random.default_rng(0).uniform(0, 1, (N, H, W)).astype(np.float32))
    fails(capsys, ["simulate", "synth:default", "--frames", N, "--size", H, W, "--code", "file", "--code-file",
                   tmp_path / "cal.npy", "--cacti-out", tmp_path / "c.mat", "--output", tmp_path / "cap"],
          "c.mat", "cal.npy", "calibrated", root=tmp_path)


def test_one_saturated_capture_of_a_raw_stack_is_named_not_all_of_them(files, tmp_path, capsys):
    """A flash in capture 3 of 4: the error said every pixel of the coded image was saturated."""
    coded = np.rint(np.load(files / "coded.npy"))  # (raw counts are whole numbers)
    np.save(tmp_path / "stack.npy", np.stack([coded, coded, np.full_like(coded, 4095.0), coded]))
    fails(capsys, [*reconstruct_args(files, tmp_path, coded=tmp_path / "stack.npy"), "--bits", 12],
          "stack.npy, capture 3 of 4", root=tmp_path)


def test_one_blown_out_capture_of_a_stream_is_said_and_the_rest_go_on(files, tmp_path, capsys):
    """With --white-level a capture saturated everywhere stopped the whole stack; it is now its clipped values."""
    coded = np.load(files / "coded.npy")
    np.save(tmp_path / "stack.npy", np.stack([coded, coded, np.full_like(coded, 4000.0), coded]))
    out = tmp_path / "out" / "r.npy"
    with pytest.warns(UserWarning, match="stack.npy, capture 3 of 4: every measured pixel is at or above"):
        assert main(["-q", *map(str, reconstruct_args(files, tmp_path, coded=tmp_path / "stack.npy", output=out)),
                     "--white-level", "3000", "--data-range", "255", "--independent-captures"]) == 0
    video = np.load(out)
    assert video.shape[0] == 4 * N and np.isfinite(video).all()
    alone = tmp_path / "alone.npy"
    assert main(["-q", *map(str, reconstruct_args(files, tmp_path, output=alone)), "--white-level", "3000",
                 "--data-range", "255"]) == 0
    np.testing.assert_array_equal(video[:N], np.load(alone))  # the other captures as they are alone


def test_a_code_that_opens_nothing_is_refused_before_anything_is_written(tmp_path, capsys):
    """(--p 1e-9 wrote an all-zero mask that codes check and reconstruct then refused.)"""
    fails(capsys, ["simulate", "synth:default", "--frames", N, "--size", H, W, "--code", "bernoulli", "--p", 1e-9,
                   "--output", tmp_path / "cap"], "bernoulli", "opens no pixel", root=tmp_path)


@pytest.mark.parametrize("options,names", [
    (["--code", "bernoulli", "--bump", 3], ["--bump 3", "bernoulli"]),   # bernoulli has no bump
    (["--p", 0.3], ["--p 0.3", "hitomi"]),                                # hitomi has no open probability
    (["--gain", 3], ["--gain", "--shot-noise"]),                          # the sensor of the shot noise only
])
def test_simulate_options_its_code_or_sensor_would_ignore_are_refused(tmp_path, capsys, options, names):
    fails(capsys, ["simulate", "synth:default", "--frames", N, "--size", H, W, *options, "--output", tmp_path / "c"],
          *names, root=tmp_path)


def test_options_that_do_not_go_together_are_one_line(files, tmp_path, capsys):
    """A dictionary for a method that has none, and --code file without its file: one line each, naming
    the options as the command line spells them, before any work."""
    fails(capsys, [*reconstruct_args(files, tmp_path), "--method", "gaptv"], "--dictionary", "gaptv", root=tmp_path)
    fails(capsys, ["simulate", "synth:default", "--size", 16, 16, "--frames", 4, "--code", "file", "--output",
                   tmp_path / "s"], "--code-file", root=tmp_path)


def test_a_synthetic_sequence_past_the_free_memory_is_refused_before_any_work(tmp_path, capsys):
    """A synthetic scene is made whole in memory: asking for more captures than fit is one line, at once."""
    fails(capsys, ["simulate", "synth:default", "--size", 2048, 2048, "--frames", 32, "--captures", 100000,
                   "--output", tmp_path / "s"], "--captures", "GiB", root=tmp_path)


def test_a_config_with_no_stage_is_refused(tmp_path, capsys):
    """stages: [] would run nothing and write an empty metrics file: the key is named, nothing written."""
    (tmp_path / "p.yaml").write_text(f"stages: []\noutput: {{dir: {tmp_path / 'out'}}}\n")
    fails(capsys, ["run", tmp_path / "p.yaml"], "stages", root=tmp_path)


def test_outputs_named_for_another_format_and_captures_with_no_positive_value(files, tmp_path, capsys):
    """A dictionary named .npy (it is a Zarr store), scores named .npy (they are JSON), and a coded image
    with no value above 0 (a sum of frames never is): one line each, nothing written."""
    fails(capsys, ["train", "--kind", "dct", "--frames", N, "--output", tmp_path / "d.npy"], "d.npy", ".zarr",
          root=tmp_path)
    np.save(tmp_path / "t.npy", np.zeros((N, H, W), np.float32))
    fails(capsys, ["evaluate", "--recon", tmp_path / "t.npy", "--truth", tmp_path / "t.npy", "--output",
                   tmp_path / "s.npy"], "s.npy", "JSON", root=tmp_path)
    np.save(tmp_path / "neg.npy", -np.abs(np.load(files / "coded.npy")) - 1)
    fails(capsys, reconstruct_args(files, tmp_path, coded=tmp_path / "neg.npy"), "neg.npy", "above 0",
          root=tmp_path)


def test_dotted_dictionary_folders_and_dark_captures_with_a_data_range_still_work(tmp_path, capsys):
    """The checks above refuse file formats, not folder names with dots; and a capture dark everywhere is
    reconstructed when its data range is given."""
    assert main(["-q", "train", "--kind", "dct", "--frames", "4", "--output", str(tmp_path / "dict-v1.5")]) == 0
    np.save(tmp_path / "dark.npy", np.zeros((16, 16), np.float32))
    np.save(tmp_path / "m.npy", np.ones((4, 16, 16), np.uint8))
    assert main(["-q", "reconstruct", "--coded", str(tmp_path / "dark.npy"), "--mask", str(tmp_path / "m.npy"),
                 "--method", "dct", "--data-range", "255", "--output", str(tmp_path / "r.npy"), "--cache",
                 str(tmp_path / "cache")]) == 0
    dark = np.load(tmp_path / "r.npy")
    assert dark.shape == (4, 16, 16) and np.abs(dark).max() < 1e-3  # it measured nothing: every frame is dark
    D, _ = load_dictionary(tmp_path / "dict-v1.5")
    assert D.shape[0] == 4 * 49  # the dotted folder is the N = 4 dictionary store it was written as


def test_a_colour_npy_is_read_as_its_luma_like_a_colour_image(files, tmp_path, capsys):
    """(H, W, 3) in a .npy is a colour image (a stack of images 3 pixels wide is narrower than any patch)."""
    coded = np.load(files / "coded.npy")
    np.save(tmp_path / "colour-coded.npy", np.stack([coded, coded, coded], axis=-1))
    for name, c in (("grey", files / "coded.npy"), ("colour", tmp_path / "colour-coded.npy")):
        assert main(["-q", *map(str, reconstruct_args(files, tmp_path, coded=c, output=tmp_path / f"{name}.npy"))]) == 0
    np.testing.assert_array_equal(np.load(tmp_path / "grey.npy"), np.load(tmp_path / "colour.npy"))


def test_color_channels_on_a_grey_coded_image_is_refused(files, tmp_path, capsys):
    """Reported: it wrote a one-channel "colour" result (1, N, H, W) without a word."""
    fails(capsys, [*reconstruct_args(files, tmp_path), "--color", "channels"], "coded.npy", "one channel",
          root=tmp_path / "out")


def test_dictionary_records_that_do_not_fit_are_named_plainly(tmp_path):
    """A store whose record says frames '8' (a string) was refused as 'built for N = 8, the mask has N = 8'; one
    whose atoms have the wrong rows was refused without its file; training's --init spoke of a mask."""
    from codedvideo.formats.store import check_dictionary

    with pytest.raises(cv.InputError, match=r"d.zarr: its record's frames '8' is not a whole number"):
        check_dictionary(dict(patch=7, frames="8"), 8, tmp_path / "d.zarr")
    with pytest.raises(cv.InputError, match=r"d.zarr: atoms of 300 rows; N = 8 needs N x 49 = 392"):
        check_dictionary(dict(patch=7, frames=8), 8, tmp_path / "d.zarr", np.zeros((300, 4), np.float32))
    with pytest.raises(cv.InputError, match=r"built for N = 16 sub-frames, training for N = 8"):
        check_dictionary(dict(patch=7, frames=16), 8, tmp_path / "d.zarr", needs="training for")
