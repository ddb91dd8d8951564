"""A camera diagnosis whose rerun on re-admitted pixels the CPU budget cuts short keeps the
finished pass (it once reported nothing named at 17x the floor after naming the right effects),
and a handful of re-admitted pixels does not start a rerun."""

from dataclasses import replace

import numpy as np

import metrology.diagnosis.camera as cam
from metrology.matching.instrument import Placement

import filegen


def _diagnose(monkeypatch, run, later_keep, budget=1e6):
    """The overlay case diagnosed with ``run`` in place of the selection and ``later_keep(first,
    keep)`` choosing the pixels the robust rule keeps after the first pass."""
    case = filegen.make_case(["mask_overlay"], 11, design_px=40, field_px=130)
    placement = Placement(np.asarray(case.instrument["matrix"]), np.asarray(case.instrument["offset"]))
    real_valid = cam.robust_valid
    masks = []

    def valid(*args, **kw):
        keep = real_valid(*args, **kw)
        masks.append(keep)
        return keep if len(masks) == 1 else later_keep(masks[0], keep)

    monkeypatch.setattr(cam.dg, "run_diagnosis", run)
    monkeypatch.setattr(cam, "robust_valid", valid)
    return cam.diagnose_camera(case.levels, filegen.PITCH_M, case.height_m, placement,
                               candidates=["mask_overlay", "etch_depth"], window_px=96, cpu_budget_s=budget)


def _more_than_the_share(first, keep):
    """More than RERUN_SHARE of the pixels dropped: the fit reruns."""
    keep = keep.copy()
    drop = np.argwhere(keep)[::50][:int(2 * cam.RERUN_SHARE * keep.size)]
    keep[tuple(drop.T)] = False
    return keep


def test_a_rerun_cut_short_by_the_budget_leaves_the_finished_pass(monkeypatch):
    real_run = cam.dg.run_diagnosis
    runs = []

    def run(*args, **kw):
        runs.append(kw.get("cpu_budget_s"))
        diag = real_run(*args, **kw)
        if len(runs) == 1:
            return diag
        # The second pass as a spent budget leaves it: stopped before its first round.
        nuisance = {k: v for k, v in diag.model.items() if k == cam.CAMERA.name}
        return replace(diag, steps=[], model=nuisance, stopped_early={
            "reason": "time budget: no further candidates were tried", "budget_cpu_s": 0.0})

    diag = _diagnose(monkeypatch, run, _more_than_the_share)
    assert len(runs) == 2
    assert [s.effect for s in diag.steps if s.kind != "artefact"] == ["mask_overlay"]
    assert "previous pass stands" in diag.stopped_early["reason"]
    assert diag.stopped_early["budget_cpu_s"] == 1e6
    assert diag.final_residual_rms < 1.3 * diag.noise_floor


def test_a_handful_of_readmitted_pixels_does_not_rerun_the_selection(monkeypatch):
    real_run = cam.dg.run_diagnosis
    runs = []

    def run(*args, **kw):
        runs.append(1)
        return real_run(*args, **kw)

    def three_dropped(first, keep):  # the first pass's pixels, three dropped: far below RERUN_SHARE
        keep = first.copy()
        keep[tuple(np.argwhere(keep)[:3].T)] = False
        return keep

    diag = _diagnose(monkeypatch, run, three_dropped)
    assert len(runs) == 1
    assert [s.effect for s in diag.steps if s.kind != "artefact"] == ["mask_overlay"]


def test_a_rerun_the_budget_left_cannot_pay_is_not_started(monkeypatch):
    # A rerun is a whole selection again: with less of the budget left than the first pass took, it
    # would only be cut short (a trenching case spent 41 CPU s so), so it does not start. The CPU
    # clock is a fake one that each pass advances by 100 s: 150 s of budget leave 50.
    real_run = cam.dg.run_diagnosis
    clock = [0.0]
    runs = []

    def run(*args, **kw):
        runs.append(kw.get("cpu_budget_s"))
        diag = real_run(*args, **kw)
        clock[0] += 100.0
        return diag

    monkeypatch.setattr(cam.clock, "cpu_seconds", lambda: clock[0])
    diag = _diagnose(monkeypatch, run, _more_than_the_share, budget=150.0)
    assert runs == [150.0]
    assert "not started" in diag.stopped_early["reason"]
    assert [s.effect for s in diag.steps if s.kind != "artefact"] == ["mask_overlay"]
    assert diag.final_residual_rms < 1.3 * diag.noise_floor
