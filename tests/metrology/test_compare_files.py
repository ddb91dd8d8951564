"""`doe compare` on profilometer files from the independent generator (tests/metrology/filegen.py).

The generator never calls the process model or the instrument model: its camera averages a
blurred super-fine surface over each rotated, possibly mirrored pixel footprint. The
comparison must read depths, overlay and bias from such a file in the camera's own frame.
"""

import json

import numpy as np
import pytest

import filegen
from doedesign.cli import main

EFFECTS = ["etch_depth", "mask_overlay", "linewidth_bias"]


@pytest.fixture(scope="module")
def compared(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("cmp")
    case = filegen.make_case(EFFECTS, 2, design_px=36, field_px=120)
    design, measured = case.write(tmp)
    out = tmp / "out"
    assert main(["compare", str(measured), "--design", str(design), "--out", str(out), "--no-psf",
                 "--no-render"]) == 0
    return case, json.loads((out / "report.json").read_text())


def test_depths_overlay_and_bias_from_a_file_in_the_camera_frame(compared):
    case, rep = compared
    truth = case.truth
    depths = np.array(filegen.DEPTHS_M) * (1 + truth["etch_depth"]["error"])
    overlay = np.zeros((4, 2))
    overlay[truth["mask_overlay"]["mask"]] = truth["mask_overlay"]["shift_m"]
    # The limits: etch depths within 2 nm, overlay within 0.15 um; the camera-frame
    # fit does far better (a few nm of overlay, a few hundredths of a nm of depth).
    np.testing.assert_allclose(rep["etch_depths_nm"], depths * 1e9, atol=2.0)
    np.testing.assert_allclose(rep["overlay_um"], overlay * 1e6, atol=0.15)
    np.testing.assert_allclose(rep["overlay_um"], overlay * 1e6, atol=0.01)
    np.testing.assert_allclose(rep["linewidth_bias_um"], truth["linewidth_bias"]["bias_m"] * 1e6, atol=0.01)
    inst = rep["instrument_frame"]
    # The objective blur is told apart from the pixel integral, and the residual is the noise.
    assert inst["blur_sigma_um"] == pytest.approx(case.instrument["blur_sigma_m"] * 1e6, abs=0.03)
    assert inst["rms_residual_nm"] < 1.3 * case.instrument["noise_m"] * 1e9


def test_placement_refined_with_uncertainties_and_spikes_excluded(compared):
    case, rep = compared
    placement = rep["instrument_frame"]["placement"]
    # A feature-rich field pins the placement (issue 11: < 0.02 camera px and 0.002 deg).
    assert max(placement["shift_uncertainty_camera_px"]) < 0.02
    assert placement["rotation_uncertainty_deg"] < 0.002
    # The refined placement maps camera pixels onto the generator's true placement.
    rows, cols = np.mgrid[:120:17, :120:17]
    pts = np.stack([rows.ravel(), cols.ravel()]).astype(float)
    fit = np.array(placement["matrix"]) @ pts + np.array(placement["offset"])[:, None]
    true = case.instrument["matrix"] @ pts + case.instrument["offset"][:, None]
    assert np.abs(fit - true).max() * filegen.PITCH_M / case.instrument["pixel_m"] < 0.05
    assert rep["spikes_removed"] + rep["instrument_frame"]["excluded_pixels"] >= case.instrument["n_spikes"]


def test_terrace_fit_agrees_with_the_camera_frame_fit(compared):
    """Issue 52, must 4: the terrace fit of the flat interiors and the camera-frame fit agree on
    every step and mask within twice their combined standard uncertainty, and both find the truth."""
    case, rep = compared
    terr = rep["terrace_fit"]
    check = terr["against_camera_frame"]
    assert check["agree"] is True and check["warnings"] == []
    assert len(check["masks"]) == 4 and len(check["steps"]) == 15
    depths = np.array(filegen.DEPTHS_M) * (1 + case.truth["etch_depth"]["error"]) * 1e9
    err = np.asarray(terr["etch_depths_err_nm"])
    assert np.all(np.abs(np.asarray(terr["etch_depths_nm"]) - depths) < 3 * err)
    # The terrace residual is the instrument's white noise: no edge pixel left on a terrace.
    assert terr["rms_residual_nm"] < 1.3 * case.instrument["noise_m"] * 1e9


def test_texture_figures_beside_the_doe_figures(compared):
    """Issue 52, must 5: Sa, Sq, Sz of each level's flat interiors and of the residual, its band rms."""
    case, rep = compared
    tex = rep["texture"]
    noise = case.instrument["noise_m"] * 1e9
    sq = [d["Sq_nm"] for d in tex["levels"] if d["pixels"]]
    assert len(sq) >= 8
    # Flat interiors hold the instrument's white noise only: Sq near it, Sa = Sq sqrt(2 / pi).
    assert np.median(sq) == pytest.approx(noise, rel=0.25)
    sa = [d["Sa_nm"] / d["Sq_nm"] for d in tex["levels"] if d["pixels"] > 100]
    assert np.median(sa) == pytest.approx(np.sqrt(2 / np.pi), rel=0.05)
    res = tex["residual"]
    # The residual's Sq is the report's height error rms about its mean; its bands add up to it.
    assert res["Sq_nm"] <= rep["height_error_rms_nm"] * 1.0001
    bands = np.array([b["rms_nm"] for b in res["bands"]])
    assert np.sqrt(np.sum(bands ** 2)) == pytest.approx(res["Sq_nm"], rel=0.15)
    assert "texture.png" in rep["figures"]
