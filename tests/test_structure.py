"""Code a reader can hold in their head: no function over 80 lines of code (docstrings, comments and blank lines
left out; numba kernels and the command line's argparse table excepted), no module over 1,000 lines, and no
function that reassigns its own parameters (a parameter keeps the value the caller gave it)."""
import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SOURCES = sorted((ROOT / "src" / "codedvideo").rglob("*.py")) + sorted((ROOT / "tasks").glob("*.py"))
MAX_FUNCTION_LINES, MAX_MODULE_LINES = 80, 1000
#: Functions allowed to run longer: the argparse table of the command line (one add_argument a line).
LONG_TABLES = {"_parser"}


def _functions(tree: ast.AST):
    for node in ast.walk(tree):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            yield node


def _is_kernel(fn) -> bool:
    """A numba kernel (``@njit``, ``@jit``): one loop nest, kept whole so that it compiles as one."""
    for d in fn.decorator_list:
        target = d.func if isinstance(d, ast.Call) else d
        name = target.attr if isinstance(target, ast.Attribute) else getattr(target, "id", "")
        if name in ("njit", "jit"):
            return True
    return False


def code_lines(fn, lines: list[str]) -> int:
    """Lines of code of a function: its lines less its docstring, blank lines and comment lines."""
    body = fn.body
    doc = range(0)
    if body and isinstance(body[0], ast.Expr) and isinstance(body[0].value, ast.Constant) \
            and isinstance(body[0].value.value, str):
        doc = range(body[0].lineno, body[0].end_lineno + 1)
    return sum(1 for i in range(fn.lineno, fn.end_lineno + 1)
               if i not in doc and lines[i - 1].strip() and not lines[i - 1].strip().startswith("#"))


def _bound_names(node) -> list[ast.Name]:
    """The names an assignment-like node binds (a subscript or attribute target binds none)."""
    if isinstance(node, ast.Assign):
        targets = node.targets
    elif isinstance(node, (ast.AugAssign, ast.AnnAssign, ast.For, ast.AsyncFor, ast.comprehension, ast.NamedExpr)):
        targets = [node.target]
    elif isinstance(node, ast.withitem):
        targets = [node.optional_vars] if node.optional_vars is not None else []
    else:
        return []
    found = []

    def visit(t):
        if isinstance(t, ast.Name):
            found.append(t)
        elif isinstance(t, (ast.Tuple, ast.List)):
            for e in t.elts:
                visit(e)
        elif isinstance(t, ast.Starred):
            visit(t.value)

    for t in targets:
        visit(t)
    return found


def reassigned_parameters(fn) -> list[tuple[int, str]]:
    """(line, name) of each parameter of ``fn`` that its own body binds again (nested functions are their own)."""
    a = fn.args
    params = {p.arg for p in a.posonlyargs + a.args + a.kwonlyargs + [a.vararg, a.kwarg] if p is not None}
    params -= {"self", "cls"}
    found, stack = [], list(fn.body)
    while stack:
        node = stack.pop()
        found += [(n.lineno, n.id) for n in _bound_names(node) if n.id in params]
        stack += [c for c in ast.iter_child_nodes(node)
                  if not isinstance(c, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda, ast.ClassDef))]
    return sorted(found)


def _parsed(path: Path):
    text = path.read_text()
    return ast.parse(text), text.splitlines()


@pytest.mark.parametrize("path", SOURCES, ids=lambda p: str(p.relative_to(ROOT)))
def test_no_function_runs_over_80_lines_of_code(path):
    tree, lines = _parsed(path)
    long = [(fn.name, code_lines(fn, lines)) for fn in _functions(tree)
            if fn.name not in LONG_TABLES and not _is_kernel(fn) and code_lines(fn, lines) > MAX_FUNCTION_LINES]
    assert not long, f"{path.name}: {long}"


@pytest.mark.parametrize("path", SOURCES, ids=lambda p: str(p.relative_to(ROOT)))
def test_no_module_runs_over_1000_lines(path):
    assert len(path.read_text().splitlines()) <= MAX_MODULE_LINES


@pytest.mark.parametrize("path", SOURCES, ids=lambda p: str(p.relative_to(ROOT)))
def test_no_function_reassigns_its_parameters(path):
    tree, _ = _parsed(path)
    found = [(fn.name, *hit) for fn in _functions(tree) for hit in reassigned_parameters(fn)]
    assert not found, f"{path.name}: {found}"


MAX_PARAMETERS = 8


def parameter_count(fn) -> int:
    """The parameters of ``fn`` a caller may give (``self`` and ``cls`` aside; ``*args``, ``**kwargs`` one each)."""
    a = fn.args
    named = [p for p in a.posonlyargs + a.args + a.kwonlyargs if p.arg not in ("self", "cls")]
    return len(named) + (a.vararg is not None) + (a.kwarg is not None)


def test_no_function_takes_more_than_8_parameters():
    """Related parameters travel as one small settings object (numba kernels aside: they take arrays)."""
    package = ROOT / "src" / "codedvideo"
    wide = [(str(path.relative_to(package)), fn.name, parameter_count(fn))
            for path in sorted(package.rglob("*.py")) for fn in _functions(_parsed(path)[0])
            if not _is_kernel(fn) and parameter_count(fn) > MAX_PARAMETERS]
    assert not wide, f"functions of more than {MAX_PARAMETERS} parameters: {wide}"


def test_the_checks_see_what_they_look_for():
    """The three measures on a small module: a long function, a kernel, a reassigned parameter and a
    subscript write (which is not a reassignment)."""
    body = "\n".join(f"    x{i} = {i}" for i in range(81))
    source = (f"def long(a):\n    '''doc'''\n    # note\n{body}\n\n"
              f"@njit(cache=True)\ndef kernel(out):\n{body}\n    out[0] = 1\n\n"
              "def f(a, b, *c, d=1):\n    a = 2\n    for b in c: pass\n    d[0] = 1\n    (e, *c) = 1, 2\n")
    tree = ast.parse(source)
    lines = source.splitlines()
    fns = {fn.name: fn for fn in _functions(tree)}
    assert code_lines(fns["long"], lines) == 82 and not _is_kernel(fns["long"]) and _is_kernel(fns["kernel"])
    assert [name for _, name in reassigned_parameters(fns["f"])] == ["a", "b", "c"]
    assert reassigned_parameters(fns["kernel"]) == []
    assert parameter_count(fns["f"]) == 4 and parameter_count(fns["kernel"]) == 1
    method = ast.parse("class C:\n    def m(self, a, *, b, **k): pass\n").body[0].body[0]
    assert parameter_count(method) == 3
