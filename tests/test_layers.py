"""The package's layers import only downward, with no cycle (imports inside functions included): the contracts
in .importlinter, checked by import-linter over the installed package; and app/ (the command line, run, report)
reaches the engine and the solvers only through the API."""
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_layers_import_only_downward_and_without_cycles():
    lint = Path(sys.executable).with_name("lint-imports")
    done = subprocess.run([str(lint), "--config", str(ROOT / ".importlinter")], capture_output=True, text=True,
                          cwd=ROOT)
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-2000:]
    assert "3 kept, 0 broken" in done.stdout


def test_the_contract_names_every_subpackage():
    """A new subpackage outside the layers would escape the contract."""
    import codedvideo

    packages = {p.parent.name for p in Path(codedvideo.__file__).parent.glob("*/__init__.py")}
    contract = (ROOT / ".importlinter").read_text()
    assert len(packages) >= 3
    for name in packages:
        assert f"codedvideo.{name}\n" in contract, name


def test_numba_is_imported_by_one_module_of_the_solvers():
    """The solvers' compiled kernels take ``njit`` and ``prange`` from ``solvers/_jit.py``, the one module of the
    layer that imports numba (imports inside functions included)."""
    import ast

    importers = set()
    for path in sorted((ROOT / "src" / "codedvideo" / "solvers").glob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            names = [a.name for a in node.names] if isinstance(node, ast.Import) else (
                [node.module or ""] if isinstance(node, ast.ImportFrom) else [])
            if any(name.split(".")[0] == "numba" for name in names):
                importers.add(path.name)
    assert importers == {"_jit.py"}
