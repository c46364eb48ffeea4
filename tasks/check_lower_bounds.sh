#!/usr/bin/env bash
# Install codedvideo with every dependency at the lower bound pyproject.toml states (a fresh venv), and run the
# tests of the API, the command line, the formats, the methods and the cache against them.
# Usage: tasks/check_lower_bounds.sh [PYTHON]    (make lower-bounds)
set -euo pipefail
case "${1:-}" in
  -h|--help)
    echo "usage: tasks/check_lower_bounds.sh [PYTHON]"
    echo
    echo "Install codedvideo into a fresh venv with PYTHON (default: python3) and every dependency at its lower"
    echo "bound in pyproject.toml, then run a part of the test suite against them."
    exit 0 ;;
esac
root="$(cd "$(dirname "$0")/.." && pwd)"
python="${1:-python3}"
work="$(mktemp -d -t codedvideo-lower-XXXXXX)"
trap 'rm -rf "$work"' EXIT
# the lower bounds: each "name>=X" of [project] dependencies pinned to X
"$python" - "$root/pyproject.toml" > "$work/lower.txt" <<'PY'
import re, sys, tomllib
for spec in tomllib.load(open(sys.argv[1], "rb"))["project"]["dependencies"]:
    m = re.match(r"^([A-Za-z0-9_.-]+)(?:\[[^]]*\])?>=([0-9][0-9A-Za-z.]*)$", spec.split(";")[0].strip())
    if m:
        print(f"{m.group(1)}=={m.group(2)}")
PY
cat "$work/lower.txt"
"$python" -m venv "$work/venv"
"$work/venv/bin/python" -m pip install --quiet -c "$work/lower.txt" "$root[test]"
cd "$root"
# (its own numba cache: the kernels compiled by another numba stay as they are)
NUMBA_CACHE_DIR="$work/numba" "$work/venv/bin/python" -m pytest -q -p no:cacheprovider \
  tests/test_api.py tests/test_one_door.py tests/test_cli.py tests/test_io.py tests/test_units.py \
  tests/test_data_range_rule.py tests/test_nonlocal.py tests/test_refine.py tests/test_presets.py \
  tests/test_camera_guide.py tests/test_distributed.py tests/test_cacti.py tests/test_adapt.py \
  tests/test_config_command.py tests/test_owned_outputs.py tests/test_resume.py tests/test_cache.py
