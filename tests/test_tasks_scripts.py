"""The scripts in tasks/: each answers ``--help`` (exit 0, a usage text) without doing work, and the modules of
tasks/ import one another without a cycle (imports inside functions included).  Modules whose name starts with
an underscore (_common.py, _bench_common.py) are shared helpers, not scripts: they are checked for cycles only.
The shell scripts (tasks/*.sh) answer --help too."""
from __future__ import annotations

import ast
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
TASKS = ROOT / "tasks"
MODULES = sorted(TASKS.glob("*.py"))
SCRIPTS = [p for p in MODULES if not p.name.startswith("_")] + sorted(TASKS.glob("*.sh"))


def test_tasks_holds_scripts():
    assert len(SCRIPTS) >= 5, SCRIPTS


@pytest.fixture(scope="module")
def helps() -> dict[str, subprocess.CompletedProcess]:
    """Every script run with --help, all at once (each mostly waits on its imports)."""
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(filter(None, [str(ROOT / "src"), os.environ.get("PYTHONPATH")])))
    procs = {p.name: subprocess.Popen([sys.executable if p.suffix == ".py" else "bash", str(p), "--help"], stdout=subprocess.PIPE,
                                      stderr=subprocess.PIPE, text=True, cwd=ROOT, env=env) for p in SCRIPTS}
    done = {}
    for name, proc in procs.items():
        out, err = proc.communicate(timeout=120)
        done[name] = subprocess.CompletedProcess(proc.args, proc.returncode, out, err)
    return done


@pytest.mark.parametrize("script", [p.name for p in SCRIPTS])
def test_script_answers_help(script, helps):
    done = helps[script]
    assert done.returncode == 0, done.stderr[-2000:]
    assert "usage" in done.stdout.lower(), done.stdout[-2000:]


def local_imports(path: Path, names: set[str]) -> set[str]:
    """The modules of tasks/ that ``path`` imports, anywhere in it (top level or inside functions)."""
    found = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            found.update(alias.name.split(".")[0] for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            found.add(node.module.split(".")[0])
    return found & names


def find_cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """One import cycle of ``graph`` (module -> the modules it imports) as a path back to its start, or None."""
    state: dict[str, int] = {}  # 1: on the current path, 2: done
    path: list[str] = []

    def visit(node: str) -> list[str] | None:
        state[node] = 1
        path.append(node)
        for nxt in sorted(graph[node]):
            if state.get(nxt) == 1:
                return path[path.index(nxt):] + [nxt]
            if nxt not in state and (cycle := visit(nxt)):
                return cycle
        path.pop()
        state[node] = 2
        return None

    for node in sorted(graph):
        if node not in state and (cycle := visit(node)):
            return cycle
    return None


def test_find_cycle_sees_a_cycle():
    assert find_cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]
    assert find_cycle({"a": {"b"}, "b": set(), "c": {"a", "b"}}) is None


def test_tasks_have_no_import_cycle():
    names = {p.stem for p in MODULES}
    graph = {p.stem: local_imports(p, names) - {p.stem} for p in MODULES}
    assert find_cycle(graph) is None, " -> ".join(find_cycle(graph))
