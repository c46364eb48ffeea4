#!/usr/bin/env bash
# Build the wheel from this checkout, install it into a fresh virtual environment, and run the commands and
# the Python API from an empty folder: what a user who runs `pip install codedvideo` gets (the built-in
# pipeline.yaml run with no file, the default cache in the user's cache folder); then into an environment that
# already holds napari and scikit-image.
# Usage: tasks/check_wheel.sh [PYTHON]    (CI runs it after `make test`; `make wheel-check`)
set -euo pipefail
case "${1:-}" in
  -h|--help)
    echo "usage: tasks/check_wheel.sh [PYTHON]"
    echo
    echo "Build the wheel, install it into a fresh venv with PYTHON (default: python3), and run the CLI and the"
    echo "Python API from an empty folder."
    exit 0 ;;
esac
root="$(cd "$(dirname "$0")/.." && pwd)"
python="${1:-python3}"
work="$(mktemp -d -t codedvideo-wheel-XXXXXX)"
trap 'rm -rf "$work"' EXIT
"$python" -m pip wheel --quiet --no-deps --wheel-dir "$work/dist" "$root"
"$python" -m venv "$work/venv"
"$work/venv/bin/python" -m pip install --quiet "$work"/dist/codedvideo-*.whl
mkdir "$work/empty"
cd "$work/empty"
cli="$work/venv/bin/codedvideo"
export XDG_CACHE_HOME="$work/xdg"  # the user's cache folder, the default cache: here, removed with the rest
# the built-in pipeline.yaml: printed, and run with no file of one's own
"$cli" config > pipeline.yaml
grep -q "^stages:" pipeline.yaml
"$cli" -q run
test -f out/run/recon.metrics.json && test -d "$XDG_CACHE_HOME/codedvideo"
rm -rf out pipeline.yaml
"$cli" -q simulate synth:default --frames 8 --bump 2 --size 64 64 --seed 0 --output cap
"$cli" -q reconstruct --coded cap/coded.npy --mask cap/mask.npy --truth cap/truth.npy --output rec.npy
"$work/venv/bin/python" - <<'PY'
import json
import numpy as np
m = json.load(open("rec.metrics.json"))
assert m["quality"]["psnr"] > 20, m["quality"]
rec = np.load("rec.npy")
assert rec.shape == (8, 64, 64) and np.isfinite(rec).all()
print(f"wheel: simulate and reconstruct from an empty folder, PSNR {m['quality']['psnr']:.2f} dB")
PY
# the Python API from the same folder: the README's quick start
"$work/venv/bin/python" "$root/examples/quickstart.py"
# beside the scientific stack: into an environment that already holds napari and scikit-image (at the versions
# their own requirements chose), the wheel installs without changing any package there, and pip finds every
# requirement met
"$python" -m venv "$work/stack"
"$work/stack/bin/python" -m pip install --quiet napari scikit-image
"$work/stack/bin/python" -m pip freeze | grep -v '^codedvideo' | sort > "$work/before.txt"
"$work/stack/bin/python" -m pip install --quiet "$work"/dist/codedvideo-*.whl
"$work/stack/bin/python" -m pip check
"$work/stack/bin/python" -m pip freeze | sort > "$work/after.txt"
if comm -23 "$work/before.txt" "$work/after.txt" | grep .; then
  echo "wheel: installing codedvideo changed the packages above in an environment with napari" >&2
  exit 1
fi
echo "wheel: installed beside $(grep -i '^napari==' "$work/after.txt") and $(grep -i '^scikit-image==' "$work/after.txt"), nothing changed"
