"""Quantization and binary mask decomposition against exact arithmetic."""

import numpy as np
import pytest

from doedesign.errors import DoeError
from masks.decompose import (DEFAULT_DEPTHS_M, binary_depths_m, check_etch_order, levels_to_masks,
                             masks_to_height, masks_to_levels)
from masks.quantize import level_step_m, quantize


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
    h = -np.array([15.6, -0.6, 17.2, -0.3]) * step
    q = quantize(h, step)
    assert q.levels.tolist() == [0, 15, 1, 0]
    assert q.wrapped_pixels == 3
    np.testing.assert_allclose(q.error_m / step, [0.4, -0.4, -0.2, 0.3], atol=1e-12)


def test_quantize_uniform_error_is_step_over_sqrt12():
    rng = np.random.default_rng(0)
    step = level_step_m("fused_silica", 550e-9)
    h = -rng.uniform(0, 16 * step, 200_000)
    q = quantize(h, step)
    assert q.rms_error_m == pytest.approx(step / np.sqrt(12), rel=0.01)


def test_quantize_rejects_nan():
    with pytest.raises(DoeError, match="NaN"):
        quantize(np.array([0.0, np.nan]), 75e-9)


@pytest.mark.parametrize("kind", ["random", "ramp", "rings"])
def test_decompose_compose_exact(kind):
    rng = np.random.default_rng(1)
    yy, xx = np.mgrid[:90, :110]
    levels = {"random": rng.integers(0, 16, (90, 110)),
              "ramp": xx % 16,
              "rings": (((xx - 55) ** 2 + (yy - 45) ** 2) // 40) % 16}[kind].astype(np.int16)
    m = levels_to_masks(levels)
    assert m.shape == (4, 90, 110) and m.dtype == bool
    assert np.array_equal(masks_to_levels(m), levels)
    # nominal depths 75 * 2**j reproduce level * 75 nm exactly
    np.testing.assert_allclose(masks_to_height(m, DEFAULT_DEPTHS_M), -levels * 75e-9, atol=1e-15)


def test_mask_bits_and_wrong_depths():
    m = levels_to_masks(np.array([[5, 10]], np.int16))
    assert m[:, 0, 0].tolist() == [True, False, True, False]
    assert m[:, 0, 1].tolist() == [False, True, False, True]
    h = masks_to_height(m, (70e-9, 150e-9, 310e-9, 600e-9))
    np.testing.assert_allclose(h[0], [-380e-9, -750e-9])
    assert binary_depths_m(74.74e-9)[3] == pytest.approx(8 * 74.74e-9)


@pytest.mark.parametrize("levels, msg", [(np.array([[1.0, 2.0]]), "integer"),
                                          (np.array([[0, 16]]), "0..15"),
                                          (np.array([[-1, 3]]), "0..15")])
def test_levels_to_masks_validates(levels, msg):
    with pytest.raises(DoeError, match=msg):
        levels_to_masks(levels)


def test_etch_order_checked():
    assert check_etch_order([3, 2, 1, 0]) == (3, 2, 1, 0)
    with pytest.raises(DoeError, match="exactly once"):
        check_etch_order([0, 0, 1, 2])
