"""`codedvideo run CONFIG` with a user's own files: every input checked before training, a user's video
taken whole unless a crop is asked for, and config keys a setting would ignore refused."""
import json

import numpy as np
import pytest

from codedvideo.app.cli import main
from codedvideo.data.synth import make_scene
from cli_inputs import fails


@pytest.fixture
def user_video(tmp_path):
    path = tmp_path / "mine.npy"
    np.save(path, make_scene("coins-translate", frames=12, size=(30, 41)))
    return path


def run(tmp_path, capsys, text: str):
    cfg = tmp_path / "p.yaml"
    cfg.write_text(text)
    capsys.readouterr()
    rc = main(["-q", "run", str(cfg)])
    return rc, capsys.readouterr().err.strip()


def test_a_missing_scene_or_code_file_ends_the_run_before_training(tmp_path, capsys, user_video):
    common = (f"frames: 4\ncache: {tmp_path / 'cache'}\noutput: {{dir: {tmp_path / 'out'}, frames: none}}\n"
              f"dictionary: {{atoms: 64, samples: 3000, iterations: 2, training: [{user_video}]}}\n")
    for extra, name in ((f"scene: {{video: {tmp_path / 'nothere.npy'}}}\n", "nothere.npy"),
                        (f"scene: {{video: {user_video}}}\ncode: {{name: file, path: {tmp_path / 'nomask.npy'}}}\n",
                         "nomask.npy")):
        rc, err = run(tmp_path, capsys, common + extra)
        assert rc == 2 and name in err and len(err.splitlines()) == 1, err
        # before: K-SVD ran to the end (and its dictionary was cached) before the file was found missing
        assert not list((tmp_path / "cache").glob("dict-*")), list((tmp_path / "cache").iterdir())


def test_a_user_video_is_taken_whole_unless_a_size_is_given(tmp_path, capsys, user_video):
    base = (f"frames: 4\ncache: {tmp_path / 'cache'}\ndictionary: {{kind: dct}}\nreconstruct: {{tile: 32}}\n")
    rc, err = run(tmp_path, capsys, base + f"scene: {{video: {user_video}}}\n"
                                          f"output: {{dir: {tmp_path / 'whole'}, frames: none}}\n")
    assert rc == 0, err
    assert np.load(tmp_path / "whole" / "recon.npy").shape == (4, 30, 41)  # before: cropped to 256x256 (or refused)
    rc, err = run(tmp_path, capsys, base + f"scene: {{video: {user_video}, size: [24, 24]}}\n"
                                          f"output: {{dir: {tmp_path / 'crop'}, frames: none}}\n")
    assert rc == 0, err
    assert np.load(tmp_path / "crop" / "recon.npy").shape == (4, 24, 24)
    metrics = json.loads((tmp_path / "crop" / "recon.metrics.json").read_text())
    assert metrics["config"]["scene"]["size"] == [24, 24]


@pytest.mark.parametrize("section, names", [
    ("code: {name: hitomi, p: 0.3}", ["code.p", "hitomi"]),
    ("code: {name: bernoulli, bump: 3}", ["code.bump", "bernoulli"]),
    ("noise: {gain: 0.01, full_well: 10}", ["noise.full_well", "noise.gain", "shot_noise"]),
    ("dictionary: {path: mine.zarr, atoms: 1024}", ["dictionary.path", "dictionary.atoms"]),
    ("dictionary: {training: [mine.npy], max_speed: 8.0}", ["dictionary.max_speed", "synth:train"]),
])
def test_config_values_the_run_would_ignore_are_refused(tmp_path, capsys, section, names):
    """Before: each ran to the end exactly as with the defaults (the command line already refused them)."""
    rc, err = run(tmp_path, capsys, f"frames: 4\n{section}\noutput: {{dir: {tmp_path / 'out'}}}\n")
    assert rc == 2 and len(err.splitlines()) == 1, err
    for name in names:
        assert name in err, err
    assert not (tmp_path / "out").exists()


def test_defaults_listed_beside_a_setting_that_ignores_them_are_accepted(tmp_path):
    """pipeline.yaml lists every key with its default: switching the code or the training set alone runs."""
    from codedvideo.engine.config import PipelineConfig

    from pydantic import ValidationError

    accepted = dict(code=dict(name="bernoulli", bump=2, p=0.3), noise=dict(full_well=20000.0, gain=10.0),
                    dictionary=dict(training=["mine.npy"], clips=144, max_speed=4.0))
    PipelineConfig.model_validate(accepted)
    # the same keys at any other value are refused: the defaults pass because they are the defaults
    for section, key, other in [("code", "bump", 3), ("noise", "gain", 5.0), ("dictionary", "max_speed", 8.0)]:
        changed = {k: dict(v) for k, v in accepted.items()}
        changed[section][key] = other
        with pytest.raises(ValidationError, match=f"{section}.{key}"):
            PipelineConfig.model_validate(changed)


def test_train_refuses_max_speed_for_user_videos(tmp_path, capsys, user_video):
    capsys.readouterr()
    rc = main(["-q", "train", "--frames", "4", "--max-speed", "1", "--output", str(tmp_path / "d.zarr"),
               "--cache", str(tmp_path / "cache"), str(user_video)])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and "--max-speed" in err and len(err.splitlines()) == 1, err
    assert not (tmp_path / "cache").exists() or not list((tmp_path / "cache").glob("dict-*"))


def test_make_targets_take_a_config_path_with_a_space(tmp_path):
    """Reported: `make run CONFIG="my config.yaml"` split the path ("unrecognized arguments: config.yaml")."""
    import subprocess
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    folder = tmp_path / "my configs"
    folder.mkdir()
    cfg = folder / "my config.yaml"
    cfg.write_text(f"frames: 4\nscene: {{video: synth:default, size: [24, 24]}}\n"
                   f"output: {{dir: '{tmp_path / 'out dir'}'}}\n")
    proc = subprocess.run(["make", "-s", "simulate", f"CONFIG={cfg}"], cwd=root, capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    assert (tmp_path / "out dir" / "capture" / "coded.npy").exists()


def test_a_stage_script_interrupted_says_so_in_one_line(capsys):
    from codedvideo.app.cli import guarded

    def stopped():
        raise KeyboardInterrupt

    assert guarded(stopped) == 130
    assert capsys.readouterr().err == "codedvideo: interrupted\n"  # before: a KeyboardInterrupt traceback


def test_simulating_again_keeps_the_last_reconstructions_record_and_says_it_is_stale(tmp_path, capsys):
    """Reported: `make simulate` after `run` rewrote recon.metrics.json without its PSNR, beside a recon.mp4
    that was no longer of the capture in capture/."""
    from codedvideo.engine.config import load_config
    from codedvideo.api import run_pipeline

    out = tmp_path / "out"
    cfg_text = (f"frames: 4\ncache: {tmp_path / 'cache'}\nscene: {{video: synth:default, size: [24, 24]}}\n"
                f"dictionary: {{kind: dct}}\nreconstruct: {{tile: 32}}\noutput: {{dir: {out}, frames: none}}\n")
    rc, err = run(tmp_path, capsys, cfg_text)
    assert rc == 0, err
    record = (out / "recon.metrics.json").read_text()
    assert "psnr" in record
    cfg = load_config(tmp_path / "p.yaml")
    with pytest.warns(UserWarning, match="from an earlier run"):
        report = run_pipeline(cfg.model_copy(update=dict(stages=["simulate"], seed=1)), progress=False)
    assert (out / "recon.metrics.json").read_text() == record
    assert report["metrics_path"] == str(out / "capture" / "metrics.json")
    assert json.loads((out / "capture" / "metrics.json").read_text())["capture"]


def _small_run(tmp_path, capsys, output_extra: str = ""):
    """A full run of a 24x24 capture with the DCT dictionary into tmp_path/out: (the folder, its config)."""
    from codedvideo.engine.config import load_config

    out = tmp_path / "out"
    cfg_text = (f"frames: 4\ncache: {tmp_path / 'cache'}\nscene: {{video: synth:default, size: [24, 24]}}\n"
                f"dictionary: {{kind: dct}}\nreconstruct: {{tile: 32}}\noutput: {{dir: {out}{output_extra}}}\n")
    rc, err = run(tmp_path, capsys, cfg_text)
    assert rc == 0, err
    return out, load_config(tmp_path / "p.yaml")


def test_a_full_run_after_simulating_leaves_no_record_of_the_replaced_capture(tmp_path, capsys):
    """Reported: after `stages: [simulate]` (seed 1) and a full run (seed 0), capture/metrics.json still held the
    seed-1 record beside the seed-0 capture; the simulate-only warning named the video and recon.npy, not the
    frames folder, stale as well."""
    from codedvideo.api import run_pipeline

    out, cfg = _small_run(tmp_path, capsys)
    with pytest.warns(UserWarning, match="from an earlier run") as said:
        run_pipeline(cfg.model_copy(update=dict(stages=["simulate"], seed=1)), progress=False)
    assert any(str(out / "frames") in str(w.message) for w in said)
    assert (out / "capture" / "metrics.json").exists()
    report = run_pipeline(cfg, progress=False)
    assert not (out / "capture" / "metrics.json").exists()
    assert json.loads((out / "recon.metrics.json").read_text())["capture"] == report["capture"]


def test_training_alone_keeps_the_captures_and_the_reconstructions_records(tmp_path, capsys):
    """Reported: `stages: [train]` replaced capture/metrics.json (the record of the capture in the folder, made with
    another seed) with a record of the training; it now writes train.metrics.json and leaves both alone."""
    from codedvideo.api import run_pipeline

    out, cfg = _small_run(tmp_path, capsys, ", frames: none")
    run_pipeline(cfg.model_copy(update=dict(stages=["simulate"], seed=5)), progress=False)
    kept = {p: p.read_text() for p in (out / "recon.metrics.json", out / "capture" / "metrics.json")}
    report = run_pipeline(cfg.model_copy(update=dict(stages=["train"])), progress=False)
    assert {p: p.read_text() for p in kept} == kept
    assert report["metrics_path"] == str(out / "train.metrics.json")
    assert json.loads((out / "train.metrics.json").read_text())["dictionary"]


@pytest.mark.parametrize("section, value", [
    ("code: {name: hitomi, p: 0.3}", lambda cfg: cfg.code.p == 0.3),
    ("dictionary: {path: mine.zarr, atoms: 1024, sparsity: 4}", lambda cfg: cfg.dictionary.sparsity == 4),
])
def test_values_report_uses_are_taken_by_report_and_still_refused_by_run(tmp_path, capsys, monkeypatch, section,
                                                                         value):
    """Reported: report's Bernoulli runs read code.p and its dictionaries train with the dictionary: section
    (never dictionary.path), yet the config was refused for them at load."""
    import codedvideo.app.report

    class Loaded(Exception):
        pass

    def loaded(cfg, **kwargs):  # the config `report` gets, without running a report
        assert value(cfg)
        raise Loaded

    monkeypatch.setattr(codedvideo.app.report, "run_report", loaded)
    cfg = tmp_path / "p.yaml"
    cfg.write_text(f"frames: 4\n{section}\noutput: {{dir: {tmp_path / 'out'}}}\n")
    with pytest.raises(Loaded):
        main(["-q", "report", str(cfg)])
    rc, err = run(tmp_path, capsys, cfg.read_text())
    assert rc == 2 and len(err.splitlines()) == 1 and section.split(":")[0] in err, err


@pytest.mark.parametrize("section, said", [
    ("output: {dir: ''}", "p.yaml: output.dir = '': name a folder"),
    ("dictionary: {atoms: 2}", "p.yaml: dictionary.atoms = 2: below dictionary.sparsity 6"),
    ("code: {bump: 20}", "p.yaml: code.bump = 20: a bump of 1 to 4 sub-frames"),
])
def test_config_values_a_run_trips_over_are_refused_naming_the_key(tmp_path, capsys, section, said):
    """Before: output.dir '' wrote into the current folder, 2 atoms with sparsity 6 trained, and a bump of 20
    failed when the code was made, without the config's key."""
    rc, err = run(tmp_path, capsys, f"frames: 4\n{section}\n")
    assert rc == 2 and len(err.splitlines()) == 1 and said in err, err


def test_training_a_dictionary_for_one_sub_frame_is_refused(tmp_path, capsys):
    """frames 1: every pixel opens alike and the still estimate needs no dictionary; training one took 10 s."""
    rc, err = run(tmp_path, capsys, "frames: 1\nstages: [train]\n")
    assert rc == 2 and "frames 1" in err and "leave train out" in err, err


def test_run_writes_the_record_reconstruct_writes_with_its_stages_beside_it(tmp_path, capsys):
    """One record schema: `run`'s holds every key of `reconstruct`'s record of the same capture (its quality, its
    video as written, its settings and inputs), with the run's stages beside them.  The videos are FFV1: the same
    frames give the same file (libx264 does not promise that, docs/guarantees.md)."""
    out, _ = _small_run(tmp_path, capsys, ", video: recon.mkv")
    ran = json.loads((out / "recon.metrics.json").read_text())
    cap = out / "capture"
    assert main(["-q", "reconstruct", "--coded", str(cap / "coded.npy"), "--mask", str(cap / "mask.npy"),
                 "--truth", str(cap / "truth.npy"), "--dictionary", ran["dictionary"]["path"], "--tile", "32",
                 "--output", str(tmp_path / "r.mkv"), "--cache", str(tmp_path / "cache")]) == 0
    alone = json.loads((tmp_path / "r.metrics.json").read_text())
    assert set(alone) <= set(ran) and {"config", "seconds", "capture", "outputs"} <= set(ran) - set(alone)
    for key in ("reconstruction", "quality", "trivial", "data_range", "settings"):
        assert set(alone[key]) == set(ran[key]), key
    assert ran["quality"]["psnr"] == pytest.approx(alone["quality"]["psnr"], abs=1e-9)
    assert ran["quality"]["output_file"]["psnr"] == pytest.approx(alone["quality"]["output_file"]["psnr"], abs=1e-6)


@pytest.mark.parametrize("stages,names", [
    ("[simulate, reconstruct, reconstruct]", ["stages", "reconstruct", "twice"]),
    ("[train, train]", ["stages", "train", "twice"]),
    ("[evaluate, reconstruct, simulate]", ["stages", "order", "train, simulate, reconstruct, evaluate"]),
    ("[reconstruct, train]", ["stages", "order"]),
])
def test_stages_with_duplicates_or_out_of_pipeline_order_are_refused(tmp_path, capsys, stages, names):
    cfg = tmp_path / "p.yaml"
    cfg.write_text(f"stages: {stages}\noutput: {{dir: {tmp_path / 'out'}}}\ncache: {tmp_path / 'c'}\n")
    fails(capsys, ["run", cfg], "p.yaml", *names, root=tmp_path)
