"""The measurement model against analytic moments and the independent file generator."""

import numpy as np
import pytest

from masks.process import ProcessParams
from metrology.matching.instrument import InstrumentModel, Placement, footprint_kernel
from metrology.matching.level import Leveller, levelling_basis, robust_valid

import filegen

QUIET = dict(noise_m=0.0, n_spikes=0, invalid_fraction=0.0, tilt_rad=np.zeros(2), piston_m=0.0)


def _moments(kernel, step):
    k = kernel.shape[0] // 2
    x = np.arange(-k, k + 1) * step
    cov = np.empty((2, 2))
    for a, xa in enumerate((x[:, None], x[None, :])):
        for b, xb in enumerate((x[:, None], x[None, :])):
            cov[a, b] = np.sum(kernel * xa * xb)
    return np.array([np.sum(kernel * x[:, None]), np.sum(kernel * x[None, :])]), cov


@pytest.mark.parametrize("angle_deg,flip", [(0.0, False), (0.8, True), (30.0, False)])
def test_kernel_moments_are_pixel_box_plus_blur(angle_deg, flip):
    # A uniform parallelogram footprint M [-1/2, 1/2]^2 has covariance M M^T / 12; the blur adds
    # sigma^2 I, the fine cell step^2 / 12 I. Centred, unit sum.
    pitch, step, sigma = 5.4e-6, 5.4e-6 / 40, 0.35e-6
    a = np.radians(angle_deg)
    rot = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    matrix = 1.1e-6 / pitch * rot @ np.diag([1.0, -1.0 if flip else 1.0]) @ np.diag([1.0, 1.003])
    kern = footprint_kernel(matrix, pitch, step, sigma)
    mean, cov = _moments(kern, step)
    m = matrix * pitch
    expect = m @ m.T / 12 + (sigma ** 2 + step ** 2 / 12) * np.eye(2)
    assert kern.sum() == pytest.approx(1.0)
    assert np.abs(mean).max() < 1e-3 * step
    assert np.allclose(cov, expect, rtol=2e-3, atol=1e-4 * 1.1e-6 ** 2)


@pytest.mark.parametrize("sigma_m", [0.05e-6, 0.4e-6, 1.5e-6])
def test_camera_map_is_the_kernel_correlation_then_the_spline_prefilter(sigma_m):
    # The one-FFT map against the two-step route: correlate with the footprint kernel (edge
    # values beyond the window; SciPy's own float64 correlation, by FFT for the wide kernels:
    # equal to the direct sum to ~1e-16 relative), then SciPy's cubic spline prefilter; equal
    # where the camera samples (the window's margin aside), to float32 rounding of ~1 um heights.
    from scipy import ndimage as ndi
    from scipy.signal import correlate

    from masks.process import ProcessParams

    rng = np.random.default_rng(2)
    levels = rng.integers(0, 16, (24, 24))
    pl = Placement(np.array([[0.2, 0.01], [-0.01, 0.2]]), np.array([6.3, 7.1]))
    model = InstrumentModel(levels, 5.4e-6, (40, 40), pl)
    fine = model.fine_surface(ProcessParams.ideal().copy(linewidth_bias=np.array([0, 0.1e-6, 0, -0.2e-6])))
    kernel = footprint_kernel(pl.matrix, 5.4e-6, model.step_m, sigma_m)
    k = kernel.shape[0] // 2
    direct = ndi.spline_filter(correlate(np.pad(fine, k, mode="edge"), kernel, mode="valid",
                                                       method="direct" if k < 20 else "fft"),
                               order=3, mode="nearest")
    fast = model.camera_map(fine, sigma_m)
    m = 3 * model.upsample - k - 30
    assert fast.shape == fine.shape
    assert np.abs(fast - direct)[m:-m, m:-m].max() < 1e-12
    np.testing.assert_allclose(model.sample(fast, pl), model.sample(direct, pl), rtol=0, atol=1e-12)


def test_fine_surface_reuses_unchanged_masks_exactly():
    # The cache of each mask's etch: a change of one mask's overlay gives the same surface as
    # a fresh model (nothing stale), and the other masks' etches are not recomputed.
    from masks.process import ProcessParams

    rng = np.random.default_rng(4)
    levels = rng.integers(0, 16, (20, 20))
    pl = Placement(np.array([[0.2, 0.0], [0.0, 0.2]]), np.array([5.0, 5.0]))
    model = InstrumentModel(levels, 5.4e-6, (40, 40), pl)
    base = ProcessParams.ideal().copy(sidewall_slope=0.5e-6)
    model.fine_surface(base)
    overlay = np.zeros((4, 3))
    overlay[2, :2] = [0.13e-6, -0.05e-6]
    moved = base.copy(mask_overlay=overlay)
    calls = []
    import masks.process as mp
    real = mp.mask_etch
    try:
        mp.mask_etch = lambda *a, **kw: calls.append(a[3]) or real(*a, **kw)
        cached = model.fine_surface(moved)
    finally:
        mp.mask_etch = real
    assert calls == [2]
    fresh = InstrumentModel(levels, 5.4e-6, (40, 40), pl).fine_surface(moved)
    np.testing.assert_array_equal(cached, fresh)


def test_a_trenched_etch_is_the_process_models_and_a_change_of_its_depths_prints_nothing():
    # The model's etch of a trenched mask is D E + t F(w) (linear in both depths); against
    # masks.process printing each variant itself, with loading and a gradient that shape the
    # depth: the same to rounding. A change of the etch or trench depth prints no mask; a new
    # width prints once.
    import masks.process as mp
    from masks.process import ProcessParams

    rng = np.random.default_rng(7)
    levels = rng.integers(0, 16, (20, 20))
    pl = Placement(np.array([[0.2, 0.0], [0.0, 0.2]]), np.array([5.0, 5.0]))
    model = InstrumentModel(levels, 5.4e-6, (40, 40), pl)
    trench = np.zeros((4, 2))
    trench[1] = [30e-9, 0.4e-6]
    base = ProcessParams.ideal().copy(microtrenching=trench, etch_loading=0.1, etch_gradient=np.array([20.0, -10.0]))
    model._etch(base, 1, 2)
    calls = []
    real = mp.mask_etch
    variants = []
    for depth, t, w in [(160e-9, 30e-9, 0.4e-6), (150e-9, 55e-9, 0.4e-6), (140e-9, 55e-9, 0.7e-6)]:
        depths = np.array(base.etch_depth, float)
        depths[1] = depth
        trench = np.array(base.microtrenching, float)
        trench[1] = [t, w]
        variants.append(base.copy(etch_depth=depths, microtrenching=trench))
    try:
        mp.mask_etch = lambda *a, **kw: calls.append(a[3]) or real(*a, **kw)
        got = [model._etch(p, 1, 2) for p in variants]
    finally:
        mp.mask_etch = real
    assert len(calls) == 1  # the new width's trench only
    for p, etch in zip(variants, got):
        want = real(levels, 5.4e-6, p, 1, step_m=model.step_m, region=model.region, pad_px=2)
        # The loading's depth map is single precision in the process model: 1e-7 of the etch.
        assert np.abs(etch - want).max() < 1e-6 * np.abs(want).max()
    # The check can fail: the trench is a visible part of the etch.
    assert np.abs(got[1] - got[0]).max() > 0.1 * 25e-9


def test_leveller_removes_plane_and_curvature_only():
    shape = (40, 50)
    rng = np.random.default_rng(0)
    valid = rng.random(shape) > 0.1
    basis = levelling_basis(shape, curvature=True)
    plane = (basis @ np.array([3.0, -2.0, 0.5, 0.7])).reshape(shape)
    signal = rng.standard_normal(shape)
    out = Leveller(shape, valid, curvature=True)((plane + signal)[valid])
    ref = Leveller(shape, valid, curvature=True)(signal[valid])
    assert np.allclose(out, ref)
    assert np.std(out) > 0.95 * np.std(signal)


def test_robust_rule_excludes_spikes_not_noise():
    rng = np.random.default_rng(1)
    r = rng.standard_normal((100, 100)) * 1e-9
    r[10, 10] += 3e-7
    r[50, 60] -= 1e-6
    keep = robust_valid(r, np.ones(r.shape, bool))
    assert not keep[10, 10] and not keep[50, 60]
    assert keep.sum() >= r.size - 10


def _truth_params(truth):
    p = ProcessParams.ideal()
    if "mask_overlay" in truth:
        ov = np.zeros((4, 3))
        ov[truth["mask_overlay"]["mask"], :2] = truth["mask_overlay"]["shift_m"]
        p = p.copy(mask_overlay=ov)
    if "linewidth_bias" in truth:
        p = p.copy(linewidth_bias=truth["linewidth_bias"]["bias_m"])
    if "etch_depth" in truth:
        p = p.copy(etch_depth=p.etch_depth * (1 + truth["etch_depth"]["error"]))
    return p


@pytest.mark.parametrize("effects,seed", [([], 3), (["mask_overlay"], 5), (["linewidth_bias"], 3),
                                          (["etch_depth"], 7)])
def test_model_renders_the_independent_camera_to_its_noise(effects, seed):
    # Truth placement and process: the only difference left is the generator's noise, spikes
    # and invalid pixels (excluded by the robust rule) and its tilt (levelled out).
    case = filegen.make_case(effects, seed, design_px=36, field_px=120)
    inst = case.instrument
    pl = Placement(inst["matrix"], inst["offset"])
    model = InstrumentModel(case.levels, filegen.PITCH_M, case.height_m.shape, pl)
    r = case.height_m - model.render(_truth_params(case.truth), pl, inst["blur_sigma_m"])
    valid = np.isfinite(r)
    first = np.full(r.shape, np.nan)
    first[valid] = Leveller(r.shape, valid)(r[valid])
    keep = robust_valid(first, valid)
    rms = np.std(Leveller(r.shape, keep)(r[keep]))
    assert rms < 1.3 * inst["noise_m"]
    # A placement off by 0.03 camera pixels is visible far above the noise.
    off = pl.refined([0.03 * inst["pixel_m"] / filegen.PITCH_M, 0, 0, 0, 0], r.shape)
    r2 = case.height_m - model.render(_truth_params(case.truth), off, inst["blur_sigma_m"])
    assert np.std(Leveller(r.shape, keep)(r2[keep])) > 2 * rms


def test_generator_is_independent_of_the_model():
    # The generator must not import the model it tests (only the file writers and Design).
    import ast
    import inspect

    tree = ast.parse(inspect.getsource(filegen))
    names = {n.module for n in ast.walk(tree) if isinstance(n, ast.ImportFrom)}
    names |= {a.name for n in ast.walk(tree) if isinstance(n, ast.Import) for a in n.names}
    assert not any(m.startswith(("masks", "metrology.diagnosis", "metrology.matching")) for m in names)


def test_screening_crop_renders_the_whole_windows_pixels_under_the_same_nuisance():
    # A crop refined about its whole window's centre reads the same nuisance values alike:
    # under a rotated, shifted, rescaled placement, its pixels are the whole window's.
    from masks.process import ProcessParams
    from metrology.diagnosis.camera import CAMERA, CameraHeightProblem
    from metrology.diagnosis.effects import effects_for

    case = filegen.make_case(["mask_overlay"], 5, design_px=36, field_px=100)
    inst = case.instrument
    pl = Placement(np.array(inst["matrix"]), np.array(inst["offset"]))
    whole = CameraHeightProblem(case.levels, filegen.PITCH_M, case.height_m, pl, ProcessParams.ideal(),
                                effects_for("height", ["mask_overlay"]))
    part = whole.crop(48)
    model = {CAMERA.name: np.array([0.3, -0.2, 2e-3, 1e-3, -2e-3, 0.45e-6]),
             "mask_overlay": np.array([0, 0, 0.1e-6, 0, 0, -0.2e-6])}
    r0 = int(np.rint((part.placement.offset - pl.offset) @ np.linalg.inv(pl.matrix).T)[0])
    c0 = int(np.rint((part.placement.offset - pl.offset) @ np.linalg.inv(pl.matrix).T)[1])
    assert part.measured.shape == (48, 48)
    np.testing.assert_allclose(part.render(model), whole.render(model)[r0:r0 + 48, c0:c0 + 48], rtol=0, atol=1e-12)


def test_a_held_batwing_renders_as_a_fitted_one_and_is_no_candidate():
    # A calibration's batwing (amplitude, sigma) is rendered with every model, crops included,
    # exactly as the same values fitted as a nuisance; it is neither fitted nor screened.
    from masks.process import ProcessParams
    from metrology.diagnosis.camera import CAMERA, CameraHeightProblem
    from metrology.diagnosis.camera_nuisance import BATWING
    from metrology.diagnosis.effects import effects_for

    case = filegen.make_case([], 7, design_px=36, field_px=100)
    inst = case.instrument
    pl = Placement(np.array(inst["matrix"]), np.array(inst["offset"]))
    values = (0.1, 0.3e-6)
    args = (case.levels, filegen.PITCH_M, case.height_m, pl, ProcessParams.ideal(), effects_for("height"))
    held = CameraHeightProblem(*args, batwing=values)
    fitted = CameraHeightProblem(*args, batwing=True)
    plain = CameraHeightProblem(*args)
    cam = {CAMERA.name: np.array([0.1, -0.1, 1e-3, 0, 0, 0.3e-6, 0.8])}
    assert BATWING not in held.effects and BATWING not in held.nuisance
    np.testing.assert_allclose(held.render(cam), fitted.render({**cam, BATWING: np.array(values)}), rtol=0,
                               atol=1e-15)
    assert np.abs(held.render(cam) - plain.render(cam)).max() > 1e-9
    np.testing.assert_allclose(held.crop(48).render(cam), fitted.crop(48).render({**cam, BATWING: np.array(values)}),
                               rtol=0, atol=1e-15)


# The fine grid's discretization, against the same render on a grid 4x finer (a convergence test):
# what the default step (FINE_STEP_M, 0.2 um, with the cells' first moments) costs. Here: the ideal
# element 0.004-0.10 nm rms, a trench 0.03-0.11 nm, batwing 0.04-0.28 nm, 80 nm bias 0.09-0.30 nm,
# a 0.3 um sidewall ramp 0.01-0.22 nm. Without the moments the bias differs by 0.75-2.1 nm and the
# ramp by 0.47-1.3 nm; at 0.25 um the bias by up to 0.59 nm, the ramp 0.47, the trench 0.23, the
# batwing 0.45. (At the former 0.125 um, without moments: bias 0.25-0.7 nm.) Under an objective the
# footprint's continuous spectrum is used: the discrete kernel's, whose aliases the objective's
# transfer on the grid passes, left the sharp full pixel's trench at 0.26 nm.
_TRANSFERS = {"point sampling": (0.25e-6, 0.0, 0.0), "full pixel": (0.4e-6, 1.0, 0.0), "CSI": (0.05e-6, 0.7, 0.45),
              "sharp full pixel": (0.022e-6, 0.98, 0.26)}


@pytest.mark.parametrize("transfer", list(_TRANSFERS))
def test_the_default_fine_step_renders_within_its_discretization_budget(transfer):
    import sys
    from pathlib import Path

    from metrology.matching.transfer import LateralTransfer

    sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
    from benchmarks.bench_fine_step import cases, rotated_field

    sigma, fill, na = _TRANSFERS[transfer]
    lateral = LateralTransfer(sigma, fill, na=na, wavelength_m=0.58e-6)
    levels, placement, shape = rotated_field(20, 40, 4.0)
    default = InstrumentModel(levels, filegen.PITCH_M, shape, placement)
    fine = InstrumentModel(levels, filegen.PITCH_M, shape, placement, step_m=default.step_m / 4)
    models = cases()
    limits = {"trench": 0.2e-9, "batwing": 0.35e-9, "80 nm bias": 0.4e-9, "sidewall ramp": 0.3e-9}
    for name, limit in limits.items():
        params, surface = models[name]
        d = default.render(params, placement, lateral, surface) - fine.render(params, placement, lateral, surface)
        assert np.std(d) < limit, (name, np.std(d))
    # Without the moments, the same step misses the limits on edges inside a cell.
    plain = InstrumentModel(levels, filegen.PITCH_M, shape, placement, moments=False)
    params, _ = models["80 nm bias"]
    d = plain.render(params, placement, lateral) - fine.render(params, placement, lateral)
    assert np.std(d) > limits["80 nm bias"]
