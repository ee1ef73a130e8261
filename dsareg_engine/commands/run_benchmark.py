"""``dsareg bench NAME …``: the engine's benchmarks, which live in the source repository (``benchmarks/engine``,
not in the installed package: they print tables for the docs and are run from a checkout).

The command replaces itself with ``python -m benchmarks.engine NAME …`` run with this checkout on the module path;
the working directory is kept, so relative paths in the arguments mean what they meant. Its own parser takes no
options (``prefix_chars="+"``): ``dsareg bench clinical --help`` is the benchmark's help. Outside a checkout it
says where the benchmarks are (exit 2).
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

CHECKOUT = Path(__file__).resolve().parents[2]
"""The directory holding ``dsareg_engine/``; a source checkout when ``benchmarks/engine`` is beside it."""


def add_parser(subparsers) -> None:
    parser = subparsers.add_parser(
        "bench", add_help=False, prefix_chars="+",
        help="run a benchmark that prints a Markdown table (from a source checkout: python -m benchmarks.engine)",
        description="Run one of the engine's benchmarks: `dsareg bench --help` lists them.")
    parser.add_argument("arguments", nargs=argparse.REMAINDER, help="the benchmark's name and its arguments")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from ..errors import DsaregInputError

    if not (CHECKOUT / "benchmarks" / "engine" / "cli.py").is_file():
        raise DsaregInputError(f"the benchmarks ship with the source repository (benchmarks/engine), not with this "
                               f"installation ({CHECKOUT}); run `dsareg bench` or `python -m benchmarks.engine NAME` in a checkout")
    command = [sys.executable, "-m", "benchmarks.engine", *(["--debug"] if args.debug else []),
               *(args.arguments or ["--help"])]
    path = os.pathsep.join(p for p in (str(CHECKOUT), os.environ.get("PYTHONPATH", "")) if p)
    sys.stdout.flush()
    sys.stderr.flush()
    os.execve(sys.executable, command, {**os.environ, "PYTHONPATH": path})
    return 0  # not reached: execve replaces this process
