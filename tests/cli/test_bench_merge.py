"""The benchmark table keeps the rows of benchmarks that were not rerun."""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
from benchmarks.run import merge  # noqa: E402


def _row(bench, figure, value):
    return {"benchmark": bench, "figure": figure, "value": value}


def test_merge_replaces_rerun_benchmarks_in_place():
    old = [_row("a", "x", 1), _row("b", "y", 2), _row("b", "stale", 3), _row("c", "z", 4)]
    new = [_row("b", "y", 20), _row("d", "w", 5)]
    got = merge(old, new)
    assert got == [_row("a", "x", 1), _row("b", "y", 20), _row("c", "z", 4), _row("d", "w", 5)]
