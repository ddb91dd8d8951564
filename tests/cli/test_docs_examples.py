"""The documentation's examples work: every Python block of the pages runs, and every `doe`
command line shown in the pages and the README parses with the real parser (each command
and option it names exists and takes the value shown)."""

from __future__ import annotations

import re
import shlex
from pathlib import Path

import pytest

from doedesign.cli import build_parser

ROOT = Path(__file__).resolve().parents[2]
PAGES = sorted(p for p in (ROOT / "docs").rglob("*.md") if "_build" not in p.parts) + [ROOT / "README.md"]
FENCE = re.compile(r"^```(\w*)[^\n]*\n(.*?)^```", re.S | re.M)


def _blocks(path, languages):
    return [body for lang, body in FENCE.findall(path.read_text()) if lang in languages]


PYTHON = [(p, i, code) for p in PAGES for i, code in enumerate(_blocks(p, {"python"}))]
COMMANDS = sorted({(p.relative_to(ROOT).as_posix(), line.split("#")[0].strip())
                   for p in PAGES for body in _blocks(p, {"", "console", "bash", "shell"})
                   for line in body.replace("\\\n", " ").splitlines() if line.strip().startswith("doe ")})


def command_words(line):
    """The words of a command line as shown, optional parts (``[--x3p]``) taken as given."""
    return [w for w in shlex.split(line.replace("[", " ").replace("]", " ")) if w not in ("|",)][1:]


def test_the_pages_hold_examples():
    assert len(PYTHON) >= 3, PYTHON
    assert len(COMMANDS) >= 20, COMMANDS


@pytest.mark.parametrize("path,index,code", PYTHON, ids=[f"{p.relative_to(ROOT)}#{i}" for p, i, _ in PYTHON])
def test_python_example_runs(path, index, code, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    exec(compile(code, f"{path.name}#{index}", "exec"), {"__name__": "__docs__"})


@pytest.mark.parametrize("page,line", COMMANDS, ids=[f"{p}: {c}" for p, c in COMMANDS])
def test_command_line_parses(page, line):
    argv = command_words(line)
    try:
        args = build_parser(argv).parse_args(argv)
    except SystemExit as exc:
        pytest.fail(f"{page}: `{line}` does not parse (exit {exc.code})")
    assert getattr(args, "func", None), f"{page}: `{line}` names no command"


def test_a_wrong_option_is_caught():
    # the check above must fail on what it guards against
    for bad in ("doe masks design.npz --out m/ --no-such-option", "doe psf design.npz --out p.npz --png"):
        with pytest.raises(SystemExit):
            argv = command_words(bad)
            build_parser(argv).parse_args(argv)
