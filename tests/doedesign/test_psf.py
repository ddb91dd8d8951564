"""The PSF engine against analytic optics (grating orders, Airy zero, energy, gradients)."""

import numpy as np
import pytest
from scipy import integrate

from doedesign.camera import Camera
from doedesign.engine.psf import PSFEngine, parse_wavelengths_nm
from doedesign.errors import DoeError, SamplingError
from doedesign.materials import FUSED_SILICA

PITCH = 5.4e-6
Z = 50e-3


def blazed_grating(n_pix, period_px=16, levels=16, wavelength=550e-9):
    """Staircase blazed grating along columns, heights <= 0, phase rising with column."""
    step = FUSED_SILICA.height_2pi_m(wavelength) / levels
    col = np.arange(n_pix)
    level = (col % period_px) * levels // period_px
    # Deeper at low level index so the phase increases with column: h = -(levels-1-level) step.
    h = -(levels - 1 - level) * step
    return np.tile(h, (n_pix, 1))


def box_energy(psf, row, col, half):
    r, c = int(round(row)), int(round(col))
    return psf[r - half:r + half + 1, c - half:c + half + 1].sum()


def grating_orders(wavelength, n_pix=512, period_px=16, orders=(0, 1, 2), half=30):
    """Order efficiencies: energy in a box around each order over a clear pupil's box energy.

    The clear pupil's box normalizes out the aperture's own sidelobes; ``half`` trades the
    spot's tails (larger box) against leakage from the neighbouring orders (smaller box).
    """
    cam = Camera(aperture_diameter_m=None, doe_side="full", window_shape=(512, 512), axis_pixel=(256, 256))
    eng = PSFEngine(cam, PITCH, (n_pix, n_pix), wavelengths_m=[wavelength])
    res = eng.psf(blazed_grating(n_pix, period_px))
    coded, clear = res.psf[0, 0, 0], res.psf[1, 0, 0]
    ref = box_energy(clear, 256, 256, half)
    out = {}
    for m in orders:
        x_px = m * wavelength * Z / (period_px * PITCH) / cam.pixel_pitch_m
        out[m] = box_energy(coded, 256, 256 + x_px, half) / ref
    return out


def eta_staircase(m, n_levels, a):
    """Order efficiency of an N-level staircase with step-phase scale a (reference formula)."""
    env = np.sinc(m / n_levels) ** 2
    x = a - m
    if abs(np.sin(np.pi * x / n_levels)) < 1e-12:
        return env
    return env * (np.sin(np.pi * x) / (n_levels * np.sin(np.pi * x / n_levels))) ** 2


def test_sixteen_level_first_order_at_design():
    eta = grating_orders(550e-9)
    assert eta[1] == pytest.approx(np.sinc(1 / 16) ** 2, abs=0.003)  # 98.72 %
    assert eta[1] == pytest.approx(0.9872, abs=0.003)
    weak = grating_orders(550e-9, half=8)
    assert weak[0] < 1e-3 and weak[2] < 1e-3


@pytest.mark.parametrize("wavelength,eta1,eta0", [(450e-9, 0.812, 0.032), (650e-9, 0.910, 0.032)])
def test_sixteen_level_orders_off_design(wavelength, eta1, eta0):
    eta = grating_orders(wavelength)
    eta[0] = grating_orders(wavelength, orders=(0,), half=8)[0]
    assert eta[1] == pytest.approx(eta1, abs=0.01)
    assert eta[0] == pytest.approx(eta0, abs=0.01)
    a = (FUSED_SILICA.n(wavelength) - 1) / wavelength * 550e-9 / (FUSED_SILICA.n(550e-9) - 1)
    assert eta[1] == pytest.approx(eta_staircase(1, 16, a), abs=0.005)
    assert eta[0] == pytest.approx(eta_staircase(0, 16, a), abs=0.005)


def test_pixel_envelope_at_quarter_zone():
    # A 4-level grating of period 4 px diffracts to u = 1/4 cycle per pixel: sinc^2(1/4) = 81.1 %.
    n = 256
    step = FUSED_SILICA.height_2pi_m(550e-9) / 4
    h = np.tile(-(3 - np.arange(n) % 4) * step, (n, 1))
    cam = Camera(aperture_diameter_m=None, doe_side="full")
    res = PSFEngine(cam, PITCH, (n, n), wavelengths_m=[550e-9]).psf(h)
    x_px = 550e-9 * Z / (4 * PITCH) / PITCH
    ratio = box_energy(res.psf[0, 0, 0], 256, 256 + x_px, 12) / box_energy(res.psf[1, 0, 0], 256, 256, 12)
    assert ratio == pytest.approx(np.sinc(0.25) ** 2, abs=0.005)


def test_height_sign_point_reflects_psf():
    rng = np.random.default_rng(1)
    h = -rng.uniform(0, 1e-6, (48, 48))
    cam = Camera(aperture_diameter_m=None, doe_side="full", window_shape=(65, 65), axis_pixel=(32, 32))
    eng = PSFEngine(cam, PITCH, h.shape, wavelengths_m=[550e-9])
    a = eng.psf(h, views=("coded",)).psf[0, 0, 0]
    b = eng.psf(-h, views=("coded",)).psf[0, 0, 0]
    np.testing.assert_allclose(b, a[::-1, ::-1], atol=1e-12)


def test_airy_first_zero():
    wl, d = 550e-9, 2e-3
    cam = Camera(aperture_diameter_m=d, doe_side="full", pixel_pitch_m=0.5e-6,
                 window_shape=(9, 161), axis_pixel=(4, 80))
    n = int(round(d / PITCH))
    res = PSFEngine(cam, PITCH, (n, n), wavelengths_m=[wl]).psf(np.zeros((n, n)), views=("uncoded",))
    profile = res.psf[0, 0, 0, 4, 80:]
    i = 20 + np.argmin(profile[20:60])
    # Parabolic refinement of the minimum.
    y0, y1, y2 = profile[i - 1:i + 2]
    frac = 0.5 * (y0 - y2) / (y0 - 2 * y1 + y2)
    r_zero = (i + frac) * cam.pixel_pitch_m
    expected = 1.22 * wl * cam.focal_length_m / d
    # The ideal lens forms the image at the sensor distance; use it for the F-number there.
    expected_at_sensor = 1.22 * wl * cam.sensor_distance_m / d
    assert r_zero == pytest.approx(expected_at_sensor, rel=0.02)
    assert expected == pytest.approx(expected_at_sensor, rel=0.02)


def _window_fraction(length, wl, lo, hi):
    scale = length / (wl * Z)
    val, _ = integrate.quad(lambda x: np.sinc(scale * x) ** 2, lo, hi, limit=2000)
    return val * scale


def test_energy_matches_analytic_window_fraction():
    n, wl = 100, 600e-9
    cam = Camera(aperture_diameter_m=None, doe_side="full", window_shape=(300, 300), axis_pixel=(150, 150))
    res = PSFEngine(cam, PITCH, (n, n), wavelengths_m=[wl]).psf(np.zeros((n, n)), views=("coded",))
    lo, hi = -150.5 * PITCH, 149.5 * PITCH
    fx = _window_fraction(n * PITCH, wl, lo, hi)
    expected = fx * fx
    assert res.energy_in_window[0, 0, 0] == pytest.approx(expected, abs=1e-6)
    assert expected < 0.999  # the window really loses light: no renormalization hides it


def test_energy_reported_not_renormalized():
    # A steep grating sends its first order out of a small window; the energy says so.
    cam = Camera(aperture_diameter_m=None, doe_side="full", window_shape=(64, 64), axis_pixel=(32, 32))
    h = blazed_grating(128, period_px=16)
    res = PSFEngine(cam, PITCH, h.shape, wavelengths_m=[550e-9]).psf(h)
    assert res.energy_in_window[0, 0, 0] < 0.05
    assert res.energy_in_window[1, 0, 0] > 0.9


def test_split_aperture_views_share_the_light():
    # Left and right halves of a clear pupil: each view's PSF holds ~ the same energy, and the
    # coded half of a flat DOE equals the uncoded half mirrored left-right.
    cam = Camera(aperture_diameter_m=64 * PITCH, doe_side="left", window_shape=(129, 129), axis_pixel=(64, 64))
    res = PSFEngine(cam, PITCH, (64, 64), wavelengths_m=[500e-9]).psf(np.zeros((64, 64)))
    np.testing.assert_allclose(res.psf[0, 0, 0], res.psf[1, 0, 0][:, ::-1], atol=1e-12)
    # Both halves carry the same grating: the first order lands where the grating equation says.
    n = 256
    h = blazed_grating(n)
    x1 = 500e-9 * Z / (16 * PITCH) / PITCH
    for side in ("left", "right"):
        cam = Camera(aperture_diameter_m=n * PITCH, doe_side=side, window_shape=(129, 129), axis_pixel=(64, 64))
        coded = PSFEngine(cam, PITCH, (n, n), wavelengths_m=[500e-9]).psf(h).psf[0, 0, 0]
        profile = coded.sum(axis=0)
        lo = int(64 + x1) - 10
        cols = np.arange(lo, lo + 21)
        centroid = np.sum(cols * profile[cols]) / profile[cols].sum()
        assert centroid - 64 == pytest.approx(x1, abs=0.3)


def test_defocus_spreads_the_spot_and_refocus_matches():
    cam = Camera(aperture_diameter_m=4e-3, doe_side="full", focus_distance_m=5.0,
                 window_shape=(65, 65), axis_pixel=(32, 32))
    n = int(np.ceil(4e-3 / PITCH))
    eng = PSFEngine(cam, PITCH, (n, n), wavelengths_m=[550e-9], depths_m=[5.0, 2.0, 1.0])
    res = eng.psf(np.zeros((n, n)), views=("uncoded",))
    peak = res.psf[0, :, 0].max(axis=(-2, -1))
    assert peak[0] > peak[1] > peak[2]
    # Geometric blur of a source at 1 m: its image lies behind the sensor, and the cone of
    # diameter D cut by the sensor has diameter D (z_img - z) / z_img.
    z_img = 1 / (1 / cam.focal_length_m - 1 / 1.0)
    blur_px = 4e-3 * (z_img - cam.sensor_distance_m) / z_img / cam.pixel_pitch_m
    spot = res.psf[0, 2, 0]
    profile = spot.sum(axis=0)
    # The column sum of a uniform disc is a semicircle: its half-maximum width is sqrt(3)/2 D.
    width_px = np.count_nonzero(profile > 0.5 * profile.max())
    assert width_px == pytest.approx(np.sqrt(3) / 2 * blur_px, rel=0.15)


def test_gradient_matches_finite_differences():
    rng = np.random.default_rng(0)
    n = 24
    cam = Camera(aperture_diameter_m=n * PITCH, doe_side="left", window_shape=(40, 40), axis_pixel=(20, 20),
                 focus_distance_m=2.0)
    eng = PSFEngine(cam, PITCH, (n, n), wavelengths_m=[480e-9, 620e-9], depths_m=[np.inf, 1.5])
    target = rng.random((2, 2, 40, 40))
    target /= target.sum() * 2

    def loss(psf):
        diff = psf - target
        return float(np.sum(diff ** 2)) * 1e3, 2e3 * diff

    h = -rng.uniform(0, 1.2e-6, (n, n))
    value, grad = eng.value_and_grad(h, loss)
    assert np.any(grad != 0)
    eps = 1e-10
    for (r, c) in [(3, 4), (12, 5), (20, 10), (7, 11)]:
        hp, hm = h.copy(), h.copy()
        hp[r, c] += eps
        hm[r, c] -= eps
        fd = (eng.value_and_grad(hp, loss)[0] - eng.value_and_grad(hm, loss)[0]) / (2 * eps)
        assert grad[r, c] == pytest.approx(fd, rel=1e-4, abs=1e-6 * np.abs(grad).max())
    # Pixels on the uncoded side do not influence the coded PSF.
    assert np.all(grad[:, n // 2 + 1:] == 0)


def test_gradient_with_doe_oversampling():
    rng = np.random.default_rng(3)
    n = 16
    cam = Camera(aperture_diameter_m=None, doe_side="full", window_shape=(24, 24), axis_pixel=(12, 12))
    eng = PSFEngine(cam, PITCH, (n, n), wavelengths_m=[550e-9], doe_oversample=2)

    def loss(psf):
        return float(psf[0, 0, 12, 14]), np.eye(24)[12][None, None, :, None] * np.eye(24)[14][None, None, None, :]

    h = -rng.uniform(0, 1e-6, (n, n))
    _, grad = eng.value_and_grad(h, loss)
    eps = 1e-10
    hp, hm = h.copy(), h.copy()
    hp[5, 6] += eps
    hm[5, 6] -= eps
    fd = (eng.value_and_grad(hp, loss)[0] - eng.value_and_grad(hm, loss)[0]) / (2 * eps)
    assert grad[5, 6] == pytest.approx(fd, rel=1e-4)


def test_oversampling_does_not_change_in_focus_psf():
    rng = np.random.default_rng(2)
    h = -rng.uniform(0, 1e-6, (20, 20))
    cam = Camera(aperture_diameter_m=None, doe_side="full", window_shape=(31, 31), axis_pixel=(15, 15))
    a = PSFEngine(cam, PITCH, h.shape, wavelengths_m=[550e-9]).psf(h).psf
    b = PSFEngine(cam, PITCH, h.shape, wavelengths_m=[550e-9], doe_oversample=3).psf(h).psf
    np.testing.assert_allclose(a, b, atol=1e-10)


def test_bad_inputs_are_clear_errors():
    cam = Camera(aperture_diameter_m=None, doe_side="full", window_shape=(16, 16), axis_pixel=(8, 8))
    eng = PSFEngine(cam, PITCH, (8, 8), wavelengths_m=[550e-9])
    with pytest.raises(DoeError, match="NaN"):
        eng.psf(np.full((8, 8), np.nan))
    with pytest.raises(DoeError, match="pitch"):
        PSFEngine(cam, 0.0, (8, 8))
    with pytest.raises(DoeError, match="outside the valid range"):
        PSFEngine(cam, PITCH, (8, 8), wavelengths_m=[5e-6])
    with pytest.raises(DoeError, match="larger than the aperture grid"):
        PSFEngine(Camera(), PITCH, (1700, 1700))
    with pytest.raises(SamplingError, match="doe_oversample"):
        PSFEngine(Camera(aperture_diameter_m=8.64e-3, focus_distance_m=5.0), PITCH, (100, 100),
                  wavelengths_m=[400e-9], depths_m=[0.05])
    with pytest.raises(DoeError, match="wavelengths"):
        parse_wavelengths_nm("red")
    np.testing.assert_allclose(parse_wavelengths_nm("400:700:10")[[0, -1]], [400e-9, 700e-9])
    assert parse_wavelengths_nm("400:700:10").size == 31


def test_single_precision_stays_within_a_few_1e7_of_the_peak():
    n = 96
    cam = Camera(aperture_diameter_m=n * PITCH)
    h = blazed_grating(n, period_px=12) * np.random.default_rng(4).uniform(0.5, 1.0, (n, n))
    wls = [450e-9, 620e-9]
    double = PSFEngine(cam, PITCH, (n, n), wavelengths_m=wls).psf(h).psf
    single = PSFEngine(cam, PITCH, (n, n), wavelengths_m=wls, precision="single").psf(h).psf
    assert single.dtype == np.float64
    assert np.abs(single - double).max() < 2e-6 * double.max()
    assert np.abs(single - double).max() > 0  # it is really computed in single precision
    with pytest.raises(DoeError, match="precision"):
        PSFEngine(cam, PITCH, (n, n), precision="half")


def test_shared_lag_cache_reuses_only_the_wavelength_free_uncoded_lags():
    """Engines sharing a lag cache give the PSFs of engines that do not; the uncoded view in focus
    (no phase in its pupil) is transformed once for all wavelengths and engines, a defocused one
    is not reused (its pupil depends on the wavelength and the distance)."""
    cam = Camera(aperture_diameter_m=1.0e-3, window_shape=(48, 48), axis_pixel=(24, 24), doe_side="left")
    h = blazed_grating(160, period_px=16)
    shared = {}
    a = PSFEngine(cam, PITCH, h.shape, wavelengths_m=[500e-9], lag_cache=shared).psf(h)
    b = PSFEngine(cam, PITCH, h.shape, wavelengths_m=[600e-9, 650e-9], lag_cache=shared).psf(h)
    c = PSFEngine(cam, PITCH, h.shape, wavelengths_m=[600e-9], depths_m=[0.5], lag_cache=shared).psf(h)
    assert [k[1] for k in shared] == ["uncoded"]
    for res, wls, depths in ((a, [500e-9], None), (b, [600e-9, 650e-9], None), (c, [600e-9], [0.5])):
        ref = PSFEngine(cam, PITCH, h.shape, wavelengths_m=wls, depths_m=depths).psf(h)
        np.testing.assert_array_equal(res.psf, ref.psf)
    # The defocused uncoded PSF really differs from the in-focus one (the check above can fail).
    assert np.abs(c.psf[1, 0, 0] - b.psf[1, 0, 0]).max() > 0.1 * b.psf[1, 0, 0].max()


def test_wavelengths_side_by_side_give_the_serial_psfs():
    """psf(threads=2) computes wavelengths in threads (kernels cached from both, the uncoded lags
    shared) and returns exactly the serial stack, in focus and defocused, with a kernel cache
    smaller than the wavelengths so that entries are evicted while threads add theirs."""
    from doedesign.progress import Progress

    cam = Camera(aperture_diameter_m=1.0e-3, window_shape=(40, 56), axis_pixel=(20, 28), doe_side="left")
    h = blazed_grating(160, period_px=16)
    wls = np.linspace(450e-9, 650e-9, 11)
    serial = PSFEngine(cam, PITCH, h.shape, wavelengths_m=wls, depths_m=[cam.focus_distance_m, 0.5]).psf(h).psf
    with Progress(2 * wls.size * 2, enabled=False) as bar:
        threaded = PSFEngine(cam, PITCH, h.shape, wavelengths_m=wls, depths_m=[cam.focus_distance_m, 0.5]).psf(
            h, progress=bar, threads=2).psf
        assert bar.count == 2 * wls.size * 2
    np.testing.assert_array_equal(threaded, serial)
    # Each channel is its own wavelength's (the comparison above can fail on a mix-up).
    assert np.abs(serial[0, 0, 0] - serial[0, 0, -1]).max() > 0.1 * serial[0, 0, 0].max()


def test_design_aperture_blocks_light():
    # The design's clear region masks the coded view: an all-closed aperture passes no light, an
    # all-open one changes nothing, and closing the left half of a full-pupil element leaves half
    # its light: exactly the right-half view's PSF (normalized to its own half) times 1/2.
    from doedesign.engine.psf import PSFEngine

    n, p = 16, 5.4e-6
    h = -np.random.default_rng(5).uniform(0, 1.2e-6, (n, n))
    kw = dict(window_shape=(24, 24), axis_pixel=(12, 12), aperture_diameter_m=None)
    full = Camera(doe_side="full", **kw)
    ref = PSFEngine(full, p, (n, n)).psf(h, views=("coded",)).psf
    closed = PSFEngine(full, p, (n, n), aperture=np.zeros((n, n), bool)).psf(h, views=("coded",)).psf
    assert closed.max() == 0.0
    opened = PSFEngine(full, p, (n, n), aperture=np.ones((n, n), bool)).psf(h, views=("coded",)).psf
    assert np.array_equal(opened, ref)
    left_closed = np.ones((n, n), bool)
    left_closed[:, : n // 2] = False
    half = PSFEngine(full, p, (n, n), aperture=left_closed).psf(h, views=("coded",)).psf
    right = PSFEngine(Camera(doe_side="right", **kw), p, (n, n)).psf(h, views=("coded",)).psf
    assert np.abs(2 * half - right).max() <= 1e-12 * right.max()
    with pytest.raises(DoeError, match="aperture must be a boolean array"):
        PSFEngine(full, p, (n, n), aperture=np.ones((n, n - 1), bool))


def test_psf_command_honours_the_design_aperture(tmp_path):
    # doe psf on a design file whose aperture is all chrome: no light (it reported 0.99 before).
    from doedesign.cli import main
    from doedesign.design import Design
    from doedesign.engine import PSFResult

    n = 16
    h = -np.random.default_rng(6).uniform(0, 1.1e-6, (n, n))
    for name, ap in (("open", np.ones((n, n), bool)), ("closed", np.zeros((n, n), bool))):
        Design(height_m=h, pitch_m=5.4e-6, aperture=ap).save(tmp_path / f"{name}.npz")
        assert main(["psf", str(tmp_path / f"{name}.npz"), "--aperture-mm", "0", "--side", "full",
                     "--wavelengths-nm", "550", "--device", "cpu", "--out", str(tmp_path / f"{name}_psf.npz")]) == 0
    opened, closed = (PSFResult.load(tmp_path / f"{k}_psf.npz") for k in ("open", "closed"))
    assert opened.energy_in_window[0].max() > 1e-3
    assert closed.psf[0].max() == 0.0 and closed.energy_in_window[0].max() == 0.0
