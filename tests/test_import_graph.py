"""The import graph, read statically (``ast``), function-level imports included:

* ``dsareg_engine`` never imports ``service`` (the engine has no web code);
* in ``service/`` only the boundary module ``service.engine_adapter`` imports the engine, and only
  ``dsareg_engine.api`` (``service.bench`` is developer tooling that makes phantom cases);
* nothing in the engine imports ``dsareg_engine.api`` (it is the top of the engine's graph);
* neither package has an import cycle.

Imports under ``if TYPE_CHECKING:`` never run and are not counted.
"""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("dsareg_engine", "service")
BOUNDARY = "service.engine_adapter"
ENGINE_API = "dsareg_engine.api"
DEV_TOOLING = ("service.bench",)


def _modules() -> dict[str, Path]:
    found = {}
    for package in PACKAGES:
        for path in sorted((ROOT / package).rglob("*.py")):
            parts = list(path.relative_to(ROOT).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts.pop()
            found[".".join(parts)] = path
    return found


def _is_type_checking(node: ast.If) -> bool:
    test = node.test
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
        isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING")


def _import_nodes(tree: ast.AST):
    for node in ast.iter_child_nodes(tree):
        if isinstance(node, ast.If) and _is_type_checking(node):
            for child in node.orelse:
                yield from _import_nodes(ast.Module(body=[child], type_ignores=[]))
            continue
        if isinstance(node, (ast.Import, ast.ImportFrom)):
            yield node
        yield from _import_nodes(node)


def _imports(module: str, path: Path, modules: dict[str, Path]) -> set[str]:
    """Every module of the two packages that ``module`` imports (anywhere in its code)."""
    is_package = path.name == "__init__.py"
    targets: set[str] = set()
    for node in _import_nodes(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            names = [alias.name for alias in node.names]
        else:
            if node.level:
                base = module.split(".") if is_package else module.split(".")[:-1]
                base = base[: len(base) - (node.level - 1)]
                stem = ".".join([*base, node.module] if node.module else base)
            else:
                stem = node.module or ""
            names = [f"{stem}.{alias.name}" if f"{stem}.{alias.name}" in modules else stem for alias in node.names]
        for name in names:
            while name and name not in modules:  # `import a.b.c` where only a.b is ours, or a name in a module
                name = name.rpartition(".")[0]
            if name:
                targets.add(name)
    targets.discard(module)
    return targets


def _graph() -> dict[str, set[str]]:
    modules = _modules()
    return {name: _imports(name, path, modules) for name, path in modules.items()}


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []

    def visit(node: str) -> None:
        index[node] = low[node] = len(index)
        stack.append(node)
        on_stack.add(node)
        for target in sorted(graph.get(node, ())):
            if target not in index:
                visit(target)
                low[node] = min(low[node], low[target])
            elif target in on_stack:
                low[node] = min(low[node], index[target])
        if low[node] == index[node]:
            component = []
            while True:
                member = stack.pop()
                on_stack.discard(member)
                component.append(member)
                if member == node:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for node in sorted(graph):
        if node not in index:
            visit(node)
    return found


def test_the_graph_is_read():
    graph = _graph()
    assert {"dsareg_engine.api", "dsareg_engine.pipeline", "service.app", "service.api.registrations"} <= set(graph)
    assert "service.api.deps" in graph["service.api.registrations"]
    assert ENGINE_API in graph[BOUNDARY]


def test_engine_never_imports_service():
    bad = {m: sorted(t for t in ts if t.split(".")[0] == "service")
           for m, ts in _graph().items() if m.startswith("dsareg_engine")}
    assert not {m: ts for m, ts in bad.items() if ts}


def test_only_the_boundary_imports_the_engine():
    bad = {}
    for module, targets in _graph().items():
        if module.split(".")[0] != "service" or module.startswith(DEV_TOOLING):
            continue
        engine = sorted(t for t in targets if t.split(".")[0] == "dsareg_engine")
        allowed = [ENGINE_API] if module == BOUNDARY else []
        if engine != allowed and engine:
            bad[module] = engine
    assert not bad, f"only {BOUNDARY} may import the engine, and only {ENGINE_API}: {bad}"


def test_nothing_in_the_engine_imports_its_api():
    assert not [m for m, ts in _graph().items() if m.startswith("dsareg_engine") and ENGINE_API in ts]


def test_no_import_cycles():
    assert _cycles(_graph()) == []


def test_cycle_finder_finds_cycles():
    assert _cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
