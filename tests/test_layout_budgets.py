"""Budgets of the layout, read statically (``ast``): function length, modules at the package roots, clashing
module names, and the one place where an engine input error becomes an HTTP 422."""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
MAX_FUNCTION_LINES = {"service": 60, "dsareg_engine": 80}
MAX_ROOT_MODULES = {"service": 8, "dsareg_engine": 12}  # .py files directly in the package, __init__ included
LONG_FUNCTIONS_ALLOWED = {
    # being split into a stage runner and a summary (issue 25, engineer "partial"); remove when that lands
    "dsareg_engine/registration/solver.py:_register",
}
UNIQUE_NAMES = ("metrics", "limits", "commands", "errors")


def _sources(package: str):
    for path in sorted((ROOT / package).rglob("*.py")):
        yield path, ast.parse(path.read_text(), str(path))


def _functions(tree: ast.AST):
    for node in ast.walk(tree):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            yield node


def long_functions(package: str) -> dict[str, int]:
    """``"path:name"`` → lines (decorators excluded, docstring included) of functions over the package's budget."""
    found = {}
    for path, tree in _sources(package):
        for node in _functions(tree):
            lines = node.end_lineno - node.lineno + 1
            if lines > MAX_FUNCTION_LINES[package]:
                found[f"{path.relative_to(ROOT)}:{node.name}"] = lines
    return found


def test_no_function_is_longer_than_the_budget():
    over = {name: lines for package in MAX_FUNCTION_LINES for name, lines in long_functions(package).items()
            if name not in LONG_FUNCTIONS_ALLOWED}
    assert not over, f"functions over {MAX_FUNCTION_LINES} lines: {over}"


def test_package_roots_hold_few_modules():
    counts = {package: len(list((ROOT / package).glob("*.py"))) for package in MAX_ROOT_MODULES}
    assert all(counts[p] <= MAX_ROOT_MODULES[p] for p in counts), (counts, MAX_ROOT_MODULES)


def test_no_two_modules_share_a_clashing_name():
    places: dict[str, list[str]] = {name: [] for name in UNIQUE_NAMES}
    for package in MAX_ROOT_MODULES:
        for path in (ROOT / package).rglob("*"):
            stem = path.stem if path.suffix == ".py" else path.name if path.is_dir() else None
            if stem in places and "__pycache__" not in path.parts:
                places[stem].append(str(path.relative_to(ROOT)))
    assert all(len(found) <= 1 for found in places.values()), places


def _maps_input_error_to_problem(tree: ast.AST) -> list[int]:
    """Lines of ``except …DsaregInputError`` blocks that raise a ``Problem`` by hand."""
    lines = []
    for node in ast.walk(tree):
        if isinstance(node, ast.ExceptHandler) and node.type is not None and \
                "DsaregInputError" in ast.unparse(node.type):
            raises = [n for child in node.body for n in ast.walk(child) if isinstance(n, ast.Raise) and n.exc]
            if any("Problem" in ast.unparse(r.exc) for r in raises):
                lines.append(node.lineno)
    return lines


def test_one_handler_maps_engine_input_errors_to_422():
    hand_written = {str(path.relative_to(ROOT)): lines for path, tree in _sources("service")
                    if (lines := _maps_input_error_to_problem(tree))}
    assert not hand_written, f"let DsaregInputError reach service/api/handlers.py (on_input_error): {hand_written}"
    handlers = (ROOT / "service" / "api" / "handlers.py").read_text()
    assert "add_exception_handler(engine.DsaregInputError, on_input_error)" in handlers


def test_the_budget_readers_see_violations():
    tree = ast.parse("def f():\n    try:\n        g()\n    except engine.DsaregInputError as exc:\n"
                     "        raise Problem(422, exc.message) from None\n")
    assert _maps_input_error_to_problem(tree) == [4]
    long = ast.parse("def f():\n" + "    x = 1\n" * 100)
    assert [n.end_lineno - n.lineno + 1 for n in _functions(long)] == [101]
