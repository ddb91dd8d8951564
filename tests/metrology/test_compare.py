"""Comparison of synthetic measurements (made by the process model) with their design."""

import json

import numpy as np
import pytest

from doedesign.camera import Camera
from doedesign.cli import main
from doedesign.design import Design
from doedesign.errors import DoeError
from masks.process import ProcessParams
from metrology.matching import compare, level, measured_psf, register
from metrology.formats.measurement import Measurement
from metrology.formats.readers import read_measurement
from metrology.formats.writers import write_measurement

PITCH = 5.4e-6
PIXEL = 1.1e-6
SMALL_CAMERA = Camera(aperture_diameter_m=None, doe_side="full", window_shape=(48, 64), axis_pixel=(24, 32))


def _design(levels, camera=SMALL_CAMERA):
    step = Design(height_m=np.zeros((2, 2)), pitch_m=PITCH).height_2pi_m() / 16
    return Design(height_m=-levels * step, pitch_m=PITCH, levels=levels,
                  metadata={"name": "random16", "camera": camera.to_dict()})


@pytest.fixture(scope="module")
def case():
    """A wafer with a 6 % deep third etch, 0.4 um overlay on the 600 nm mask, bias, blur, tilt, noise.

    The field (300 x 300 px of 1.1 um) is rotated by 1 deg and mirrored (rows flipped).
    """
    rng = np.random.default_rng(0)
    levels = rng.integers(0, 16, (100, 100))
    design = _design(levels)
    nominal = design.height_2pi_m() / 16 * np.array([1, 2, 4, 8])
    depths = nominal.copy()
    depths[2] *= 1.06
    overlay = np.zeros((4, 3))
    overlay[3, :2] = (0.4e-6, 0.0)
    overlay[1, :2] = (0.0, -0.25e-6)
    params = ProcessParams(etch_depth=depths, mask_overlay=overlay,
                           linewidth_bias=np.array([0.05, 0.1, -0.1, 0.05]) * 1e-6)
    truth = register.Registration.from_parameters(PIXEL / PITCH, 1.0, (False, True, False), (50.3, 45.6),
                                                  PITCH, levels.shape, (300, 300))
    h = compare.process_on_measurement(levels, PITCH, params, truth, blur_m=0.5e-6)
    h += level.plane_image(np.array([1e-6, 0.5e-9, -0.3e-9]), h.shape) + rng.normal(0, 1e-9, h.shape)
    return {"design": design, "params": params, "truth": truth, "height": h, "nominal": nominal}


def _check(comp, case):
    rep = comp.report()
    np.testing.assert_allclose(rep["etch_depths_nm"], case["params"].etch_depth * 1e9, atol=2.0)
    np.testing.assert_allclose(rep["etch_depths_edge_fit_nm"], case["params"].etch_depth * 1e9, atol=2.0)
    np.testing.assert_allclose(rep["overlay_um"], case["params"].mask_overlay[:, :2] * 1e6, atol=0.15)
    np.testing.assert_allclose(rep["linewidth_bias_um"], case["params"].linewidth_bias * 1e6, atol=0.03)
    assert rep["registration"]["flip_rows"] and not rep["registration"]["transpose"]
    assert rep["registration"]["rotation_deg"] == pytest.approx(1.0, abs=0.02)
    assert rep["registration"]["pixel_size_um"] == pytest.approx(1.1, rel=1e-3)
    # Roughness = the 1 nm noise; the etches add up (no loading in this wafer).
    assert rep["roughness_rms_nm"] == pytest.approx(1.0, abs=0.15)
    assert rep["etch_sum"]["p_value"] > 0.01
    # The fitted process model explains the surface far better than the design does.
    assert rep["height_error_model_rms_nm"] < 0.3 * rep["height_error_rms_nm"]
    return rep


def test_in_memory_comparison_recovers_process(case):
    comp = compare.compare_measurement(Measurement(case["height"], PIXEL), case["design"])
    rep = _check(comp, case)
    # Level 4 (mask 2 only) sits 6 % of 299 nm deeper than designed; level 0 at the top.
    assert rep["level_heights_nm"][4] == pytest.approx(-case["params"].etch_depth[2] * 1e9, abs=1.0)
    assert abs(rep["level_heights_nm"][0]) < 1.0
    assert np.all(rep["level_pixel_counts"] > 100)


# Three formats in make test; the readers' own round trips cover the rest, these run with the slow cases.
@pytest.mark.parametrize("ext", ["dat", "datx", "asc", *(pytest.param(e, marks=pytest.mark.slow) for e in ("xyz", "npz", "tif"))])
def test_comparison_through_file_formats(case, tmp_path, ext):
    path = tmp_path / f"wafer.{ext}"
    write_measurement(path, case["height"], pixel_size_m=PIXEL)
    meas = read_measurement(path)
    assert meas.pixel_size_m == pytest.approx(PIXEL, rel=1e-6)
    _check(compare.compare_measurement(meas, case["design"]), case)


def test_chi_square_flags_etches_that_do_not_add_up():
    b = compare.binary_code_matrix()
    depths = np.array([75.0, 150.0, 300.0, 600.0]) * 1e-9
    rng = np.random.default_rng(3)
    mean = -(b @ depths) + rng.normal(0, 0.2e-9, 16)
    stats_ = compare.LevelStats(mean, np.full(16, 1e-9), mean, np.full(16, 500))
    good = compare.fit_etch_depths(stats_)
    np.testing.assert_allclose(good.depths_m, depths, atol=0.5e-9)
    assert good.dof == 11 and good.p_value > 0.01
    # Level 5 (masks 0 and 2) 3 nm shallower than the sum of its etches, as from loading.
    mean2 = mean.copy()
    mean2[5] += 3e-9
    bad = compare.fit_etch_depths(compare.LevelStats(mean2, np.full(16, 1e-9), mean2, np.full(16, 500)))
    assert bad.p_value < 1e-4
    assert np.nanargmax(np.abs(bad.residual_m)) == 5


def test_interior_is_the_central_third_of_a_feature():
    labels = np.zeros((40, 60), int)
    labels[:, 20:29] = 3  # a 9-px-wide line: its central third is columns 23..25
    inner = compare.interior_mask(labels, pitch_px=9.0)
    assert np.array_equal(np.flatnonzero(inner[20, 20:29]) + 20, [23, 24, 25])
    # Wide features keep all but one pitch (9 px) from their edges.
    assert inner[20, 0:11].sum() == 11 and not inner[20, 11:20].any()


def test_psf_of_scaled_depths_follows_the_staircase_formula():
    """All etches 10 % deep: first-order efficiency falls by [sin(pi e) / (N sin(pi e / N))]^2."""
    period, n = 16, 16
    levels = np.tile((np.arange(64) % period) * n // period, (32, 1))
    camera = Camera(aperture_diameter_m=None, doe_side="full", window_shape=(24, 160), axis_pixel=(12, 80))
    design = _design(levels, camera)
    e = 0.10
    params = ProcessParams(etch_depth=design.height_2pi_m() / 16 * np.array([1, 2, 4, 8]) * (1 + e))
    res = measured_psf.compare_psf(design, params, wavelengths_m=(550e-9,), oversample=1)
    expected = (np.sin(np.pi * e) / (n * np.sin(np.pi * e / n))) ** 2
    assert res.measured_on_target[0] / res.design_on_target[0] == pytest.approx(expected, abs=0.004)
    # The design's target is its first order, 58.9 px from the axis (x = lambda z / period), on the
    # left: the level rises with the column, so the height and the phase fall toward the right.
    cols = np.nonzero(res.target[0])[1]
    assert abs(np.average(cols, weights=res.design_psf[0][res.target[0]]) - (80 - 58.9)) < 1.0
    assert res.report()["per_wavelength"]["550"]["energy_lost"] > 0


def test_cli_compare_writes_report_and_figures(case, tmp_path):
    design_path = tmp_path / "design.npz"
    case["design"].save(design_path)
    meas_path = tmp_path / "wafer.datx"
    write_measurement(meas_path, case["height"], pixel_size_m=PIXEL)
    out = tmp_path / "cmp"
    code = main(["compare", str(meas_path), "--design", str(design_path), "--out", str(out),
                 "--wavelengths-nm", "550"])
    assert code == 0
    # Strict JSON: no NaN / Infinity tokens.
    rep = json.loads((out / "report.json").read_text(), parse_constant=lambda c: pytest.fail(f"{c} in report"))
    for key in ("etch_depths_nm", "level_heights_nm", "overlay_um", "linewidth_bias_um", "registration",
                "height_error_rms_nm", "psf"):
        assert key in rep
    assert len(rep["level_heights_nm"]) == 16 and len(rep["etch_depths_nm"]) == 4
    assert rep["overlay_um"][0] == [0.0, 0.0]
    assert rep["overlay_um"][3][0] == pytest.approx(0.4, abs=0.15)
    # A random-level design names no target: the light is counted in the design PSF's core, under
    # that name (not the "on target" of a design's figure of merit); check the section is complete.
    assert rep["psf"]["merit"]["name"] == "light in the design PSF's core" and "design_on_target" not in rep["psf"]
    psf = rep["psf"]["per_wavelength"]["550"]
    assert psf["energy_lost"] == pytest.approx(psf["design_in_psf_core"] - psf["measured_in_psf_core"])
    assert 0 < psf["design_in_psf_core"] <= psf["design_in_window"] <= 1 and psf["difference_rms"] > 0
    for name in ("levels.png", "error_map.png", "masks.png", "psf.png"):
        assert (out / name).stat().st_size > 1000
    assert rep["render3d"] == "surface3d.png" or rep["render3d"].startswith("3-D rendering failed")


def test_cli_compare_bad_inputs_exit_2(case, tmp_path, capsys):
    design_path = tmp_path / "design.npz"
    case["design"].save(design_path)
    code = main(["compare", str(tmp_path / "missing.datx"), "--design", str(design_path), "--out", str(tmp_path)])
    assert code == 2
    assert "missing.datx" in capsys.readouterr().err
    # A measurement of another design: registration finds no match; nothing is written.
    other = _design(np.random.default_rng(7).integers(0, 16, (100, 100)))
    other_path = tmp_path / "other.npz"
    other.save(other_path)
    meas_path = tmp_path / "wafer.npz"
    write_measurement(meas_path, case["height"], pixel_size_m=PIXEL)
    out = tmp_path / "bad"
    code = main(["compare", str(meas_path), "--design", str(other_path), "--out", str(out), "--no-psf"])
    err = capsys.readouterr().err
    assert code == 2 and "does not match the design" in err and "wafer.npz" in err
    assert not (out / "report.json").exists()


def test_ideal_process_gives_the_design_psf_on_the_finer_grid():
    """Design PSF on the DOE grid and fabricated PSF on pitch/2 agree for a perfect wafer.

    Only the circular aperture's edge is sampled differently on the two grids.
    """
    levels = np.tile((np.arange(64) % 16), (64, 1))
    camera = Camera(aperture_diameter_m=64 * PITCH, doe_side="full", window_shape=(32, 160), axis_pixel=(16, 80))
    design = _design(levels, camera)
    params = ProcessParams(etch_depth=design.height_2pi_m() / 16 * np.array([1, 2, 4, 8]))
    res = measured_psf.compare_psf(design, params, wavelengths_m=(500e-9, 600e-9), oversample=2)
    assert np.all(res.design_on_target > 0.7)
    np.testing.assert_allclose(res.measured_on_target, res.design_on_target, rtol=2e-3)
    np.testing.assert_allclose(res.measured_psf, res.design_psf, atol=5e-3 * res.design_psf.max())


@pytest.mark.slow  # 40 s; the refusal through files: test_match_files.py
def test_wrong_design_is_refused_unless_forced(case, tmp_path, capsys):
    """A design that shares the lattice but not the levels still registers; the read-out's
    correlation with the printed design and the share of its edges found say it is another design."""
    right = compare.compare_measurement(Measurement(case["height"], PIXEL), case["design"])
    assert right.match["confidence"] == "high" and right.match["readout_correlation"] > 0.99
    assert right.match["edges_found"] > 0.95
    levels = case["design"].levels.copy()
    rng = np.random.default_rng(11)
    swap = rng.random(levels.shape) < 0.3
    levels[swap] = rng.integers(0, 16, swap.sum())
    wrong = _design(levels)
    with pytest.raises(DoeError, match="another design") as exc:
        compare.compare_measurement(Measurement(case["height"], PIXEL), wrong)
    assert "--force" in str(exc.value)
    forced = compare.compare_measurement(Measurement(case["height"], PIXEL), wrong, force=True)
    assert forced.match["confidence"] == "low" and forced.match["forced"]
    assert forced.match["readout_correlation"] < 0.9 and "another design" in forced.match["problem"]


def test_simulated_camera_pixels_integrate_the_surface():
    """A straight 600 nm step under 1.1 um camera pixels: each pixel reports the step times the
    fraction of its footprint on the etched side (no blur), not the value at its centre."""
    levels = np.zeros((12, 12), int)
    levels[:, 6:] = 8  # mask 3 open right of design column 5.5
    params = ProcessParams.ideal()
    scale = PIXEL / PITCH
    reg = register.Registration.from_parameters(scale, 0.0, (False, False, False), (5.5, 5.42), PITCH,
                                                levels.shape, (20, 20))
    h = compare.process_on_measurement(levels, PITCH, params, reg, step_m=PITCH / 64, pixel_subsamples=16)
    _, c_design = reg.to_design(np.zeros(20), np.arange(20.0))
    # Fraction of each pixel's footprint (width = scale design px) right of the edge at 5.5.
    frac = np.clip((c_design + scale / 2 - 5.5) / scale, 0, 1)
    np.testing.assert_allclose(h[10], -params.etch_depth[3] * frac, atol=0.02 * params.etch_depth[3])
    straddling = (frac > 0.2) & (frac < 0.8)
    assert straddling.any()
    point = compare.process_on_measurement(levels, PITCH, params, reg, step_m=PITCH / 64)
    assert np.all(np.abs(point[10][straddling] + params.etch_depth[3] * frac[straddling]) > 0.1 * params.etch_depth[3])
