"""Registration recovers known rotation, scale, shift, flips and transposes."""

import numpy as np
import pytest

from doedesign.errors import DoeError
from masks.decompose import DEFAULT_DEPTHS_M
from masks.process import ProcessParams
from metrology.matching import compare, register

PITCH = 5.4e-6


def _design(seed=0, shape=(120, 130)):
    levels = np.random.default_rng(seed).integers(0, 16, shape)
    height = -(compare.binary_code_matrix() @ np.array(DEFAULT_DEPTHS_M))[levels]
    return levels, height


def _measure(levels, truth, noise_m=1e-9, seed=1):
    """Ideal process, 0.5 um instrument blur, 1 nm noise, sampled through ``truth``."""
    h = compare.process_on_measurement(levels, PITCH, ProcessParams.ideal(), truth, blur_m=0.5e-6, step_m=0.5e-6)
    return h + np.random.default_rng(seed).normal(0, noise_m, h.shape)


@pytest.mark.parametrize("orientation,rotation_deg,pixel_m", [
    ((False, False, False), 1.0, 1.1e-6),
    ((False, True, False), -0.7, 1.08e-6),
    ((True, False, True), 2.5, 1.13e-6),
])
def test_recovers_orientation_rotation_scale_and_shift(orientation, rotation_deg, pixel_m):
    levels, height = _design()
    shape = (260, 280)
    truth = register.Registration.from_parameters(pixel_m / PITCH, rotation_deg, orientation, (58.3, 61.7),
                                                  PITCH, levels.shape, shape)
    meas = _measure(levels, truth)
    # The file claims 1.0 um pixels (8-13 % off): registration finds the real size from the pitch.
    reg = register.register(meas, height, PITCH, pixel_size_m=1.0e-6, scale_tolerance=0.2)
    got, want = reg.to_dict(), truth.to_dict()
    assert (got["transpose"], got["flip_rows"], got["flip_cols"]) == orientation
    assert got["rotation_deg"] == pytest.approx(rotation_deg, abs=0.01)
    assert got["pixel_size_um"] == pytest.approx(pixel_m * 1e6, rel=3e-4)
    np.testing.assert_allclose(got["shift_um"], want["shift_um"], atol=0.1)
    # Every measurement pixel lands within 0.03 design pixels (0.16 um) of where it should.
    rr, cc = np.meshgrid(np.arange(0, shape[0], 17), np.arange(0, shape[1], 17), indexing="ij")
    err = np.hypot(*(np.subtract(reg.to_design(rr, cc), truth.to_design(rr, cc))))
    assert err.max() < 0.03


def test_resampled_measurement_matches_design_heights_inside_pixels():
    levels, height = _design(seed=4)
    truth = register.Registration.from_parameters(1.1e-6 / PITCH, 0.8, (False, False, True), (60.0, 64.0),
                                                  PITCH, levels.shape, (240, 240))
    meas = _measure(levels, truth, noise_m=0.0)
    reg = register.register(meas, height, PITCH, pixel_size_m=1.1e-6)
    on_design = register.resample_to_design(meas, reg)
    covered = np.isfinite(on_design)
    # The field spans ~264 um = ~49 pitches: about that many design rows are covered.
    assert 40 * 40 < covered.sum() < 52 * 52
    # Design pixel centres are 2.7 um from the edges, far beyond the 0.5 um blur.
    np.testing.assert_allclose(on_design[covered], height[covered], atol=1e-9)
    labels = register.design_on_measurement(levels, reg)
    assert labels.min() >= 0 and set(np.unique(labels)) <= set(range(16))


def test_unrelated_design_is_refused():
    levels, height = _design(seed=0)
    _, other = _design(seed=9)
    truth = register.Registration.from_parameters(1.1e-6 / PITCH, 0.0, (False, False, False), (60.0, 60.0),
                                                  PITCH, levels.shape, (200, 200))
    meas = _measure(levels, truth)
    with pytest.raises(DoeError, match="does not match the design"):
        register.register(meas, other, PITCH, pixel_size_m=1.1e-6)


def test_flat_field_is_refused():
    flat = np.random.default_rng(0).normal(0, 1e-9, (100, 100))
    with pytest.raises(DoeError):
        register.register(flat, _design()[1], PITCH, pixel_size_m=1.1e-6)
