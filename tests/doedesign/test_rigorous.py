"""The rigorous solver (doedesign.rigorous, fmmax) against analytic limits and a published table."""

import numpy as np
import pytest
from scipy.special import jv

from doedesign.errors import DoeError
from doedesign.rigorous import (relief_layers, rigorous_efficiencies, smallest_feature_m, thin_element_efficiencies,
                                validity)

pytest.importorskip("fmmax")

WL = 1e-6
N_GLASS = 1.5


def _relative(result, pol="te"):
    e = result.polarized(pol)[0]
    return e / e.sum()


def test_relief_layers_slice_a_staircase_top_first():
    h = np.array([[0.0, -1e-7, -3e-7, -1e-7]])
    patterns, thick = relief_layers(h)
    assert np.allclose(thick, [1e-7, 2e-7])
    assert patterns[0].tolist() == [[True, False, False, False]]
    assert patterns[1].tolist() == [[True, True, False, True]]


def test_shallow_binary_grating_reaches_the_scalar_limit():
    # 50 % lamellar grating, period 20 wavelengths, phase step pi/2: eta_0 = cos^2(phi/2) = 0.5,
    # eta_1 = (2/pi)^2 sin^2(phi/2) = 0.2026 (the thin-element Fourier series of a square wave).
    px = 40
    depth = (np.pi / 2) * WL / (2 * np.pi * (N_GLASS - 1))
    h = np.zeros((1, px))
    h[0, px // 2:] = -depth
    r = rigorous_efficiencies(h, 20 * WL / px, [WL], N_GLASS, n_terms=81)
    rel = _relative(r)
    assert rel[r.order_index(0)] == pytest.approx(0.5, abs=0.01)
    assert rel[r.order_index(1)] == pytest.approx((2 / np.pi) ** 2 * 0.5, abs=0.01)
    assert rel[r.order_index(2)] < 0.003  # even orders vanish at 50 % duty


def test_thin_sinusoidal_grating_gives_raman_nath_orders():
    # A shallow sinusoidal relief (phase amplitude 1.2 rad, period 20 wavelengths, depth 0.48 um,
    # Q = 2 pi lambda d / (n Lambda^2) = 0.005): eta_m = J_m^2(1.2) in the Raman-Nath regime.
    px, amp_rad, n_steps = 64, 1.2, 16
    a = amp_rad * WL / (2 * np.pi * (N_GLASS - 1))
    h = a * np.sin(2 * np.pi * np.arange(px) / px) - a
    h = (np.round(h / (2 * a / n_steps)) * (2 * a / n_steps))[None, :]
    r = rigorous_efficiencies(h, 20 * WL / px, [WL], N_GLASS, n_terms=61)
    rel = _relative(r)
    thin = thin_element_efficiencies(h, [WL], N_GLASS, r.orders)[0]
    for m in range(-2, 3):
        k = r.order_index(m)
        # the staircase sinusoid is within 0.015 of the Bessel values; the rigorous orders within
        # 0.003 of that staircase's own thin-element orders
        assert rel[k] == pytest.approx(jv(m, amp_rad) ** 2, abs=0.015)
        assert rel[k] == pytest.approx(thin[k], abs=0.003)


def test_subwavelength_grating_is_the_effective_medium_film_per_polarization():
    # Period 0.2 wavelength, 50 % glass, 0.5 um deep: only order 0 propagates and the layer acts
    # as a film with eps_TE = f eps + (1 - f) (E along the lines) and 1/eps_TM = f/eps + (1 - f).
    px, depth = 20, 0.5e-6
    h = np.zeros((1, px))
    h[0, px // 2:] = -depth
    r = rigorous_efficiencies(h, 0.2 * WL / px, [WL], N_GLASS, n_terms=41, incidence="air")

    def film(n_eff):  # Airy transmittance air | film | glass at normal incidence
        r12, r23 = (1 - n_eff) / (1 + n_eff), (n_eff - N_GLASS) / (n_eff + N_GLASS)
        t12, t23 = 2 / (1 + n_eff), 2 * n_eff / (n_eff + N_GLASS)
        ph = np.exp(2j * np.pi * n_eff * depth / WL)
        return N_GLASS * abs(t12 * t23 * ph / (1 + r12 * r23 * ph ** 2)) ** 2

    te, tm = film(np.sqrt(0.5 * N_GLASS ** 2 + 0.5)), film(1 / np.sqrt(0.5 / N_GLASS ** 2 + 0.5))
    assert te - tm > 0.01  # the two are told apart
    assert r.polarized("te")[0, r.order_index(0)] == pytest.approx(te, abs=0.002)
    assert r.polarized("tm")[0, r.order_index(0)] == pytest.approx(tm, abs=0.002)


def test_deep_checkerboard_grating_matches_li_1997_example_1():
    # L. Li, "New formulation of the Fourier modal method for crossed surface-relief gratings",
    # JOSA A 14, 2758 (1997), Example 1: a checkerboard of eps = 2.25 squares of side 1.25 wavelengths,
    # one wavelength deep, on eps = 2.25, lit from air at normal incidence. Converged transmitted
    # efficiencies as tabulated with that example (K. C. Johnson's GD-Calc, gdc_demo3, unit cell B):
    # (0,0) 0.1761; (+-1,0)_B 0.1302 and (0,+-1)_B 0.13133; (-1,-1)_B 0.039708 (E along x) and
    # 0.054638 (E along y). In this square cell of side 2.5 wavelengths, B order (m1, m2) is (m1 - m2, m1 + m2).
    w, px = 1.25e-6, 20
    h = np.full((px, px), -WL)
    h[:px // 2, :px // 2] = 0.0
    h[px // 2:, px // 2:] = 0.0
    r = rigorous_efficiencies(h, 2 * w / px, [WL], N_GLASS, n_terms=200, incidence="air")
    te, tm = r.polarized("te")[0], r.polarized("tm")[0]
    tol = 0.003  # 200 terms; the 0,0 order converges from below (0.1729 at 100 terms, 0.1745 at 200)
    assert te[r.order_index(0, 0)] == pytest.approx(0.1761, abs=tol)
    for p, q in [(1, 1), (-1, -1), (1, -1), (-1, 1)]:
        assert te[r.order_index(p, q)] == pytest.approx(0.1307, abs=tol)
    # B(-1,-1) is (0,-2) here: 0.054638 with E along y (te), 0.039708 with E along x (tm)
    assert te[r.order_index(0, -2)] == pytest.approx(0.054638, abs=tol)
    assert tm[r.order_index(0, -2)] == pytest.approx(0.039708, abs=tol)
    assert tm[r.order_index(2, 0)] == pytest.approx(0.054638, abs=tol)


def test_thin_element_model_gives_the_staircase_efficiency():
    # 16-level blazed grating of 16 px: eta_1 = sinc^2(1/16) = 0.9872 at the design wavelength.
    step = WL / (N_GLASS - 1) / 16
    h = (-(15 - np.arange(16)) * step)[None, :]  # phase rising toward higher columns: order +1
    orders = np.array([[1, 0], [0, 0], [-15, 0], [17, 0]])
    eta = thin_element_efficiencies(h, [WL], N_GLASS, orders)[0]
    assert eta[0] == pytest.approx(np.sinc(1 / 16) ** 2, abs=1e-9)
    assert eta[1] == pytest.approx(0.0, abs=1e-12)
    assert eta[2] == pytest.approx(np.sinc(15 / 16) ** 2, rel=1e-6)  # orders 1 + 16 k: sinc^2(m / 16)
    assert eta[3] == pytest.approx(np.sinc(17 / 16) ** 2, rel=1e-6)


def test_validity_statement_and_smallest_feature():
    h = np.zeros((1, 16))
    h[0, 5:8] = -1e-7
    assert smallest_feature_m(h, 1e-6) == pytest.approx(3e-6)
    ok = validity(5.4e-6, 1.125e-6, [486e-9, 656e-9])
    assert ok["holds"] and ok["feature_over_wavelength"] == pytest.approx(5.4 / 0.656)
    # limits from the blazed-grating benchmark: 2 wavelengths of feature, 1 feature of depth
    assert validity(1.8e-6, 1.125e-6, [486e-9, 656e-9])["holds"]  # the paper's 1.8 um pixels: 2.7 wavelengths
    narrow = validity(1.2e-6, 1.125e-6, [486e-9, 656e-9])
    assert not narrow["holds"] and "outside" in narrow["statement"]
    assert not validity(5.4e-6, 6e-6, [550e-9])["holds"]  # deeper than wide


def test_bad_requests_are_one_line_errors():
    with pytest.raises(DoeError, match="incidence"):
        rigorous_efficiencies(np.zeros((1, 4)), 1e-6, [WL], N_GLASS, incidence="side")
    with pytest.raises(DoeError, match="distinct heights"):
        relief_layers(np.linspace(0, -1e-6, 200)[None, :])
