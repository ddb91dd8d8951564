"""Process model (masks.process): each effect against its analytic signature.

Most tests use a 4 um pitch and a 0.25 um step (16 fine pixels per design pixel, so
the fine grid is exactly 0.25 um) and one feature of mask 3 (level 8, 600 nm).
"""

import numpy as np
import pytest
from scipy import ndimage as ndi
from scipy.optimize import brentq
from scipy.special import erf

from doedesign.errors import DoeError
from masks import litho
from masks.decompose import DEFAULT_DEPTHS_M
from masks.process import EFFECTS, ProcessParams, SimulatedSurface, simulate_surface

PITCH = 4e-6
STEP = 0.25e-6
U = 16
D3 = DEFAULT_DEPTHS_M[3]


def designed_height(levels, depths=DEFAULT_DEPTHS_M):
    """-sum_j bit_j(level) d_j, upsampled by U (the ideal surface, written independently)."""
    h = np.zeros(levels.shape)
    for j, d in enumerate(depths):
        h -= ((levels >> j) & 1) * d
    return np.kron(h, np.ones((U, U)))


def square(n=12, r0=4, r1=8, c0=4, c1=8, level=8):
    levels = np.zeros((n, n), dtype=int)
    levels[r0:r1, c0:c1] = level
    return levels


def overlay(j, dx=0.0, dy=0.0, rot=0.0, n=4):
    ov = np.zeros((n, 3))
    ov[j] = (dx, dy, rot)
    return ov


def simulate(levels, **changes):
    return simulate_surface(levels, PITCH, ProcessParams.ideal().copy(**changes), step_m=STEP)


# ---------------------------------------------------------------- ideal behaviour

def test_ideal_is_the_designed_surface_exactly():
    rng = np.random.default_rng(3)
    levels = rng.integers(0, 16, (10, 13))
    surf = simulate_surface(levels, PITCH, step_m=STEP)
    assert surf.upsample == U and surf.step_m == pytest.approx(STEP, abs=0)
    assert surf.height_m.shape == (10 * U, 13 * U)
    np.testing.assert_allclose(surf.height_m, designed_height(levels), rtol=0, atol=1e-20)
    # Printed masks are the bits of the level, upsampled.
    bits = np.stack([np.kron((levels >> j) & 1, np.ones((U, U))) for j in range(4)])
    np.testing.assert_array_equal(surf.masks_printed, bits)


def test_ideal_region_and_design_coords():
    rng = np.random.default_rng(4)
    levels = rng.integers(0, 16, (12, 12))
    surf = simulate_surface(levels, PITCH, step_m=STEP, region=(3, 7, 2, 9))
    np.testing.assert_allclose(surf.height_m, designed_height(levels[3:7, 2:9]), rtol=0, atol=1e-20)
    rows, cols = surf.design_coords()
    assert rows.shape == (4 * U,) and cols.shape == (7 * U,)
    # First fine pixel centre: half a fine pixel below the top edge of design pixel 3.
    assert rows[0] == pytest.approx(3 - 0.5 + 0.5 / U, abs=0)
    assert cols[-1] == pytest.approx(8 + 0.5 - 0.5 / U, abs=0)
    # Each design pixel holds exactly U fine centres.
    assert np.all(np.round(rows).reshape(4, U) == np.arange(3, 7)[:, None])


def test_upsample_rounds_up_to_the_requested_step():
    surf = simulate_surface(np.zeros((3, 3), int), 5.4e-6, step_m=0.25e-6)
    assert surf.upsample == 22
    assert surf.step_m == pytest.approx(5.4e-6 / 22, abs=0)
    assert surf.step_m <= 0.25e-6


def test_unetched_design_stays_flat_whatever_the_litho():
    levels = np.zeros((8, 8), dtype=int)
    surf = simulate(levels, mask_overlay=overlay(3, 0.4e-6, -0.2e-6, 1e-3),
                    linewidth_bias=np.full(4, 0.3e-6), proximity_blur=1e-6,
                    sidewall_slope=0.5e-6, etch_loading=0.2, loading_radius=10e-6)
    assert np.all(surf.height_m == 0)


# ---------------------------------------------------------------- overlay

def test_overlay_shift_makes_antisymmetric_slivers_of_the_mask_depth():
    levels = square()
    ideal = simulate(levels).height_m
    dx = 0.5e-6                                    # 2 fine pixels toward +x (columns)
    diff = simulate(levels, mask_overlay=overlay(3, dx)).height_m - ideal
    rows = slice(4 * U, 8 * U)
    # Left edge (x = 4 px): the opening moved away, 0.5 um of it is no longer etched.
    np.testing.assert_allclose(diff[rows, 4 * U:4 * U + 2], +D3, rtol=1e-6)
    # Right edge: 0.5 um beyond the design is now etched 600 nm.
    np.testing.assert_allclose(diff[rows, 8 * U:8 * U + 2], -D3, rtol=1e-6)
    band = np.zeros(diff.shape, bool)
    band[rows, 4 * U:4 * U + 2] = band[rows, 8 * U:8 * U + 2] = True
    assert np.all(diff[~band] == 0)
    # Volume is conserved: the feature only moved.
    assert abs(diff.sum()) < 1e-9 * D3


def test_overlay_subpixel_shift_area_and_sign_convention_for_y():
    levels = square()
    ideal = simulate(levels).height_m
    dy = 0.3e-6                                     # 1.2 fine pixels UP (toward row 0)
    diff = simulate(levels, mask_overlay=overlay(3, dy=dy)).height_m - ideal
    top, bottom = diff[:6 * U], diff[6 * U:]
    feature_width = 4 * PITCH
    # Top edge gains etch (deeper), bottom edge loses it; each sliver holds d * dy * width.
    assert top.min() == pytest.approx(-D3, abs=0) and top.max() == 0
    assert bottom.max() == pytest.approx(D3, abs=0) and bottom.min() == 0
    assert -top.sum() * STEP ** 2 == pytest.approx(D3 * dy * feature_width, rel=1e-6, abs=0)
    assert bottom.sum() * STEP ** 2 == pytest.approx(D3 * dy * feature_width, rel=1e-6, abs=0)


def test_overlay_rotation_moves_features_around_the_design_centre():
    # A 2x2 feature 8 px right of the centre of a 21x21 design (centre = pixel 10).
    levels = np.zeros((21, 21), dtype=int)
    levels[9:11, 17:19] = 8          # feature centre at (9.5, 17.5): 7.5 px right, 0.5 px up
    theta = 2e-3
    surf = simulate(levels, mask_overlay=overlay(3, rot=theta))
    rows, cols = surf.design_coords()
    w = -surf.height_m
    r_c = (w.sum(axis=1) * rows).sum() / w.sum()
    c_c = (w.sum(axis=0) * cols).sum() / w.sum()
    # Counter-clockwise (x right, y up) by theta: (x, y) = (7.5, 0.5) px -> moves by
    # theta * (-y, x): x by -0.001 px, y by +0.015 px (up = smaller row).
    x, y = 7.5, 0.5
    assert c_c - 17.5 == pytest.approx(-theta * y, abs=2e-5)
    assert r_c - 9.5 == pytest.approx(-theta * x, rel=0.02, abs=0)
    assert abs(w.sum() * STEP ** 2 - 4 * PITCH ** 2 * D3) < 1e-3 * 4 * PITCH ** 2 * D3


# ---------------------------------------------------------------- linewidth bias

@pytest.mark.parametrize("bias", [0.3e-6, 0.55e-6, -0.3e-6])
def test_bias_grows_area_by_bias_times_perimeter(bias):
    # Isolated square (4 x 4 px = 16 um) and an isolated line (1 x 8 px = 4 x 32 um).
    for (r0, r1, c0, c1) in ((4, 8, 4, 8), (6, 7, 2, 10)):
        levels = square(12, r0, r1, c0, c1)
        h, w = (r1 - r0) * PITCH, (c1 - c0) * PITCH
        surf = simulate(levels, linewidth_bias=np.array([0, 0, 0, bias]))
        area = surf.masks_printed[3].sum() * STEP ** 2
        expected = (h + 2 * bias) * (w + 2 * bias)    # = A + b P + 4 b^2
        assert area == pytest.approx(expected, rel=0.01, abs=0)
        # Depth stays that of the mask; area scales the etched volume.
        assert -surf.height_m.sum() * STEP ** 2 == pytest.approx(expected * D3, rel=0.01, abs=0)


def test_bias_is_per_mask():
    levels = square(level=8 + 1)            # masks 0 and 3 open on the square
    surf = simulate(levels, linewidth_bias=np.array([0.5e-6, 0, 0, 0]))
    a0 = surf.masks_printed[0].sum() * STEP ** 2
    a3 = surf.masks_printed[3].sum() * STEP ** 2
    assert a3 == pytest.approx((4 * PITCH) ** 2, abs=0)
    assert a0 == pytest.approx((4 * PITCH + 1e-6) ** 2, rel=1e-3, abs=0)


# ---------------------------------------------------------------- proximity blur + threshold

def _printed_width_isolated(L, sigma, threshold):
    """Analytic edge position on the centre line of an isolated L x L square's aerial image."""
    def profile(x):
        return 0.25 * (erf((L / 2 - x) / (np.sqrt(2) * sigma)) + erf((L / 2 + x) / (np.sqrt(2) * sigma)))

    peak_y = 2 * profile(0.0)         # the other axis' factor on the centre line
    x_edge = brentq(lambda x: 2 * profile(x) * peak_y - threshold, 0.0, L)
    return 2 * x_edge


def test_isolated_pixel_prints_smaller_than_the_same_pixel_in_a_cluster():
    sigma, thr = 1.2e-6, 0.5
    iso = np.zeros((11, 11), int)
    iso[5, 5] = 8
    cluster = np.zeros((11, 11), int)
    cluster[3:8, 3:8] = 8
    s_iso = simulate(iso, proximity_blur=sigma, resist_threshold=thr)
    s_clu = simulate(cluster, proximity_blur=sigma, resist_threshold=thr)
    pix = (slice(5 * U, 6 * U), slice(5 * U, 6 * U))
    iso_area = s_iso.masks_printed[3].sum() * STEP ** 2
    assert s_clu.masks_printed[3][pix].mean() > 0.999
    assert iso_area < 0.8 * PITCH ** 2
    # Width on the centre row against the analytic aerial image of a box pixel.
    centre_row = s_iso.masks_printed[3][5 * U + U // 2 - 1:5 * U + U // 2 + 1].mean(axis=0)
    width = centre_row.sum() * STEP
    assert width == pytest.approx(_printed_width_isolated(PITCH, sigma, thr), abs=0.05e-6)


def test_blur_rounds_corners_area_matches_thresholded_analytic_aerial_image():
    L = 4 * PITCH
    thr = 0.5
    areas = []
    for sigma in (0.5e-6, 1.0e-6, 2.0e-6):
        surf = simulate(square(), proximity_blur=sigma, resist_threshold=thr)
        area = surf.masks_printed[3].sum() * STEP ** 2
        # Independent reference: the analytic aerial image of the square on a 20 nm grid.
        x = np.arange(-L, L, 20e-9) + 10e-9
        f = 0.5 * (erf((L / 2 - x) / (np.sqrt(2) * sigma)) + erf((L / 2 + x) / (np.sqrt(2) * sigma)))
        ref_area = np.count_nonzero(np.outer(f, f) > thr) * (20e-9) ** 2
        assert area == pytest.approx(ref_area, rel=0.005, abs=0)
        areas.append(area)
    # Straight edges stay put at threshold 0.5, so the area lost is the rounded corners:
    # it grows with the blur.
    assert areas[0] > areas[1] > areas[2] and areas[0] < L ** 2


def test_threshold_moves_long_edges_like_the_erf():
    # A wide line (8 px) far from other features: the edge sits where 0.5 erfc(x / sqrt2 s) = thr.
    levels = square(16, 2, 14, 4, 12)
    sigma, thr = 1.0e-6, 0.3
    surf = simulate(levels, proximity_blur=sigma, resist_threshold=thr)
    row = surf.masks_printed[3][8 * U]
    from scipy.special import erfinv
    grow_each_side = -np.sqrt(2) * sigma * erfinv(2 * thr - 1)
    assert row.sum() * STEP == pytest.approx(8 * PITCH + 2 * grow_each_side, abs=0.02e-6)


def test_block_blur_matches_full_resolution_blur():
    rng = np.random.default_rng(0)
    img = np.kron(rng.random((20, 20)) > 0.5, np.ones((16, 16))).astype(np.float32)
    sigma = 13.0
    full = ndi.gaussian_filter(img, sigma, mode="constant", cval=0.0)
    fast = litho.blurred(img, sigma, block=4)
    assert np.abs(fast - full).max() < 2e-3


# ---------------------------------------------------------------- sidewall

@pytest.mark.parametrize("ramp", [1.0e-6, 0.6e-6, 0.1e-6])
def test_sidewall_is_a_linear_ramp_of_the_given_width(ramp):
    levels = square(12, 1, 11, 4, 8)                   # a 16 x 40 um trench
    surf = simulate(levels, sidewall_slope=ramp)
    profile = -surf.height_m[6 * U] / D3               # 0 outside, 1 inside
    _, cols = surf.design_coords()
    x = (cols - 3.5) * PITCH                           # distance from the designed left edge
    # Sampled at the fine-pixel centres, the step is exactly clip(0.5 + x / w, 0, 1).
    left = slice(2 * U, 6 * U)
    np.testing.assert_allclose(profile[left], np.clip(0.5 + x[left] / ramp, 0, 1), atol=1e-9)
    # Depth in the middle of the trench and the etched volume are untouched.
    assert profile[6 * U] == pytest.approx(1.0, abs=0)
    assert surf.height_m.sum() == pytest.approx(simulate(levels).height_m.sum(), rel=1e-9, abs=0)


def test_sidewall_10_90_width_is_0p8_of_the_ramp():
    ramp = 1.0e-6
    surf = simulate(square(12, 1, 11, 4, 8), sidewall_slope=ramp)
    profile = -surf.height_m[6 * U] / D3
    x = surf.design_coords()[1] * PITCH
    left = slice(2 * U, 6 * U)
    x10, x50, x90 = np.interp([0.1, 0.5, 0.9], profile[left], x[left])
    assert x90 - x10 == pytest.approx(0.8 * ramp, abs=0.25 * STEP)
    assert x50 == pytest.approx(3.5 * PITCH, abs=0.1 * STEP)


# ---------------------------------------------------------------- etch loading

def test_loading_sparse_regions_etch_deeper_than_dense_ones():
    radius = 20e-6
    loading = 0.1
    levels = np.zeros((80, 80), int)
    levels[:, :30] = 8                      # dense: a 120 um wide open field
    levels[40, 60] = 8                      # sparse: one isolated 4 um pixel
    params = ProcessParams.ideal().copy(etch_loading=loading, loading_radius=radius)
    dense = simulate_surface(levels, PITCH, params, STEP, region=(39, 42, 10, 13))
    sparse = simulate_surface(levels, PITCH, params, STEP, region=(40, 41, 60, 61))
    # Gaussian-weighted open fraction: at column 11 of a field spanning columns -0.5..29.5
    # (the design edge is unetched beyond), Phi(18.5 p / s) - Phi(-11.5 p / s); at the
    # centre of the lone pixel, erf(p / (2 sqrt2 s))**2.
    from scipy.stats import norm
    rho_dense = norm.cdf(18.5 * PITCH / radius) - norm.cdf(-11.5 * PITCH / radius)
    rho_sparse = erf(PITCH / (2 * np.sqrt(2) * radius)) ** 2
    depth_dense = -dense.height_m[U + U // 2, U + U // 2]
    depth_sparse = -sparse.height_m[U // 2, U // 2]
    assert depth_dense == pytest.approx(D3 * (1 - loading * rho_dense), rel=2e-4, abs=0)
    assert depth_sparse == pytest.approx(D3 * (1 - loading * rho_sparse), rel=2e-4, abs=0)
    assert depth_sparse > depth_dense
    # No loading: no pattern dependence.
    flat = ProcessParams.ideal()
    a = simulate_surface(levels, PITCH, flat, STEP, region=(39, 42, 10, 13)).height_m
    b = simulate_surface(levels, PITCH, flat, STEP, region=(40, 41, 60, 61)).height_m
    assert np.all(a == -D3) and b[U // 2, U // 2] == -D3


# ---------------------------------------------------------------- roughness

def test_roughness_rms_and_seed():
    rng = np.random.default_rng(5)
    levels = rng.integers(0, 16, (8, 8))
    ideal = simulate(levels).height_m
    a = simulate(levels, roughness=1e-9, seed=7).height_m
    b = simulate(levels, roughness=1e-9, seed=7).height_m
    c = simulate(levels, roughness=1e-9, seed=8).height_m
    assert np.std(a - ideal) == pytest.approx(1e-9, rel=0.1, abs=0)
    assert abs(np.mean(a - ideal)) < 0.05e-9
    np.testing.assert_array_equal(a, b)
    assert np.abs(a - c).max() > 1e-9


# ---------------------------------------------------------------- continuity and crops

def test_surface_is_continuous_in_overlay():
    rng = np.random.default_rng(11)
    levels = rng.integers(0, 16, (8, 8))
    dxs = np.arange(0, 0.305e-6, 0.01e-6)
    surfaces = [simulate(levels, mask_overlay=overlay(3, dx)).height_m for dx in dxs]
    steps = np.diff(np.array(surfaces), axis=0)
    # Each 0.01 um move changes any fine pixel by at most d * 0.01 / 0.25 (area coverage)...
    assert np.abs(steps).max() <= D3 * 0.01 / 0.25 * 1.001
    # ...and the changed volume per step is constant: edges move at a steady rate, no jumps.
    l1 = np.abs(steps).sum(axis=(1, 2))
    assert l1.min() > 0.95 * l1.mean() and l1.max() < 1.05 * l1.mean()


def test_surface_is_continuous_with_blur_bias_and_sidewall():
    rng = np.random.default_rng(12)
    levels = np.pad(rng.integers(0, 16, (8, 8)), 1)     # unetched border: nothing leaves the crop
    base = dict(proximity_blur=0.8e-6, resist_threshold=0.45, sidewall_slope=0.3e-6,
                linewidth_bias=np.full(4, 0.05e-6))
    l1 = []
    prev = None
    for dx in np.arange(0, 0.305e-6, 0.01e-6):
        h = simulate(levels, mask_overlay=overlay(2, dx, 0.5 * dx), **base).height_m
        if prev is not None:
            l1.append(np.abs(h - prev).sum())
        prev = h
    l1 = np.array(l1)
    assert l1.min() > 0 and l1.max() < 2.0 * np.median(l1)
    # Bias through zero: no jump at b = 0.
    hs = [simulate(levels, linewidth_bias=np.full(4, b)).height_m for b in (-0.02e-6, 0.0, 0.02e-6)]
    assert np.abs(hs[1] - hs[0]).max() <= 0.02 / 0.25 * sum(DEFAULT_DEPTHS_M) * 1.01
    assert np.abs(hs[2] - hs[1]).sum() == pytest.approx(np.abs(hs[1] - hs[0]).sum(), rel=0.05, abs=0)


def test_result_does_not_depend_on_the_crop():
    rng = np.random.default_rng(13)
    levels = rng.integers(0, 16, (24, 24))
    params = ProcessParams.ideal().copy(
        mask_overlay=np.array([[0, 0, 0], [0.2e-6, -0.1e-6, 5e-4], [0.4e-6, 0, 0], [0, 0.3e-6, 0]]),
        linewidth_bias=np.array([0.1e-6, -0.1e-6, 0.2e-6, 0]), proximity_blur=2e-6,
        resist_threshold=0.45, sidewall_slope=0.4e-6, etch_loading=0.05, loading_radius=12e-6)
    full = simulate_surface(levels, PITCH, params, STEP).height_m
    part = simulate_surface(levels, PITCH, params, STEP, region=(8, 14, 5, 12))
    np.testing.assert_allclose(part.height_m, full[8 * U:14 * U, 5 * U:12 * U], rtol=0, atol=1e-12)


# ---------------------------------------------------------------- parameters and bad input

def test_params_round_trip_and_copy():
    p = ProcessParams.ideal().copy(mask_overlay=overlay(2, 1e-7), proximity_blur=1e-6, seed=3)
    q = ProcessParams.from_dict(p.to_dict())
    assert q.to_dict() == p.to_dict()
    r = p.copy(proximity_blur=2e-6)
    r.mask_overlay[2, 0] = 5.0
    assert p.mask_overlay[2, 0] == 1e-7 and p.proximity_blur == 1e-6
    three = ProcessParams.ideal(n_masks=3)
    assert three.n_masks == 3 and three.mask_overlay.shape == (3, 3)
    np.testing.assert_allclose(three.etch_depth, DEFAULT_DEPTHS_M[:3])
    assert set(EFFECTS) <= set(p.to_dict())


def test_custom_depths_and_fewer_masks():
    levels = np.array([[0, 1], [2, 3]])
    surf = simulate_surface(levels, PITCH, ProcessParams.ideal(depths_m=[100e-9, 210e-9]), STEP)
    assert surf.height_m[0, U] == pytest.approx(-100e-9, abs=0)
    assert surf.height_m[U, 0] == pytest.approx(-210e-9, abs=0)
    assert surf.height_m[U, U] == pytest.approx(-310e-9, abs=0)
    assert isinstance(surf, SimulatedSurface) and surf.masks_printed.shape[0] == 2


@pytest.mark.parametrize("levels, match", [
    (np.array([[0.0, np.nan]]), "NaN"),
    (np.array([[0.0, 1.5]]), "whole"),
    (np.array([[0, 16]]), "0..15"),
    (np.array([[-1, 0]]), "0..15"),
    (np.array([0, 1]), "2-D"),
])
def test_bad_levels(levels, match):
    with pytest.raises(DoeError, match=match):
        simulate_surface(levels, PITCH, step_m=STEP)


@pytest.mark.parametrize("changes, match", [
    (dict(mask_overlay=np.zeros((3, 3))), "mask_overlay"),
    (dict(linewidth_bias=np.zeros(2)), "linewidth_bias"),
    (dict(proximity_blur=-1e-6), "proximity_blur"),
    (dict(resist_threshold=1.2), "resist_threshold"),
    (dict(roughness=float("nan")), "roughness"),
    (dict(roughness="rough"), "^process parameter roughness must be a number, got 'rough'$"),
    (dict(etch_loading=float("inf")), "^process parameter etch_loading must be finite, got inf$"),
    (dict(etch_depth=[1e-7, -1e-7, 1e-7, 1e-7]), "etch_depth"),
    (dict(loading_radius=0.0), "loading_radius"),
])
def test_bad_parameters(changes, match):
    with pytest.raises(DoeError, match=match):
        ProcessParams.ideal().copy(**changes)


def test_bad_call_arguments():
    levels = np.zeros((4, 4), int)
    with pytest.raises(DoeError, match="pitch_m"):
        simulate_surface(levels, -1e-6)
    with pytest.raises(DoeError, match="region"):
        simulate_surface(levels, PITCH, region=(0, 5, 0, 2))
    with pytest.raises(DoeError, match="unknown"):
        ProcessParams.from_dict({"blur": 1e-6})
    with pytest.raises(DoeError, match="0..7"):
        simulate_surface(np.full((2, 2), 8), PITCH, ProcessParams.ideal(n_masks=3))
