"""The newer process effects (mask_rotation, microtrenching, etch_gradient) against
analytic results written here, not taken from masks.process.

4 um pitch, 0.25 um fine step (16 fine pixels per design pixel); design pixel (i, j) spans
rows i*16 .. i*16+15 of the fine grid; the field centre is the geometric centre of the design.
"""

import dataclasses

import numpy as np
import pytest

from doedesign.errors import DoeError
from masks.decompose import DEFAULT_DEPTHS_M
from masks.effects import EFFECTS, PROCESS_EFFECTS, effect_spec
from masks.process import ProcessParams, simulate_surface

PITCH = 4e-6
STEP = 0.25e-6
U = 16


def simulate(levels, **changes):
    return simulate_surface(levels, PITCH, ProcessParams.ideal().copy(**changes), step_m=STEP).height_m


def fine_x_m(n_cols):
    """x of each fine column centre from the field centre (m), x toward increasing column."""
    return (np.arange(n_cols * U) + 0.5) * STEP - n_cols * PITCH / 2


def fine_y_m(n_rows):
    """y of each fine row centre from the field centre (m), y up (toward row 0)."""
    return n_rows * PITCH / 2 - (np.arange(n_rows * U) + 0.5) * STEP


# ---------------------------------------------------------------- the vocabulary table

def test_every_effect_is_a_process_field_with_bounded_named_parameters():
    fields = {f.name for f in dataclasses.fields(ProcessParams)}
    assert {"mask_rotation", "microtrenching", "etch_gradient"} <= set(EFFECTS)
    assert len(set(EFFECTS)) == len(EFFECTS)
    for effect in PROCESS_EFFECTS:
        assert effect.name in fields and set(effect.extra_fields) <= fields
        assert effect.description.endswith(".") and effect.description.count(". ") == 0
        for p in effect.params:
            assert p.lower < p.upper and p.name.endswith(("_m", "_deg", "_rad", "_per_m", "_fraction"))
    assert [p.name for p in effect_spec("microtrenching").params] == ["depth_m", "width_m"]
    with pytest.raises(KeyError):
        effect_spec("tilt")


def test_new_fields_default_off_round_trip_and_follow_the_mask_count():
    p = ProcessParams.ideal()
    assert not p.mask_rotation.any() and p.microtrenching.shape == (4, 2) and not p.etch_gradient.any()
    q = p.copy(mask_rotation=[0, 0.01, 0, 0], microtrenching=[[0, 0], [5e-9, 1e-6], [0, 0], [0, 0]],
               etch_gradient=[3.0, -1.0])
    r = ProcessParams.from_dict(q.to_dict())
    for name in ("mask_rotation", "microtrenching", "etch_gradient"):
        np.testing.assert_array_equal(getattr(r, name), getattr(q, name))
    r.microtrenching[1, 0] = 1.0
    assert q.microtrenching[1, 0] == 5e-9
    three = q.copy(etch_depth=[1e-7, 2e-7, 4e-7])
    assert three.mask_rotation.shape == (3,) and three.microtrenching.shape == (3, 2)
    np.testing.assert_array_equal(three.etch_gradient, [3.0, -1.0])


@pytest.mark.parametrize("changes, word", [
    (dict(mask_rotation=[0, 0, 0]), "mask_rotation"),
    (dict(mask_rotation=[0, 0, 90, 0]), "mask_rotation"),
    (dict(microtrenching=np.zeros(4)), "microtrenching"),
    (dict(microtrenching=[[0, 0], [1e-9, 0], [0, 0], [0, 0]]), "microtrenching"),
    (dict(microtrenching=[[0, 0], [-1e-9, 1e-6], [0, 0], [0, 0]]), "microtrenching"),
    (dict(etch_gradient=[1.0]), "etch_gradient"),
    (dict(etch_gradient=[np.nan, 0]), "etch_gradient"),
])
def test_bad_new_parameters_are_refused(changes, word):
    with pytest.raises(DoeError, match=word):
        ProcessParams.ideal().copy(**changes)


# ---------------------------------------------------------------- mask rotation

def test_rotated_mask_moves_a_centred_edge_by_theta_times_distance():
    # Mask 2 open over the top half of a 20 x 40 design: a horizontal edge through the centre.
    levels = np.zeros((20, 40), dtype=int)
    levels[:10] = 4
    theta_deg = 0.05
    surf = simulate_surface(levels, PITCH, ProcessParams.ideal().copy(mask_rotation=[0, 0, theta_deg, 0]),
                            step_m=STEP)
    printed = surf.masks_printed[2].astype(float)
    # Opening length in the rows between the centre -5 px and +5 px: its edge position.
    band = printed[5 * U:15 * U].sum(axis=0) * STEP - 5 * PITCH
    x = fine_x_m(40)
    inner = np.abs(x) < 15 * PITCH                     # away from the rotated side edges
    # Counter-clockwise: the edge at x rises by theta * x, so the opening below it shrinks.
    expected = -np.radians(theta_deg) * x
    np.testing.assert_allclose(band[inner], expected[inner], atol=0.002 * STEP)
    assert expected[inner].max() > 0.2 * STEP          # the test resolves the motion
    # The other masks did not move.
    assert not surf.masks_printed[1].any() and not surf.masks_printed[3].any()


def test_rotation_in_degrees_adds_to_the_overlay_rotation():
    rng = np.random.default_rng(5)
    levels = rng.integers(0, 16, (12, 12))
    ideal = simulate(levels)
    overlay = np.zeros((4, 3))
    overlay[1, 2] = -np.radians(0.2)
    cancelled = simulate(levels, mask_rotation=[0, 0.2, 0, 0], mask_overlay=overlay)
    np.testing.assert_allclose(cancelled, ideal, atol=1e-12)
    assert np.abs(simulate(levels, mask_rotation=[0, 0.2, 0, 0]) - ideal).max() > 0.5 * DEFAULT_DEPTHS_M[1]


# ---------------------------------------------------------------- etch gradient

def test_gradient_makes_mean_depth_linear_across_the_field_for_every_mask():
    levels = np.full((24, 30), 15)
    g = np.array([12.0, -5.0])                      # 1.2 %/mm along x, -0.5 %/mm along y
    h = simulate(levels, etch_gradient=g)
    total = sum(DEFAULT_DEPTHS_M)
    x, y = fine_x_m(30), fine_y_m(24)
    np.testing.assert_allclose(h, -total * (1 + g[0] * x[None, :] + g[1] * y[:, None]), rtol=1e-9)
    # Mean depth of a column at x is d (1 + g_x x), and the relative change is the same per mask.
    np.testing.assert_allclose(-h.mean(axis=0), total * (1 + g[0] * x), rtol=1e-9)
    single = simulate(np.full((24, 30), 2), etch_gradient=g)
    np.testing.assert_allclose(single / h, DEFAULT_DEPTHS_M[1] / total, rtol=1e-9)


def test_gradient_leaves_unetched_areas_flat():
    levels = np.zeros((10, 10), dtype=int)
    levels[3:6, 3:6] = 8
    h = simulate(levels, etch_gradient=[50.0, 50.0])
    assert np.all(h[(np.kron(levels, np.ones((U, U))) == 0)] == 0)


# ---------------------------------------------------------------- microtrenching

def test_microtrench_profile_is_exponential_inside_the_etched_edges_of_its_mask():
    levels = np.zeros((24, 24), dtype=int)
    levels[4:20, 6:18] = 8                         # mask 3 opening, 48 um wide
    levels[1:3, 1:3] = 1                           # a mask 0 feature: no trench asked for it
    t, w = 30e-9, 1e-6
    trench = np.zeros((4, 2))
    trench[3] = (t, w)
    diff = simulate(levels, microtrenching=trench) - simulate(levels)
    opening = np.kron(levels == 8, np.ones((U, U), bool))
    assert np.all(diff[~opening] == 0)
    # Middle row, far from the top and bottom edges: distance s inside the left and right edges.
    row = diff[12 * U]
    s_left = (np.arange(24 * U) - 6 * U + 0.5) * STEP
    s_right = (18 * U - np.arange(24 * U) - 0.5) * STEP
    inside = opening[12 * U]
    expected = -t * np.exp(-np.minimum(s_left, s_right) / w)   # the nearer sidewall sets the depth
    np.testing.assert_allclose(row[inside], expected[inside], rtol=1e-6, atol=1e-20)
    assert row[inside][0] == pytest.approx(-t * np.exp(-0.5 * STEP / w), rel=1e-6, abs=0)


def test_microtrench_volume_is_depth_times_width_times_edge_length():
    levels = np.zeros((20, 20), dtype=int)
    levels[6:14, 6:14] = 4                         # square opening of mask 2, 32 um side
    t, w = 20e-9, 2e-6
    trench = np.zeros((4, 2))
    trench[2] = (t, w)
    volume = -(simulate(levels, microtrenching=trench) - simulate(levels)).sum() * STEP ** 2
    perimeter = 4 * 8 * PITCH
    # t w per unit of straight edge; in each of the four corner quadrants the two edges' feet
    # would count min(e_x, e_y) = e^{-max(x, y)/w} twice, and the nearer wall alone sets the
    # depth: the integral of e^{-max(x, y)/w} over a quadrant is 2 w^2, so P - 8 w.
    assert volume == pytest.approx(t * w * (perimeter - 8 * w), rel=2e-3, abs=0)


def test_microtrench_scales_with_the_local_etch_depth():
    levels = np.zeros((10, 40), dtype=int)
    levels[2:8, 4:36] = 2                          # mask 1, left edge at x = -64 um, right at +64 um
    g = np.array([40.0, 0.0])                      # 4 %/mm
    t, w = 10e-9, 0.5e-6
    trench = np.zeros((4, 2))
    trench[1] = (t, w)
    diff = simulate(levels, etch_gradient=g, microtrenching=trench) - simulate(levels, etch_gradient=g)
    x = fine_x_m(40)
    row = diff[5 * U]
    first_left, first_right = 4 * U, 36 * U - 1
    foot = t * np.exp(-0.5 * STEP / w)
    assert -row[first_left] == pytest.approx(foot * (1 + g[0] * x[first_left]), rel=1e-6, abs=0)
    assert -row[first_right] == pytest.approx(foot * (1 + g[0] * x[first_right]), rel=1e-6, abs=0)


def test_new_effects_do_not_depend_on_the_simulated_region():
    rng = np.random.default_rng(11)
    levels = rng.integers(0, 16, (16, 16))
    params = ProcessParams.ideal().copy(mask_rotation=[0, 0.03, -0.02, 0.01], etch_gradient=[20.0, -10.0],
                                        microtrenching=[[5e-9, 0.5e-6], [0, 0], [15e-9, 1e-6], [20e-9, 0.3e-6]])
    full = simulate_surface(levels, PITCH, params, step_m=STEP).height_m
    part = simulate_surface(levels, PITCH, params, step_m=STEP, region=(5, 11, 3, 9)).height_m
    np.testing.assert_allclose(part, full[5 * U:11 * U, 3 * U:9 * U], atol=1e-4 * 20e-9)


def test_microtrench_at_an_opening_corner_follows_the_nearest_sidewall():
    levels = np.zeros((20, 20), dtype=int)
    levels[6:14, 6:14] = 8                         # square opening of mask 3
    t, w = 30e-9, 0.5e-6
    trench = np.zeros((4, 2))
    trench[3] = (t, w)
    diff = simulate(levels, microtrenching=trench) - simulate(levels)
    # The fine pixel in the opening's top-left corner is 0.5 step from both sidewalls.
    corner = diff[6 * U, 6 * U]
    assert corner == pytest.approx(-t * np.exp(-0.5 * STEP / w), rel=0.05)


def test_microtrench_inside_an_opening_corner_and_beside_a_closed_corner():
    """Chessboard distance to the nearest closed pixel: along the diagonal of an opening's
    corner s = the distance to either wall; beside a closed block's corner (an L-shaped
    opening) s = max(dx, dy) from that corner."""
    levels = np.zeros((20, 20), dtype=int)
    levels[4:16, 4:16] = 8                         # opening of mask 3 ...
    levels[4:8, 4:8] = 0                           # ... with a closed block in its top-left corner
    t, w = 30e-9, 0.5e-6
    trench = np.zeros((4, 2))
    trench[3] = (t, w)
    diff = simulate(levels, microtrenching=trench) - simulate(levels)
    # Diagonally out from the block's corner (fine pixel (8U, 8U) is the first open one).
    for k in range(4):
        s = (k + 0.5) * STEP
        assert diff[8 * U + k, 8 * U + k] == pytest.approx(-t * np.exp(-s / w), rel=1e-9)
    # One pixel right of the block's corner row, k pixels below it: s = max(k, 0) + 0.5 steps.
    for k in range(1, 4):
        s = (k + 0.5) * STEP
        assert diff[8 * U + k, 8 * U] == pytest.approx(-t * np.exp(-s / w), rel=1e-9)


def test_microtrench_sees_no_wall_inside_a_moved_blurred_opening():
    """The trench counts any partly closed pixel as a wall: a shifted, rotated, biased and
    proximity-blurred opening must print exactly open in its interior, so the trench there is
    exp(-s / w) of the true walls only (here far below 1e-6 of t)."""
    levels = np.zeros((24, 24), dtype=int)
    levels[4:20, 4:20] = 8                         # 64 um opening of mask 3
    t, w = 30e-9, 0.5e-6
    trench = np.zeros((4, 2))
    trench[3] = (t, w)
    moved = dict(mask_overlay=np.array([[0, 0, 0], [0, 0, 0], [0, 0, 0], [0.37e-6, -0.21e-6, 0.0]]),
                 mask_rotation=np.array([0, 0, 0, 0.01]), linewidth_bias=np.array([0, 0, 0, 0.13e-6]),
                 proximity_blur=0.3e-6)
    diff = simulate(levels, microtrenching=trench, **moved) - simulate(levels, **moved)
    interior = diff[8 * U:16 * U, 8 * U:16 * U]    # >= 14 um (28 w) from every wall
    assert np.abs(interior).max() < 1e-6 * t
    assert diff.min() < -0.5 * t                    # the trench is there at the walls


def test_trench_foot_is_recomputed_for_each_coverage_and_kept_for_the_same():
    # The foot's distance map is kept between calls on the same coverage (a fit of the trench's
    # depth and width); a changed coverage must get its own, equal to a fresh transform's.
    from scipy.ndimage import distance_transform_cdt

    from masks import litho

    def reference(coverage, width):
        padded = np.pad(1.0 - coverage.astype(float), 1, constant_values=1.0)
        dist, (ri, ci) = distance_transform_cdt(padded <= 0.0, metric="chessboard", return_indices=True)
        s = (dist + 0.5 - padded[ri, ci])[1:-1, 1:-1]
        return np.minimum(np.exp(-s / width), 1.0)

    a = litho.grow(litho.upsample_mask(np.array([[0, 1, 1, 0], [0, 1, 0, 0], [1, 1, 0, 0]]), 8), 0.3)
    b = a.copy()
    b[10:14, 12:20] = 0.0
    for coverage in (a, b, a, a):
        for width in (2.0, 5.0):
            np.testing.assert_allclose(litho.edge_foot(coverage, width), reference(coverage, width), rtol=0, atol=1e-6)
    assert not np.allclose(litho.edge_foot(a, 2.0), litho.edge_foot(b, 2.0))


def test_grown_mask_is_grow_of_the_upsampled_mask():
    """The design-resolution growth equals the fine grid's maximum filters bit for bit: widening
    and narrowing, whole and fractional pixels, up to half a block and past it (the filters'
    route), at the edges of the design; and a square opening grows by the bias on every edge."""
    from masks import litho

    rng = np.random.default_rng(7)
    for _ in range(200):
        u = int(rng.integers(1, 40))
        mask = rng.random(tuple(rng.integers(1, 9, 2))) < 0.5
        bias = float(rng.uniform(-u, u) * rng.choice([1.0, 0.2]))
        bias = float(np.trunc(bias)) if rng.random() < 0.2 else bias
        expected = litho.grow(litho.upsample_mask(mask, u), bias)
        got = litho.grown_mask(mask, u, bias)
        assert got.dtype == np.float32 and got.shape == expected.shape
        np.testing.assert_array_equal(got, expected)
    square = np.zeros((5, 5), bool)
    square[2, 2] = True
    area = float(litho.grown_mask(square, 20, 3.25).sum())
    assert area == pytest.approx((20 + 2 * 3.25) ** 2, abs=0.25 ** 2 + 1e-3)
