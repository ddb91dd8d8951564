"""The ``doe`` command-line program.

Each package plugs its own subcommands in through the ``doe.commands`` entry-point group
(``[project.entry-points."doe.commands"]`` in pyproject.toml): each entry names a
``register(subparsers)`` function. This root only discovers and assembles them, so it
names no package above ``doedesign``. User mistakes (:class:`~doedesign.errors.DoeError`)
print one line and exit 2.
"""

from __future__ import annotations

import argparse
from collections.abc import Sequence
from importlib.metadata import entry_points
import logging
import sys

from ..errors import DoeError

__all__ = ["ENTRY_POINT_GROUP", "build_parser", "main"]

ENTRY_POINT_GROUP = "doe.commands"


log = logging.getLogger("doe")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="doe",
        description="Design, mask making and metrology of multi-level diffractive optical elements.")
    parser.add_argument("-v", "--verbose", action="store_true", help="log progress details")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for entry in sorted(entry_points(group=ENTRY_POINT_GROUP), key=lambda e: e.name):
        entry.load()(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    import matplotlib

    # Files only, no windows: the CLI never needs an interactive backend.
    matplotlib.use("Agg")
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:  # argparse refused an option (one line, status 2) or printed --help
        return exc.code if isinstance(exc.code, int) else 2
    logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING,
                        format="%(levelname)s %(name)s: %(message)s")
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    try:
        return int(args.func(args) or 0)
    except DoeError as exc:
        print(f"doe {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("doe: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
