"""A camera diagnosis whose rerun on re-admitted pixels the CPU budget cuts short keeps the
finished pass (it once reported nothing named at 17x the floor after naming the right effects)."""

from dataclasses import replace

import numpy as np

import metrology.diagnosis.camera as cam
from metrology.matching.instrument import Placement

import filegen


def test_a_rerun_cut_short_by_the_budget_leaves_the_finished_pass(monkeypatch):
    case = filegen.make_case(["mask_overlay"], 11, design_px=40, field_px=130)
    placement = Placement(np.asarray(case.instrument["matrix"]), np.asarray(case.instrument["offset"]))
    real_run, real_valid = cam.dg.run_diagnosis, cam.robust_valid
    runs, masks = [], []

    def run(*args, **kw):
        runs.append(kw.get("cpu_budget_s"))
        diag = real_run(*args, **kw)
        if len(runs) == 1:
            return diag
        # The second pass as a spent budget leaves it: stopped before its first round.
        nuisance = {k: v for k, v in diag.model.items() if k == cam.CAMERA.name}
        return replace(diag, steps=[], model=nuisance, stopped_early={
            "reason": "time budget: no further candidates were tried", "budget_cpu_s": 0.0})

    def valid(*args, **kw):
        keep = real_valid(*args, **kw)
        masks.append(keep)
        if len(masks) > 1:  # pixels re-admitted or dropped: the fit reruns
            keep = keep.copy()
            keep[tuple(np.argwhere(keep)[0])] = False
        return keep

    monkeypatch.setattr(cam.dg, "run_diagnosis", run)
    monkeypatch.setattr(cam, "robust_valid", valid)
    diag = cam.diagnose_camera(case.levels, filegen.PITCH_M, case.height_m, placement,
                               candidates=["mask_overlay", "etch_depth"], window_px=96, cpu_budget_s=1e6)
    assert len(runs) == 2
    assert [s.effect for s in diag.steps if s.kind != "artefact"] == ["mask_overlay"]
    assert "previous pass stands" in diag.stopped_early["reason"]
    assert diag.stopped_early["budget_cpu_s"] == 1e6
    assert diag.final_residual_rms < 1.3 * diag.noise_floor
