"""The wall clock ends a diagnosis as its CPU budget does (``doe diagnose --wall-limit-s``): the
issue's 60 s a field is a wall-clock promise, and on two cores a case that spends the whole CPU
budget ran to 61-63 s."""

import json
from types import SimpleNamespace

from doedesign.cli import main
from metrology.diagnosis import budget
from metrology.diagnosis.budget import Deadline

import filegen


def _clocks(monkeypatch, cpu, wall):
    monkeypatch.setattr(budget, "cpu_seconds", lambda: cpu[0])
    monkeypatch.setattr(budget, "time", SimpleNamespace(monotonic=lambda: wall[0]))


def test_whichever_limit_comes_first_ends_it(monkeypatch):
    cpu, wall = [0.0], [1000.0]
    _clocks(monkeypatch, cpu, wall)
    d = Deadline.after(50.0, wall=1030.0)
    assert d.cpu == 50.0 and not d.past() and d.spent_by() is None
    assert d.affords(40.0, 20.0) and not d.affords(60.0, 20.0) and not d.affords(40.0, 40.0)
    # Which clock refuses a cost (a forecast: the rerun not started says which option would pay).
    assert d.refuses(40.0, 20.0) is None and d.refuses(60.0, 20.0) == "cpu" and d.refuses(40.0, 40.0) == "wall"
    wall[0] = 1031.0  # the wall clock first, with CPU seconds left
    assert d.past() and d.spent_by() == "wall" and d.cpu_left() == 50.0
    wall[0], cpu[0] = 1000.0, 51.0
    assert d.past() and d.spent_by() == "cpu" and d.cpu_left() == 0.0
    assert not Deadline().past() and Deadline().affords(1e9, 1e9) and Deadline().cpu_left() is None


def test_a_spent_wall_clock_stops_the_selection_and_the_report_says_which(tmp_path, monkeypatch):
    # A wall clock already past the command's limit (a fake one): the CPU budget is untouched, yet
    # no candidate is tried, the report says the wall clock ended it, and the command still writes
    # its report (status 0), the residual judged as it stands.
    case = filegen.make_case(["mask_overlay"], 3, design_px=32, field_px=100)
    design, measured = case.write(tmp_path)
    monkeypatch.setattr(budget, "time", SimpleNamespace(monotonic=lambda: float("inf")))
    out = tmp_path / "diag"
    assert main(["diagnose", "--design", str(design), "--measured", str(measured), "--frame", "camera",
                 "--window-px", "64", "--out", str(out), "--cpu-budget-s", "1000"]) == 0
    report = json.loads((out / "report.json").read_text())
    stop = report["stopped_early"]
    assert stop["limit"] == "wall" and stop["reason"].startswith("time budget")
    assert [s["effect"] for s in report["steps"] if not s["measurement_artefact"]] == []
    assert report["unexplained"]
    assert "--wall-limit-s" in (out / "report.md").read_text()


def test_the_wall_limit_is_checked_like_any_number(tmp_path, capsys):
    assert main(["diagnose", "--design", "d.npz", "--measured", "m.datx", "--wall-limit-s", "-3",
                 "--out", str(tmp_path / "o")]) == 2
    assert "--wall-limit-s" in capsys.readouterr().err
