"""The ``dsareg`` command line: one sub-command per job, each in its own module.

Sub-command modules expose ``add_parser(subparsers)``; the parser they register sets
``func`` to a callable ``(args) -> int``. Errors go through one path
(:mod:`dsareg_engine.commands.errors`): one line on stderr, exit status 2 for usage and
input errors, 1 when the work failed; no traceback reaches the user unless ``--debug``.
"""

from __future__ import annotations

import argparse
import importlib
import sys

from .commands.errors import run_guarded

COMMAND_MODULES = (
    "dsareg_engine.commands.render",
    "dsareg_engine.commands.inputs",
    "dsareg_engine.commands.register",
    "dsareg_engine.commands.bench",
    "service.commands",
)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="dsareg", description="3D/2D vessel registration for biplane DSA. `dsareg COMMAND --help` describes "
        "each command.",
        epilog="Exit status: 0 done, 1 the work failed (server unreachable, job failed), 2 usage or input error.")
    parser.add_argument("--debug", action="store_true", help="show Python tracebacks of errors (for bug reports)")
    subparsers = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name in COMMAND_MODULES:
        try:
            module = importlib.import_module(name)
        except ModuleNotFoundError as exc:
            if exc.name != name:  # a real import error inside the module: surface it
                raise
            continue
        module.add_parser(subparsers)
    return parser


def main(argv: list[str] | None = None) -> int:
    return run_parsed(build_parser().parse_args(argv))


def run_parsed(args: argparse.Namespace) -> int:
    """Run a parsed sub-command; errors become one line on stderr and exit status 2 (usage) or 1."""
    return run_guarded(args.func, args)


if __name__ == "__main__":
    sys.exit(main())
