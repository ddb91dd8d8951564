"""The fab loop closed on files (issue 27): wafer 1 from the ideal masks under a hidden
systematic process plus field-to-field spread, three fields diagnosed, ``doe correct``, wafer 2
made with the job sheet through the same hidden process, diagnosed again.

Required: every corrected systematic effect on wafer 2 below its detection limit or at most
20 % of wafer 1's; wafer 2's merit within 2 % of the design's; the spread not "corrected".
Etch loading stays on wafer 2 (the fab cannot switch it off; it must be measured again, not
faked away): what the etch targets correct is the mean depth error over each mask's openings
(loading and depth error together), and that is what is compared between the wafers.
Both cases are slow (each diagnosis takes 15-60 s); tests/metrology/test_correct.py checks the
command fast on hand-made diagnosis reports."""

import json
import math

import numpy as np
import pytest

import fabloop
import filegen
from doedesign.cli import main


def _correct(design, diags, out):
    assert main(["correct", "--design", str(design), *[a for d in diags for a in ("--diagnosis", str(d))],
                 "--out", str(out), "--samples", "4"]) == 0
    return json.loads((out / "job.json").read_text())


def _loop(tmp_path, systematic, n_fields, design_px, field_px, window_px, effects, fine):
    levels = filegen.random_levels((design_px, design_px), np.random.default_rng(3))
    meta = fabloop.design_metadata()
    design, fields = fabloop.make_wafer(tmp_path / "w1", levels, systematic, n_fields, 1, design_px, field_px, meta, fine)
    d1 = [tmp_path / f"d1_{k}" for k in range(n_fields)]
    for m, d in zip(fields, d1):
        fabloop.diagnose(main, design, m, d, window_px, effects)
    job1 = _correct(design, d1, tmp_path / "c1")
    truth2 = fabloop.apply_job_sheet(systematic, job1)
    _, fields2 = fabloop.make_wafer(tmp_path / "w2", levels, truth2, n_fields, 2, design_px, field_px, meta, fine)
    d2 = [tmp_path / f"d2_{k}" for k in range(n_fields)]
    for m, d in zip(fields2, d2):
        fabloop.diagnose(main, design, m, d, window_px, effects)
    job2 = _correct(design, d2, tmp_path / "c2")
    return job1, job2


def _check(job1, job2, expect_corrected):
    est1 = {f"{e['effect']}.{e['param']}": e for e in job1["estimates"]}
    est2 = {f"{e['effect']}.{e['param']}": e for e in job2["estimates"]}
    assert set(expect_corrected) <= set(job1["corrected"]), job1["corrected"]
    loading = "etch_loading.loading" in job1["corrected"]
    for key in job1["corrected"]:
        if loading and key.split(".")[0] in ("etch_depth", "etch_loading"):
            continue  # the targets act on the mean depth over the openings: compared below
        before = est1[key]["mean"]
        after = est2[key]["mean"] if key in est2 else 0.0  # not named on any field of wafer 2
        limit = est1[key]["detection_limit"]
        assert abs(after) < limit or abs(after) <= 0.2 * abs(before), (key, before, after)
    if loading:
        # The loading is measured again on wafer 2, the same within the errors ...
        l1, l2 = est1["etch_loading.loading"], est2["etch_loading.loading"]
        assert abs(l2["mean"] - l1["mean"]) < 3 * math.hypot(l1["standard_error"], l2["standard_error"]), (l1, l2)
        # ... while each mask's mean depth error over its openings went out with the targets.
        limit = est1["etch_depth.depth_error_mask0"]["detection_limit"]
        for m1, m2 in zip(job1["masks"], job2["masks"]):
            e1, e2 = m1["etch_mean_error_measured"], m2["etch_mean_error_measured"]
            assert abs(e2) < limit or abs(e2) <= 0.2 * abs(e1), (m1["mask"], e1, e2)
        # What no knob corrects is a warning with the measured value.
        assert any(w.startswith(f"etch_loading loading = {l1['mean']:.4g}") and "cannot be corrected" in w
                   for w in job1["warnings"]), job1["warnings"]
    # The spread is not corrected: what was not systematic got no dial, no target, no offset.
    for key in job1["spread_only"]:
        assert key not in job1["corrected"]
    merit1, merit2 = job1["merit"], job2["merit"]
    loss1 = merit1["measured_wafer"]["primary_change_percent"]
    loss2 = merit2["measured_wafer"]["primary_change_percent"]
    assert abs(loss2) <= 2.0, (loss1, loss2)
    assert abs(loss2) < abs(loss1)
    return loss1, loss2


@pytest.mark.slow
def test_two_wafers_overlay_rotation_bias_deep_etch_loading(tmp_path):
    job1, job2 = _loop(tmp_path, fabloop.SYSTEMATIC, 3, 32, 100, 48, fabloop.EFFECTS, 40)
    _check(job1, job2, ["mask_overlay.dx_mask1_m", "mask_overlay.dy_mask1_m", "mask_overlay.dx_mask3_m",
                        "mask_overlay.dy_mask3_m", "mask_rotation.rotation_mask2_deg", "linewidth_bias.bias_mask0_m",
                        "linewidth_bias.bias_mask3_m", "etch_depth.depth_error_mask3", "etch_loading.loading"])
    # Mask 2 was never shifted: its field-to-field scatter gets no aligner dial.
    mask2 = job1["masks"][2]
    assert mask2["align_offset_um"] == [0.0, 0.0]


@pytest.mark.slow
def test_one_field_per_wafer_bias_and_deep_etch(tmp_path):
    """The short variant: one field per wafer, a bias and one deep etch, a small window (about
    40 s of CPU; the fast tests of the command on hand-made reports are in test_correct.py)."""
    systematic = {"linewidth_bias": fabloop.SYSTEMATIC["linewidth_bias"], "etch_depth": fabloop.SYSTEMATIC["etch_depth"]}
    job1, job2 = _loop(tmp_path, systematic, 1, 32, 100, 48, "etch_depth,linewidth_bias", 40)
    _check(job1, job2, ["linewidth_bias.bias_mask1_m", "etch_depth.depth_error_mask3"])


@pytest.mark.slow
def test_one_field_per_wafer_overlay_bias_deep_etch_loading(tmp_path):
    """The hidden process of the two-wafer proof but its rotation (one field resolves 0.03 deg only
    to about 0.01 deg), one field per wafer: the loading must be taken out in the mean and measured
    again on wafer 2."""
    systematic = {k: v for k, v in fabloop.SYSTEMATIC.items() if k != "mask_rotation"}
    effects = ",".join(e for e in fabloop.EFFECTS.split(",") if e != "mask_rotation")
    job1, job2 = _loop(tmp_path, systematic, 1, 32, 100, 48, effects, 40)
    _check(job1, job2, ["mask_overlay.dx_mask1_m", "mask_overlay.dy_mask3_m", "linewidth_bias.bias_mask0_m",
                        "etch_depth.depth_error_mask3", "etch_loading.loading"])
