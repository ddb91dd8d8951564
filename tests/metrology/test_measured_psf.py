"""PSF from measured heights against the scalar theory of a too-deep blazed grating."""

import numpy as np
import pytest

from doedesign.camera import Camera
from doedesign.design import Design
from doedesign.levels import level_step_m
from masks.process import ProcessParams
from metrology.matching.measured_psf import compare_psf, target_from_psf

PITCH = 5.4e-6
N = 16


def _grating(n_px=64):
    levels = np.tile(N - 1 - np.arange(n_px) % N, (n_px, 1)).astype(np.int16)  # phase rises with column
    cam = Camera(aperture_diameter_m=None, doe_side="full", window_shape=(32, 128), axis_pixel=(16, 32),
                 focus_distance_m=np.inf)
    step = level_step_m("fused_silica", 550e-9)
    return Design(height_m=-levels * step, pitch_m=PITCH, levels=levels,
                  metadata={"name": "blazed", "camera": cam.to_dict()}), step


def _first_order_efficiency(a, n=N):
    """eta_1 of an n-level staircase whose 2 pi step is scaled by ``a`` (optics reference)."""
    x = a - 1
    return np.sinc(1 / n) ** 2 * (1.0 if abs(x) < 1e-12 else (np.sin(np.pi * x) / (n * np.sin(np.pi * x / n))) ** 2)


def test_target_holds_the_requested_share():
    psf = np.array([[[0.5, 0.3], [0.15, 0.05]]])
    np.testing.assert_array_equal(target_from_psf(psf, 0.8)[0], [[True, True], [False, False]])
    np.testing.assert_array_equal(target_from_psf(psf, 0.81)[0], [[True, True], [True, False]])


@pytest.mark.parametrize("scale", [1.0, 1.1, 0.85])
def test_over_and_under_etch_lose_the_light_scalar_theory_predicts(scale):
    design, step = _grating()
    params = ProcessParams.ideal().copy(etch_depth=step * np.array([1, 2, 4, 8]) * scale)
    cmp = compare_psf(design, params, wavelengths_m=[550e-9], oversample=1)
    expected = _first_order_efficiency(scale) / _first_order_efficiency(1.0)
    assert cmp.measured_on_target[0] / cmp.design_on_target[0] == pytest.approx(expected, abs=0.01)
    # The first order sits about 59 px right of the axis (x = lambda z / period).
    col = np.argmax(cmp.design_psf[0].sum(axis=0))
    assert col - 32 == pytest.approx(550e-9 * 50e-3 / (N * PITCH) / PITCH, abs=1.5)
