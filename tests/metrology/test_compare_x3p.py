"""`doe compare --x3p` writes the levelled measurement and the residual as ISO 25178-72 files that
an independent reader (SurfaceTopography) opens with the report's heights and pitch."""

import json

import numpy as np
import pytest

import filegen
from doedesign.cli import main


def test_compare_writes_x3p_read_back_by_surfacetopography(tmp_path):
    from SurfaceTopography import open_topography

    case = filegen.make_case(["etch_depth"], 2, design_px=36, field_px=120)
    design, measured = case.write(tmp_path)
    out = tmp_path / "out"
    assert main(["compare", str(measured), "--design", str(design), "--out", str(out), "--no-psf",
                 "--no-render", "--x3p"]) == 0
    report = json.loads((out / "report.json").read_text())
    assert report["x3p"] == ["levelled.x3p", "residual.x3p"]
    levelled = open_topography(str(out / "levelled.x3p")).topography()
    h = np.ma.filled(levelled.heights(), np.nan).T
    assert h.shape == (120, 120)
    dx = levelled.physical_sizes[0] / levelled.nb_grid_pts[0]
    assert dx == pytest.approx(levelled.physical_sizes[1] / levelled.nb_grid_pts[1])
    assert dx == pytest.approx(case.instrument["header_pixel_m"], rel=1e-6)
    # The levelled field's deepest level lies near the report's deepest level height.
    deepest = min(v for v in report["level_heights_nm"] if v is not None) * 1e-9
    assert np.nanpercentile(h, 1) == pytest.approx(deepest, abs=0.2 * abs(deepest))
    res = np.ma.filled(open_topography(str(out / "residual.x3p")).topography().heights(), np.nan).T
    assert np.sqrt(np.nanmean(res ** 2)) * 1e9 == pytest.approx(report["height_error_rms_nm"], rel=0.05)


def test_diagnose_writes_x3p_read_back_by_two_readers(tmp_path):
    """Issue 52, must 2: `doe diagnose --x3p` writes the levelled measurement and the final residual;
    the project's reader and SurfaceTopography read the same heights and pitch."""
    from SurfaceTopography import open_topography

    from metrology.formats.readers import read_measurement

    case = filegen.make_case(["etch_depth"], 2, design_px=24, field_px=72)
    design, measured = case.write(tmp_path)
    out = tmp_path / "diag"
    assert main(["diagnose", "--design", str(design), "--measured", str(measured), "--out", str(out),
                 "--effects", "etch_depth", "--window-px", "48", "--x3p"]) == 0
    report = json.loads((out / "report.json").read_text())
    assert report["inputs"]["x3p"] == ["levelled.x3p", "residual.x3p"]
    ours = read_measurement(out / "levelled.x3p")
    theirs = open_topography(str(out / "levelled.x3p")).topography()
    h = np.ma.filled(theirs.heights(), np.nan).T
    assert h.shape == ours.height_m.shape == (72, 72)
    np.testing.assert_array_equal(np.isnan(h), np.isnan(ours.height_m))
    np.testing.assert_allclose(h[np.isfinite(h)], ours.height_m[np.isfinite(h)], rtol=0, atol=1e-15)
    assert ours.pixel_size_m == pytest.approx(case.instrument["header_pixel_m"], rel=1e-6)
    res = read_measurement(out / "residual.x3p").height_m
    assert res.shape == (48, 48)
    rms = float(np.sqrt(np.nanmean(res ** 2)))
    assert rms == pytest.approx(report["final_residual_rms"], rel=1e-6)
    assert rms < 2 * case.instrument["noise_m"] + 1e-9


def test_diagnose_x3p_needs_camera_frame_height_maps(tmp_path, capsys):
    case = filegen.make_case([], 1, design_px=24, field_px=40)
    design, measured = case.write(tmp_path)
    code = main(["diagnose", "--design", str(design), "--measured", str(measured), "--out", str(tmp_path / "o"),
                 "--frame", "design", "--x3p"])
    assert code == 2
    assert "--x3p" in capsys.readouterr().err
