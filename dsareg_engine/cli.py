"""The ``dsareg`` command line: one sub-command per job, each in its own module.

Sub-command modules expose ``add_parser(subparsers)``; the parser they register sets
``func`` to a callable ``(args) -> int``. Errors go through one path
(:mod:`dsareg_engine.commands.failures`): one line on stderr, exit status 2 for usage and
input errors, 1 when the work failed; no traceback reaches the user unless ``--debug``.
"""

from __future__ import annotations

import argparse
import importlib
import importlib.metadata
import sys
import tomllib
from pathlib import Path

from .commands.failures import run_guarded
from .commands.process_exit import skip_exit_collections

COMMAND_MODULES = (
    "dsareg_engine.commands.render",
    "dsareg_engine.commands.inputs",
    "dsareg_engine.commands.register",
    "dsareg_engine.commands.warmup",
    "dsareg_engine.commands.phantom_study",
    "dsareg_engine.commands.run_benchmark",
)
"""The engine's own sub-commands (modules with ``add_parser``). They import only what their arguments need
(no torch, no numba: ``dsareg --help`` and argument errors take well under a second); the work loads when a
command runs (``func`` imports it, or is a :func:`~dsareg_engine.commands.deferred.deferred` reference)."""

COMMAND_GROUP = "dsareg.commands"
"""Entry-point group through which other packages contribute sub-commands: each entry point is a
callable ``add_parser(subparsers)`` (the service's: ``service = "service.cli.subcommands:add_parser"``)."""


def contributed_commands() -> list[tuple[str, str]]:
    """``(name, "module:function")`` of the sub-commands other installed packages contribute.

    Read from the installed metadata; where it has no such group (an editable install made before
    the group was declared, or a source tree on ``PYTHONPATH``), from the group in this checkout's
    ``pyproject.toml``.
    """
    found = sorted((ep.name, ep.value) for ep in importlib.metadata.entry_points(group=COMMAND_GROUP))
    return found or source_tree_commands()


def source_tree_commands(pyproject: Path | None = None) -> list[tuple[str, str]]:
    """The ``dsareg.commands`` entry points declared in the ``pyproject.toml`` next to this package."""
    pyproject = pyproject or Path(__file__).resolve().parents[1] / "pyproject.toml"
    try:
        project = tomllib.loads(pyproject.read_text()).get("project", {})
    except (OSError, tomllib.TOMLDecodeError):
        return []
    if project.get("name") != "dsareg":
        return []
    return sorted(project.get("entry-points", {}).get(COMMAND_GROUP, {}).items())


def _load(module_name: str, attribute: str = "add_parser"):
    """``module.attribute``, or None when the module is not installed (an optional contributor)."""
    try:
        module = importlib.import_module(module_name)
    except ModuleNotFoundError as exc:
        if exc.name is None or not (module_name == exc.name or module_name.startswith(exc.name + ".")):
            raise  # a real import error inside the module: surface it
        return None
    return getattr(module, attribute)


def _load_target(target: str):
    """The callable an entry-point value ``"module:attribute"`` names, or None when the module is not installed."""
    module_name, _, attribute = target.partition(":")
    return _load(module_name.strip(), attribute.strip() or "add_parser")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="dsareg", description="3D/2D vessel registration for biplane DSA. `dsareg COMMAND --help` describes "
        "each command.",
        epilog="Exit status: 0 done, 1 the work failed (server unreachable, job failed), 2 usage or input error.")
    parser.add_argument("--debug", action="store_true", help="show Python tracebacks of errors (for bug reports)")
    subparsers = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    adders = [_load(name) for name in COMMAND_MODULES]
    in_checkout = dict(source_tree_commands())
    for name, target in contributed_commands():
        add_parser = _load_target(target)
        if add_parser is None and in_checkout.get(name, target) != target:
            add_parser = _load_target(in_checkout[name])  # stale install metadata: the module moved in this checkout
        adders.append(add_parser)
    for add_parser in adders:
        if add_parser is not None:
            _add_commands(add_parser, subparsers)
    return parser


def _add_commands(add_parser, subparsers) -> None:
    """Let a contributor add its sub-commands; one whose own dependencies are missing is left out with a
    one-line note (the engine's commands keep working: e.g. the service's without SQLAlchemy)."""
    try:
        add_parser(subparsers)
    except ModuleNotFoundError as exc:
        owner = getattr(add_parser, "__module__", "?")
        print(f"dsareg: the commands of {owner} are unavailable: missing module {exc.name!r}", file=sys.stderr)


def main(argv: list[str] | None = None) -> int:
    return run_parsed(build_parser().parse_args(argv))


def run_parsed(args: argparse.Namespace) -> int:
    """Run a parsed sub-command; errors become one line on stderr and exit status 2 (usage) or 1."""
    skip_exit_collections()  # `dsareg serve`, `worker`, every command: seconds less at exit (process_exit)
    return run_guarded(args.func, args)


if __name__ == "__main__":
    sys.exit(main())
