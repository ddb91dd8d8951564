"""No clock decides a diagnosis: with no limit (the default) the same file gives the same names
and parameters on an idle machine and beside a CPU hog, with one worker thread or two; a limit
the user asks for (``doe diagnose --wall-limit-s``) ends it, and the run says INCOMPLETE in its
summary's first line, lists the candidates not tried and exits with its own status."""

import json
import subprocess
import sys
from types import SimpleNamespace

import pytest

from doedesign.cli import main
from metrology.cli.diagnose import EXIT_INCOMPLETE
from metrology.diagnosis import budget
from metrology.diagnosis.budget import Deadline

import filegen


def _strict(text):
    """The report as strict JSON: NaN or infinity refused."""
    def refuse(name):
        raise ValueError(f"non-strict JSON constant {name}")
    return json.loads(text, parse_constant=refuse)


def _case(tmp_path):
    case = filegen.make_case(["mask_overlay"], 3, design_px=32, field_px=100)
    return case.write(tmp_path)


def _diagnose(design, measured, out, *extra):
    code = main(["diagnose", "--design", str(design), "--measured", str(measured), "--frame", "camera",
                 "--window-px", "64", "--out", str(out), *extra])
    return code, _strict((out / "report.json").read_text())


def test_a_limit_records_which_clock_ended_it_and_none_never_ends(monkeypatch):
    cpu, wall = [0.0], [1000.0]
    monkeypatch.setattr(budget, "cpu_seconds", lambda: cpu[0])
    monkeypatch.setattr(budget, "time", SimpleNamespace(monotonic=lambda: wall[0]))
    d = Deadline.after(50.0, 30.0)
    assert d.active and not d.past() and d.hit is None
    wall[0] = 1031.0  # the wall clock first, with CPU seconds left
    assert d.past() and d.hit == "wall"
    wall[0] = 1000.0  # once ended, it stays ended: what it cut is cut
    assert d.past() and d.hit == "wall"
    cpu[0] = 51.0
    c = Deadline(cpu=50.0)
    assert c.past() and c.hit == "cpu"
    cpu[0], wall[0] = 1e12, 1e12
    assert not Deadline().active and not Deadline().past() and Deadline.after().hit is None


def _signature(report):
    """What a diagnosis decided: the names, every fitted parameter and the placement's."""
    steps = {s["effect"]: s["params"] for s in report["steps"]}
    placement = report["inputs"]["placement"]
    numbers = {k: v for k, v in placement.items() if isinstance(v, (int, float)) and not isinstance(v, bool)}
    return [s["effect"] for s in report["steps"]], steps, numbers, report["final_residual_rms"]


def test_the_same_file_gives_the_same_answer_idle_and_beside_a_cpu_hog_with_one_worker(tmp_path, monkeypatch,
                                                                                      capsys):
    design, measured = _case(tmp_path)
    monkeypatch.setenv("DOE_PROGRESS", "1")
    code, idle = _diagnose(design, measured, tmp_path / "idle")
    assert code == 0 and not idle["incomplete"] and idle["summary"].startswith("complete")
    assert "mask_overlay" in idle["effects_found"]
    # The long work showed its stage and each candidate as it was scored.
    bars = capsys.readouterr().err
    for shown in ("comparison", "instrument stage", "selection, pass 1", "diagnosis step 1", "mask_overlay"):
        assert shown in bars, shown
    monkeypatch.setenv("DOE_PROGRESS", "0")
    # Beside a busy process (both cores contended), with the fits' worker threads cut to one and
    # the BLAS pool set to two threads before the command (another machine's default): the same
    # names and parameters, bit for bit (the command runs on one BLAS thread whatever it finds).
    import metrology.diagnosis.parallel as parallel

    monkeypatch.setattr(parallel, "WORKERS", 1)  # read at each call (fit_workers, parallel_map)
    from threadpoolctl import threadpool_limits

    hog = subprocess.Popen([sys.executable, "-c", "while True: pass"])
    try:
        with threadpool_limits(limits=2, user_api="blas"):
            code, busy = _diagnose(design, measured, tmp_path / "busy")
    finally:
        hog.kill()
        hog.wait()
    assert code == 0 and not busy["incomplete"]
    assert _signature(idle) == _signature(busy)


def test_a_tiny_wall_limit_says_incomplete_lists_the_untried_and_exits_with_its_own_status(tmp_path, capsys):
    design, measured = _case(tmp_path)
    out = tmp_path / "cut"
    code, report = _diagnose(design, measured, out, "--wall-limit-s", "0.001")
    assert code == EXIT_INCOMPLETE and code not in (0, 2)
    assert report["incomplete"] and report["summary"].startswith("INCOMPLETE")
    assert "--wall-limit-s" in report["summary"]
    stop = report["stopped_early"]
    assert stop["limit"] == "wall"
    # Nothing was named, so nothing was tried: every candidate is listed, in the summary too.
    assert [s["effect"] for s in report["steps"] if not s["measurement_artefact"]] == []
    assert report["tested"] == [] and report["untried"] == report["candidates"] == stop["untried"]
    assert "mask_overlay" in report["untried"] and "mask_overlay" in report["summary"]
    page = (out / "report.md").read_text()
    first = next(line for line in page.splitlines() if line.startswith("- "))
    assert first.startswith("- INCOMPLETE:") and "mask_overlay" in first
    # The command's own line says it too; the folder holds the whole report and nothing partial.
    said = json.loads(capsys.readouterr().out)
    assert said["incomplete"] and said["summary"] == report["summary"]
    assert sorted(p.name for p in out.iterdir()) == ["breakdown.png", "report.json", "report.md",
                                                     "residual_steps.png"]


def test_the_limits_are_opt_in_checked_like_any_number_and_documented(tmp_path, capsys):
    assert main(["diagnose", "--design", "d.npz", "--measured", "m.datx", "--wall-limit-s", "-3",
                 "--out", str(tmp_path / "o")]) == 2
    assert "--wall-limit-s" in capsys.readouterr().err
    from metrology.cli import diagnose

    import argparse
    parser = argparse.ArgumentParser()
    diagnose.register(parser.add_subparsers())
    args = parser.parse_args(["diagnose", "--design", "d", "--measured", "m", "--out", "o"])
    assert args.wall_limit_s is None and args.cpu_budget_s is None
    with pytest.raises(SystemExit):
        parser.parse_args(["diagnose", "--help"])
    assert f"exits with status {EXIT_INCOMPLETE}" in " ".join(capsys.readouterr().out.split())
