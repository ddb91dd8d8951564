"""Checks of the independent proximity-print generator against analytic results."""

import numpy as np
import pytest
from scipy.special import fresnel

import filegen
import proximitygen as pg


def test_straight_edge_matches_fresnel_half_plane():
    # Coherent, one wavelength, normal incidence: a 100 um wide slit, long in y (periodic rows).
    lam, g, dx = 365e-9, 30e-6, 0.05e-6
    n, a, b = 16384, 0.0, 100e-6
    x = (np.arange(n) - n // 4) * dx
    t = np.tile(((x >= a) & (x < b)).astype(float), (2, 1))
    xs = x + dx / 2  # the sampled edge sits between samples
    inten = np.abs(pg.propagate(t, dx, g, lam)[0]) ** 2
    k = np.sqrt(2 / (lam * g))
    ca, sa = fresnel((a - xs) * k)
    cb, sb = fresnel((b - xs) * k)
    slit = 0.5 * ((cb - ca) ** 2 + (sb - sa) ** 2)
    near = np.abs(xs) < 5e-6  # paraxial (Fresnel) phase error < 0.1 rad here
    assert np.interp(0.0, xs, inten) == pytest.approx(0.25, abs=0.01)
    assert inten[near].max() == pytest.approx(1.37, abs=0.02)
    # The half-plane form: 0.25 at the edge, maximum ~1.37. (The paraxial slit formula's far-edge
    # fringes at 100 um have spatial frequencies beyond 1/lambda, evanescent in the exact
    # angular spectrum: the numeric image is compared with the half plane.)
    c, s = fresnel(xs[near] * k)
    half = 0.5 * ((c + 0.5) ** 2 + (s + 0.5) ** 2)
    assert np.sqrt(np.mean((inten[near] - half) ** 2)) < 0.01
    assert np.abs(slit[near] - half).max() < 0.05
    assert np.interp(0.0, xs[near], half) == pytest.approx(0.25, abs=1e-3)
    assert half.max() == pytest.approx(1.37, abs=0.01)


def test_zero_gap_prints_the_mask_as_drawn():
    rng = np.random.default_rng(3)
    levels = filegen.random_levels((16, 16), rng)
    fine = 20
    drawn = filegen.wafer_surface(levels, {}, fine)
    printed = pg.proximity_surface(levels, 0.0, 0.5, fine=fine)
    diff = np.abs(printed - drawn)
    assert diff.mean() < 0.01 * np.abs(drawn).mean()
    assert np.mean(diff > 10e-9) < 0.01  # only at the corners the resist blur rounds


def test_energy_mean_intensity_is_open_fraction():
    rng = np.random.default_rng(4)
    mask = filegen.masks_of(filegen.random_levels((16, 16), rng))[1]
    inten, pad = pg.aerial_image(mask, 30e-6)
    open_frac = mask.sum() * pg.AERIAL_PER_PX ** 2 / inten.size
    assert inten.mean() == pytest.approx(open_frac, rel=2e-3)


def _printed_widths(gap, threshold):
    fine = 40
    square = np.zeros((15, 15), bool)
    square[7, 7] = True
    line = np.zeros((41, 15), bool)
    line[:, 7] = True
    cell = filegen.PITCH_M / fine
    sq = pg.printed_coverage(square, gap, threshold, fine=fine)
    ln = pg.printed_coverage(line, gap, threshold, fine=fine)
    mid = 7 * fine + fine // 2
    mid_line = 20 * fine + fine // 2
    return sq[mid].sum() * cell, ln[mid_line].sum() * cell, np.sqrt(sq.sum()) * cell


def test_printed_size_depends_on_feature_size():
    """At 30 um and T = 0.5 the printed size of a 5.4 um feature depends on its shape. Measured:
    across its centre an isolated 5.4 um square prints 4.62 um wide and a 5.4 um line 3.56 um
    (square sqrt(area) 3.77 um): the square prints LARGER along its centre line, not smaller.
    This is Fresnel physics, not a bug: at Fresnel number (a/2)**2/(lambda g) ~ 0.6 the slit's
    centre is a bright fringe (|U|**2 = 2 (C(1.1)**2 + S(1.1)**2) ~ 1.7 at 405 nm), and the
    square's field is about the product of two slits', so its centre is brighter still (~3)."""
    sq_w, line_w, sq_side = _printed_widths(30e-6, 0.5)
    assert abs(sq_w - line_w) > 0.5e-6
    assert sq_w > line_w
    sq0, line0, _ = _printed_widths(0.0, 0.5)
    assert sq0 == pytest.approx(5.4e-6, abs=0.1e-6) and line0 == pytest.approx(5.4e-6, abs=0.1e-6)
