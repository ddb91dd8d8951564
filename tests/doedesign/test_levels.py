"""The level rule (doedesign.levels) against exact arithmetic and published numbers."""

import numpy as np
import pytest

from doedesign.errors import DoeError
from doedesign.design import Design
from doedesign.levels import design_levels, level_step_m, quantize, quantize_design, wrap_height_m


def test_level_step_fused_silica_published():
    # optics-and-fabrication.md: 2 pi at 550 nm is 1195.9 nm, one of 16 levels 74.74 nm
    assert level_step_m("fused_silica", 550e-9) == pytest.approx(74.74e-9, abs=0.01e-9)
    assert level_step_m("fused_silica", 550e-9, 8) == pytest.approx(1195.9e-9 / 8, abs=0.1e-9)


def test_quantize_rounds_not_floors():
    step = 100e-9
    h = -np.array([0.0, 0.49, 0.51, 1.49, 1.51, 14.6]) * step
    q = quantize(h, step)
    assert q.levels.tolist() == [0, 0, 1, 1, 2, 15]
    assert q.max_error_m <= step / 2 + 1e-18
    assert q.wrapped_pixels == 0
    np.testing.assert_allclose(q.height_m, -q.levels * step)
    np.testing.assert_allclose(q.error_m, h - q.height_m, atol=1e-18)


def test_quantize_wraps_by_one_2pi_height():
    step = 100e-9
    # 15.6 steps deep rounds to 16 = level 0 one 2 pi deeper; +0.6 step above the top -> 15
    h = -np.array([15.6, -0.6, 17.2, -0.3, 2.5]) * step
    q = quantize(h, step)
    assert q.levels.tolist() == [0, 15, 1, 0, 3]
    assert q.wrapped_pixels == 3
    np.testing.assert_allclose(q.error_m / step, [0.4, -0.4, -0.2, 0.3, 0.5], atol=1e-12)
    # Same phase at the design wavelength: the wrapped heights differ by whole 2 pi heights.
    np.testing.assert_allclose(np.mod((h - q.height_m) / (16 * step) + 0.5, 1) - 0.5, q.error_m / (16 * step),
                               atol=1e-12)


def test_quantize_uniform_error_is_step_over_sqrt12():
    rng = np.random.default_rng(0)
    step = level_step_m("fused_silica", 550e-9)
    h = -rng.uniform(0, 16 * step, 200_000)
    q = quantize(h, step)
    assert q.rms_error_m == pytest.approx(step / np.sqrt(12), rel=0.01)


def test_quantize_rejects_nan():
    with pytest.raises(DoeError, match="NaN"):
        quantize(np.array([0.0, np.nan]), 75e-9)


def test_wrap_height_keeps_phase_and_range():
    step = 100e-9
    h = np.array([0.0, 50e-9, -1599e-9, -1600e-9, -3210e-9, 2e-6])
    w = wrap_height_m(h, step)
    assert np.all(w <= 0) and np.all(w > -1600e-9)
    np.testing.assert_allclose(np.round((h - w) / 1600e-9), (h - w) / 1600e-9, atol=1e-9)
    np.testing.assert_allclose(w[[0, 3, 4]], [0.0, 0.0, -10e-9], atol=1e-15)


def test_design_levels_prefers_stored_levels_and_checks_them():
    step = level_step_m("fused_silica", 550e-9)
    h = -np.array([[0.2, 3.9]]) * step
    assert design_levels(Design(height_m=h, pitch_m=5.4e-6)).tolist() == [[0, 4]]
    levels, q = quantize_design(Design(height_m=h, pitch_m=5.4e-6, levels=np.array([[1, 2]])))
    assert levels.tolist() == [[1, 2]] and q is None
    with pytest.raises(DoeError, match="0..15"):
        design_levels(Design(height_m=h, pitch_m=5.4e-6, levels=np.array([[1, 16]])), source="x.npz")
    assert Design(height_m=h, pitch_m=5.4e-6).level_step_m(8) == pytest.approx(2 * step)
