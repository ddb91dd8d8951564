"""Robust design: the optimizer's perturbation hook and the smooth process samples it takes."""

import math
from importlib.metadata import entry_points

import numpy as np
import pytest

from doedesign import targets
from doedesign.camera import Camera
from doedesign.engine.psf import PSFEngine
from doedesign.errors import DoeError
from doedesign.levels import level_step_m
from doedesign.optimizer.losses import LossSpec, make_loss
from doedesign.optimizer.optimize import OptimizerSettings, design_doe, robust_value_and_grad
from masks.fabricated import fabricated_height
from masks.process import ProcessParams
from masks.tolerance.robust import process_perturbations, spec_perturbations
from masks.tolerance.smooth import SmoothProcess, soft_bits
from masks.tolerance.spec import build_spec

STEP = level_step_m("fused_silica", 550e-9, 16)
DEPTHS = np.array([STEP * 2 ** j for j in range(4)])
PITCH = 5.4e-6
# A spec the small elements below feel strongly (the study in the notebook uses milder values).
ROUGH_FAB = {"etch_depth": {"sigma_rel": 0.08}, "mask_overlay": {"sigma_um": 1.0}, "linewidth_bias": {"sigma_um": 0.3}}


def _shift(a):
    return lambda h: (h + a, lambda g: g)


def _blocky_levels(seed=1, blocks=8, size=3):
    """Random levels in size x size blocks, unetched border: edges on pixel boundaries, no 1-px lines."""
    lev = np.kron(np.random.default_rng(seed).integers(0, 16, (blocks, blocks)), np.ones((size, size), int))
    return np.pad(lev, size)


def test_mean_and_cvar_of_shifted_quadratics():
    """f(x) = |x|^2 at x + a_k: mean = |x|^2 + mean|a_k|^2 + 2 x.mean(a); gradient 2 (x + mean a)."""
    x = np.array([0.3, -0.2])
    shifts = [np.array([1.0, 0.0]), np.array([-0.5, 0.5]), np.array([0.0, 2.0])]

    def vg(h):
        return float(h @ h), 2 * h

    value, grad = robust_value_and_grad(vg, x, [_shift(a) for a in shifts])
    losses = [float((x + a) @ (x + a)) for a in shifts]
    assert value == pytest.approx(np.mean(losses))
    assert grad == pytest.approx(2 * (x + np.mean(shifts, axis=0)))
    # CVaR over the worst third = the single worst sample.
    value, grad = robust_value_and_grad(vg, x, [_shift(a) for a in shifts], "cvar", 1 / 3)
    worst = int(np.argmax(losses))
    assert value == pytest.approx(losses[worst]) and grad == pytest.approx(2 * (x + shifts[worst]))


def test_soft_bits_are_the_masks_on_levels_and_linear_between():
    levels = np.arange(16)
    bits, _ = soft_bits(-levels * STEP, STEP, 16)
    assert np.array_equal(bits.T, (levels[:, None] >> np.arange(4)) & 1)
    # Half-way between level 7 (0111) and 8 (1000) every bit is 1/2; level 16 wraps to 0.
    bits, slope = soft_bits(np.array([-7.5 * STEP, -15.25 * STEP]), STEP, 16)
    assert bits[:, 0] == pytest.approx([0.5] * 4)
    assert bits[:, 1] == pytest.approx([0.75] * 4)
    assert slope[:, 0] * -STEP == pytest.approx([-1, -1, -1, 1])
    assert np.dot(DEPTHS, bits[:, 0]) == pytest.approx(7.5 * STEP)


@pytest.mark.parametrize("name, params, tol_steps", [
    ("etch depth per mask", ProcessParams(etch_depth=DEPTHS * [1.03, 0.98, 1.05, 0.96]), 1e-9),
    ("etch gradient", ProcessParams(etch_depth=DEPTHS, etch_gradient=np.array([300.0, -200.0])), 1e-9),
    ("overlay", ProcessParams(etch_depth=DEPTHS, mask_overlay=np.array(
        [[0, 0, 0], [0.4e-6, -0.3e-6, 0], [-1.2e-6, 0.7e-6, 0], [0.2e-6, 2.1e-6, 0]])), 1e-5),
    ("rotation", ProcessParams(etch_depth=DEPTHS, mask_rotation=np.array([0, 0.05, -0.03, 0.02])), 1e-4),
    # First order in the bias: inner corners differ by b^2 of the deepest mask (b = 0.074 px).
    ("bias, growth", ProcessParams(etch_depth=DEPTHS, linewidth_bias=np.array([0.2, 0.3, 0.1, 0.4]) * 1e-6), 0.12),
    ("bias, shrink", ProcessParams(etch_depth=DEPTHS, linewidth_bias=-np.array([0.2, 0.3, 0.1, 0.4]) * 1e-6), 0.12),
])
def test_smooth_sample_on_levels_matches_the_process_model(name, params, tol_steps):
    """On levels, the smooth map is the process model's area coverage (8 x 8 sub-samples per pixel)."""
    levels = _blocky_levels()
    made, _ = SmoothProcess(params, DEPTHS, STEP, PITCH)(-levels * STEP)
    truth = fabricated_height(levels, PITCH, params, oversample=1, process_upsample=8)
    effect = np.abs(truth + levels * STEP).max()
    assert effect > 0.05 * STEP, "the case must move the surface"
    assert np.abs(made - truth).max() < tol_steps * STEP
    assert np.abs(made - truth).max() < 0.1 * effect


def test_ideal_sample_leaves_continuous_heights_alone():
    h = -np.random.default_rng(0).uniform(0, 16, (20, 20)) * STEP
    made, vjp = SmoothProcess(ProcessParams(etch_depth=DEPTHS), DEPTHS, STEP, PITCH)(h)
    assert made == pytest.approx(h, abs=1e-15)
    g = np.random.default_rng(1).standard_normal(h.shape)
    assert vjp(g) == pytest.approx(g, abs=1e-12)


def _small_bayer(n=20, window=12):
    cam = Camera(aperture_diameter_m=n * PITCH, focus_distance_m=math.inf, sensor_distance_m=50e-3 * n / 1600,
                 window_shape=(window, window), axis_pixel=(window // 2, window // 2))
    return cam, targets.bayer(cam)


def test_robust_objective_gradient_matches_finite_differences():
    """Mean loss over 3 process samples (overlay, bias, depth, gradient, rotation) through the PSF
    engine's adjoint, against central differences along random directions."""
    cam, target = _small_bayer()
    n = 20
    engine = PSFEngine(cam, PITCH, (n, n), "fused_silica", target.wavelengths_m, target.depths_m)
    loss = make_loss(target, LossSpec.parse("l1,energy"))
    spec = build_spec({**ROUGH_FAB, "etch_gradient": {"sigma_percent_per_mm": 5},
                       "mask_rotation": {"sigma_urad": 2000}}, DEPTHS, "t")
    perts = spec_perturbations(spec, 3, 0, DEPTHS, STEP, PITCH)
    rng = np.random.default_rng(2)
    h = -rng.uniform(0.5, 14.5, (n, n)) * STEP

    def f(x):
        return robust_value_and_grad(lambda y: engine.value_and_grad(y, loss), x, perts)

    _, grad = f(h)
    for _ in range(3):
        v = rng.standard_normal(h.shape)
        eps = 1e-4 * STEP
        fd = (f(h + eps * v)[0] - f(h - eps * v)[0]) / (2 * eps)
        assert float(np.sum(grad * v)) == pytest.approx(fd, rel=1e-4)


def test_robust_design_beats_the_plain_one_on_its_own_objective():
    cam, target = _small_bayer(n=24, window=12)
    spec = build_spec(ROUGH_FAB, DEPTHS, "t")
    perts = spec_perturbations(spec, 4, 0, DEPTHS, STEP, PITCH)
    settings = OptimizerSettings(max_iter=40, anneal_iter=4, init="zeros", objective="softmin")
    loss = LossSpec.parse("l1,energy")
    runs = {name: design_doe(target, cam, PITCH, (24, 24), loss=loss, settings=settings, perturbations=p)
            for name, p in (("plain", None), ("robust", perts))}
    engine = PSFEngine(cam, PITCH, (24, 24), "fused_silica", target.wavelengths_m, target.depths_m)
    from doedesign.optimizer.objectives import plane_weights, softmin_loss

    objective = softmin_loss(target, plane_weights(target, None), settings.softmin_tau)

    def robust_loss(h):
        return robust_value_and_grad(lambda y: engine.value_and_grad(y, objective), h, perts)[0]

    for heights in ("continuous_height_m",):
        plain, robust = (robust_loss(getattr(runs[k], heights)) for k in ("plain", "robust"))
        assert robust < plain
    plain, robust = (robust_loss(runs[k].design.height_m) for k in ("plain", "robust"))
    assert robust < plain


def test_maxmin_objective_refuses_perturbations():
    cam, target = _small_bayer()
    with pytest.raises(DoeError, match="maxmin"):
        design_doe(target, cam, PITCH, (20, 20), settings=OptimizerSettings(objective="maxmin"),
                   perturbations=[_shift(0.0)])


def test_provider_is_registered_and_seeded_like_the_tolerance_run():
    (entry,) = [e for e in entry_points(group="doe.perturbations") if e.name == "process"]
    provider = entry.load()
    a = provider(None, 3, 5, PITCH)
    b = process_perturbations(None, 3, 5, PITCH)
    assert len(a) == 3 and all(isinstance(p, SmoothProcess) for p in a)
    assert np.array_equal(a[2].params.mask_overlay, b[2].params.mask_overlay)
    assert not np.array_equal(a[0].params.mask_overlay, a[1].params.mask_overlay)


def test_doe_design_robust_runs_the_soft_min_over_process_samples(tmp_path):
    """`doe design bayer --robust SPEC`: the default max-min Bayer objective becomes the soft
    minimum (which has a robust form) and the report counts the process samples."""
    import json

    from doedesign.cli import main

    (tmp_path / "run.toml").write_text(
        "[camera]\nwindow_shape = [12, 12]\naxis_pixel = [6, 6]\nsensor_distance_m = 0.0006\n"
        "focus_distance_m = inf\n")
    (tmp_path / "fab.toml").write_text("[etch_depth]\nsigma_rel = 0.05\n[mask_overlay]\nsigma_um = 0.5\n")
    out = tmp_path / "d.npz"
    code = main(["design", "bayer", "--config", str(tmp_path / "run.toml"), "--size", "20", "--iterations", "3",
                 "--anneal-iterations", "1", "--init", "zeros", "--out", str(out), "--robust",
                 str(tmp_path / "fab.toml"), "--robust-samples", "2"])
    report = json.loads((tmp_path / "report.json").read_text())
    assert code == 0 and out.is_file()
    assert report["robust_samples"] == 2 and report["objective"] == "softmin"


@pytest.mark.parametrize("warm_start", [False, True])
def test_nominal_vs_robust_pairs_the_two_designs_on_the_same_samples(tmp_path, warm_start):
    from masks.tolerance.robust import nominal_vs_robust

    r = nominal_vs_robust(16, 12, {"etch_depth": {"sigma_rel": 0.06}}, tmp_path, robust_samples=2, eval_samples=3,
                          iterations=2, anneal_iterations=1, init="zeros", warm_start=warm_start)
    plain, robust = (np.array(r[k]["samples"]) for k in ("nominal", "robust"))
    assert plain.size == robust.size == 3
    assert r["paired"]["mean_difference"] == pytest.approx(np.mean(robust - plain))
    assert r["paired"]["robust_better_fraction"] == pytest.approx(np.mean(robust > plain))
    assert r["nominal"]["threshold"] == r["robust"]["threshold"]
