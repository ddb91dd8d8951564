"""The nlopt driver: the L-BFGS size limit (nlopt issue #632) and no silent return of the start."""

import logging

import numpy as np
import pytest

from doedesign.errors import DoeError
from doedesign.optimizer.nlopt_driver import LARGE_ALGORITHM, LBFGS_MAX_VARIABLES, choose_algorithm, minimize


def separable_quadratic(n, spread=1.5, seed=0):
    """sum a_i (x_i - c_i)^2, |c_i| < spread, bounds [-1, 1]: the minimum is at clip(c, -1, 1)."""
    rng = np.random.default_rng(seed)
    a = rng.uniform(1.0, 4.0, n)
    c = rng.uniform(-spread, spread, n)

    def fun(x):
        d = x - c
        return float(np.sum(a * d * d)), 2.0 * a * d

    x_min = np.clip(c, -1.0, 1.0)
    return fun, x_min, float(np.sum(a * (x_min - c) ** 2))


def test_switch_rule(caplog):
    # PLIS forms -999 * n in a C int: the limit is the largest n for which that fits.
    assert 999 * LBFGS_MAX_VARIABLES <= 2**31 - 1 < 999 * (LBFGS_MAX_VARIABLES + 1)
    with caplog.at_level(logging.INFO, logger="doedesign.optimizer.nlopt_driver"):
        assert choose_algorithm("LD_LBFGS", LBFGS_MAX_VARIABLES) == "LD_LBFGS"
        assert not caplog.records
        assert choose_algorithm("LD_LBFGS", LBFGS_MAX_VARIABLES + 1) == LARGE_ALGORITHM == "LD_CCSAQ"
        assert "running LD_CCSAQ instead" in caplog.text
    for algorithm in ("LD_MMA", "LD_CCSAQ"):
        assert choose_algorithm(algorithm, 10 * LBFGS_MAX_VARIABLES) == algorithm


def test_small_quadratic_converges():
    # An interior minimum: nlopt's L-BFGS converges slowly when many bounds are active.
    fun, x_min, f_min = separable_quadratic(1000, spread=0.9)
    x, history = minimize(fun, np.zeros(1000), -1.0, 1.0, max_iter=60, ftol_rel=0)
    assert np.abs(x - x_min).max() < 1e-6
    assert history[-1] == pytest.approx(f_min, abs=1e-9)


def test_switched_run_scales_a_small_objective(monkeypatch):
    # Gains per variable of ~1e-9 (like heights in metres): plain MMA's curvature bound (>= 1e-5)
    # swamps them; the switched run scales the objective and reaches the closed-form minimum.
    import doedesign.optimizer.nlopt_driver as driver

    fun, x_min, f_min = separable_quadratic(2000)
    calls = []

    def tiny(x):
        calls.append(1)
        value, g = fun(x)
        return 1e-9 * value, 1e-9 * g

    x_plain, _ = minimize(tiny, np.zeros(2000), -1.0, 1.0, "LD_MMA", max_iter=40, ftol_rel=0)
    assert np.abs(x_plain - x_min).max() > 0.1
    monkeypatch.setattr(driver, "LBFGS_MAX_VARIABLES", 100)
    calls.clear()
    x, history = minimize(tiny, np.zeros(2000), -1.0, 1.0, "LD_LBFGS", max_iter=40, ftol_rel=0)
    assert np.abs(x - x_min).max() < 1e-4
    assert history[-1] == pytest.approx(1e-9 * f_min, rel=1e-6)
    # The start, evaluated for the scale, is not evaluated again.
    assert len(history) == len(calls) <= 40


def test_budget_stop_is_not_a_failure(caplog):
    # L-BFGS's line search asks past maxeval; the driver's stop comes back from nlopt as a failure.
    def fun(x):
        return float(np.sum((x - 0.3) ** 2)), 2 * (x - 0.3)

    with caplog.at_level(logging.INFO, logger="doedesign.optimizer.nlopt_driver"):
        _, history = minimize(fun, np.zeros(5), -1.0, 1.0, max_iter=2)
    assert len(history) == 2
    assert "stopped by the evaluation budget" in caplog.text
    assert not [r for r in caplog.records if r.levelno >= logging.WARNING]


def test_failure_before_any_step_raises():
    # An infinite gradient makes nlopt's L-BFGS fail after its first evaluation: the start must
    # not come back as if it were a result.
    def fun(x):
        return 1.0, np.full(x.shape, np.inf)

    with pytest.raises(DoeError, match="failed after 1 evaluation.*before any step"):
        minimize(fun, np.zeros(10), -1.0, 1.0, max_iter=20, desc="stage")


@pytest.mark.slow
def test_above_lbfgs_limit_converges(caplog):
    """2.2 million variables: raw LD_LBFGS fails after one evaluation; minimize switches and converges."""
    import nlopt

    n = 2_200_000
    fun, x_min, f_min = separable_quadratic(n)
    raw = nlopt.opt(nlopt.LD_LBFGS, n)
    raw.set_lower_bounds(-1.0)
    raw.set_upper_bounds(1.0)
    raw.set_maxeval(30)

    def raw_objective(x, grad):
        value, g = fun(x)
        grad[:] = g
        return value

    raw.set_min_objective(raw_objective)
    with pytest.raises((RuntimeError, getattr(nlopt, "runtime_error", RuntimeError))):
        raw.optimize(np.zeros(n))
    assert raw.get_numevals() == 1

    with caplog.at_level(logging.INFO, logger="doedesign.optimizer.nlopt_driver"):
        x, history = minimize(fun, np.zeros(n), -1.0, 1.0, "LD_LBFGS", max_iter=40, ftol_rel=0)
    assert "running LD_CCSAQ instead" in caplog.text
    assert len(history) <= 40
    # Start loss ~ 2.5 n; the closed-form minimum is reached to 1e-6 relative and 1e-4 per variable.
    assert history[-1] - f_min < 1e-6 * history[0]
    assert np.abs(x - x_min).max() < 1e-4
