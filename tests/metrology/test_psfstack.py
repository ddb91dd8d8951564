"""Measured PSF stacks against PSFs from the engine: calibration steps, extrapolation, comparison, export."""

import numpy as np
import pytest

from doedesign.camera import Camera
from doedesign.engine.psf import PSFEngine, PSFResult
from doedesign.errors import DoeError
from doedesign.materials import get_material
from metrology.calibration import psfstack as ps

PITCH = 5.4e-6
PERIOD_PX = 16
N = 384
DEPTH_SCALE = 1.05  # fabricated 5 % too deep: the 0th and 2nd orders show
SILICA = get_material("fused_silica")
# Small window: orders 0..2 at <= 2 x 48 px right of the axis at 450 nm.
WINDOW, AXIS = (96, 160), (48, 32)


def grating(scale=1.0):
    """16-level blazed grating along columns (phase rising to the right), 550 nm design."""
    level = np.arange(N) % PERIOD_PX
    h = -(PERIOD_PX - 1 - level) / PERIOD_PX * SILICA.height_2pi_m(550e-9) * scale
    return np.tile(h, (N, 1))


def engine(wavelengths_nm, window=WINDOW, axis=AXIS):
    cam = Camera(aperture_diameter_m=None, window_shape=window, axis_pixel=axis, doe_side="right")
    return PSFEngine(cam, PITCH, (N, N), wavelengths_m=np.asarray(wavelengths_nm) * 1e-9)


def to_stack(result, measured=None):
    return ps.as_stack(result) if measured is None else ps.PSFStack(
        psf=ps.as_stack(result).psf, wavelengths_m=result.wavelengths_m, pixel_pitch_m=PITCH,
        axis_pixel=result.axis_pixel, measured=measured)


@pytest.fixture(scope="module")
def fabricated():
    return engine([400, 420, 440, 450, 500, 550]).psf(grating(DEPTH_SCALE))


@pytest.fixture(scope="module")
def design_psf():
    return engine([400, 410, 420, 430, 440, 450, 500, 550]).psf(grating())


def analytic_eta(m, wl_nm, scale):
    """Order efficiency of an N-level staircase with step-phase scale a (reference table)."""
    a = scale * (SILICA.n(wl_nm * 1e-9) - 1) / wl_nm / ((SILICA.n(550e-9) - 1) / 550)
    n = PERIOD_PX
    x = a - m
    if abs(np.sin(np.pi * x / n)) < 1e-12:
        return np.sinc(m / n) ** 2
    return np.sinc(m / n) ** 2 * (np.sin(np.pi * x) / (n * np.sin(np.pi * x / n))) ** 2


def test_locate_orders_follows_grating_equation(design_psf):
    # x_1 = lambda z / period. At the design wavelength only the first order exists and the
    # centroid is exact; away from it the coherent tails of the 0th and 2nd orders (slow, from
    # the straight edge of the half-aperture) move the intensity peak by up to ~0.6 px.
    stack = ps.as_stack(design_psf)
    for i, wl in enumerate(stack.wavelengths_m):
        pos = ps.locate_orders(stack.view("coded")[i], AXIS, orders=(0, 1, 2))
        x1 = wl * 50e-3 / (PERIOD_PX * PITCH) / PITCH
        tol = 0.15 if np.isclose(wl, 550e-9) else 0.7
        np.testing.assert_allclose(pos[1] - AXIS, [0, x1], atol=tol)
        np.testing.assert_allclose(pos[2] - AXIS, [0, 2 * x1], atol=2 * tol)
        np.testing.assert_allclose(pos[0], AXIS)


def test_extrapolation_moves_orders_to_simulation_and_keeps_ratios(fabricated, design_psf):
    measured_nm = [450, 500, 550]
    idx = [list(np.round(fabricated.wavelengths_m * 1e9)).index(w) for w in measured_nm]
    full = ps.as_stack(fabricated)
    stack = ps.PSFStack(psf=full.psf[:, idx], wavelengths_m=full.wavelengths_m[idx], pixel_pitch_m=PITCH,
                        axis_pixel=AXIS)
    out = ps.extrapolate_orders(stack, design_psf, np.array([400, 420, 440]) * 1e-9)
    np.testing.assert_allclose(out.wavelengths_m * 1e9, [400, 420, 440, 450, 500, 550])
    assert out.measured.tolist() == [False, False, False, True, True, True]
    src = stack.view("coded")[0]
    x1_450 = 450e-9 * 50e-3 / (PERIOD_PX * PITCH) / PITCH
    src_pos = ps.locate_orders(src, AXIS)
    src_e = ps.order_energies(src, src_pos, x1_450 / 3)
    # The measurement really has visible 0th and 2nd orders, in the analytic ratio (to the few %
    # the first order's diffraction tails add to a neighbouring order's disk).
    eta = np.array([analytic_eta(m, 450, DEPTH_SCALE) for m in (0, 1, 2)])
    np.testing.assert_allclose(src_e / src_e[1], eta / eta[1], rtol=0.06)
    assert src_e[0] / src_e[1] > 0.02 and src_e[2] / src_e[1] > 0.02
    for k, wl_nm in enumerate([400, 420, 440]):
        got = out.view("coded")[k]
        x1 = wl_nm * 1e-9 * 50e-3 / (PERIOD_PX * PITCH) / PITCH
        # Where the simulation puts the orders: x_m = m lambda z / period. The bright first order
        # lands within 0.15 px; the weak ones within 0.7 px (the first order's tails bias their
        # centroids). The fabricated grating's own engine PSF agrees to within ~1 px (coherent tails).
        truth = ps.as_stack(fabricated).view("coded")[list(np.round(fabricated.wavelengths_m * 1e9)).index(wl_nm)]
        for m in (0, 1, 2):
            guess = (AXIS[0], AXIS[1] + round(m * x1))
            found = ps.centroid(got, guess, 6)
            np.testing.assert_allclose(found, [AXIS[0], AXIS[1] + m * x1], atol=0.15 if m == 1 else 0.7)
            np.testing.assert_allclose(found, ps.centroid(truth, guess, 6), atol=1.2)
        pos = np.array([[AXIS[0], AXIS[1] + m * x1] for m in (0, 1, 2)])
        e = ps.order_energies(got, pos, x1_450 / 3)
        np.testing.assert_allclose(e / e[1], src_e / src_e[1], rtol=0.01)
        np.testing.assert_allclose(e.sum(), src_e.sum(), rtol=0.01)
        np.testing.assert_array_equal(out.view("uncoded")[k], stack.view("uncoded")[0])
    assert out.info["extrapolation"]["energy_kept"] > 0.9


def test_calibrate_capture_recovers_engine_psf():
    big = engine([500], window=(160, 224), axis=(80, 64)).psf(grating())
    counts = 2e6
    frame = big.psf[:, 0, 0] * counts + 37.0  # constant background
    centre = (80, 64)
    window, info = ps.calibrate_capture(frame[0], frame[1], WINDOW, AXIS, border_px=6)
    assert info["centre"] == list(centre)
    # The PSF's own tails reach the border strip: 0.02 counts of 2e6.
    np.testing.assert_allclose(info["background"], [37.0, 37.0], atol=0.05)
    e_unc = big.psf[1, 0, 0].sum()
    expect = ps.crop_to_window(big.psf[:, 0, 0], centre, WINDOW, AXIS) / e_unc
    # The background error (0.02 counts on each of 36k pixels) shifts the total by 3e-4.
    np.testing.assert_allclose(window, expect, rtol=1e-3, atol=0.05 / counts)
    # Coded efficiency relative to the uncoded half is kept, not renormalized away.
    assert info["coded_to_uncoded_total"] == pytest.approx(big.psf[0, 0, 0].sum() / e_unc, rel=1e-3)
    per_view, _ = ps.calibrate_capture(frame[0], frame[1], WINDOW, AXIS, border_px=6, normalization="per_view")
    np.testing.assert_allclose(per_view[0].sum(), expect[0].sum() * e_unc / big.psf[0, 0, 0].sum(), rtol=1e-3)


def test_dark_frame_and_given_axis():
    rng = np.random.default_rng(2)
    dark = rng.normal(100, 3, (2, 60, 70))
    img = np.zeros((2, 60, 70))
    img[1, 20, 30] = 500.0
    img[0, 20, 45] = 250.0
    window, info = ps.calibrate_capture(*(img + dark), window_shape=(32, 32), axis_pixel=(16, 16), dark=dark)
    assert window[1, 16, 16] == pytest.approx(1.0) and window[0, 16, 31] == pytest.approx(0.5)
    window, info = ps.calibrate_capture(*(img + dark), window_shape=(32, 32), axis_pixel=(16, 16), dark=dark,
                                        centre=(20, 29))
    assert window[1, 16, 17] == pytest.approx(1.0)


def test_compare_reports_orders_and_difference(fabricated, design_psf):
    meas = ps.as_stack(fabricated)
    keep = [3, 4, 5]  # 450, 500, 550 nm
    meas = ps.PSFStack(psf=meas.psf[:, keep], wavelengths_m=meas.wavelengths_m[keep], pixel_pitch_m=PITCH,
                       axis_pixel=AXIS)
    target = np.zeros(WINDOW)
    report, diff = ps.compare_stacks(meas, design_psf, target=target)
    pred = ps.as_stack(design_psf)
    np.testing.assert_allclose(diff, meas.psf - pred.psf[:, [5, 6, 7]], atol=1e-15)
    for row in report["wavelengths"]:
        e_m = np.array(row["order_energies"]["measured"])
        e_p = np.array(row["order_energies"]["predicted"])
        wl = row["wavelength_nm"]
        eta_m = np.array([analytic_eta(m, wl, DEPTH_SCALE) for m in (0, 1, 2)])
        eta_p = np.array([analytic_eta(m, wl, 1.0) for m in (0, 1, 2)])
        # Tolerance: the first order's diffraction tails put ~0.3 % of its energy in the 0th-order disk.
        np.testing.assert_allclose(e_m[0] / e_m[1], eta_m[0] / eta_m[1], rtol=0.05, atol=4e-3)
        np.testing.assert_allclose(e_p[0] / e_p[1], eta_p[0] / eta_p[1], rtol=0.05, atol=4e-3)
        if wl == 450:  # the 5 % depth error is visible above that floor
            assert e_m[0] / e_m[1] - e_p[0] / e_p[1] > 0.01
        pos_m, pos_p = np.array(row["order_positions"]["measured"]), np.array(row["order_positions"]["predicted"])
        np.testing.assert_allclose(pos_m[1], pos_p[1], atol=0.3)
        assert row["energy_on_target"]["measured"] == 0.0


def test_export_layouts(tmp_path, fabricated):
    stack = ps.as_stack(fabricated)
    spec_wl = np.linspace(380e-9, 720e-9, 341)
    spectra = np.exp(-0.5 * ((spec_wl[None] - stack.wavelengths_m[:, None]) / 4.25e-9) ** 2)
    stack.spectrum_wavelengths_m, stack.spectra = spec_wl, spectra
    path = ps.save_stack(stack, tmp_path / "stack.npz")
    res = PSFResult.load(path)
    assert res.psf.shape == (2, 1) + stack.psf.shape[1:] and res.views == ("coded", "uncoded")
    np.testing.assert_array_equal(res.psf[:, 0], stack.psf)
    back = ps.load_stack(path)
    np.testing.assert_array_equal(back.psf, stack.psf)
    # A Gaussian band of sigma 4.25 nm has a FWHM of 2.3548 sigma = 10.0 nm.
    np.testing.assert_allclose(back.band_stats()[:, 1], 10.0e-9, rtol=0.01)
    np.testing.assert_allclose(back.band_stats()[:, 0], stack.wavelengths_m, atol=0.05e-9)
    npy = np.load(ps.save_network_npy(stack, tmp_path / "psf.npy"))
    assert npy.shape == (2,) + stack.psf.shape[2:] + (stack.wavelengths_m.size,)
    np.testing.assert_allclose(npy[0, ..., 2], stack.view("uncoded")[2], rtol=1e-6)
    np.testing.assert_allclose(npy[1, ..., 2], stack.view("coded")[2], rtol=1e-6)
    assert ps.network_array([stack, stack]).shape == (2, 2) + npy.shape[1:]


def test_bad_wavelengths_raise(design_psf):
    with pytest.raises(DoeError, match="increase strictly"):
        ps.check_wavelengths([450e-9, 440e-9])
    with pytest.raises(DoeError, match="one capture per wavelength"):
        ps.build_stack([(np.ones((8, 8)), np.ones((8, 8)))], [450e-9, 460e-9], PITCH)
    stack = ps.as_stack(design_psf)
    with pytest.raises(DoeError, match="no PSF at 405 nm"):
        ps.extrapolate_orders(stack, design_psf, [405e-9])
    shifted = ps.PSFStack(psf=stack.psf[:, :1], wavelengths_m=[460e-9], pixel_pitch_m=PITCH, axis_pixel=AXIS)
    with pytest.raises(DoeError, match="no PSF at 460 nm"):
        ps.compare_stacks(shifted, design_psf)
    with pytest.raises(DoeError, match="differ in size"):
        ps.calibrate_capture(np.ones((8, 8)), np.ones((8, 9)))


def write_captures(folder, fabricated_nm, response=(0.3, 0.9, 0.85, 0.5)):
    """Synthetic dual-pixel mosaics of the fabricated grating; the stored view is the uncoded one."""
    from metrology.calibration.dualpixel import cfa_channels

    res = engine(fabricated_nm, window=(128, 192), axis=(64, 48)).psf(grating(DEPTH_SCALE))
    folder.mkdir()
    resp = np.asarray(response)[cfa_channels((128, 192))]
    for i, wl in enumerate(fabricated_nm):
        coded, uncoded = res.psf[0, 0, i] * 1e7 * resp, res.psf[1, 0, i] * 1e7 * resp
        np.save(folder / f"{wl}nm_sum.npy", coded + uncoded + 20.0)
        np.save(folder / f"{wl}nm_view.npy", uncoded + 10.0)
    return res


def test_cli_psf_stack(tmp_path, design_psf):
    import json

    from doedesign.cli import main

    truth = write_captures(tmp_path / "caps", [450, 500, 550])
    design_psf.save(tmp_path / "design_psf.npz")
    out = tmp_path / "out"
    code = main(["calibrate", "psf", "--captures", str(tmp_path / "caps"), "--wavelengths-nm", "450:550:50",
                 "--coded-view", "other", "--black-level", "10", "--window", "96,160", "--axis-pixel", "48,32",
                 "--background", "none", "--predicted", str(tmp_path / "design_psf.npz"),
                 "--extrapolate-nm", "400,420", "--out", str(out)])
    assert code == 0
    stack = ps.load_stack(out / "psf_stack.npz")
    np.testing.assert_allclose(stack.wavelengths_m * 1e9, [400, 420, 450, 500, 550])
    assert stack.measured.tolist() == [False, False, True, True, True]
    # Coded efficiency relative to the uncoded half survives the CFA gains and the crop.
    e_true = truth.psf[0, 0].sum(axis=(-2, -1)) / truth.psf[1, 0].sum(axis=(-2, -1))
    np.testing.assert_allclose(stack.energy_in_window[0, 2:], e_true, rtol=0.03)
    report = json.loads((out / "report.json").read_text())
    rows = report["comparison"]["wavelengths"]
    assert [r["measured"] for r in rows] == [False, False, True, True, True]
    pos = np.array(rows[2]["order_positions"]["measured"])
    np.testing.assert_allclose(pos[1], [48, 32 + 450e-9 * 50e-3 / (PERIOD_PX * PITCH) / PITCH], atol=0.7)
    npy = np.load(out / "psf_network.npy")
    assert npy.shape == (2, 96, 160, 5)
    for name in ("psf_stack.png", "orders.png", "comparison.npz"):
        assert (out / name).stat().st_size > 0


def test_cli_psf_bad_input(tmp_path, capsys):
    from doedesign.cli import main

    write_captures(tmp_path / "caps", [450, 460])
    base = ["calibrate", "psf", "--captures", str(tmp_path / "caps"), "--coded-view", "other", "--window", "32,32",
            "--out", str(tmp_path / "out")]
    assert main(base + ["--wavelengths-nm", "450:470:10"]) == 2
    assert "no capture (NNNnm_sum + NNNnm_view) for 470 nm" in capsys.readouterr().err
    assert main(base + ["--wavelengths-nm", "460,450"]) == 2
    assert "increase strictly" in capsys.readouterr().err
    listing = tmp_path / "list.txt"
    listing.write_text("460 caps/460nm_sum.npy caps/460nm_view.npy\n450 caps/450nm_sum.npy caps/450nm_view.npy\n")
    assert main(base[:3] + [str(listing)] + base[4:]) == 2
    assert "increase strictly" in capsys.readouterr().err
    np.save(tmp_path / "caps" / "450nm_view.npy", np.full((128, 192), 1e9))
    assert main(base) == 2
    assert "brighter than the sum" in capsys.readouterr().err
    assert not (tmp_path / "out").exists()
