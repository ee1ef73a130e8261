"""The import graph, read statically (``ast``), function-level imports included:

* ``dsareg_engine`` never imports ``service`` (the engine has no web code);
* in ``service/`` only the boundary module ``service.engine_adapter`` imports the engine, and only its two
  public modules: ``dsareg_engine.api`` and the command line's ``dsareg_engine.commands.kit``
  (``benchmarks`` is developer tooling that makes phantom cases);
* nothing in the engine imports either (they are the top of the engine's graph), and ``dsareg_engine.api``
  holds no command-line helper (it imports neither ``dsareg_engine.cli`` nor ``dsareg_engine.commands``, but
  ``commands.process_exit``, a process's set-up);
* no package re-exports lazily: a module-level ``__getattr__`` only in ``dsareg_engine.api``, whose lazy names
  are the heavy ones its docstring measures (:func:`test_lazy_names_only_where_start_up_needs_them`);
* the service's folders are layers: ``service.storage`` imports nothing else of the service,
  ``service.jobs`` never imports ``service.api``, and only ``service.app`` imports ``service.api``;
* the store's callers take the narrow interface they use (``service.storage.interfaces``): only the code that
  opens the store names the whole of it (``JobStore``, ``SqlJobStore``);
* submission is a service layer: ``service.intake`` and ``service.pacs`` never import ``service.api``, and
  ``service.intake`` imports no web framework (fastapi, starlette);
* every benchmark lives in ``benchmarks/`` (not packaged): nothing in the two packages imports it, and
  ``benchmarks.engine`` imports the engine only (it runs where only the engine's packages are installed);
* neither package has an import cycle, counting imports under ``if TYPE_CHECKING:`` too
  (:func:`test_no_import_cycles_even_type_only`).

The first rules count only imports that run: those under ``if TYPE_CHECKING:`` are skipped.
"""

from __future__ import annotations

import ast
from functools import cache
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("dsareg_engine", "service")
BOUNDARY = "service.engine_adapter"
ENGINE_API = "dsareg_engine.api"
ENGINE_PUBLIC = (ENGINE_API, "dsareg_engine.commands.kit")
LAZY_MODULES = {"dsareg_engine.pipeline", "dsareg_engine.io.case", "dsareg_engine.io.xa_run",
                "dsareg_engine.hemodynamics.intake", "dsareg_engine.io.model_cache", "dsareg_engine.io.volume_cost"}
"""What ``dsareg_engine.api`` loads on first use: torch and numba, or pydicom and PIL, or scipy (the model cache reads
volume readouts; its docstring measures them; the volume cost reads the volume's headers with the readers)."""


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


def _import_nodes(tree: ast.AST, type_only: bool = False):
    for node in ast.iter_child_nodes(tree):
        if isinstance(node, ast.If) and _is_type_checking(node) and not type_only:
            for child in node.orelse:
                yield from _import_nodes(ast.Module(body=[child], type_ignores=[]), type_only)
            continue
        if isinstance(node, (ast.Import, ast.ImportFrom)):
            yield node
        yield from _import_nodes(node, type_only)


def _imports(module: str, path: Path, modules: dict[str, Path], type_only: bool = False) -> set[str]:
    """Every module of the two packages that ``module`` imports (anywhere in its code; with ``type_only``
    also under ``if TYPE_CHECKING:``)."""
    is_package = path.name == "__init__.py"
    targets: set[str] = set()
    for node in _import_nodes(ast.parse(path.read_text(), str(path)), type_only):
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


@cache  # the files do not change during a run: read once for the ~20 rules (it was ~13 CPU-s, parsed per rule)
def _graph(type_only: bool = False) -> dict[str, frozenset[str]]:
    modules = _modules()
    return {name: frozenset(_imports(name, path, modules, type_only)) for name, path in modules.items()}


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
    assert {"dsareg_engine.api", "dsareg_engine.pipeline", "service.app", "service.api.routes.registrations"} <= set(graph)
    assert "service.api.deps" in graph["service.api.routes.registrations"]
    assert set(ENGINE_PUBLIC) <= graph[BOUNDARY]


def test_engine_never_imports_service():
    bad = {m: sorted(t for t in ts if t.split(".")[0] == "service")
           for m, ts in _graph().items() if m.startswith("dsareg_engine")}
    assert not {m: ts for m, ts in bad.items() if ts}


def test_only_the_boundary_imports_the_engine():
    bad = {}
    for module, targets in _graph().items():
        if module.split(".")[0] != "service":
            continue
        engine = sorted(t for t in targets if t.split(".")[0] == "dsareg_engine")
        allowed = list(ENGINE_PUBLIC) if module == BOUNDARY else []
        if engine != allowed and engine:
            bad[module] = engine
    assert not bad, f"only {BOUNDARY} may import the engine, and only {ENGINE_PUBLIC}: {bad}"


def test_nothing_in_the_engine_imports_its_api():
    assert not [m for m, ts in _graph().items() if m.startswith("dsareg_engine") and set(ENGINE_PUBLIC) & ts]


def test_the_api_holds_no_command_line_helper():
    commands = [t for t in _graph(type_only=True)[ENGINE_API]
                if _inside(t, "dsareg_engine.commands") or t == "dsareg_engine.cli"]
    assert commands == ["dsareg_engine.commands.process_exit"]


def _module_getattr(path: Path) -> bool:
    return any(isinstance(node, ast.FunctionDef) and node.name == "__getattr__"
               for node in ast.parse(path.read_text(), str(path)).body)


def _lazy_targets(path: Path) -> set[str]:
    """The module names in the ``_LAZY`` table of ``path`` (``{name: module}``)."""
    for node in ast.parse(path.read_text(), str(path)).body:
        if isinstance(node, ast.Assign) and any(isinstance(t, ast.Name) and t.id == "_LAZY" for t in node.targets):
            return {value.value for value in node.value.values}
    return set()


def test_lazy_names_only_where_start_up_needs_them():
    modules = _modules()
    lazy = sorted(m for m, path in modules.items() if _module_getattr(path))
    assert lazy == [ENGINE_API], "re-export plainly, or import from the defining module (docs/concepts/layout.md)"
    assert _lazy_targets(modules[ENGINE_API]) == LAZY_MODULES


def test_no_import_cycles():
    assert _cycles(_graph()) == []


def test_no_import_cycles_even_type_only():
    assert _cycles(_graph(type_only=True)) == []


def _service_imports(prefix: str) -> dict[str, list[str]]:
    """``service`` modules under ``prefix`` → the service modules they import (type-only imports included)."""
    return {m: sorted(t for t in ts if t.split(".")[0] == "service")
            for m, ts in _graph(type_only=True).items() if m == prefix or m.startswith(prefix + ".")}


def _inside(module: str, prefix: str) -> bool:
    return module == prefix or module.startswith(prefix + ".")


def test_storage_imports_nothing_else_of_the_service():
    bad = {m: [t for t in ts if not _inside(t, "service.storage") and t != "service"]
           for m, ts in _service_imports("service.storage").items()}
    assert not {m: ts for m, ts in bad.items() if ts}


def test_jobs_never_import_the_api():
    bad = {m: [t for t in ts if _inside(t, "service.api")] for m, ts in _service_imports("service.jobs").items()}
    assert not {m: ts for m, ts in bad.items() if ts}


def test_only_the_app_imports_the_api():
    bad = {m: [t for t in ts if _inside(t, "service.api")] for m, ts in _service_imports("service").items()
           if not _inside(m, "service.api") and m != "service.app"}
    assert not {m: ts for m, ts in bad.items() if ts}


def test_intake_and_pacs_never_import_the_api():
    bad = {m: [t for t in ts if _inside(t, "service.api")] for prefix in ("service.intake", "service.pacs")
           for m, ts in _service_imports(prefix).items()}
    assert not {m: ts for m, ts in bad.items() if ts}


STORE_OPENERS = {"service.intake.context", "service.cli.subcommands"}
"""The modules that open the job store (the service's context; ``dsareg db``'s first start) and so hold all of it."""


def _imported_names(path: Path) -> set[str]:
    """The names ``path`` imports with ``from … import name`` (type-only imports included)."""
    return {alias.name for node in _import_nodes(ast.parse(path.read_text(), str(path)), type_only=True)
            if isinstance(node, ast.ImportFrom) for alias in node.names}


def test_store_callers_take_a_narrow_interface():
    whole = {m for m, path in _modules().items() if _inside(m, "service") and not _inside(m, "service.storage")
             and {"JobStore", "SqlJobStore"} & _imported_names(path)}
    assert whole == STORE_OPENERS, "take Jobs, Leases, Reviews, DeliveryStore, Upkeep or DicomInbox"


WEB_FRAMEWORKS = ("fastapi", "starlette")


def _external_imports(path: Path) -> set[str]:
    """The top-level names of the absolute imports in ``path`` (type-only imports included)."""
    found = set()
    for node in _import_nodes(ast.parse(path.read_text(), str(path)), type_only=True):
        if isinstance(node, ast.Import):
            found |= {alias.name.split(".")[0] for alias in node.names}
        elif node.level == 0 and node.module:
            found.add(node.module.split(".")[0])
    return found


def test_benchmarks_live_outside_the_packages():
    benchmarks = sorted((ROOT / "benchmarks").rglob("*.py"))
    assert ROOT / "benchmarks" / "engine" / "cli.py" in benchmarks and ROOT / "benchmarks" / "service" / "load.py" in benchmarks
    importers = {m for m, path in _modules().items() if "benchmarks" in _external_imports(path)}
    assert not importers, f"the packages never import benchmarks/: {sorted(importers)}"
    assert not [p for p in (ROOT / "dsareg_engine").rglob("*.py") if p.name.startswith("bench")]
    engine = {str(p.relative_to(ROOT)): sorted(_external_imports(p) & {"service", "tests", "sqlalchemy", "fastapi"})
              for p in benchmarks if "engine" in p.relative_to(ROOT).parts}
    assert not {path: names for path, names in engine.items() if names}, engine


def test_intake_imports_no_web_framework():
    bad = {m: sorted(_external_imports(path) & set(WEB_FRAMEWORKS)) for m, path in _modules().items()
           if _inside(m, "service.intake")}
    assert bad and not {m: names for m, names in bad.items() if names}


def test_folder_rules_see_a_violation():
    graph = _graph(type_only=True)
    assert "service.jobs.sweeper" in graph["service.api.deps"]  # a type-only import is read
    assert "service.storage.store" in graph["service.jobs.worker"]
    assert "fastapi" in _external_imports(ROOT / "service" / "api" / "deps.py")
    assert "service.intake.submission" in graph["service.pacs.dimse.submit"]


def test_cycle_finder_finds_cycles():
    assert _cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
