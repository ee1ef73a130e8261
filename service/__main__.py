"""``python -m service serve|submit ...`` (the same commands as ``dsareg serve|submit``)."""

from __future__ import annotations

import argparse
import sys


def main(argv: list[str] | None = None) -> int:
    from .cli.subcommands import add_parser
    from .engine_adapter import commands

    parser = argparse.ArgumentParser(prog="python -m service")
    add_parser(parser.add_subparsers(dest="command", required=True))
    return commands.run_parsed(parser.parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
