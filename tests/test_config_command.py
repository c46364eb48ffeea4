"""A run from an installed package, with no file of one's own: `codedvideo config` prints the built-in
pipeline.yaml (the project's own, key for key), `codedvideo run` with no file runs it, and the default cache is
the user's cache folder, its working stores within a budget; the help of each command is in groups and shows
its defaults."""
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from codedvideo import api
from codedvideo.api.config import DEFAULT_CACHE, DEFAULT_CACHE_BUDGET, default_config_path, load_config
from codedvideo.app.cli import _parser, main

ROOT = Path(__file__).resolve().parents[1]


def test_the_built_in_pipeline_yaml_is_the_projects_own(capsys):
    assert default_config_path().read_text() == (ROOT / "pipeline.yaml").read_text()
    assert main(["config"]) == 0
    assert capsys.readouterr().out == (ROOT / "pipeline.yaml").read_text()
    cfg = load_config(default_config_path())
    assert cfg.cache == DEFAULT_CACHE and yaml.safe_load(default_config_path().read_text())["cache"] is None


def test_config_writes_a_new_file_and_keeps_a_users_file(tmp_path, capsys):
    out = tmp_path / "mine.yaml"
    assert main(["config", "-o", str(out)]) == 0
    assert out.read_text() == default_config_path().read_text()
    assert main(["config", "-o", str(out)]) == 0  # its own file: replaced
    users = tmp_path / "users.yaml"
    users.write_text("frames: 16\n")
    assert main(["config", "-o", str(users)]) == 2
    assert "users.yaml" in capsys.readouterr().err and users.read_text() == "frames: 16\n"
    assert main(["config", "-o", str(tmp_path / "p.txt")]) == 2
    assert "name it .yaml" in capsys.readouterr().err and not (tmp_path / "p.txt").exists()


@pytest.mark.slow
def test_run_with_no_file_in_an_empty_folder_uses_the_built_in_pipeline_and_the_users_cache(tmp_path):
    """As after `pip install codedvideo`: a fresh process in an empty folder, the user's cache folder from the
    environment (XDG_CACHE_HOME), nothing written to the folder but the outputs."""
    work, xdg = tmp_path / "empty", tmp_path / "xdg"
    work.mkdir()
    env = dict(os.environ, XDG_CACHE_HOME=str(xdg))
    done = subprocess.run([sys.executable, "-m", "codedvideo", "-q", "run"], cwd=work, env=env,
                          capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr
    assert sorted(p.name for p in work.iterdir()) == ["out"]
    metrics = json.loads((work / "out" / "run" / "recon.metrics.json").read_text())
    assert metrics["quality"]["psnr"] > 25
    assert any(p.name.startswith("recon-") for p in (xdg / "codedvideo").iterdir())


def test_the_default_cache_folder_has_a_budget_and_a_folder_of_ones_own_has_none(tmp_path):
    assert Path(DEFAULT_CACHE).name == "codedvideo"
    default = api.resolve_settings(api.ReconstructSettings(cache=DEFAULT_CACHE))
    own = api.resolve_settings(api.ReconstructSettings(cache=str(tmp_path / "cache")))
    chosen = api.resolve_settings(api.ReconstructSettings(cache=DEFAULT_CACHE, cache_budget="1G"))
    assert default.rc.cache_budget == DEFAULT_CACHE_BUDGET and own.rc.cache_budget is None
    assert chosen.rc.cache_budget == 2**30
    parsed = _parser().parse_args(["reconstruct", "--output", "r.npy"])
    assert parsed.cache == DEFAULT_CACHE


def _subparsers():
    top = _parser()
    sub = next(a for a in top._actions if a.choices and isinstance(a.choices, dict))
    return top, sub.choices


def test_every_option_has_help_and_every_default_is_shown_by_the_formatter():
    top, commands = _subparsers()
    for name, parser in commands.items():
        text = parser.format_help()
        assert "README" not in text, name
        for action in parser._actions:
            if action.dest == "help" or not (action.option_strings or action.nargs in ("?", "*")):
                continue
            assert action.help, f"{name} {action.option_strings or action.dest}: no help"
            shown = action.default is not None and action.default is not False
            if shown and action.option_strings:
                assert "default" in parser._get_formatter()._get_help_string(action), (name, action.dest)
    assert "codedvideo config" in top.format_help()


def test_reconstruct_help_is_in_groups():
    _, commands = _subparsers()
    titles = [g.title for g in commands["reconstruct"]._action_groups]
    assert {"input", "sensor", "method", "output", "performance"} <= set(titles)
    for name in ("simulate", "train"):
        assert {"input", "output"} <= {g.title for g in commands[name]._action_groups}


def test_the_reference_lists_every_option_and_every_key_and_is_the_generated_one():
    """docs/reference.md is generated (`make docs`): it names every option of every command and every
    pipeline.yaml key, each with what it does, and the committed page is what the code generates now."""
    from codedvideo.app.reference import config_keys, reference

    text = reference()
    _, commands = _subparsers()
    for name, parser in commands.items():
        for action in parser._actions:
            for option in action.option_strings:
                if option not in ("-h", "--help"):
                    assert f"`{option}`" in text, (name, option)
    for key in config_keys():
        row = next((line for line in text.splitlines() if line.startswith(f"| `{key}` |")), None)
        assert row is not None, key
        assert not row.endswith("|  |"), f"{key}: no description (a comment in pipeline.yaml)"
    assert (ROOT / "docs" / "reference.md").read_text() == text, "docs/reference.md is stale: run make docs"


@pytest.mark.parametrize("preset, given", [("fast", []), ("best", []), ("default", [])])
def test_the_shipped_pipeline_yaml_with_only_a_preset_records_nothing_given_as_the_command_line_does(tmp_path, preset,
                                                                                                     given):
    """The shipped pipeline.yaml leaves every key a preset may set commented, so `preset: NAME` alone records the
    same `given` as `reconstruct --preset NAME` (max_atoms set there was recorded as given)."""
    text = default_config_path().read_text().replace("  preset: null ", f"  preset: {preset} ", 1)
    assert f"preset: {preset}" in text
    (tmp_path / "p.yaml").write_text(text)
    record = load_config(tmp_path / "p.yaml").reconstruct.preset_used()
    cli = api.resolve_settings(api.ReconstructSettings(preset=preset)).preset
    assert record["given"] == given == (cli or {}).get("given", []), (record, cli)


@pytest.mark.parametrize("extra, named", [("atoms: 100", "dictionary.atoms"), ("training: [/nowhere.npy]",
                                                                               "dictionary.training"),
                                          ("iterations: 3\n  augment: false", "dictionary.iterations, dictionary.augment")])
def test_a_dct_dictionary_in_pipeline_yaml_refuses_training_settings_as_train_kind_dct_does(tmp_path, extra, named):
    """`dictionary.kind: dct` beside training settings ran and ignored them (the record said atoms 100 where the
    dictionary held 392); `codedvideo train --kind dct --atoms 100` refuses them, and so does the config now."""
    (tmp_path / "p.yaml").write_text(f"dictionary:\n  kind: dct\n  {extra}\n")
    with pytest.raises(api.ConfigError, match=f"dictionary.kind dct: {named} .*for learned dictionaries only"):
        load_config(tmp_path / "p.yaml")
    (tmp_path / "q.yaml").write_text("dictionary:\n  kind: dct\n")
    assert load_config(tmp_path / "q.yaml").dictionary.kind == "dct"
