"""Proximity printing (masks.proximity) against analytic Fresnel diffraction, the contact limit,
Parseval, the per-angle loop and the Gaussian stand-in's stated error.

The Fresnel references are written here from scipy.special.fresnel (paraxial slit diffraction),
not taken from the model; the angular spectrum agrees with them where the paraxial phase error
k x^4 / (8 g^3) is small (|x| < 3.2 um at 30 um, 0.01 rad).
"""

import math

import numpy as np
import pytest
from scipy.special import erfinv, fresnel

from doedesign.errors import DoeError
from masks import litho
from masks.proximity import (GAUSSIAN_ERROR, ProximityOptics, aerial_image, aerial_image_naive, print_coverage, reach_m,
                             source_angles, threshold_for_dose)

GAP = 30e-6
PITCH = 5.4e-6


def _slit_profile(step, wl, optics, n=65536):
    """Image across a 1.6 mm slit (periodic along the rows), and x from its left edge (m)."""
    cov = np.zeros((4, n), np.float32)
    a, b = n // 4, 3 * n // 4
    cov[:, a:b] = 1
    image = aerial_image(cov, step, optics, periodic=True)[1]
    x = (np.arange(n) + 0.5 - a) * step
    return x, image, (b - a) * step


def test_coherent_edge_is_fresnel_quarter_and_ringing_137():
    wl, step = 365e-9, 0.05e-6
    x, image, width = _slit_profile(step, wl, ProximityOptics(GAP, (wl,), (1.0,), 0.0, 0.0))
    s = math.sqrt(2 / (wl * GAP))
    s1, c1 = fresnel(x * s)
    s2, c2 = fresnel((width - x) * s)
    ref = 0.5 * ((c1 + c2) ** 2 + (s1 + s2) ** 2)
    near = np.abs(x) < 3.2e-6
    assert np.abs(image[near] - ref[near]).max() < 3e-3
    assert np.interp(0.0, x[near], image[near]) == pytest.approx(0.25, abs=2e-3)
    assert image[near].max() == pytest.approx(1.3704, abs=3e-3)
    # Where the maximum stands: w = 1.2172 (Fresnel integrals), x = w sqrt(lambda g / 2).
    assert x[near][np.argmax(image[near])] == pytest.approx(1.2172 / s, abs=0.05e-6)


def test_partially_coherent_edge_and_dose_linewidth():
    """Lines, 2 deg and 0.1 um blur: the edge keeps 0.27 of the open field, the ringing falls to 1.25,
    and the threshold moves the printed edge into the opening by 0.48 / 0.78 / 1.04 um (the
    issue's independent simulator's figures)."""
    x, image, _ = _slit_profile(0.05e-6, 365e-9, ProximityOptics(GAP), n=8192 * 4)
    near = np.abs(x) < 20e-6
    assert np.interp(0.0, x[near], image[near]) == pytest.approx(0.27, abs=0.01)
    assert image[near].max() == pytest.approx(1.25, abs=0.02)
    for t, moved in ((0.4, 0.48e-6), (0.5, 0.78e-6), (0.6, 1.04e-6)):
        k = np.argmax(image[near] >= t)
        assert x[near][k] == pytest.approx(moved, abs=0.05e-6)


def test_contact_limit_prints_the_mask_as_drawn():
    rng = np.random.default_rng(3)
    cov = litho.upsample_mask(rng.random((10, 12)) < 0.5, 8)
    optics = ProximityOptics(0.0, collimation_half_angle_rad=math.radians(2), resist_blur_m=0.0)
    image = aerial_image(cov, PITCH / 8, optics)
    np.testing.assert_allclose(image, cov, atol=1e-5)
    printed = print_coverage(cov, PITCH / 8, optics, 0.5)
    np.testing.assert_array_equal(printed, cov)


def test_energy_conservation_parseval():
    """All propagating (Nyquist below 1/lambda and the band limit): the image's sum is the mask's
    transmitted power, before and after the collimation and blur kernels (their DC gain is 1)."""
    rng = np.random.default_rng(4)
    cov = litho.upsample_mask(rng.random((24, 24)) < 0.4, 22)  # 0.245 um steps, 528 px
    for optics in (ProximityOptics(GAP, collimation_half_angle_rad=0.0, resist_blur_m=0.0), ProximityOptics(GAP)):
        image = aerial_image(cov, PITCH / 22, optics, periodic=True)
        assert float(image.sum(dtype=np.float64)) == pytest.approx(float(cov.sum()), rel=5e-5)
        assert image.max() > 1.05  # it did diffract


def test_fast_sum_matches_the_per_angle_loop():
    rng = np.random.default_rng(1)
    u = 8
    cov = litho.upsample_mask(rng.random((12, 12)) < 0.5, u)
    optics = ProximityOptics(GAP)
    angles = source_angles(optics.collimation_half_angle_rad, 3)
    assert len(angles) == 29
    fast = aerial_image(cov, PITCH / u, optics, angles=angles)
    naive = aerial_image_naive(cov, PITCH / u, optics, angles)
    assert np.sqrt(np.mean((fast - naive) ** 2)) < 0.006
    assert np.abs(fast - naive).max() < 0.05
    disc = aerial_image(cov, PITCH / u, optics)
    assert np.sqrt(np.mean((disc - naive) ** 2)) < 0.008
    # A real difference (the test can fail): the coherent image is far from both.
    coherent = aerial_image(cov, PITCH / u, ProximityOptics(GAP, collimation_half_angle_rad=0.0))
    assert np.sqrt(np.mean((coherent - naive) ** 2)) > 0.03


def test_tiles_equal_one_transform():
    rng = np.random.default_rng(2)
    cov = litho.upsample_mask(rng.random((40, 40)) < 0.5, 4)
    optics = ProximityOptics(GAP)
    whole = aerial_image(cov, PITCH / 4, optics)
    tiled = aerial_image(cov, PITCH / 4, optics, tile_px=128)
    assert np.abs(whole - tiled).max() < 0.012


def test_gaussian_stand_in_error_as_stated():
    rng = np.random.default_rng(1)
    u, n = 11, 40
    cov = litho.upsample_mask(rng.random((n, n)) < 0.5, u)
    step = PITCH / u
    optics = ProximityOptics(GAP)
    sigma = math.sqrt(365e-9 * GAP) / 2
    proximity = print_coverage(cov, step, optics, 0.274)
    gauss = litho.expose(cov, sigma / step, 0.5, u)
    per_pixel = (proximity - gauss).reshape(n, u, n, u).mean(axis=(1, 3))
    assert np.sqrt(np.mean((proximity - gauss) ** 2)) == pytest.approx(GAUSSIAN_ERROR["coverage_rms"], rel=0.2)
    assert np.sqrt(np.mean(per_pixel ** 2)) == pytest.approx(GAUSSIAN_ERROR["pixel_area_rms"], rel=0.2)
    # One threshold 0.3: the Gaussian's edge stands sigma sqrt(2) erfinv(0.4) outside the drawn
    # one, this model's 0.12 um inside (long edge, 0.05 um grid).
    x, image, _ = _slit_profile(0.05e-6, 365e-9, optics, n=8192 * 4)
    near = np.abs(x) < 20e-6
    prox_edge = x[near][np.argmax(image[near] >= 0.3)]
    gauss_edge = sigma * math.sqrt(2) * erfinv(2 * 0.3 - 1)
    assert prox_edge - gauss_edge == pytest.approx(GAUSSIAN_ERROR["edge_offset_m"], abs=0.1e-6)


def test_undercut_moves_a_long_edge_outward():
    cov = np.zeros((64, 256), np.float32)
    cov[:, 128:] = 1
    optics = ProximityOptics(GAP)
    step = 0.25e-6
    base = print_coverage(cov, step, optics, 0.3)[32].sum()
    cut = print_coverage(cov, step, optics, 0.3, cr_undercut_m=0.1e-6)[32].sum()
    # grow()'s fractional rule on the partly covered edge pixels: 0.066 um of 0.1 um here.
    assert (cut - base) * step == pytest.approx(0.1e-6, abs=0.04e-6)


def test_dose_and_bad_input():
    assert threshold_for_dose(9.0, 2.7) == pytest.approx(0.3)
    with pytest.raises(DoeError, match="does not clear"):
        threshold_for_dose(2.0, 4.0)
    with pytest.raises(DoeError, match="gap_m"):
        ProximityOptics(-1e-6)
    with pytest.raises(DoeError, match="wavelengths"):
        ProximityOptics(GAP, (365e-9,), (0.5, 0.5))
    with pytest.raises(DoeError, match="threshold"):
        print_coverage(np.ones((4, 4)), 0.25e-6, ProximityOptics(GAP), 1.5)


def test_process_model_prints_through_the_gap():
    """simulate_surface with a gap: a lone 5.4 um pixel of mask 3 prints smaller (relative to its
    drawn area) than a 6 x 6 pixel block, the long edges near their place at the in-place dose;
    gap 0 is the ideal surface bit for bit."""
    from masks.process import ProcessParams, simulate_surface

    levels = np.zeros((24, 24), int)
    levels[4, 4] = 8
    levels[10:16, 10:16] = 8
    ideal = simulate_surface(levels, PITCH, ProcessParams.ideal(), step_m=0.5e-6)
    params = ProcessParams.ideal().copy(proximity_gap=GAP, resist_threshold=0.274)
    printed = simulate_surface(levels, PITCH, params, step_m=0.5e-6)
    u = printed.upsample
    cov = printed.masks_printed[3]
    lone = cov[3 * u:6 * u, 3 * u:6 * u].sum() / u ** 2
    block = cov[9 * u:17 * u, 9 * u:17 * u].sum() / (36 * u ** 2)
    assert lone < 0.95 and block == pytest.approx(1.0, abs=0.06) and lone < block - 0.05
    same = simulate_surface(levels, PITCH, ProcessParams.ideal().copy(proximity_gap=0.0), step_m=0.5e-6)
    np.testing.assert_array_equal(same.height_m, ideal.height_m)
    with pytest.raises(DoeError, match="exclusive"):
        ProcessParams.ideal().copy(proximity_gap=GAP, proximity_blur=1e-6)


def test_tolerance_spec_varies_gap_dose_and_collimation():
    from masks.process import ProcessParams
    from masks.tolerance.spec import build_spec

    depths = np.array([75e-9, 150e-9, 300e-9, 600e-9])
    spec = build_spec({"proximity_gap": {"mean_um": 30, "sigma_um": 3},
                       "resist_threshold": {"dist": "uniform", "low": -0.02, "high": 0.02},
                       "collimation_half_angle": {"dist": "uniform", "low_deg": 1.5, "high_deg": 2.5}}, depths, "t")
    values, _ = spec.draw(7, 0)
    assert spec.params[1].ppf(0.0) == pytest.approx(-0.02)  # a dose offset may lower the threshold
    base = ProcessParams.ideal(depths_m=depths).copy(resist_threshold=0.274)
    params = spec.params_for(values, base)
    assert params.proximity_gap == pytest.approx(values["proximity_gap_um"])
    assert 20e-6 < params.proximity_gap < 40e-6
    assert abs(params.resist_threshold - 0.274) <= 0.02 + 1e-12
    assert math.radians(3.5) <= params.collimation_half_angle <= math.radians(4.5)  # base 2 deg + 1.5..2.5
    with pytest.raises(DoeError, match="plausible"):
        build_spec({"proximity_gap": {"mean_um": 500}}, depths, "t")


def test_print_check_reports_what_the_gap_prints():
    """Fine random structure (about one edge per pixel) loses more field overlap through 30 um than
    through 10 um; the contact print is perfect; isolated pixels are found and lost at a low dose."""
    from masks.print_check import print_check
    from masks.process import ProcessParams

    rng = np.random.default_rng(5)
    levels = rng.integers(0, 16, (32, 32))
    contact = print_check(levels, PITCH, ProcessParams.ideal(), step_m=0.6e-6)
    assert contact["field_overlap"] == pytest.approx(1.0, abs=1e-9)
    assert all(m["area_ratio"] == pytest.approx(1.0) for m in contact["masks"])
    near = print_check(levels, PITCH, ProcessParams.ideal().copy(proximity_gap=10e-6, resist_threshold=0.3), 0.6e-6)
    far = print_check(levels, PITCH, ProcessParams.ideal().copy(proximity_gap=30e-6, resist_threshold=0.3), 0.6e-6)
    assert far["field_overlap"] < near["field_overlap"] < 1.0
    assert far["masks"][0]["isolated_pixels"] > 0
    low = print_check(levels, PITCH, ProcessParams.ideal().copy(proximity_gap=30e-6, resist_threshold=0.6), 0.6e-6)
    assert all(m["edge_placement_um"] < -0.5 for m in low["masks"])  # a low dose shrinks every opening
    assert low["masks"][0]["isolated_lost"] >= far["masks"][0]["isolated_lost"]


def test_sampling_rule_holds_the_collimation_and_37_degrees():
    """The fine step ``g tan(theta) / 2`` (0.25 um at contact); the process model's image grid at
    most 435.8 nm / 1.2 = 0.363 um (light up to sine 0.6 of the g line), finer below 20.8 um."""
    from masks.proximity import image_step_m, recommended_step_m

    half = math.tan(math.radians(2)) / 2
    assert recommended_step_m(ProximityOptics(30e-6)) == pytest.approx(30e-6 * half)
    assert recommended_step_m(ProximityOptics(0.0)) == 0.25e-6
    assert image_step_m(ProximityOptics(10e-6)) == pytest.approx(10e-6 * half)
    for gap in (30e-6, 40e-6, 60e-6):
        assert image_step_m(ProximityOptics(gap)) == pytest.approx(435.8e-9 / 1.2)


def test_cubic_spline_interpolation_has_no_chord_error():
    """The image's interpolation onto the fine grid: on samples of x^2 a bilinear interpolant sits
    h^2 f'' / 8 = 0.25 above the curve halfway between samples (its chords), the cubic spline on it."""
    x = np.arange(40.0)
    samples = np.repeat((x ** 2)[:, None], 6, axis=1)
    mid = x[10:30] + 0.5
    cols = np.arange(6.0)
    linear = litho.interpolate_separable(samples, mid, cols, order=1)[:, 0]
    cubic = litho.interpolate_separable(samples, mid, cols, order=3)[:, 0]
    np.testing.assert_allclose(linear - mid ** 2, 0.25, atol=1e-3)
    np.testing.assert_allclose(cubic, mid ** 2, atol=2e-3)
    with pytest.raises(ValueError, match="order"):
        litho.interpolate_separable(samples, mid, cols, order=2)


def test_padding_by_half_the_reach_less_the_chrome_rim_is_one_wide_window():
    """One window is padded by (reach - rim) / 2: the same image as a periodic window with the full
    reach of chrome on every side, with and without a chrome rim around the openings."""
    rng = np.random.default_rng(6)
    step = PITCH / 8
    optics = ProximityOptics(40e-6)
    reach = int(math.ceil(reach_m(optics, step) / step)) + 1
    for rim in (0, 3, 40):
        mask = np.zeros((20 + 2 * rim, 22 + 2 * rim), bool)
        mask[rim:rim + 20, rim:rim + 22] = rng.random((20, 22)) < 0.5
        cov = litho.upsample_mask(mask, 8)
        wide = np.pad(cov, 2 * reach)
        ref = aerial_image(wide, step, optics, periodic=True)[2 * reach:-2 * reach, 2 * reach:-2 * reach]
        np.testing.assert_allclose(aerial_image(cov, step, optics), ref, atol=2e-3)
