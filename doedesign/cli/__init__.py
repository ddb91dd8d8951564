"""The ``doe`` command-line program.

Each package plugs its own subcommands in through the ``doe.commands`` entry-point group
(``[project.entry-points."doe.commands"]`` in pyproject.toml): each entry names a
``register(subparsers)`` function. This root only discovers and assembles them, so it
names no package above ``doedesign``. Only the named command's entry point is loaded (its
imports are the start-up cost of every run); ``doe``, ``doe --help`` and a name that is no
command load them all, so the help lists every command. User mistakes
(:class:`~doedesign.errors.DoeError`) print one line and exit 2; so does a ``MemoryError``
that no size check foresaw (the size asked and the limits the process runs under).
"""

from __future__ import annotations

import argparse
import ctypes
from collections.abc import Sequence
from importlib.metadata import entry_points
import logging
import os
import sys

from ..errors import DoeError

__all__ = ["ENTRY_POINT_GROUP", "build_parser", "main"]

ENTRY_POINT_GROUP = "doe.commands"
# mallopt(3) parameters.
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3


log = logging.getLogger("doe")


def build_parser(argv: Sequence[str] | None = None) -> argparse.ArgumentParser:
    """The ``doe`` parser with every command, or only the one ``argv`` names.

    Parameters
    ----------
    argv : list of str, optional
        The command line (without the program name). When its first word that is not an
        option names a command, only that command's entry point is loaded.
    """
    parser = argparse.ArgumentParser(
        prog="doe",
        description="Design, mask making and metrology of multi-level diffractive optical elements.")
    parser.add_argument("-v", "--verbose", action="store_true", help="log progress details")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    entries = sorted(entry_points(group=ENTRY_POINT_GROUP), key=lambda e: e.name)
    # the root has flag options only, so the first bare word is the command
    named = next((a for a in (argv or []) if not a.startswith("-")), None)
    chosen = [e for e in entries if e.name == named] or entries
    for entry in chosen:
        entry.load()(sub)
    return parser


def _files_only_backend() -> None:
    """Files only, no windows: the CLI never needs an interactive matplotlib backend.

    Set through the environment so that a command which draws nothing never imports
    matplotlib (a second of start-up); a matplotlib already imported is switched directly.
    """
    if "matplotlib" in sys.modules:
        sys.modules["matplotlib"].use("Agg")
    else:
        os.environ["MPLBACKEND"] = "Agg"


def _keep_freed_memory() -> None:
    """Ask glibc's allocator to keep freed memory for reuse instead of returning it.

    Fits render large arrays again and again; each one returned to the kernel comes back as
    fresh pages that the kernel zeroes, at about 1 GB/s on a virtual machine (a fifth of a
    512 px camera diagnosis went there). Arrays up to 32 MiB (the allocator's largest
    threshold) then come from the heap, which is never trimmed. Elsewhere: nothing.
    """
    try:
        libc = ctypes.CDLL("libc.so.6")
    except OSError:
        return
    libc.mallopt(_M_TRIM_THRESHOLD, ctypes.c_int(2 ** 31 - 1))
    libc.mallopt(_M_MMAP_THRESHOLD, ctypes.c_int(32 * 2 ** 20))


def main(argv: Sequence[str] | None = None) -> int:
    """Run the ``doe`` command with ``argv`` (default the process's arguments); return the exit code."""
    _files_only_backend()
    _keep_freed_memory()
    argv = sys.argv[1:] if argv is None else list(argv)
    parser = build_parser(argv)
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
    except MemoryError as exc:  # numpy's _ArrayMemoryError too: what no estimate foresaw
        from ..budget import memory_message

        print(f"doe {args.command}: error: {memory_message(exc)}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("doe: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
