"""Run every ``benchmarks/bench_*.py`` and write one table (Markdown and JSON).

Each module exposes ``run(quick=False) -> list[dict]`` with rows holding ``benchmark``,
``figure``, ``value``, ``unit``, ``peer``, ``peer_value``, ``ratio``, ``limit``, ``notes``.

With ``--only`` (or ``--rows FILE.json``, rows measured by a separate long run) the new rows
replace, in place, every row of the same ``benchmark`` in the existing table; the other rows stay.
"""

from __future__ import annotations

import argparse
import importlib
import json
import logging
import os
import platform
import sys
import time
import traceback
from pathlib import Path

from doedesign.fileio import atomic_path, write_json

log = logging.getLogger("benchmarks")
COLUMNS = ("benchmark", "figure", "value", "unit", "peer", "peer_value", "ratio", "limit", "notes")


def discover():
    here = Path(__file__).parent
    return sorted(p.stem for p in here.glob("bench_*.py"))


def machine():
    import numpy as np

    info = {"python": platform.python_version(), "platform": platform.platform(), "cpus": os.cpu_count(),
            "numpy": np.__version__, "processor": platform.processor() or platform.machine()}
    try:
        mem = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
        info["memory_gib"] = round(mem / 2 ** 30, 1)
    except (ValueError, OSError, AttributeError):
        pass
    return info


def _fmt(v):
    if v is None:
        return ""
    if isinstance(v, float):
        return f"{v:.4g}"
    return str(v)


def markdown(rows, info):
    lines = [f"Machine: {info['cpus']} CPUs, {info.get('memory_gib', '?')} GiB, {info['platform']}, "
             f"Python {info['python']}, numpy {info['numpy']}.", "",
             "| " + " | ".join(COLUMNS) + " |", "|" + "---|" * len(COLUMNS)]
    for row in rows:
        lines.append("| " + " | ".join(_fmt(row.get(c)).replace("|", "/") for c in COLUMNS) + " |")
    return "\n".join(lines) + "\n"


def run_all(names, quick):
    rows = []
    for name in names:
        start = time.perf_counter()
        try:
            module = importlib.import_module(f"benchmarks.{name}")
            got = module.run(quick=quick)
        except Exception as exc:  # a broken benchmark is a row in the table, not a lost run
            log.error("%s failed: %s", name, exc)
            traceback.print_exc()
            got = [{"benchmark": name, "figure": "error", "value": None, "notes": f"{type(exc).__name__}: {exc}"}]
        for row in got:
            rows.append({c: row.get(c) for c in COLUMNS})
        log.info("%s: %d rows in %.1f s", name, len(got), time.perf_counter() - start)
    return rows


def merge(old, new):
    """``old`` with every row of a benchmark named in ``new`` replaced by ``new``'s rows, in place."""
    names = {r["benchmark"] for r in new}
    out, placed = [], set()
    for row in old:
        name = row.get("benchmark")
        if name not in names:
            out.append(row)
        elif name not in placed:
            out.extend(r for r in new if r["benchmark"] == name)
            placed.add(name)
    out.extend(r for r in new if r["benchmark"] not in placed)
    return out


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--out", default="benchmarks/results", help="output folder")
    parser.add_argument("--quick", action="store_true", help="small sizes (smoke test)")
    parser.add_argument("--only", nargs="*", help="benchmark module names (default: all); merged into the table")
    parser.add_argument("--rows", help="JSON list of rows measured elsewhere, merged into the table (runs nothing)")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(name)s: %(message)s")
    out = Path(args.out)
    if args.rows:
        rows = [{c: r.get(c) for c in COLUMNS} for r in json.loads(Path(args.rows).read_text())]
    else:
        rows = run_all(args.only or discover(), args.quick)
    info = machine()
    old = out / "results.json"
    if (args.only or args.rows) and old.exists():
        rows = merge(json.loads(old.read_text())["rows"], rows)
    write_json(out / "results.json", {"machine": info, "quick": args.quick, "rows": rows})
    with atomic_path(out / "results.md") as tmp:
        tmp.write_text(markdown(rows, info))
    sys.stdout.write(markdown(rows, info))
    return 0


if __name__ == "__main__":
    sys.exit(main())
