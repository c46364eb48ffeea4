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
SMALL = 16  # the side of the captures that need no more


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


def test_a_muted_call_keeps_its_own_warnings_and_leaves_other_threads_theirs():
    """The first passes of --adapt and a Bayer capture's channels mute warnings their last job says again; they
    did so with ``warnings.catch_warnings``, which changes the filters of the whole process, so a reconstruction
    in another thread lost its warnings meanwhile."""
    import threading

    from codedvideo.model import doors

    with pytest.warns(UserWarning) as said:
        with doors.muted("never open"):
            doors.warn("12 pixels are never open")  # muted: this call's own
            doors.warn("said: another warning of this call")
            with doors.muted():
                doors.warn("muted: everything in the inner block")
            other = threading.Thread(target=doors.warn, args=("said: 3 pixels are never open (another thread)",))
            other.start()
            other.join()
        doors.warn("said: 5 pixels are never open, after the block")
    assert sorted(str(w.message) for w in said) == [
        "said: 3 pixels are never open (another thread)", "said: 5 pixels are never open, after the block",
        "said: another warning of this call"]


def test_a_command_quoted_in_an_api_message_keeps_its_options():
    """The API's messages name its arguments, but a command they quote is run as written (`--frames`, not
    `frames`)."""
    mask = cv.make_code("hitomi", (SMALL, SMALL), frames=4, bump=2, seed=0)
    with pytest.raises(cv.InputError) as raised:
        cv.reconstruct(np.ones((SMALL, SMALL), np.float32), mask)
    assert "`codedvideo train --frames 4 --output dict-N4.zarr`" in str(raised.value), str(raised.value)


def test_a_dask_inputs_warnings_name_the_apis_arguments():
    """Warnings said while a dask input's graph is computed named the command line's options (--tol-rms)."""
    import dask.array as da

    mask = cv.make_code("hitomi", (SMALL, SMALL), frames=N, bump=2, seed=0)
    coded = cv.simulate(cv.synthetic_scene("default", frames=N, size=(SMALL, SMALL)), mask)
    with warnings.catch_warnings(record=True) as said:
        warnings.simplefilter("always")
        cv.reconstruct(da.from_array(coded), mask, data_range=65535).compute()
    messages = [str(w.message) for w in said]
    assert any("data_range" in m for m in messages), messages
    assert not any("--" in m for m in messages), messages
