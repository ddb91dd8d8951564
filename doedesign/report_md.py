"""Small Markdown building blocks shared by every report a person reads (``report.md``).

Each command writes its machine-readable ``report.json`` and, beside it, a Markdown page
built from these pieces: headings, tables with units in the column names, numbers with
uncertainties, verdicts in words, inline figures and a link to the JSON. Nothing here
knows about a particular report; the pages are assembled by the commands.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from pathlib import Path

from .fileio import atomic_path

__all__ = ["fmt", "fmt_pm", "table", "figure", "verdict", "json_link", "join", "write_markdown", "MISSING"]

MISSING = "n/a"


def fmt(value: object, digits: int = 3, unit: str = "") -> str:
    """``value`` with ``digits`` significant digits (and a unit); ``n/a`` for None / NaN / text."""
    if value is None or isinstance(value, bool) or not isinstance(value, (int, float)) or \
            (isinstance(value, float) and not math.isfinite(value)):
        return MISSING if not isinstance(value, str) else value
    text = str(value) if isinstance(value, int) else f"{value:.{digits}g}"
    return f"{text} {unit}".rstrip()


def fmt_pm(value: float | None, err: float | None, digits: int = 3, unit: str | None = "") -> str:
    """``value ± err`` (``n/a`` parts stay visible); the unit once at the end."""
    unit = "" if unit in (None, "1") else unit
    if err is None or (isinstance(err, float) and not math.isfinite(err)):
        return fmt(value, digits, unit)
    return f"{fmt(value, digits)} ± {fmt(err, 2)} {unit}".rstrip()


def _cell(value):
    text = fmt(value) if not isinstance(value, str) else value
    return text.replace("|", "\\|").replace("\n", " ")


def table(rows: Iterable[Sequence[object]], header: Sequence[str]) -> str:
    """A Markdown table; put units in the header names (``"depth (nm)"``)."""
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(_cell(c) for c in row) + " |" for row in rows]
    return "\n".join(lines) + "\n"


def figure(folder: str | Path, rel: str, caption: str) -> str:
    """An inline figure if ``folder/rel`` exists, else a line saying it was not produced."""
    if (Path(folder) / rel).exists():
        return f"![{caption}]({rel})\n\n*{caption}*\n"
    return f"*({caption}: not produced)*\n"


def verdict(ok: bool | None, good: str, bad: str) -> str:
    """A verdict in words: ``**OK**: good`` or ``**CHECK**: bad`` (``ok`` None: not judged)."""
    if ok is None:
        return f"**NOT JUDGED**: {bad}"
    return f"**OK**: {good}" if ok else f"**CHECK**: {bad}"


def json_link(name: str = "report.json") -> str:
    """The closing line that points to the machine-readable report beside the page."""
    return f"All numbers above, and more, are in [{name}]({name}) beside this page.\n"


def join(parts: Iterable[str | None]) -> str:
    """One page from ``parts``: consecutive lines stay together (lists), headings, tables and
    figures get a blank line around them."""
    lines: list[str] = []
    for part in parts:
        if part is None:
            continue
        text = part.rstrip("\n")
        if not text:  # an explicit paragraph break
            if lines and lines[-1] != "":
                lines.append("")
            continue
        block = text.startswith(("#", "|", "![", "*(")) or "\n" in text
        if lines and (block or lines[-1].startswith(("#", "|", "![", "*"))) and lines[-1] != "":
            lines.append("")
        lines.append(text)
    return "\n".join(lines).rstrip("\n") + "\n"


def write_markdown(path: str | Path, parts: Iterable[str | None]) -> Path:
    """Join ``parts`` (see :func:`join`) and write them atomically to ``path``."""
    text = join(parts)
    with atomic_path(path) as tmp:
        tmp.write_text(text, encoding="utf-8")
    return Path(path)
