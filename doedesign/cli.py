"""The ``doe`` command-line program.

Each stage adds its own subcommands from a module with a ``register(subparsers)``
function; this file only assembles them, so stages do not edit one shared file.
User mistakes (:class:`~doedesign.errors.DoeError`) print one line and exit 2.
"""

from __future__ import annotations

import argparse
import importlib
import json
import logging
import sys

from .errors import DoeError

# Stage modules providing ``register(subparsers)``. masks and metrology are imported
# by name at run time: the CLI is the application on top of all three packages.
COMMAND_MODULES = (
    "doedesign.cli_core",
    "doedesign.cli_design",
    "masks.cli",
    "metrology.cli",
    "metrology.cli_calibrate",
    "metrology.cli_diagnose",
    "metrology.cli_demo",
)

log = logging.getLogger("doe")


def build_parser():
    parser = argparse.ArgumentParser(
        prog="doe",
        description="Design, mask making and metrology of multi-level diffractive optical elements.")
    parser.add_argument("-v", "--verbose", action="store_true", help="log progress details")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in COMMAND_MODULES:
        try:
            module = importlib.import_module(name)
        except ModuleNotFoundError as exc:
            if exc.name != name:
                raise
            continue
        module.register(sub)
    return parser


def main(argv=None):
    import matplotlib

    # Files only, no windows: the CLI never needs an interactive backend.
    matplotlib.use("Agg")
    parser = build_parser()
    args = parser.parse_args(argv)
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


def print_json(obj):
    """Print ``obj`` as JSON on stdout (numpy values allowed)."""
    from .fileio import _json_default

    sys.stdout.write(json.dumps(obj, indent=2, default=_json_default) + "\n")


if __name__ == "__main__":
    sys.exit(main())
