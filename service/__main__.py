"""``python -m service serve|submit ...`` (the same commands as ``dsareg serve|submit``)."""

from __future__ import annotations

import argparse
import sys


def main(argv: list[str] | None = None) -> int:
    from dsareg_engine.errors import DsaregInputError

    from .commands import add_parser

    parser = argparse.ArgumentParser(prog="python -m service")
    add_parser(parser.add_subparsers(dest="command", required=True))
    args = parser.parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except DsaregInputError as exc:
        print(f"dsareg: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    sys.exit(main())
