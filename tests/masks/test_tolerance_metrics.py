"""Figures of merit of `doe tolerance` against analytic diffraction results.

Each case runs the whole sample path (process model -> PSF engine -> metric) on an element
whose far field is known in closed form; ratios of one metric between cases cancel the share
of an order's light that its target pixels catch, which is the same for every case.
"""

import math

import numpy as np
import pytest
from scipy import special

from doedesign.camera import Camera
from doedesign.design import Design
from doedesign.levels import level_step_m
from masks.tolerance.analysis import build_evaluator, nominal_depths
from masks.tolerance.spec import build_spec

PITCH = 5.4e-6
STEP = level_step_m("fused_silica", 550e-9, 16)


def _design(levels, camera, target):
    meta = {"camera": camera.to_dict(), "n_levels": 16, "target": {"wavelengths_nm": [550.0], "depths_m": ["inf"],
                                                                   **target}}
    levels = np.asarray(levels, np.int16)
    return Design(height_m=-levels * STEP, pitch_m=PITCH, levels=levels, metadata=meta)


def _metrics(design, depth_error_rel=None):
    """Metrics of the element made with every etch ``1 + depth_error_rel`` deep (None: ideal)."""
    table = {} if depth_error_rel is None else {"etch_depth": {"dist": "fixed", "value_rel": depth_error_rel}}
    spec = build_spec(table, nominal_depths(design), "t")
    ev, nominal, _ = build_evaluator(design, spec)
    if depth_error_rel is None:
        return nominal
    values = spec.nominal_values()
    return ev.metrics(ev.coded_psf(ev.height(values)))


def _grating(n_levels, n=256, period_px=16, window=(16, 96)):
    """``n_levels``-level blazed grating (16 px period, ``16 / n_levels`` px per step), order 1 to the right."""
    step_px = period_px // n_levels
    levels = (15 - (np.arange(n) % period_px) // step_px * (16 // n_levels)) % 16
    cam = Camera(aperture_diameter_m=None, focus_distance_m=math.inf, window_shape=window,
                 axis_pixel=(window[0] // 2, 16), doe_side="full")
    return _design(np.tile(levels, (n, 1)), cam, {"kind": "hyperspectral", "period_m": period_px * PITCH,
                                                  "orders": [1]})


def _sinc2(x):
    return np.sinc(x) ** 2


def test_first_order_efficiency_follows_sinc2_of_the_level_count():
    """N-level staircase: first-order efficiency sinc^2(1/N) (Swanson 1989)."""
    eff = {n: _metrics(_grating(n))["first_order_efficiency"] for n in (16, 8, 4, 2)}
    for n in (8, 4, 2):
        assert eff[n] / eff[16] == pytest.approx(_sinc2(1 / n) / _sinc2(1 / 16), rel=2e-3)


def test_zero_order_leak_follows_the_depth_error():
    """Every etch (1 + eps) deep: zero order |1/N sum_k exp(2 pi i k (1 + eps) / N)|^2
    = sin^2(pi eps) / (N^2 sin^2(pi (1 + eps) / N)); the ideal element leaks (almost) nothing."""
    design = _grating(16)

    def formula(eps):
        return math.sin(math.pi * eps) ** 2 / (256 * math.sin(math.pi * (1 + eps) / 16) ** 2)

    leak = {eps: _metrics(design, eps)["zero_order_leak"] for eps in (0.25, 0.5)}
    assert leak[0.5] / leak[0.25] == pytest.approx(formula(0.5) / formula(0.25), rel=5e-3)
    assert _metrics(design)["zero_order_leak"] < 0.02 * leak[0.25]


def test_spot_uniformity_of_a_binary_splitter_follows_the_phase_depth():
    """50 % binary grating of phase pi (1 + eps): order 0 holds sin^2(pi eps / 2), orders +-1
    (4 / pi^2) cos^2(pi eps / 2) each; uniformity over the three spots 1 - (max - min) / (max + min)."""
    n, period_px, offset_px = 256, 16, 60
    # Sensor distance putting the first orders exactly on pixel centres 60 px from the axis.
    distance = offset_px * PITCH / math.tan(math.asin(550e-9 / (period_px * PITCH)))
    cam = Camera(aperture_diameter_m=None, focus_distance_m=math.inf, sensor_distance_m=distance,
                 window_shape=(16, 160), axis_pixel=(8, 80), doe_side="full")
    levels = np.tile(np.where(np.arange(n) % period_px < period_px // 2, 8, 0), (n, 1))
    design = _design(levels, cam, {"kind": "spots", "positions_px": [[8, 80 - offset_px], [8, 80], [8, 80 + offset_px]]})
    for eps in (0.2, 0.4):
        e0 = math.sin(math.pi * eps / 2) ** 2
        e1 = 4 / math.pi ** 2 * math.cos(math.pi * eps / 2) ** 2
        expected = 1 - abs(e1 - e0) / (e1 + e0)
        assert _metrics(design, eps)["spot_uniformity"] == pytest.approx(expected, abs=3e-3)


def _pixel_sinc2(edges_px, width_px):
    """Integral of sinc^2(x / width) over each pixel [e_i, e_i+1], normalized to 1 over the line."""
    u = np.asarray(edges_px, float) / width_px

    def primitive(v):  # antiderivative of sinc^2(v) (numpy's normalized sinc)
        v = np.where(v == 0, 1e-300, v)
        return (special.sici(2 * np.pi * v)[0] / np.pi) - np.sin(np.pi * v) ** 2 / (np.pi ** 2 * v)

    return np.diff(primitive(u))


def test_streak_energy_of_a_flat_square_pupil_is_the_separable_sinc2_integral():
    """No DOE, square pupil of side D: I(x, y) ~ sinc^2(x D / lambda f) sinc^2(y D / lambda f); the
    streak's light is the sum over its pixels of products of 1-D pixel integrals (sine integral)."""
    n, window = 96, 96
    cam = Camera(aperture_diameter_m=None, focus_distance_m=math.inf, window_shape=(window, window),
                 axis_pixel=(window // 2, window // 2), doe_side="full")
    design = _design(np.zeros((n, n)), cam, {"kind": "hdr-streak", "arms": "+", "arm_width_px": 2,
                                             "arm_length_px": 30})
    from doedesign import targets

    mask = targets.hdr_streak(cam, arm_width_px=2, arm_length_px=30).mask[0, 0]
    width_px = 550e-9 * cam.sensor_distance_m / (n * PITCH) / cam.pixel_pitch_m
    edges = np.arange(window + 1) - window // 2 - 0.5
    p = _pixel_sinc2(edges, width_px)
    expected = float(np.sum(np.outer(p, p)[mask]))
    assert _metrics(design)["streak_energy"] == pytest.approx(expected, rel=2e-3)


def test_ring_radius_of_a_defocused_flat_element_is_two_thirds_of_the_blur_disk():
    """Focused at infinity, a point at distance z blurs into a disk of radius R = (D / 2) s / z on
    the sensor (geometric optics, many waves of defocus); its light-weighted mean radius is 2 R / 3."""
    n, window, z = 256, 200, 0.08
    cam = Camera(aperture_diameter_m=n * PITCH, focus_distance_m=math.inf, window_shape=(window, window),
                 axis_pixel=(window // 2, window // 2), doe_side="full")
    design = _design(np.zeros((n, n)), cam, {"kind": "depth", "depths_m": [z], "radii_px": [40.0]})
    radius_px = n * PITCH / 2 * cam.sensor_distance_m / z / cam.pixel_pitch_m
    assert radius_px > 50, "many waves of defocus (geometric regime), disk well inside the window"
    assert _metrics(design)[f"ring_radius_px[{z:g} m]"] == pytest.approx(2 * radius_px / 3, rel=0.02)
