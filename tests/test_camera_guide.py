"""docs/camera.md runs as written: its shell blocks, in order, in an empty folder, with this package's
`codedvideo` and `python` first on the PATH, make the stand-in files (16-bit PNG coded images, a folder of
0/255 PNG masks) and a video from them."""
import json
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]


def blocks() -> list[str]:
    return re.findall(r"```bash\n(.*?)```", (ROOT / "docs" / "camera.md").read_text(), re.S)


def test_the_camera_guide_runs_as_written_from_png_files_to_a_video(tmp_path):
    bin_dir = Path(sys.executable).parent
    env = dict(os.environ, PATH=f"{bin_dir}{os.pathsep}{os.environ['PATH']}", XDG_CACHE_HOME=str(tmp_path / "xdg"))
    found = blocks()
    assert len(found) >= 3
    for block in found:
        done = subprocess.run(["bash", "-euo", "pipefail", "-c", block], cwd=tmp_path, env=env,
                              capture_output=True, text=True, timeout=600)
        assert done.returncode == 0, block + done.stderr
    assert len(list((tmp_path / "camera" / "mask").glob("*.png"))) == 8
    assert (tmp_path / "video.mp4").stat().st_size > 0
    from codedvideo.formats.io import read_video

    assert read_video(tmp_path / "video.mp4").shape[0] == 24
    scored = json.loads((tmp_path / "scored.metrics.json").read_text())
    assert scored["quality"]["psnr"] > 25
    truth, frames = np.load(tmp_path / "sim" / "truth.npy"), np.load(tmp_path / "scored.npy")
    assert frames.shape == truth.shape == (24, 64, 64)
