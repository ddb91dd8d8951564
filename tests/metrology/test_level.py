"""Levelling: plane on level-0 pixels versus a plane through all pixels, spikes, joint fit."""

import numpy as np
import pytest

from doedesign.errors import DoeError
from metrology.matching import level

STEP = 75e-9


def _terraces(shape=(300, 400), seed=0):
    """Random 16-level terraces (blocks of 6 px) whose depth grows toward the right.

    The deep levels crowd on the right, so a plane through all pixels tilts toward them.
    """
    rng = np.random.default_rng(seed)
    blocks = (shape[0] // 6 + 1, shape[1] // 6 + 1)
    ramp = np.linspace(0, 1, blocks[1])[None, :]
    lv = np.clip(np.round(rng.random(blocks) * 15 * ramp + rng.normal(0, 1, blocks)), 0, 15).astype(int)
    lv = np.kron(lv, np.ones((6, 6), int))[:shape[0], :shape[1]]
    return lv, -lv * STEP


def test_top_level_plane_removes_tilt_where_all_pixel_plane_is_biased():
    lv, h = _terraces()
    slope_x, slope_y, offset = 0.8e-9, -0.5e-9, 3e-6  # m per pixel: 320 nm across the field
    tilted = h + level.plane_image(np.array([offset, slope_x, slope_y]), h.shape)
    tilted += np.random.default_rng(1).normal(0, 1e-9, h.shape)
    biased = level.fit_plane(tilted, np.ones(h.shape, bool))
    # The pattern gets deeper to the right: an all-pixel plane sees a large false x slope.
    assert abs(biased[1] - slope_x) > 0.5e-9
    res = level.level_on_top(tilted)
    assert res.plane[1] == pytest.approx(slope_x, abs=2e-12)
    assert res.plane[2] == pytest.approx(slope_y, abs=2e-12)
    # The reference is exactly the level-0 pixels, and they end up at 0.
    assert np.array_equal(res.reference, lv == 0)
    assert abs(np.mean(res.height_m[lv == 0])) < 0.2e-9
    assert np.mean(res.height_m[lv == 15]) == pytest.approx(-15 * STEP, abs=0.5e-9)


@pytest.mark.parametrize("k, a, wave, cx, cy", [(0, 9, 0, 0.1, 0.1), (1, 8.5, 0.3, 0, 0.2), (2, 9, 0.5, 0.15, 0),
                                                 (3, 7, 0.8, 0.05, 0.05)])
def test_steep_tilt_over_a_smooth_staircase_levels_on_level_zero(k, a, wave, cx, cy):
    """A demo-like field: a smooth (lens-like) staircase whose level 0 is 1-4 % of the field, in
    one place, under 2 um and 1 um of tilt across it (the demo's instrument).

    A plane through all pixels leans so far that the topmost cluster it leaves mixes levels 0
    and 1 across the field (the demo's registration then read 0.48 for a true match); the median
    step between neighbours does not lean.
    """
    n = 353
    r, c = np.mgrid[:n, :n] / n
    lv = np.clip(np.floor(a * np.hypot(r - cy, c - cx) + wave * np.sin(6 * r)), 0, 15).astype(int)
    tilt = np.array([0.0, -1e-6 / n, 2e-6 / n])
    tilted = -lv * STEP + level.plane_image(tilt, lv.shape) + np.random.default_rng(k).normal(0, 1e-9, lv.shape)
    res = level.level_on_top(tilted)
    assert np.array_equal(res.reference, lv == 0)
    assert res.plane[1:] == pytest.approx(tilt[1:], abs=2e-11)
    assert np.mean(res.height_m[lv == 1]) == pytest.approx(-STEP, abs=1.5e-9)


def test_step_plane_is_the_tilt_under_any_pattern():
    lv, h = _terraces()
    tilt = np.array([1e-6, 3e-9, -7e-9])
    valid = np.random.default_rng(3).random(h.shape) > 0.05  # dropouts
    plane = level.step_plane(h + level.plane_image(tilt, h.shape), valid)
    assert plane[1:] == pytest.approx(tilt[1:], abs=1e-13)


def test_joint_fit_recovers_tilt_and_level_offsets():
    lv, h = _terraces(seed=3)
    h = h.copy()
    h[lv == 7] += 4e-9  # one level off its nominal depth (e.g. etch loading)
    tilted = h + level.plane_image(np.array([1e-6, -1.2e-9, 0.7e-9]), h.shape)
    res = level.level_joint(tilted, lv)
    assert res.plane[1] == pytest.approx(-1.2e-9, abs=1e-15)
    assert res.plane[2] == pytest.approx(0.7e-9, abs=1e-15)
    assert res.level_offsets_m[7] == pytest.approx(-7 * STEP + 4e-9, abs=1e-15)
    assert res.level_offsets_m[3] == pytest.approx(-3 * STEP, abs=1e-15)


def test_joint_fit_with_scan_lines_recovers_each_line_offset():
    """A raster scan: a plane, a random z offset per scan line (row) and white noise on binary
    terraces; the joint fit with one offset per line gets the tilt, the step and every line's
    offset back to within the noise a row's ~400 pixels leave (1 nm / sqrt(400) = 0.05 nm)."""
    rng = np.random.default_rng(7)
    lv, _ = _terraces(seed=4)
    lv = (lv > 7).astype(int)
    step = 490e-9
    lines = rng.normal(0, 6e-9, lv.shape[0])
    lines -= np.polyval(np.polyfit(np.arange(lines.size), lines, 1), np.arange(lines.size))  # the tilt is the plane's
    plane = np.array([20e-9, 0.6e-9, -0.25e-9])
    h = -step * lv + level.plane_image(plane, lv.shape) + lines[:, None] + rng.normal(0, 1e-9, lv.shape)
    res = level.level_joint(h, lv, line_offsets=True)
    assert res.plane[1] == pytest.approx(plane[1], abs=2e-12)
    assert res.plane[2] == pytest.approx(plane[2], abs=2e-12)
    assert res.level_offsets_m[1] == pytest.approx(-step, abs=0.05e-9)
    assert np.max(np.abs(res.line_offsets_m - lines)) < 0.3e-9
    assert np.sqrt(np.mean(res.line_offsets_m ** 2)) == pytest.approx(np.sqrt(np.mean(lines ** 2)), rel=0.02)
    # Level 0 (the unetched surface) ends at 0; without the line offsets the rows stay scattered.
    assert abs(np.median(res.height_m[lv == 0])) < 0.1e-9
    plain = level.level_joint(h, lv)

    def row_scatter(height):
        return np.std([np.median(height[r][lv[r] == 0]) for r in range(lv.shape[0]) if (lv[r] == 0).any()])

    assert row_scatter(plain.height_m) > 10 * row_scatter(res.height_m)
    art = res.artefacts()
    assert art["scan_lines"] == lv.shape[0] and art["tilt_x_nm_per_px"] == pytest.approx(0.6, abs=0.01)


def test_joint_fit_needs_level_zero():
    lv, h = _terraces()
    with pytest.raises(DoeError, match="level-0"):
        level.level_joint(h, np.where(lv == 0, -1, lv))


def test_spikes_removed_but_step_edges_kept():
    lv, h = _terraces(seed=5)
    spiky = h.copy()
    spiky[50, 60] += 300e-9
    spiky[120, 200] -= 600e-9
    spiky[121, 200] -= 590e-9  # a two-pixel spike needs the second pass
    out, n = level.remove_spikes(spiky)
    assert n == 3
    assert np.isnan(out[50, 60]) and np.isnan(out[120, 200]) and np.isnan(out[121, 200])
    # Every terrace edge (steps up to 15 x 75 nm) survives.
    assert np.count_nonzero(np.isnan(out)) == 3


def test_histogram_classification_matches_truth():
    lv, h = _terraces(seed=2)
    noisy = h + np.random.default_rng(0).normal(0, 1.5e-9, h.shape)
    labels, peaks = level.classify_by_histogram(noisy)
    present = np.unique(lv)
    assert peaks.size == present.size
    np.testing.assert_allclose(peaks, -present * STEP, atol=1.5e-9)
    assert np.array_equal(present[labels], lv)
