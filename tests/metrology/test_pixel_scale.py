"""`doe compare --pixel-size-um` is a starting value: a pixel size from 1/2 to 2 times the true one
registers (the scale scan of :func:`metrology.matching.register.register`), and where the field
matches at no scale the refusal says the scale did not match, with the pixel size it measured.

Profilometer files from the independent generator (tests/metrology/filegen.py), whose camera
pixel is drawn near 1 um (a DOE pixel of 5.4 um spans about 5 of them).
"""

import json

import numpy as np
import pytest

import filegen
from doedesign.cli import main

FINE = 40  # super-fine cells per design pixel: enough for the registration and the depth fit


@pytest.fixture(scope="module")
def case():
    return filegen.make_case([], 2, design_px=36, field_px=120, fine=FINE)


def _compare(case, tmp, pixel_um, levels=None):
    if levels is not None:
        case = filegen.FileCase(levels=levels, truth=case.truth, instrument=case.instrument, height_m=case.height_m)
    design, measured = case.write(tmp)
    out = tmp / "cmp"
    code = main(["compare", str(measured), "--design", str(design), "--out", str(out), "--no-psf", "--no-render",
                 "--pixel-size-um", f"{pixel_um:.6g}"])
    return code, out


@pytest.mark.parametrize("factor", [0.5, 0.8, 1.25, 2.0])
def test_a_starting_pixel_size_off_by_up_to_2x_registers(case, factor, tmp_path):
    true_um = case.instrument["pixel_m"] * 1e6
    code, out = _compare(case, tmp_path, true_um * factor)
    assert code == 0
    rep = json.loads((out / "report.json").read_text())
    reg = rep["registration"]
    # The pixel size measured against the DOE pitch, not the one given (issue 11's 1e-3).
    assert reg["pixel_size_um"] == pytest.approx(true_um, rel=1e-3)
    assert reg["match_ncc"] > 0.99
    # The refined placement maps camera pixels where the generator put them (within 0.05 px).
    placement = rep["instrument_frame"]["placement"]
    pts = np.stack([g.ravel() for g in np.mgrid[:120:17, :120:17]]).astype(float)
    fit = np.array(placement["matrix"]) @ pts + np.array(placement["offset"])[:, None]
    true = case.instrument["matrix"] @ pts + case.instrument["offset"][:, None]
    assert np.abs(fit - true).max() * filegen.PITCH_M / case.instrument["pixel_m"] < 0.05
    # And the comparison goes on at that scale: the generator's depths within 2 nm.
    np.testing.assert_allclose(rep["etch_depths_nm"], np.array(filegen.DEPTHS_M) * 1e9, atol=2.0)


def test_another_design_at_a_wrong_scale_says_the_scale_did_not_match(case, tmp_path, capsys):
    """At no scale does the read-out match (another design's file): the refusal names the scale
    the lattice measures, which is the field's true one, and the factor to the one given."""
    true_um = case.instrument["pixel_m"] * 1e6
    other = filegen.random_levels(case.levels.shape, np.random.default_rng(101))
    code, out = _compare(case, tmp_path, 2 * true_um, levels=other)
    err = capsys.readouterr().err.strip()
    assert code == 2 and "\n" not in err and "Traceback" not in err
    assert "the scale did not match" in err
    measured_um = float(err.split("measures a pixel size of ")[1].split(" um")[0])
    assert measured_um == pytest.approx(true_um, rel=5e-3)
    factor = float(err.split("pitch), ")[1].split("x the starting")[0])
    assert factor == pytest.approx(0.5, rel=5e-3)
    assert not (out / "report.json").exists()


def test_another_design_at_the_right_scale_is_still_another_design(case, tmp_path, capsys):
    true_um = case.instrument["pixel_m"] * 1e6
    other = filegen.random_levels(case.levels.shape, np.random.default_rng(101))
    code, _ = _compare(case, tmp_path, true_um, levels=other)
    err = capsys.readouterr().err.strip()
    assert code == 2 and "another design" in err and "scale did not match" not in err
