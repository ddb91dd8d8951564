"""Duty cycle of a binary design with its fitted edge shift: against the exact area of a square
hole grown by the bias (the process model's square structuring element)."""

import numpy as np
import pytest

from metrology.matching.duty import duty_cycle
from metrology.matching.register import Registration

PITCH = 0.25e-6


@pytest.mark.parametrize("bias_px", [0.0, 0.3, -0.4])
def test_square_hole_grown_by_the_bias(bias_px):
    cell, side = 40, 16
    levels = np.zeros((cell, cell), np.int16)
    levels[12:12 + side, 12:12 + side] = 1  # the hole (etched, the opening)
    tiled = np.tile(levels, (3, 3))
    reg = Registration(matrix=np.eye(2), offset=np.zeros(2), pitch_m=PITCH, design_shape=tiled.shape,
                       measurement_shape=tiled.shape)
    out = duty_cycle(tiled, tiled, np.array([bias_px * PITCH]), np.array([0.01 * PITCH]), PITCH, reg)
    exact = 1 - (side + 2 * bias_px) ** 2 / cell ** 2
    # First order in the bias: the corners' 4 b^2 per hole are left out.
    assert out["unetched_fraction"] == pytest.approx(exact, abs=4 * bias_px ** 2 / cell ** 2 + 1e-12)
    assert out["design_unetched_fraction"] == pytest.approx(1 - side ** 2 / cell ** 2)
    assert out["unetched_fraction_err"] == pytest.approx(0.01 * 4 * side / cell ** 2)
    assert out["etched_fraction"] == pytest.approx(1 - out["unetched_fraction"])
