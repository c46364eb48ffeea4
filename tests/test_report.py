"""A miniature `codedvideo report` end to end: every table and figure, finite numbers, and the cache."""
import base64
import csv
import math
from pathlib import Path

import numpy as np
import pytest
import yaml

from codedvideo.engine.config import load_config
from codedvideo.model.errors import ConfigError
from codedvideo.app.report import pareto_front, run_report

MINI = dict(
    seed=0,
    frames=4,
    report=dict(
        scenes=["default"], size=[32, 32], frames=4, bump=2, table_bumps=[1, 2], table_sigmas=[0, 8],
        fig7_frames=[4], table_frames=[6], speed_max_atoms=[4], speed_tol_rms=[4.0], speed_atoms=[32], speed_codes=["hitomi-tiled"],
        video_scene="default", dictionary=dict(atoms=64, samples=1000, iterations=1),
    ),
)


@pytest.fixture(scope="module")
def mini(tmp_path_factory):
    root = tmp_path_factory.mktemp("report")
    raw = dict(MINI, cache=str(root / "cache"))
    raw["report"] = dict(MINI["report"], dir=str(root / "out"))
    path = root / "mini.yaml"
    path.write_text(yaml.safe_dump(raw))
    cfg = load_config(path)
    first = run_report(cfg)
    first["csv_text"] = (root / "out" / "report.csv").read_text()  # as the first run, on a fresh cache, wrote it
    second = run_report(cfg)
    return root, first, second


def test_every_table_and_figure_is_produced(mini):
    root, first, _ = mini
    out = root / "out"
    for name in ("table1", "fig7", "fig4", "speed", "strips"):
        png = (out / "figures" / f"{name}.png").read_bytes()
        assert png.startswith(b"\x89PNG")
    page = (out / "report.html").read_text()
    for heading in ("Table 1", "Fig. 7", "Fig. 4", "Error against run time", "Findings of the paper", "Frames"):
        assert heading in page
    assert page.count("data:image/png;base64,") == 5
    b64 = page.split("data:image/png;base64,")[1].split('"')[0]
    assert base64.b64decode(b64).startswith(b"\x89PNG")
    assert (out / "side_by_side.mp4").stat().st_size > 0
    assert first["video"] == out / "side_by_side.mp4"
    assert len(first["findings"]) == 6 and all(isinstance(f["holds"], bool) for f in first["findings"])
    assert first["computed"] > 0


def test_table_1_at_other_n_stands_beside_the_simple_answers(mini):
    """Table 1 again at N = 6 (the miniature's table_frames): the default, GAP-TV and the still estimate in each
    cell, for the bumps of table_bumps and N / 2 and N - 2, in the page and the CSV."""
    from codedvideo.app.report import table_bumps_at

    root, first, _ = mini
    assert table_bumps_at([1, 2], 6) == [1, 2, 3, 4]
    page = (root / "out" / "report.html").read_text()
    assert "Table 1 at other N" in page
    for bump in (1, 2, 3, 4):
        assert f"N = 6, L = {bump}" in page
    rows = list(csv.DictReader(first["csv_text"].splitlines()))
    means = [r for r in rows if r["experiment"] == "table1" and r["frames"] == "6" and r["scene"] == "mean"]
    assert {r["method"] for r in means} == {"omp", "gaptv", "trivial"} and len(means) == 3 * 4 * 2
    assert all(math.isfinite(float(r["psnr"])) for r in means)


def test_every_csv_number_is_finite(mini):
    root, _, _ = mini
    with open(root / "out" / "report.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    experiments = {r["experiment"] for r in rows}
    assert experiments == {"table1", "fig7", "fig4", "speed"}
    # Table 1: 2 bumps x 2 sigmas, one scene plus the mean (at report.frames; other N: the test above)
    assert sum(r["experiment"] == "table1" and r["scene"] == "mean" and r["frames"] == "4" for r in rows) == 4
    # the non-local method is a point of the error-against-time study, timed and scored like the others
    # and with its dictionary adapted to each capture (--adapt), a point of its own
    for adapted in (False, True):
        nonlocal_rows = [r for r in rows if r["experiment"] == "speed" and r["label"].startswith("non-local")
                         and ("adapted" in r["label"]) == adapted]
        assert [r["scene"] for r in nonlocal_rows] == ["default", "mean"]
        assert all(r["method"] in ("nonlocal", "") and float(r["seconds"]) > 0 for r in nonlocal_rows)
        assert nonlocal_rows[0]["method"] == "nonlocal"
    # each preset a point of its own (issue 31): fast, default and best, on the scene and as the mean
    for name in ("fast", "default", "best"):
        preset_rows = [r for r in rows if r["experiment"] == "speed" and r["label"] == f"preset {name}"]
        assert [r["scene"] for r in preset_rows] == ["default", "mean"], name
        assert float(preset_rows[0]["seconds"]) > 0 and float(preset_rows[1]["psnr"]) > 0
    best = next(r for r in rows if r["label"] == "preset best" and r["scene"] == "default")
    assert best["method"] == "nonlocal"
    default = next(r for r in rows if r["label"] == "preset default" and r["scene"] == "default")
    assert default["method"] == "omp" and float(best["psnr"]) > float(default["psnr"])
    numbers = 0
    for r in rows:
        assert r["psnr"] != ""
        for k in ("frames", "bump", "sigma", "max_atoms", "tol_rms", "dictionary_atoms", "psnr", "ssim", "seconds",
                  "atoms_mean"):
            if r.get(k, "") != "":
                assert math.isfinite(float(r[k])), (k, r)
                numbers += 1
    assert numbers > 50


def test_the_frame_strips_show_the_best_preset(mini):
    """Beside the truth and the Fig. 7 methods, the frames figure shows --preset best (its volume kept)."""
    from codedvideo.app.report import Runner, run_experiments

    root, _, _ = mini
    runner = Runner(load_config(root / "mini.yaml"))
    results = run_experiments(runner)
    assert runner.computed == 0  # all from the first run's cache
    (strip,) = results["strips"]
    assert strip["label"].startswith("preset best") and strip["scene"] == "default" and strip["method"] == "nonlocal"
    assert (runner.folder / f"{strip['key']}.npy").exists()


def test_second_run_hits_the_cache(mini):
    _, first, second = mini
    assert second["computed"] == 0
    assert second["reused"] == first["computed"] + first["reused"]
    assert [f["detail"] for f in second["findings"]] == [f["detail"] for f in first["findings"]]


def test_pareto_front():
    pts = [(1.0, 20.0), (2.0, 25.0), (3.0, 24.0), (0.5, 10.0), (2.0, 25.0)]
    assert pareto_front(pts) == [True, True, False, True, True]


def test_report_config_rejects_training_scenes_and_unknown_keys(tmp_path):
    path = tmp_path / "bad.yaml"
    path.write_text(yaml.safe_dump(dict(report=dict(scenes=["train-3"]))))
    with pytest.raises(ConfigError, match="report.scenes"):
        load_config(path)
    path.write_text(yaml.safe_dump(dict(report=dict(nope=1))))
    with pytest.raises(ConfigError, match="unknown key"):
        load_config(path)
    path.write_text(yaml.safe_dump(dict(report=dict(frames=4, table_bumps=[1, 5]))))
    with pytest.raises(ConfigError, match="bump"):
        load_config(path)


def test_a_report_that_fails_midway_marks_what_it_wrote(mini, tmp_path, monkeypatch):
    """The figures written before a failure are codedvideo's: the rerun replaces them rather than
    refusing them as the user's."""
    from codedvideo.app import report_html
    from codedvideo.formats.outputs import written_by_codedvideo

    root, _, _ = mini
    cfg = load_config(root / "mini.yaml")
    cfg = cfg.model_copy(update=dict(report=cfg.report.model_copy(update=dict(dir=str(tmp_path / "r")))))

    def broken(*args, **kwargs):
        raise RuntimeError("encoder gone")

    monkeypatch.setattr(report_html, "side_by_side", broken)
    with pytest.raises(RuntimeError, match="encoder gone"):
        run_report(cfg)
    figures = sorted((tmp_path / "r" / "figures").glob("*.png"))
    assert figures and all(written_by_codedvideo(p) for p in figures)
    monkeypatch.undo()
    assert run_report(cfg)["html"].exists()


def test_damaged_records_and_volumes_are_computed_again(mini, tmp_path):
    """A record that parses but is not one (``{}``), or a cut volume, is reported broken by ``cache verify``
    and computed again by the next report, as a damaged tile is (it was a traceback)."""
    import json
    import shutil

    from codedvideo.engine.cache import verify_cache

    root, first, _ = mini
    shutil.copytree(root / "cache", tmp_path / "cache")
    folder = tmp_path / "cache" / "report"
    volume = sorted(folder.glob("*.npy"))[0]
    volume.write_bytes(volume.read_bytes()[:100])
    record = next(p for p in sorted(folder.glob("*.json")) if p.stem != volume.stem)
    record.write_text("{}")
    broken = {Path(r["entry"]).stem for r in verify_cache(tmp_path / "cache") if r["status"] == "broken"}
    assert broken == {volume.stem, record.stem}
    raw = dict(MINI, cache=str(tmp_path / "cache"))
    raw["report"] = dict(MINI["report"], dir=str(tmp_path / "out"))
    (tmp_path / "mini.yaml").write_text(yaml.safe_dump(raw))
    again = run_report(load_config(tmp_path / "mini.yaml"))
    assert again["computed"] == 2 and again["reused"] == first["computed"] + first["reused"] - 2
    assert json.loads(record.read_text())["key"] == record.stem
    assert not [r for r in verify_cache(tmp_path / "cache") if r["status"] != "ok"]


def test_a_claim_one_noise_level_cannot_test_is_not_tested_not_refuted():
    """Reported: with table_sigmas [0] the report said "NOT reproduced: longer bumps win as noise grows"."""
    from types import SimpleNamespace

    from codedvideo.app.report import findings
    from codedvideo.app.report_html import verdict

    rc = SimpleNamespace(table_sigmas=[0.0], table_bumps=[1, 2], bump=2, frames=4)
    table = {(1, 0.0): 20.0, (2, 0.0): 21.0}
    fig7 = {(a, 4): dict(psnr=p) for a, p in (("learned + OMP (hitomi)", 4), ("3D DCT + OMP (hitomi)", 3),
                                              ("3D interpolation (grid code)", 2), ("thin-out (thinout code)", 1))}
    fig4 = {"hitomi (L = 2)": dict(psnr=2.0, ssim=0.5), "rowwise (L = 2)": dict(psnr=1.0, ssim=0.4)}
    found = {f["claim"]: f["holds"] for f in findings(table, {0.0: 2}, fig7, fig4, rc)}
    assert found["Table 1: longer bumps win as noise grows"] is None
    assert verdict(None).startswith("not tested") and verdict(False) == "NOT reproduced"
    assert all(v is True for k, v in found.items() if "noise grows" not in k)


@pytest.mark.parametrize("change, named", [(dict(fig7_frames=[6]), "report.frames 4 must be one of"),
                                           (dict(video_scene="nosuch"), "nosuch")])
def test_report_settings_it_cannot_use_are_refused_before_any_work(tmp_path, change, named):
    """Reported: fig7_frames without report.frames ran every experiment, then a StopIteration traceback left a
    half-written report; an unknown video_scene trained the dictionary and ran Table 1 before its error."""
    from codedvideo.model.errors import CodedVideoError

    raw = dict(MINI, cache=str(tmp_path / "cache"))
    raw["report"] = dict(MINI["report"], dir=str(tmp_path / "out"), **change)
    path = tmp_path / "r.yaml"
    path.write_text(yaml.safe_dump(raw))
    with pytest.raises(CodedVideoError, match=named):
        run_report(load_config(path))
    assert not (tmp_path / "cache").exists() or not any((tmp_path / "cache").rglob("*.json"))
    assert not (tmp_path / "out").exists()


def test_the_noise_trend_reads_the_sigmas_in_order_and_needs_two_bumps():
    from types import SimpleNamespace

    from codedvideo.app.report import findings

    table = {(2, 0): 30, (3, 0): 29, (5, 0): 28, (2, 8): 27, (3, 8): 28, (5, 8): 26, (2, 40): 20, (3, 40): 21,
             (5, 40): 22}
    fig7 = {(a, 8): dict(psnr=p) for a, p in (("learned + OMP (hitomi)", 30), ("3D DCT + OMP (hitomi)", 29),
                                              ("3D interpolation (grid code)", 28), ("thin-out (thinout code)", 27))}
    fig4 = {"hitomi (L = 2)": dict(psnr=30, ssim=0.9), "rowwise (L = 2)": dict(psnr=29, ssim=0.8)}

    def trend(sigmas, bumps):
        rc = SimpleNamespace(table_sigmas=sigmas, table_bumps=bumps, frames=8, bump=2)
        best = {s: max(bumps, key=lambda b: table[(b, s)]) for s in sigmas}
        return findings(table, best, fig7, fig4, rc)[1]["holds"]

    assert trend([40, 0, 8], [2, 3, 5]) is True and trend([0, 8, 40], [2, 3, 5]) is True  # config order: False
    assert trend([0, 8, 40], [2]) is None  # one bump length: not tested ("NOT reproduced" before)


def test_one_experiment_has_one_timing_in_the_csv(mini):
    """Reported: on a fresh cache an experiment in Table 1 and Fig. 7 showed two timings (Fig. 7 ran it again
    to keep its volume and replaced the record Table 1 had shown)."""
    _, first, _ = mini
    rows = list(csv.DictReader(first["csv_text"].splitlines()))
    seconds: dict = {}
    for r in rows:
        if r.get("key"):
            seconds.setdefault(r["key"], set()).add(r["seconds"])
    assert any(len(v) == 1 for v in seconds.values()) and all(len(v) == 1 for v in seconds.values()), seconds


def test_the_report_dictionaries_ignore_the_pipeline_init_and_augment(tmp_path):
    """Reported: dictionary.init leaked into the report's dictionaries (the speed study's small ones were the
    512-atom init dictionary; Fig. 7 at an N with none shipped failed after Table 1)."""
    from codedvideo.app.report import Runner

    raw = dict(MINI, frames=8, cache=str(tmp_path / "cache"), dictionary=dict(init="shipped", augment=False))
    raw["report"] = dict(MINI["report"], dir=str(tmp_path / "out"), frames=8, fig7_frames=[4, 8])
    path = tmp_path / "r.yaml"
    path.write_text(yaml.safe_dump(raw))
    runner = Runner(load_config(path))
    dc = runner.dictionary_config(8, 128).dictionary
    assert dc.init is None and dc.augment is True
    D, meta = runner.dictionary(8, 128)
    assert D.shape[1] == 128 and meta["init"] == "dct3d+samples" and meta["augment"] is True


def test_best_is_drawn_along_its_refinement_ending_at_its_point(mini):
    """The error-against-time figure has best's PSNR along its refinement: from before it (lower) to its own
    point (the same PSNR and wall time as the preset's point)."""
    from codedvideo.app.report import Runner, run_experiments, summarise

    root, _, _ = mini
    cfg = load_config(root / "mini.yaml")
    runner = Runner(cfg)
    results = run_experiments(runner)
    best = [r for r in results["speed"] if r["label"] == "preset best"]
    assert best and all(r["refine_trace"][0]["iterations"] == 0 for r in best)
    # the passes of its adaptation first (pass 1, pass 2), then the refinement's points
    assert all([p["stage"] for p in r["stage_trace"]] == ["pass 1", "pass 2"] for r in best)
    point = summarise(results, cfg)["speed"]["preset best"]
    curve = point["refine_trace"]
    assert len(curve) == 2 + min(len(r["refine_trace"]) for r in best)
    assert curve[0][1] == pytest.approx(float(np.mean([r["stage_trace"][0]["psnr"] for r in best])))
    assert len(curve) >= 2 and curve[-1][0] == pytest.approx(point["seconds"])
    assert curve[-1][1] == pytest.approx(point["psnr"], abs=1e-9)
    assert [t for t, _ in curve] == sorted(t for t, _ in curve)
