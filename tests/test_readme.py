"""The README's snippets run as written, from an empty folder, and print the figures the README gives: each
```python block as a script, and the command-line quick start's commands in order (the report, whose
experiments take long, has its own test in test_report.py)."""
import os
import re
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
README = (ROOT / "README.md").read_text()


def _env(tmp_path: Path) -> dict:
    bin_dir = Path(sys.executable).parent
    return dict(os.environ, PATH=f"{bin_dir}{os.pathsep}{os.environ['PATH']}", XDG_CACHE_HOME=str(tmp_path / "xdg"))


def python_blocks() -> list[str]:
    return re.findall(r"```python\n(.*?)```", README, re.S)


def shell_block(after: str) -> str:
    start = README.index(after)
    return re.search(r"```(?:bash)?\n(.*?)```", README[start:], re.S).group(1)


def test_the_python_snippets_run_and_print_the_figures_they_state(tmp_path):
    blocks = python_blocks()
    assert len(blocks) >= 2
    for i, block in enumerate(blocks):
        work = tmp_path / f"snippet{i}"
        work.mkdir()
        (tmp_path / f"snippet{i}.py").write_text(block)
        done = subprocess.run([sys.executable, str(tmp_path / f"snippet{i}.py")], cwd=work, env=_env(tmp_path),
                              capture_output=True, text=True, timeout=600)
        assert done.returncode == 0, block + done.stderr[-3000:]
        stated = re.findall(r"print\(.*?\)\s*#\s*([0-9.]+) dB", block)
        printed = re.findall(r"([0-9]+\.[0-9]+)", done.stdout)
        for figure in stated:  # a figure the README states is what the snippet prints, to its digits
            assert any(round(float(p), len(figure.split(".")[1])) == float(figure) for p in printed), \
                (figure, done.stdout)
        assert not list(work.iterdir()), "a snippet wrote into the folder it ran in"


def test_the_command_line_quick_start_runs_as_written(tmp_path):
    block = shell_block("## Quick start: the command line")
    done = subprocess.run(["bash", "-euo", "pipefail", "-c", block], cwd=tmp_path, env=_env(tmp_path),
                          capture_output=True, text=True, timeout=900)
    assert done.returncode == 0, block + done.stderr[-3000:]
    for name in ("rec.mp4", "rec.metrics.json"):
        assert (tmp_path / name).exists(), name
