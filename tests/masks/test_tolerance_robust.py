"""Robust design: the optimizer's perturbation hook and the masks process-sample provider."""

from importlib.metadata import entry_points

import numpy as np
import pytest

from doedesign.optimize import robust_value_and_grad
from doedesign.levels import level_step_m
from masks.tolerance.robust import ProcessPerturbation, process_perturbations
from masks.tolerance.spec import build_spec, nominal_process

STEP = level_step_m("fused_silica", 550e-9, 16)
DEPTHS = [STEP * 2 ** j for j in range(4)]


def _shift(a):
    return lambda h: (h + a, lambda g: g)


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
    worst = int(np.argmax(losses))
    value, grad = robust_value_and_grad(vg, x, [_shift(a) for a in shifts], "cvar", 1 / 3)
    assert value == pytest.approx(losses[worst]) and grad == pytest.approx(2 * (x + shifts[worst]))


def test_process_perturbation_adds_the_process_error_to_the_heights():
    rng = np.random.default_rng(0)
    levels = rng.integers(0, 16, (12, 12))
    h = -levels * STEP + rng.uniform(-0.3, 0.3, levels.shape) * STEP  # off-level continuous heights
    ideal = ProcessPerturbation(nominal_process(DEPTHS), STEP, 5.4e-6)
    hp, vjp = ideal(h)
    assert hp == pytest.approx(h, abs=1e-15)
    g = rng.standard_normal(h.shape)
    assert vjp(g) is g
    # All etches 4 % deep: every on-level height scales by 1.04 (levels are sums of the mask depths).
    spec = build_spec({"etch_depth": {"dist": "fixed", "value_rel": 0.04}}, DEPTHS, "t")
    deep = ProcessPerturbation(spec.params_for(spec.nominal_values(), nominal_process(DEPTHS)), STEP, 5.4e-6)
    hp, _ = deep(-levels * STEP)
    assert hp == pytest.approx(-levels * STEP * 1.04, abs=1e-13)


def test_provider_is_registered_and_seeded_like_the_tolerance_run():
    (entry,) = [e for e in entry_points(group="doe.perturbations") if e.name == "process"]
    provider = entry.load()
    a = provider(None, 3, 5, 5.4e-6)
    b = process_perturbations(None, 3, 5, 5.4e-6)
    assert len(a) == 3
    assert np.array_equal(a[2].params.mask_overlay, b[2].params.mask_overlay)
    assert not np.array_equal(a[0].params.mask_overlay, a[1].params.mask_overlay)
