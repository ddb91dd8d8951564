"""Binary mask decomposition against exact arithmetic."""

import numpy as np
import pytest

from doedesign.errors import DoeError
from masks.decompose import (DEFAULT_DEPTHS_M, binary_depths_m, check_etch_order, levels_to_masks, mask_bit,
                             masks_to_height, masks_to_levels)


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


@pytest.mark.parametrize("dtype", [np.uint8, np.int16, np.uint16, np.int64])
def test_one_mask_is_that_bit_in_any_integer_type(dtype):
    """The process render's one-mask form: mask j is set where level // 2**j is odd."""
    levels = np.arange(16, dtype=dtype).reshape(4, 4)
    for j in range(4):
        one = mask_bit(levels, j)
        assert one.dtype == bool and one.shape == levels.shape
        assert np.array_equal(one, (np.arange(16).reshape(4, 4) // 2 ** j) % 2 == 1)
        assert np.array_equal(one, levels_to_masks(levels)[j])


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
