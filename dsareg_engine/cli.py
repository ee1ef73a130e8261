"""The ``dsareg`` command line: one sub-command per job, each in its own module.

Sub-command modules expose ``add_parser(subparsers)``; the parser they register sets
``func`` to a callable ``(args) -> int``. User errors (:class:`DsaregInputError`) are
printed as one line and exit with status 2; no traceback reaches the user.
"""

from __future__ import annotations

import argparse
import importlib
import sys

from .errors import DsaregInputError

COMMAND_MODULES = (
    "dsareg_engine.commands.render",
    "dsareg_engine.commands.inputs",
    "dsareg_engine.commands.register",
    "dsareg_engine.commands.bench",
    "service.commands",
)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="dsareg", description="3D/2D vessel registration for biplane DSA")
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
    """Run a parsed sub-command; user errors become one line on stderr and exit status 2."""
    try:
        return int(args.func(args) or 0)
    except DsaregInputError as exc:
        print(f"dsareg: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    sys.exit(main())
