"""Level counts 2..32 as a property of the design: blazed gratings through the PSF engine.

First-order efficiency of an N-level blazed staircase at its design wavelength is
sinc^2(1/N) (Swanson, MIT Lincoln Lab TR 854, 1989): 40.5, 81.1, 95.0, 98.7, 99.7 % for
N = 2, 4, 8, 16, 32. The engine's PSF of the design's printed heights is measured in a box
around each order, normalised by the same box around the spot of a flat element (the same
aperture's spot, so its tails outside the box cancel).
"""

import numpy as np
import pytest

from doedesign.camera import Camera
from doedesign.design import Design
from doedesign.engine.psf import PSFEngine
from doedesign.levels import printed_height_m

PITCH = 5.4e-6
N_PX, PERIOD_PX, WL = 512, 32, 550e-9
CAM = Camera(aperture_diameter_m=None, focus_distance_m=np.inf, window_shape=(96, 96), axis_pixel=(48, 48),
             doe_side="full")


def _box_energy(psf, centre_col, half):
    c = int(round(centre_col))
    return float(psf[:, c - half:c + half + 1].sum())


@pytest.fixture(scope="module")
def engine():
    return PSFEngine(CAM, PITCH, (N_PX, N_PX), wavelengths_m=[WL])


@pytest.mark.parametrize("n_levels, expected", [(2, 0.405), (4, 0.811), (8, 0.950), (16, 0.987), (32, 0.997)])
def test_blazed_grating_first_order_efficiency_is_sinc2(engine, n_levels, expected):
    cols = np.arange(N_PX)
    # Levels fall along the columns (deepest first): the phase rises toward higher column.
    level = (n_levels - 1 - (cols % PERIOD_PX) * n_levels // PERIOD_PX).astype(np.int16)
    levels = np.tile(level, (N_PX, 1))
    probe = Design(np.zeros((N_PX, N_PX)), PITCH, design_wavelength_m=WL, metadata={"n_levels": n_levels})
    design = Design(-levels * probe.level_step_m(), PITCH, design_wavelength_m=WL, levels=levels,
                    metadata={"n_levels": n_levels})
    design.check_levels()
    height = printed_height_m(design)
    assert np.unique(height).size == n_levels
    order_px = WL * CAM.sensor_distance_m / (PERIOD_PX * PITCH) / CAM.pixel_pitch_m
    half = int(order_px // 2) - 1
    flat = engine.psf(np.zeros((N_PX, N_PX)), views=("coded",)).psf[0, 0, 0]
    psf = engine.psf(height, views=("coded",)).psf[0, 0, 0]
    axis = CAM.axis_pixel[1]
    reference = _box_energy(flat, axis, half)
    first = _box_energy(psf, axis + order_px, half) / reference
    minus = _box_energy(psf, axis - order_px, half) / reference
    assert first == pytest.approx(np.sinc(1 / n_levels) ** 2, abs=0.003)
    assert round(first, 3) == pytest.approx(expected, abs=0.002)
    # Order -1 of a staircase has sinc^2(1/N) only for N = 2 (the binary grating is symmetric).
    assert minus == pytest.approx(expected if n_levels == 2 else 0.0, abs=0.003)
