"""The shared Markdown helpers: numbers, tables, figures, verdicts."""

from doedesign import report_md as md


def test_numbers_and_missing_values():
    assert md.fmt(75.123, 3, "nm") == "75.1 nm"
    assert md.fmt(float("nan")) == md.MISSING
    assert md.fmt(None, unit="nm") == md.MISSING
    assert md.fmt_pm(0.354, 0.0123, 3, "um") == "0.354 ± 0.012 um"
    assert md.fmt_pm(1.0, None, 2, "nm") == "1 nm"


def test_table_escapes_and_counts_columns():
    text = md.table([("a|b", 1.23456), ("c", None)], ("name", "value (nm)"))
    lines = text.strip().splitlines()
    assert lines[0] == "| name | value (nm) |"
    assert lines[2] == "| a\\|b | 1.23 |"
    assert lines[3].endswith(f"| {md.MISSING} |")


def test_figure_verdict_and_write(tmp_path):
    (tmp_path / "a.png").write_bytes(b"x")
    assert md.figure(tmp_path, "a.png", "cap").startswith("![cap](a.png)")
    assert "not produced" in md.figure(tmp_path, "b.png", "cap")
    assert md.verdict(True, "fine", "bad").startswith("**OK**")
    assert md.verdict(False, "fine", "bad") == "**CHECK**: bad"
    path = md.write_markdown(tmp_path / "r.md", ["# T", md.json_link()])
    assert path.read_text().startswith("# T\n")
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []


def test_join_keeps_lists_together_and_separates_blocks():
    text = md.join(["# T", "- a", "- b", "## H", md.table([(1,)], ("x (nm)",)), "after", "", "para"])
    assert text == "# T\n\n- a\n- b\n\n## H\n\n| x (nm) |\n|---|\n| 1 |\n\nafter\n\npara\n"
