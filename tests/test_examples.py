"""The scripts in examples/ run as a user runs them, and print a sensible score."""
import re
import subprocess
import sys
from pathlib import Path

import pytest

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"


@pytest.mark.parametrize("script", sorted(p.name for p in EXAMPLES.glob("*.py")))
def test_example_runs(script, tmp_path):
    done = subprocess.run([sys.executable, str(EXAMPLES / script)], capture_output=True, text=True, cwd=tmp_path,
                          timeout=600)
    assert done.returncode == 0, done.stderr[-2000:]
    psnr = float(re.search(r"PSNR ([0-9.]+) dB", done.stdout).group(1))
    assert psnr > 24.0, done.stdout
    assert not list(tmp_path.iterdir())  # nothing written where it ran
