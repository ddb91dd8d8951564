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


def _sloped_field(seed=2, sigma=1e-9, smooth=1):
    # Each flat region also slopes by its own amount (an etch depth varying across the field
    # scales with the level's depth): 2-5 nm across a region, as a 2.8 % per mm gradient on a
    # 1.1 um step over 100 um of field. ``smooth``: the noise averaged over smooth x smooth
    # pixels (correlation area smooth^2, rms sigma / smooth).
    values, groups = _flat_field(seed, sigma * smooth)
    if smooth > 1:
        from scipy.ndimage import uniform_filter

        rng = np.random.default_rng(seed + 100)
        values = uniform_filter(rng.normal(0.0, sigma * smooth, values.shape), smooth, mode="wrap")
    rows, cols = np.mgrid[:values.shape[0], :values.shape[1]]
    for k in range(1, 5):
        inside = groups == k
        values[inside] += k * 50e-9 + (k + 1) * 1e-9 * (0.8 * rows[inside] - 0.6 * cols[inside]) / 50
    return values, groups


def test_a_slope_across_each_flat_is_not_noise_about_its_plane():
    values, groups = _sloped_field()
    est = estimate_noise(values, groups, trend="plane")
    assert abs(est.sigma / 1e-9 - 1) < 0.05
    assert est.corr_area_px < 1.5
    # About the mean alone, the slopes pass for correlated noise (what the camera floor did).
    old = estimate_noise(values, groups)
    assert old.sigma > 1.3e-9 and old.corr_area_px > 5


def test_correlated_noise_about_planes_keeps_its_rms_and_correlation_area():
    # Noise averaged over 2 x 2 pixels: rms sigma, correlation area 4 (the sum of its
    # autocorrelation over lags); the plane's three parameters per region are undone.
    values, groups = _sloped_field(3, smooth=2)
    est = estimate_noise(values, groups, trend="plane")
    assert abs(est.sigma / 1e-9 - 1) < 0.07
    assert abs(est.corr_area_px / 4 - 1) < 0.15


def test_an_unknown_trend_is_refused():
    import pytest

    values, groups = _flat_field()
    with pytest.raises(ValueError, match="trend"):
        estimate_noise(values, groups, trend="quadric")
