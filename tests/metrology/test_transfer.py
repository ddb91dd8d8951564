"""The instrument's lateral transfer family against analytic results (issue 25)."""

import math

import numpy as np
import pytest
from scipy.special import erf

from metrology.matching.instrument import InstrumentModel, Placement
from metrology.matching.transfer import LateralTransfer, footprint_kernel

PITCH = 5.4e-6
PIXEL = 1.0e-6


def _model(shape=(40, 40)):
    matrix = np.diag([PIXEL / PITCH, PIXEL / PITCH])
    return InstrumentModel(np.zeros((30, 30), int), PITCH, shape, Placement(matrix, np.array([8.0, 8.0])))


def _camera_cols_m(model):
    """Design-frame position (m) of each camera column's centre, from the window's first fine cell edge."""
    c = np.arange(model.shape[1], dtype=float)
    _, col = model.placement.to_design(np.zeros_like(c), c)
    return (col - model.window[2] + 0.5) * PITCH


def _box_gauss_step(x, a, sigma):
    """Mean over a box of width ``a`` centred at ``x`` of a unit step at 0 blurred by a Gaussian
    of width ``sigma``: (G(x + a/2) - G(x - a/2)) / a, G(y) = y Phi(y/sigma) + sigma phi(y/sigma)."""
    def phi_cdf(y):
        return 0.5 * (1 + erf(y / (math.sqrt(2) * sigma))) if sigma > 0 else (y > 0).astype(float)

    def g(y):
        return y * phi_cdf(y) + (sigma * np.exp(-0.5 * (y / sigma) ** 2) / math.sqrt(2 * math.pi) if sigma > 0 else 0)

    if a == 0:
        return phi_cdf(x)
    return (g(x + a / 2) - g(x - a / 2)) / a


@pytest.mark.parametrize("fill,sigma", [(1.0, 0.3e-6), (0.5, 0.3e-6), (0.0, 0.3e-6), (0.64, 0.0), (1.0, 0.0)])
def test_a_step_through_fill_factor_box_and_blur_is_the_erf_box_convolution(fill, sigma):
    # A straight 500 nm step on a fine-cell boundary: each camera pixel reports the mean over a
    # centred square of side sqrt(fill) pixels of the step blurred by a Gaussian (the box's
    # extent along the step does not matter); closed form above.
    model = _model()
    fine = np.zeros(model._fine_shape())
    edge = fine.shape[1] // 2
    fine[:, edge:] = -500e-9
    x = _camera_cols_m(model) - edge * model.step_m
    got = model.sample(model.camera_map(fine, LateralTransfer(sigma, fill)), model.placement)[20]
    want = -500e-9 * _box_gauss_step(x, math.sqrt(fill) * PIXEL, sigma)
    tol = 1e-10 if sigma > 0 else 3e-9  # a bare box's corner lies between spline knots
    assert np.abs(got - want).max() < tol
    if fill == 1.0 and sigma == 0.3e-6:
        # The check can fail: half the fill factor is a different profile.
        other = model.sample(model.camera_map(fine, LateralTransfer(sigma, 0.5)), model.placement)[20]
        assert np.abs(other - want).max() > 5e-9


@pytest.mark.parametrize("s,mtf", [(0.25, 0.68503), (0.5, 0.39100), (0.75, 0.14429)])
def test_a_sinusoid_through_the_objective_is_attenuated_by_the_chinese_hat(s, mtf):
    # Incoherent circular pupil at s = nu / nu_c: 2/pi (acos s - s sqrt(1 - s^2)) (Goodman,
    # Fourier Optics, 6.3), values worked by hand; point sampling, no blur: the optics alone.
    na, lam = 0.3, 0.57e-6
    nu = s * 2 * na / lam
    model = _model((60, 60))
    fine = np.zeros(model._fine_shape())
    xf = (np.arange(fine.shape[1]) + 0.5) * model.step_m
    # The model's surface is uniform over each fine cell: a staircase of the cosine's values at
    # the cell centres, whose fundamental is sinc(nu step) of the cosine's (its harmonics, at
    # 1/step - nu and beyond, lie past the cut-off).
    fine[:] = 100e-9 * np.cos(2 * np.pi * nu * xf)[None, :]
    mtf *= np.sinc(nu * model.step_m)
    got = model.sample(model.camera_map(fine, LateralTransfer(0.0, 0.0, na, lam)), model.placement)[30]
    x = _camera_cols_m(model)
    basis = np.stack([np.cos(2 * np.pi * nu * x), np.sin(2 * np.pi * nu * x)], axis=1)[10:-10]
    coef, *_ = np.linalg.lstsq(basis, got[10:-10], rcond=None)
    assert np.hypot(*coef) / 100e-9 == pytest.approx(mtf, abs=2e-4)
    # Beyond the cut-off nothing passes.
    nu2 = 1.2 * 2 * na / lam
    fine[:] = 100e-9 * np.cos(2 * np.pi * nu2 * xf)[None, :]
    got2 = model.sample(model.camera_map(fine, LateralTransfer(0.0, 0.0, na, lam)), model.placement)[30]
    assert np.abs(got2[10:-10]).max() < 1e-10


def test_transfer_parameters_are_bounded_and_a_zero_width_kernel_is_a_cell():
    t = LateralTransfer(sigma_m=-0.2e-6, fill_factor=1.4, na=2.0)
    assert (t.sigma_m, t.fill_factor, t.na) == (0.0, 1.0, 0.95)
    assert LateralTransfer(na=0.01).na == 0.05 and LateralTransfer(na=0.0).na == 0.0
    kern = footprint_kernel(np.eye(2) * 0.2, PITCH, PITCH / 44, -1e-7, fill_factor=0.0)
    assert kern.shape[0] >= 3 and kern.sum() == pytest.approx(1.0)
    k = kern.shape[0] // 2
    assert kern[k, k] == pytest.approx(1.0, abs=1e-6)


@pytest.mark.parametrize("na", [0.3, 0.5])
def test_a_batwing_is_added_beside_the_objective_not_imaged_through_it(na):
    # A CSI's batwing is its own edge response of a fitted width: across a straight step of
    # height H it adds a H (x / w) phi(x / w) / phi(1) to the objective's image of the step,
    # whatever the aperture (+a H at w on the high side). Imaged again through the objective
    # (the product of the transfers) its peak would fall to a fraction of that.
    from metrology.diagnosis.effects import batwing_transfer

    amp, width, height = 0.1, 0.25e-6, 500e-9
    model = _model((60, 60))
    fine = np.zeros(model._fine_shape())
    edge = fine.shape[1] // 2
    fine[:, edge:] = -height
    x = _camera_cols_m(model) - edge * model.step_m
    t = LateralTransfer(0.0, 0.0, na)
    spectrum = model.spectrum(fine)
    wr, wc = model.fourier_grid()
    wing = batwing_transfer([amp, width], model.step_m, wr, wc, 10 ** 6)
    plain = model.sample(model.map_of(spectrum, t), model.placement)[30]
    beside = model.sample(model.map_of(spectrum, t, beside=[wing]), model.placement)[30]
    phi = lambda u: np.exp(-0.5 * u * u) / math.sqrt(2 * math.pi)  # noqa: E731
    # The surface falls by H at x = 0: the high side is x < 0.
    want = -amp * height * (x / width) * phi(x / width) / phi(1.0)
    assert np.abs((beside - plain) - want).max() < 0.01 * amp * height
    # The product of the transfers is a different (attenuated) profile: the check can fail.
    through = model.sample(model.map_of(spectrum, t, factors=[wing]), model.placement)[30]
    assert np.abs((through - plain) - want).max() > 0.1 * amp * height
    # The model keeps the last summed transfer: another wing (half the amplitude) is not served
    # the kept one, and the first again is the same map.
    half = batwing_transfer([amp / 2, width], model.step_m, wr, wc, 10 ** 6)
    halved = model.sample(model.map_of(spectrum, t, beside=[half]), model.placement)[30]
    assert np.abs((halved - plain) - want / 2).max() < 0.01 * amp * height
    again = model.sample(model.map_of(spectrum, t, beside=[wing]), model.placement)[30]
    assert np.array_equal(again, beside)


def test_the_chinese_hat_is_the_worked_values_and_nothing_beyond_the_cut_off():
    # Goodman's formula worked by hand (to 1e-6) at s = 0.25, 0.5, 0.75, at the cut-off and
    # beyond, on a grid as the model's transfer evaluates it (inside the cut-off only).
    from metrology.matching.transfer import na_mtf

    na, lam = 0.3, 0.57e-6
    nu = np.array([[0.25, 0.5, 0.75], [1.0, 1.5, -0.5]]) * 2 * na / lam
    got = na_mtf(nu, na, lam)
    assert got.shape == nu.shape
    assert got.ravel() == pytest.approx([0.685038, 0.391002, 0.144294, 0.0, 0.0, 0.391002], abs=1e-6)


@pytest.mark.parametrize("sigma,fill,na", [(0.022e-6, 0.98, 0.26), (0.1e-6, 0.6, 0.4), (0.0, 0.5, 0.55),
                                           (0.3e-6, 1.0, 0.3)])
def test_a_step_through_pixel_and_objective_is_the_continuous_convolution(sigma, fill, na):
    # A 600 nm step on a cell boundary, imaged through a box of side sqrt(fill) pixels, a
    # Gaussian and the circular pupil's transfer, against the same convolution done on a grid
    # a hundred times finer (numpy's FFT, frequencies to 250 cycles/um): the fine cells' repeats
    # beyond the grid's Nyquist are cut by the objective, not folded into the image. The
    # reference repeats the model's FFT period, the surface edge-extended around the window
    # as the model documents, so the optics' slow 1/x tail wraps the same way in both. A sharp
    # pixel's discrete footprint kernel under the objective left 0.7-2 nm here at 0.2 um.
    from metrology.matching.transfer import na_mtf

    model, height, sub = _model((60, 60)), 600e-9, 100
    fine = np.zeros(model._fine_shape())
    edge = fine.shape[1] // 2
    fine[:, edge:] = -height
    got = model.sample(model.camera_map(fine, LateralTransfer(sigma, fill, na)), model.placement)[30]
    h, shape = model._padding()
    cells = np.concatenate([np.zeros(h), fine[30], np.full(shape[1] - h - fine.shape[1], -height)])
    surface = np.repeat(cells, sub)
    dx = model.step_m / sub
    nu = np.fft.rfftfreq(surface.size, dx)
    t = (np.sinc(nu * math.sqrt(fill) * PIXEL) * np.exp(-2 * (np.pi * sigma * nu) ** 2)
         * na_mtf(nu, na, LateralTransfer().wavelength_m))
    image = np.fft.irfft(np.fft.rfft(surface) * t, surface.size)
    xs = (np.arange(surface.size) + 0.5) * dx - (h + edge) * model.step_m
    x = _camera_cols_m(model) - edge * model.step_m
    near = np.abs(x) < 8e-6
    assert np.abs(got - np.interp(x, xs, image))[near].max() < 1e-11


def test_the_objective_transfer_from_kept_factors_is_the_plain_product_bit_for_bit():
    """A Jacobian's columns of blur, fill factor and NA reuse the factors the others left; the
    transfer is still footprint x blur x chinese hat x the spline prefilter, the same bits."""
    from metrology.matching.transfer import footprint_spectrum, na_mtf

    matrix = np.array([[0.16, 0.003], [-0.003, 0.158]])
    model = InstrumentModel(np.zeros((30, 30), int), PITCH, (40, 40), Placement(matrix, np.array([8.0, 8.0])))
    _, shape = model._padding()
    wr, wc = model.fourier_grid()
    nu_r, nu_c = wr / (2 * np.pi * model.step_m), wc / (2 * np.pi * model.step_m)
    base = LateralTransfer(0.3e-6, 0.7, 0.45)
    for t in [base, LateralTransfer(0.31e-6, 0.7, 0.45), LateralTransfer(0.3e-6, 0.72, 0.45),
              LateralTransfer(0.3e-6, 0.7, 0.47), base]:
        plain = (footprint_spectrum(matrix, PITCH, model.step_m, t.sigma_m, t.fill_factor, nu_r[:, None], nu_c[None, :])
                 * na_mtf(np.hypot(nu_r[:, None], nu_c[None, :]), t.na, t.wavelength_m))
        plain[(np.abs(nu_r) >= t.cutoff_per_m)[:, None] | (np.abs(nu_c) >= t.cutoff_per_m)[None, :]] = 0.0
        expected = plain.astype(np.complex64)
        expected *= (6.0 / (4.0 + 2.0 * np.cos(wr))).astype(np.float32)[:, None]
        expected *= (6.0 / (4.0 + 2.0 * np.cos(wc))).astype(np.float32)[None, :]
        got = model._transfer(shape, t)
        assert got.dtype == np.complex64
        assert np.array_equal(got.view(np.float32), expected.view(np.float32))
