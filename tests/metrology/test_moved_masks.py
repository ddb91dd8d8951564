"""A mask's overlay and rotation rendered as a placement of its camera map (issue 11's speed).

The camera model renders each mask in place and samples its camera map under the camera's
placement taken into that mask's frame. These tests hold that render against the independent
generator (its own surface on an 80x super-fine grid, its own blur and pixel integration), and
check the motion's geometry and the fallback to the summed fine surface.
"""

import dataclasses

import numpy as np
import pytest

import filegen
from masks import litho
from masks.process import ProcessParams, mask_motion, without_motion
from metrology.diagnosis import camera
from metrology.diagnosis.camera import CAMERA, CameraHeightProblem
from metrology.diagnosis.effects import effects_for
from metrology.diagnosis.height_effects import _gaussian_taps
from metrology.matching.instrument import Placement

QUIET = {"noise_m": 0.0, "n_spikes": 0, "invalid_fraction": 0.0, "tilt_rad": np.zeros(2), "piston_m": 0.0}


def _rms_nm(r):
    return float(np.sqrt(np.mean((r - r.mean()) ** 2)) * 1e9)


def _problem(case, names):
    inst = case.instrument
    pl = Placement(np.array(inst["matrix"]), np.array(inst["offset"]))
    return CameraHeightProblem(case.levels, filegen.PITCH_M, case.height_m, pl, ProcessParams.ideal(),
                               effects_for("height", names))


@pytest.mark.parametrize("name,truth,values", [
    ("mask_overlay", {"mask": 3, "shift_m": np.array([0.3e-6, -0.2e-6])}, [0, 0, 0, 0, 0.3e-6, -0.2e-6]),
    ("mask_overlay", {"mask": 2, "shift_m": np.array([0.45e-6, 0.37e-6])}, [0, 0, 0.45e-6, 0.37e-6, 0, 0]),
    ("mask_rotation", {"mask": 3, "angle_deg": 0.04}, [0, 0, 0.04]),
])
def test_moved_mask_renders_the_independent_generator_to_a_tenth_of_a_nanometre(name, truth, values):
    # Noiseless generator file, truth placement and blur: what is left is the two
    # implementations' difference. Measured 0.06-0.07 nm rms; the summed fine-grid path, which
    # blurs a partly covered fine cell as a uniform grey one, leaves 0.13-0.36 nm.
    case = filegen.make_case([name], 5, design_px=40, field_px=100, truth={name: truth}, instrument=QUIET)
    problem = _problem(case, [name])
    model = {name: np.array(values, float),
             CAMERA.name: np.array([0, 0, 0, 0, 0, case.instrument["blur_sigma_m"]])}
    ideal = _rms_nm(case.height_m - problem.render({CAMERA.name: model[CAMERA.name]}))
    moved = _rms_nm(case.height_m - problem.render(model))
    assert ideal > 1.5  # the effect is there to be rendered
    assert moved < 0.12


def test_placement_in_the_frame_of_a_moved_mask_undoes_the_motion():
    # A mask shifted by t and turned by a about c shows at o what stood at R(-a)(o - c - t) + c:
    # the placement into its frame maps each camera pixel there.
    pl = Placement(np.array([[0.2, 0.01], [-0.01, 0.2]]), np.array([10.0, 12.0]))
    shift, angle, centre = np.array([0.3, -0.1]), 1e-3, np.array([20.0, 20.0])
    moved = pl.in_frame_of(shift, angle, centre)
    rows, cols = np.array([0.0, 7.0, 40.0]), np.array([3.0, 50.0, 9.0])
    o = np.stack(pl.to_design(rows, cols))
    # (row, col) with row down: a counter-clockwise turn (y up) of -a is [[cos, sin], [-sin, cos]].
    back = np.array([[np.cos(angle), np.sin(angle)], [-np.sin(angle), np.cos(angle)]]) \
        @ (o - (centre + shift)[:, None]) + centre[:, None]
    np.testing.assert_allclose(np.stack(moved.to_design(rows, cols)), back, rtol=0, atol=1e-12)
    # The process model's own mover uses the same rule (one place for it).
    matrix, offset = litho.inverse_motion(shift, angle, centre)
    np.testing.assert_allclose(matrix @ o + offset[:, None], back, rtol=0, atol=1e-12)


def test_mask_motion_is_the_overlay_in_design_pixels_and_the_total_rotation():
    p = ProcessParams.ideal()
    ov = np.zeros((4, 3))
    ov[2] = [0.54e-6, -1.08e-6, 2e-4]
    p = p.copy(mask_overlay=ov, mask_rotation=np.array([0, 0, 0.01, 0]))
    (dr, dc), rot = mask_motion(p, 2, 5.4e-6)
    # x toward +column, y up (toward -row).
    assert (dr, dc) == pytest.approx((0.2, 0.1))
    assert rot == pytest.approx(2e-4 + np.radians(0.01))
    still = without_motion(p)
    assert not np.any(still.mask_overlay) and not np.any(still.mask_rotation)
    assert still.etch_depth == pytest.approx(p.etch_depth)


def test_a_motion_beyond_the_rendered_window_falls_back_to_the_summed_surface():
    # On a part rendered with no margin beyond its footprint, a 3 um overlay moves the
    # mask past what was rendered: the render must not read padded values, and goes through the
    # process model's moved masks instead.
    case = filegen.make_case([], 5, design_px=36, field_px=80, instrument=QUIET)
    problem = _problem(case, ["mask_overlay"]).sub(10, 10, 40, margin_px=0)
    cam = np.array([0, 0, 0, 0, 0, 0.4e-6])
    far = {CAMERA.name: cam, "mask_overlay": np.array([0, 0, 0, 0, 3e-6, -3e-6])}
    params = problem.effects["mask_overlay"].apply(ProcessParams.ideal(), far["mask_overlay"])
    centre = ((case.levels.shape[0] - 1) / 2, (case.levels.shape[1] - 1) / 2)
    moved = problem.placement.in_frame_of(*mask_motion(params, 3, filegen.PITCH_M), centre)
    assert problem.instrument.covers(problem.placement, 0.4e-6)
    assert not problem.instrument.covers(moved, 0.4e-6)
    summed = problem.instrument.render(params, problem.placement, 0.4e-6)
    np.testing.assert_allclose(problem.render(far), summed, rtol=0, atol=1e-15)


def test_a_non_linear_surface_effect_renders_on_the_summed_surface():
    # A user's non-linear surface effect (here h + k h^2) must see the whole surface, not each
    # mask's part: the render then sums the moved masks on the fine grid first.
    case = filegen.make_case([], 5, design_px=36, field_px=80, instrument=QUIET)
    problem = _problem(case, ["mask_overlay", "batwing"])
    square = dataclasses.replace(problem.effects["batwing"], name="square", linear=False, fourier=None,
                                 apply=lambda h, v, step: h + v[0] * 1e6 * h ** 2)
    problem.effects["square"] = square
    model = {CAMERA.name: np.array([0, 0, 0, 0, 0, 0.4e-6]), "mask_overlay": np.array([0, 0, 0, 0, 0.2e-6, 0]),
             "square": np.array([0.05, 0.5e-6])}
    params = problem.effects["mask_overlay"].apply(ProcessParams.ideal(), model["mask_overlay"])
    fine = problem.instrument.fine_surface(params)
    expected = problem.instrument.sample(problem.instrument.camera_map(fine + 0.05e6 * fine ** 2, 0.4e-6),
                                         problem.placement)
    np.testing.assert_allclose(problem.render(model), expected, rtol=0, atol=1e-15)
    assert not effects_for("height", ["etch_depth"])[0].linear
    assert problem.effects["batwing"].linear


@pytest.mark.parametrize("values", [[0.1, 0.6e-6], [-0.3, 1.5e-6], [0.2, 2.8e-6]])
def test_batwing_as_a_fourier_factor_renders_as_its_taps_on_the_fine_grid(values):
    # The batwing multiplies the camera map's spectrum (its values then cost an inverse FFT, not
    # four new surfaces); the taps correlated on each mask's fine surface are the reference. The
    # FFT grid's pad is only the prefilter's guard: the widest batwing (2.8 um, taps of 113
    # cells) is served by the window's own margin past the pixels read.
    case = filegen.make_case(["mask_overlay"], 9011, design_px=36, field_px=80, instrument=QUIET)
    problem = _problem(case, ["mask_overlay", "batwing"])
    taps = dataclasses.replace(problem.effects["batwing"], fourier=None)
    reference = _problem(case, ["mask_overlay"])
    reference.effects["batwing"] = taps
    model = {CAMERA.name: np.array([0, 0, 0, 0, 0, 0.4e-6]), "mask_overlay": np.array([0.2e-6, 0, 0, 0.1e-6, 0, 0]),
             "batwing": np.array(values)}
    got, want = problem.render(model), reference.render(model)
    assert _rms_nm(want - reference.render({CAMERA.name: model[CAMERA.name],
                                            "mask_overlay": model["mask_overlay"]})) > 0.5
    np.testing.assert_allclose(got, want, rtol=0, atol=2e-12)
    # Taps reaching further than the pixels' guard fall back to the fine grid.
    half = _gaussian_taps(values[1], problem.instrument.step_m)[0].size // 2
    reach = problem.instrument.fourier_reach([problem.placement], 0.4e-6)
    assert half <= reach
    assert problem._fourier_factor(problem.effects["batwing"], values, reach) is not None
    assert problem._fourier_factor(problem.effects["batwing"], values, half - 1) is None


def test_a_large_field_renders_block_by_block_as_on_one_grid(monkeypatch):
    # A field above BLOCKED_FIELD_PX is rendered in blocks, each on its own fine grid with a
    # margin; stitched, they must be the one grid's map (placement refined, a mask moved, a
    # batwing), and a repeated model is read back, not rendered again.
    case = filegen.make_case(["mask_overlay"], 9011, design_px=36, field_px=90, instrument=QUIET)
    model = {CAMERA.name: np.array([0.1, -0.05, 2e-4, 1e-3, 0, 0.45e-6]),
             "mask_overlay": np.array([0.2e-6, 0, 0, 0.1e-6, 0, 0]), "batwing": np.array([0.1, 0.6e-6])}
    whole = _problem(case, ["mask_overlay", "batwing"]).render(model)
    monkeypatch.setattr(camera, "BLOCKED_FIELD_PX", 64)
    monkeypatch.setattr(camera, "RENDER_BLOCK_PX", 40)
    blocked = _problem(case, ["mask_overlay", "batwing"])
    got = blocked.render(model)
    np.testing.assert_allclose(got, whole, rtol=0, atol=1e-12)  # single-precision FFTs
    assert _rms_nm(whole) > 100
    assert blocked.render(model) is got
