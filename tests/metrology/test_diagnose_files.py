"""`doe diagnose --frame camera` on profilometer files from the independent generator."""

import json

import numpy as np
import pytest

import filegen
from doedesign.cli import main


def _run(case, tmp_path, *extra):
    design, measured = case.write(tmp_path)
    out = tmp_path / "diag"
    code = main(["diagnose", "--design", str(design), "--measured", str(measured), "--frame", "camera",
                 "--window-px", "72", "--out", str(out), *extra])
    assert code == 0
    return json.loads((out / "report.json").read_text())


def test_null_file_names_nothing_and_closes_at_the_floor(tmp_path):
    case = filegen.make_case([], 11, design_px=40, field_px=130)
    report = _run(case, tmp_path)
    fab = [s["effect"] for s in report["steps"] if not s["measurement_artefact"]]
    assert fab == []
    assert report["final_residual_rms"] < 1.3 * report["noise_floor"]
    assert report["stopped_early"] is None and report["summary"].startswith("complete")  # no limit: it closes
    # The placement is refined and reported with uncertainties (the blur too).
    placement = report["inputs"]["placement"]
    assert max(placement["shift_uncertainty_camera_px"]) < 0.02
    assert placement["rotation_uncertainty_deg"] < 0.002
    assert abs(placement["blur_sigma_um"] - case.instrument["blur_sigma_m"] * 1e6) < 0.1
    # The report says which design it diagnosed (doe correct refuses a diagnosis of another one).
    from doedesign.design import Design
    from metrology.correction.diagnoses import design_fingerprint

    fingerprint = design_fingerprint(Design.load(tmp_path / "design.npz"), tmp_path / "design.npz")
    assert {k: report["inputs"][k] for k in fingerprint} == fingerprint


@pytest.mark.slow
def test_hidden_overlay_in_a_file_is_named_alone_within_ten_percent(tmp_path):
    case = filegen.make_case(["mask_overlay"], 5, design_px=40, field_px=130)
    report = _run(case, tmp_path, "--effects", "etch_depth,mask_overlay,linewidth_bias,batwing")
    fab = [s["effect"] for s in report["steps"] if not s["measurement_artefact"]]
    assert fab == ["mask_overlay"]
    truth = case.truth["mask_overlay"]
    j = truth["mask"]
    step = report["steps"][[s["effect"] for s in report["steps"]].index("mask_overlay")]
    fit = np.array([step["params"][f"dx_mask{j}_m"], step["params"][f"dy_mask{j}_m"]])
    assert np.hypot(*(fit - truth["shift_m"])) < 0.1 * np.hypot(*truth["shift_m"])
    assert report["final_residual_rms"] < 1.3 * report["noise_floor"]


def test_profilometer_files_are_diagnosed_in_the_camera_frame_by_default():
    """Issue 11: a profilometer file is compared in its own pixels unless the user asks otherwise."""
    import argparse

    from metrology.cli.diagnose import register

    parser = argparse.ArgumentParser()
    register(parser.add_subparsers())
    args = parser.parse_args(["diagnose", "--design", "d.npz", "--measured", "m.datx", "--out", "o"])
    assert args.frame == "camera"
