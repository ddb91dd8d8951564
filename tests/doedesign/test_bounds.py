"""The single-colour bound against independent computations (Airy pattern, direct half-disc integral)."""

import numpy as np
import pytest
from scipy.special import j1

from doedesign import targets
from doedesign.bounds import bound_report, spot_bound
from doedesign.camera import Camera

WLS = np.array([656e-9, 589e-9, 486e-9])
D, Z, A = 8.64e-3, 50e-3, 5.4e-6


def _gauss_square(n):
    x, w = np.polynomial.legendre.leggauss(n)
    return x * A / 2, w * A / 2


def airy_pixel_energy(wl, n=48):
    """Fraction of a circular aperture's light in the square pixel centred on the spot (Airy, quadrature)."""
    x, w = _gauss_square(n)
    r = np.hypot(x[:, None], x[None, :])
    v = np.pi * D * r / (wl * Z)
    airy = np.where(v > 0, (2 * j1(v) / np.where(v > 0, v, 1)) ** 2, 1.0)
    return float(np.pi * D ** 2 / 4 / (wl * Z) ** 2 * np.sum(np.outer(w, w) * airy))


def half_disc_pixel_energy(wl, n=24, m=600):
    """Same for the left half disc: field = int_{-R}^{0} exp(-i kx s) 2 sin(ky h(s)) / ky ds, h = sqrt(R^2 - s^2)."""
    R = D / 2
    x, w = _gauss_square(n)
    s, ws = np.polynomial.legendre.leggauss(m)
    s = (s - 1) * R / 2
    ws = ws * R / 2
    h = np.sqrt(R * R - s * s)
    k = 2 * np.pi * x / (wl * Z)
    ky = np.where(np.abs(k) > 0, k, 1e-30)
    # rows: y quadrature nodes; the y integral of the chord is analytic.
    chord = 2 * np.sin(ky[:, None] * h[None, :]) / ky[:, None]
    field = chord @ (ws[:, None] * np.exp(-1j * np.outer(s, k)))  # (y nodes, x nodes)
    area = np.pi * R * R / 2
    return float(np.sum(np.outer(w, w) * np.abs(field) ** 2) / ((wl * Z) ** 2 * area))


@pytest.mark.parametrize("side, expected", [("full", (0.743, 0.788, 0.830)), ("left", (0.489, 0.548, 0.644))])
def test_bayer_bound_matches_independent_integrals(side, expected):
    cam = Camera(aperture_diameter_m=D, focus_distance_m=np.inf, doe_side=side)
    target = targets.bayer(cam)
    bound = spot_bound(cam, 5.4e-6, (1600, 1600), target)[0]
    ref = [airy_pixel_energy(wl) if side == "full" else half_disc_pixel_energy(wl) for wl in WLS]
    # The pupil of 1600 pixels samples the circle's edge by area fractions: agreement to 1e-3.
    np.testing.assert_allclose(bound, ref, atol=1.5e-3)
    np.testing.assert_allclose(bound, expected, atol=2e-3)
    # A narrower spot holds more light in the pixel: blue > green > red.
    assert bound[2] > bound[1] > bound[0]


def test_bound_of_extended_target_and_report():
    """A 3 x 3 box takes more of the spot than its centre pixel; the report names the weakest plane."""
    cam = Camera(aperture_diameter_m=400 * 5.4e-6, focus_distance_m=np.inf, window_shape=(64, 64), axis_pixel=(32, 32))
    centre = targets.spots([(40, 30)], camera=cam, wavelengths_m=[550e-9])
    box = targets.spots([(40 + i, 30 + j) for i in (-1, 0, 1) for j in (-1, 0, 1)], camera=cam,
                        wavelengths_m=[550e-9])
    b1 = spot_bound(cam, 5.4e-6, (400, 400), centre)[0, 0]
    b9 = spot_bound(cam, 5.4e-6, (400, 400), box)[0, 0]
    assert 0.05 < b1 < b9 < 1.0
    rep = bound_report([[0.1, 0.2]], [[0.4, 0.5]])
    assert rep["fraction_of_bound"] == [[0.25, 0.4]]
    assert rep["weakest_energy"] == 0.1 and rep["weakest_fraction_of_bound"] == 0.25
