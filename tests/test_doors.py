"""Each door names a setting as its user knows it, when the message is made (no message is reworded afterwards),
and the API's warnings reach the caller as they are raised, at the caller's line: a warning said "before any
work" arrives before the first pass starts (before, the API held every warning back until the call returned:
3.9 s later on a 128x128 best run, nine minutes on a 1080p one)."""
import warnings

import numpy as np
import pytest

import codedvideo as cv
from codedvideo.engine import captures

SIZE, N = 48, 8


def _capture():
    video = cv.synthetic_scene("default", frames=N, size=(SIZE, SIZE))
    mask = cv.make_code("hitomi", (SIZE, SIZE), frames=N, seed=0)
    return cv.simulate(video, mask), mask


def test_a_before_any_work_warning_arrives_before_the_first_pass(monkeypatch):
    coded, mask = _capture()
    real, heard_at_start = captures.sparse_volumes, []
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")

        def first_pass(*args, **kwargs):
            heard_at_start.append([str(w.message) for w in caught])
            return real(*args, **kwargs)

        monkeypatch.setattr(captures, "sparse_volumes", first_pass)
        cv.reconstruct(coded, mask, data_range=5100)  # (the capture peaks near 250: a range 20 times too wide)
    assert heard_at_start, "the first pass never started"
    before = [m for m in heard_at_start[0] if "data range" in m]
    assert before, heard_at_start[0]
    said = [w for w in caught if str(w.message) == before[0]]
    assert said[0].filename == __file__  # at the caller's line, not inside the package
    assert "data_range" in before[0] and "--data-range" not in before[0]  # in the API's names


def test_an_error_names_the_setting_as_each_door_does(tmp_path, capsys):
    from codedvideo.app.cli import main

    coded, mask = _capture()
    try:
        cv.reconstruct(coded, mask, method="gaptv", adapt=True)
    except cv.ConfigError as exc:
        api = str(exc)
    np.save(tmp_path / "c.npy", coded)
    np.save(tmp_path / "m.npy", mask)
    assert main(["-q", "reconstruct", "--coded", str(tmp_path / "c.npy"), "--mask", str(tmp_path / "m.npy"),
                 "--output", str(tmp_path / "r.npy"), "--method", "gaptv", "--adapt"]) == 2
    cli = capsys.readouterr().err
    assert "--adapt" in cli and "--method" in cli
    assert "adapt" in api and "--" not in api


def test_a_rule_between_settings_is_named_by_each_door_and_refused_before_training(tmp_path, capsys):
    """dictionary.atoms below dictionary.sparsity: pipeline.yaml's keys, the command line's options, the API's
    arguments (before, the API trained such a dictionary, and the command line named --atoms beside
    dictionary.sparsity)."""
    from codedvideo.app.cli import main

    with pytest.raises(cv.ConfigError, match=r"atoms = 2: below sparsity 6") as refused:
        cv.train([cv.synthetic_scene("default", frames=N, size=(SIZE, SIZE))], frames=N, atoms=2, sparsity=6)
    assert "--" not in str(refused.value) and "dictionary." not in str(refused.value)
    assert main(["-q", "train", "--frames", str(N), "--atoms", "2", "--sparsity", "6",
                 "--output", str(tmp_path / "d.zarr")]) == 2
    assert "--atoms = 2: below --sparsity 6" in capsys.readouterr().err
    (tmp_path / "p.yaml").write_text(f"frames: {N}\ndictionary: {{atoms: 2, sparsity: 6}}\n"
                                      f"output: {{dir: {tmp_path / 'out'}}}\n")
    assert main(["-q", "run", str(tmp_path / "p.yaml")]) == 2
    assert "dictionary.atoms = 2: below dictionary.sparsity 6" in capsys.readouterr().err
    assert not (tmp_path / "d.zarr").exists() and not (tmp_path / "out").exists()
