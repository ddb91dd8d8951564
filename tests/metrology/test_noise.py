"""Noise floor from the data (metrology.diagnosis.noise) against known white noise."""

import numpy as np

from metrology.diagnosis.noise import estimate_noise


def _flat_field(seed=0, sigma=1e-9):
    rng = np.random.default_rng(seed)
    values = rng.normal(0.0, sigma, (120, 120))
    groups = np.zeros(values.shape, int)
    for k, (r, c) in enumerate([(0, 0), (0, 60), (60, 0), (60, 60)]):
        groups[r + 5:r + 55, c + 5:c + 55] = k + 1
        values[r + 5:r + 55, c + 5:c + 55] += k * 50e-9  # each flat region on its own level
    return values, groups


def test_white_noise_gives_its_sigma_and_no_correlation():
    values, groups = _flat_field()
    est = estimate_noise(values, groups)
    assert abs(est.sigma / 1e-9 - 1) < 0.05
    assert est.corr_area_px < 1.5


def test_streaks_of_structure_left_in_the_interiors_do_not_inflate_the_floor():
    # 5 % of the flat pixels sit on lines 8 nm off (edge slivers of a misplaced mask): the
    # robust rule must see through them, in the rms and in the correlation area alike.
    values, groups = _flat_field(1)
    values[::20, :] += 8e-9
    est = estimate_noise(values, groups)
    assert abs(est.sigma / 1e-9 - 1) < 0.1
    assert est.corr_area_px < 2.0
