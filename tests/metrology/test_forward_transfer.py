"""The package's own synthetic measurement (``process_on_measurement``) through other lateral
transfers than a whole-pixel box (issue 25, ``doe demo --instrument``): a pixel's fill factor
and the objective's NA, each against an analytic result."""

import numpy as np

from masks.process import ProcessParams
from metrology.matching import compare, register

PITCH = 5.4e-6


def test_a_fill_factor_integrates_the_centred_part_of_each_pixel():
    levels = np.zeros((12, 12), int)
    levels[:, 6:] = 8  # mask 3 open right of design column 5.5
    params = ProcessParams.ideal()
    scale = 2.7e-6 / PITCH
    reg = register.Registration.from_parameters(scale, 0.0, (False, False, False), (5.5, 5.55), PITCH,
                                                levels.shape, (20, 21))
    h = compare.process_on_measurement(levels, PITCH, params, reg, step_m=PITCH / 64, pixel_subsamples=16,
                                       fill_factor=0.25)
    _, c = reg.to_design(np.zeros(21), np.arange(21.0))
    # A quarter of the area: a centred square of half the pixel's side.
    side = 0.5 * scale
    frac = np.clip((c + side / 2 - 5.5) / side, 0, 1)
    np.testing.assert_allclose(h[10], -params.etch_depth[3] * frac, atol=0.02 * params.etch_depth[3])
    assert ((frac > 0.2) & (frac < 0.8)).any()


def test_the_objective_passes_a_grating_by_the_circular_pupils_incoherent_transfer():
    # Stripes of the 600 nm mask one design pixel wide (period 10.8 um) through an NA 0.05
    # objective at 0.57 um: cut-off 2 NA / lambda = 0.175 /um, the fundamental at s = 0.53 of
    # it, the third harmonic beyond. Point-sampled, the profile is its mean plus the square
    # wave's fundamental (amplitude 2 H / pi) times the pupil's MTF (Goodman, Introduction to
    # Fourier Optics, 6.3): 2/pi (acos s - s sqrt(1 - s^2)).
    levels = np.zeros((48, 48), int)
    levels[:, ::2] = 8
    params = ProcessParams.ideal()
    depth = params.etch_depth[3]
    reg = register.Registration.from_parameters(0.25, 0.0, (False, False, False), (23.5, 23.5), PITCH,
                                                levels.shape, (4, 96))
    na, lam = 0.05, 0.57e-6
    h = compare.process_on_measurement(levels, PITCH, params, reg, step_m=PITCH / 32, na=na, wavelength_m=lam)
    _, c = reg.to_design(np.zeros(96), np.arange(96.0))
    basis = np.column_stack([np.ones(96), np.cos(np.pi * c), np.sin(np.pi * c)])
    coef, *_ = np.linalg.lstsq(basis, h[2], rcond=None)
    s = (1 / (2 * PITCH)) * lam / (2 * na)
    mtf = 2 / np.pi * (np.arccos(s) - s * np.sqrt(1 - s * s))
    assert abs(np.hypot(coef[1], coef[2]) / (2 * depth / np.pi * mtf) - 1) < 0.01
    # Nothing beyond the fundamental passes: the sampled profile is that sinusoid.
    assert np.abs(h[2] - basis @ coef).max() < 0.01 * depth
