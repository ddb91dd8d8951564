"""The rerun on re-admitted pixels: without a limit (the default) it always runs to its end, so
whether it runs depends on the data alone; one that a user's limit cuts short keeps the finished
pass, marked incomplete (it once reported nothing named at 17x the floor after naming the right
effects); and a handful of re-admitted pixels does not start a rerun."""

from dataclasses import replace

import numpy as np

import metrology.diagnosis.camera_diagnosis as cam
from metrology.diagnosis.budget import Deadline
from metrology.matching.instrument import Placement

import filegen


def _diagnose(monkeypatch, run, later_keep, limit=None):
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
                               candidates=["mask_overlay", "etch_depth"], window_px=96, limit=limit)


def _more_than_the_share(first, keep):
    """The first pass's pixels with more than RERUN_SHARE of them dropped (the same ones every
    time: the rerun's own rule then finds nothing more to change)."""
    keep = first.copy()
    drop = np.argwhere(keep)[::50][:int(2 * cam.RERUN_SHARE * keep.size)]
    keep[tuple(drop.T)] = False
    return keep


def test_a_rerun_cut_short_by_a_users_limit_leaves_the_finished_pass_marked_incomplete(monkeypatch):
    real_run = cam.dg.run_diagnosis
    runs = []

    def run(*args, **kw):
        runs.append(kw.get("limit"))
        diag = real_run(*args, **kw)
        if len(runs) == 1:
            return diag
        # The second pass as a spent limit leaves it: stopped before its first round.
        nuisance = {k: v for k, v in diag.model.items() if k == cam.CAMERA.name}
        return replace(diag, steps=[], model=nuisance, tested=[], stopped_early={
            "reason": "time limit: no further candidates were tried", "limit": "wall"})

    limit = Deadline.after(wall_limit_s=1e6)
    diag = _diagnose(monkeypatch, run, _more_than_the_share, limit)
    assert len(runs) == 2 and runs[0] is limit  # the command's own limit, not a copy with less left
    assert [s.effect for s in diag.steps if s.kind != "artefact"] == ["mask_overlay"]
    assert "previous pass stands" in diag.stopped_early["reason"] and diag.incomplete
    # What the finished pass named stands; what it found absent is not claimed.
    assert diag.tested == ["mask_overlay"] and diag.untried == ["etch_depth"] == diag.stopped_early["untried"]
    assert diag.to_dict()["summary"].startswith("INCOMPLETE")
    assert diag.final_residual_rms < 1.3 * diag.noise_floor


def test_without_a_limit_the_rerun_runs_to_its_end(monkeypatch):
    real_run = cam.dg.run_diagnosis
    runs = []

    def run(*args, **kw):
        runs.append(kw.get("limit"))
        return real_run(*args, **kw)

    diag = _diagnose(monkeypatch, run, _more_than_the_share)
    assert len(runs) == 2 and not runs[0].active
    assert [s.effect for s in diag.steps if s.kind != "artefact"] == ["mask_overlay"]
    assert not diag.incomplete and diag.tested == ["mask_overlay", "etch_depth"]
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
