"""``python -m service serve|submit ...`` (the same commands as ``dsareg serve|submit``)."""

from __future__ import annotations

import argparse
import sys


def main(argv: list[str] | None = None) -> int:
    from dsareg_engine.cli import run_parsed

    from .commands import add_parser

    parser = argparse.ArgumentParser(prog="python -m service")
    add_parser(parser.add_subparsers(dest="command", required=True))
    return run_parsed(parser.parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
