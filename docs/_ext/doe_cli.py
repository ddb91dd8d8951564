"""The command-line reference, generated from the real ``doe`` parser.

``.. doe-cli::`` builds the parser the installed tool uses (:func:`doedesign.cli.build_parser`,
every command from the ``doe.commands`` entry points) and renders, for the root and for every
command and sub-command, a section with its usage, its description, its epilog and a table of
its arguments (names, metavar, help, default). Nothing is copied by hand: a new option shows
up at the next build, a removed one disappears. Help texts are rendered as plain text (they
are written for a terminal), so no markup in them can break the build.
"""

from __future__ import annotations

import argparse
from collections.abc import Iterator

from docutils import nodes
from sphinx.application import Sphinx
from sphinx.util.docutils import SphinxDirective

__all__ = ["DoeCliDirective", "commands", "setup"]


def commands(parser: argparse.ArgumentParser, path: tuple[str, ...] = ()) -> Iterator[tuple[tuple[str, ...], argparse.ArgumentParser]]:
    """Every parser under ``parser``, depth first, with the command words that reach it.

    Parameters
    ----------
    parser : argparse.ArgumentParser
        The root parser (``doe``).
    path : tuple of str
        The command words of ``parser`` itself (empty for the root).

    Yields
    ------
    tuple of str, argparse.ArgumentParser
        ``("calibrate", "psf")`` and the parser of ``doe calibrate psf``, sorted by name.
    """
    yield path, parser
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name in sorted(action.choices):
                yield from commands(action.choices[name], path + (name,))


def _help_of(parser: argparse.ArgumentParser, name: str) -> str:
    """The one-line help a parent gives the sub-command ``name`` (empty when none)."""
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for choice in action._choices_actions:
                if choice.dest == name or choice.metavar == name:
                    return choice.help or ""
    return ""


def _text_blocks(text: str) -> list[nodes.Node]:
    """Paragraphs of a help text; indented or table-like blocks stay literal."""
    out: list[nodes.Node] = []
    for block in text.strip("\n").split("\n\n"):
        if not block.strip():
            continue
        lines = block.split("\n")
        if any(line.startswith(" ") for line in lines) or any("=" in line and line.strip().startswith("[") for line in lines):
            out.append(nodes.literal_block(block, block, language="text"))
        else:
            out.append(nodes.paragraph("", " ".join(line.strip() for line in lines)))
    return out


def _argument_rows(parser: argparse.ArgumentParser) -> list[tuple[str, str, str]]:
    """(names, help, default) of each argument of ``parser`` but ``--help`` and sub-commands."""
    rows = []
    for action in parser._actions:
        if isinstance(action, (argparse._HelpAction, argparse._SubParsersAction)) or action.help == argparse.SUPPRESS:
            continue
        formatter = parser._get_formatter()
        names = formatter._format_action_invocation(action)
        default = ""
        if action.option_strings and action.nargs != 0 and action.default not in (None, argparse.SUPPRESS):
            default = repr(action.default) if isinstance(action.default, str) else str(action.default)
        required = " (required)" if getattr(action, "required", False) and action.option_strings else ""
        text = formatter._expand_help(action) if action.help else ""
        rows.append((names, text + required, default))
    return rows


def _table(rows: list[tuple[str, str, str]]) -> nodes.table:
    table = nodes.table(classes=["doe-cli-options"])
    group = nodes.tgroup(cols=3)
    table += group
    for width in (30, 55, 15):
        group += nodes.colspec(colwidth=width)
    head = nodes.thead()
    group += head
    body = nodes.tbody()
    group += body
    for target, cells in ((head, ("argument", "what it sets", "default")),) + tuple((body, r) for r in rows):
        row = nodes.row()
        for i, cell in enumerate(cells):
            entry = nodes.entry()
            entry += nodes.paragraph("", "", nodes.literal(cell, cell)) if i != 1 and cell else nodes.paragraph("", cell)
            row += entry
        target += row
    return table


class DoeCliDirective(SphinxDirective):
    """``.. doe-cli::``: one section per command of the real ``doe`` parser."""

    has_content = False

    def run(self) -> list[nodes.Node]:
        from doedesign.cli import build_parser

        root = build_parser()
        sections: list[nodes.Node] = []
        parents = dict(commands(root))
        for path, parser in commands(root):
            title = " ".join(("doe",) + path)
            section = nodes.section(ids=[nodes.make_id("cli-" + "-".join(path or ("doe",)))])
            section += nodes.title(title, "", nodes.literal(title, title))
            summary = _help_of(parents[path[:-1]], path[-1]) if path else ""
            if summary:
                section += nodes.paragraph("", summary[:1].upper() + summary[1:] + ".")
            usage = parser.format_usage().strip()
            section += nodes.literal_block(usage, usage, language="text")
            for text in (parser.description, parser.epilog):
                if text:
                    section += _text_blocks(text)
            rows = _argument_rows(parser)
            if rows:
                section += _table(rows)
            sections.append(section)
        return sections


def setup(app: Sphinx) -> dict[str, object]:
    app.add_directive("doe-cli", DoeCliDirective)
    return {"parallel_read_safe": True, "parallel_write_safe": True}
