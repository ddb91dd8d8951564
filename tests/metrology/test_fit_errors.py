"""Standard errors of the diagnosis's fits against ordinary least squares in closed form."""

import numpy as np

from metrology.diagnosis import engine as dg
from metrology.diagnosis.effects import Effect, Parameter
from metrology.diagnosis.noise import NoiseEstimate


class _Line(dg.Problem):
    """y = a x + b with white noise of known sigma (correlation area 1)."""

    def __init__(self, x, y, sigma):
        self.x, self.y = x, y
        self.noise = NoiseEstimate(sigma, 1.0, x.size)
        self.effects = {"line": Effect("line", "height", "surface",
                                       [Parameter("a", "1", -10.0, 10.0, 1.0), Parameter("b", "m", -10.0, 10.0, 1.0)],
                                       lambda h, v, s: h, "a straight line")}

    def residual(self, model):
        a, b = model["line"]
        return self.y - (a * self.x + b)


def test_standard_errors_are_those_of_ordinary_least_squares():
    rng = np.random.default_rng(7)
    x = np.linspace(-1.0, 3.0, 400)
    y = 2.0 * x + 1.0 + 0.05 * rng.standard_normal(x.size)
    problem = _Line(x, y, 0.05)
    fitted, _, errors = dg.fit_effects(problem, {"line": np.zeros(2)}, ["line"])
    at_optimum = dg.standard_errors(problem, fitted, ["line"])
    # Closed form: cov = s^2 (X^T X)^-1 with s^2 the residual variance over n - 2.
    design = np.column_stack([x, np.ones_like(x)])
    coef, rss, *_ = np.linalg.lstsq(design, y, rcond=None)
    expected = np.sqrt(np.diag(np.linalg.inv(design.T @ design)) * rss[0] / (x.size - 2))
    np.testing.assert_allclose(fitted["line"], coef, rtol=1e-6)
    np.testing.assert_allclose(errors["line"], expected, rtol=1e-3)
    np.testing.assert_allclose(at_optimum["line"], expected, rtol=1e-3)


def test_smooth_parameters_take_forward_differences_in_a_central_jacobian():
    """A kinked problem's Jacobian is central in its edge positions but forward in a parameter
    marked smooth (the instrument's transfer): one evaluation for that column, not two, and the
    fit still lands on the closed-form optimum."""
    rng = np.random.default_rng(3)
    x = np.linspace(-1.0, 3.0, 400)
    y = 2.0 * x + 1.0 + 0.05 * rng.standard_normal(x.size)
    calls = []

    class Kinked(_Line):
        kinks = True

        def residual(self, model):
            calls.append(1)
            return super().residual(model)

    plain, smooth = Kinked(x, y, 0.05), Kinked(x, y, 0.05)
    smooth.effects = {"line": Effect("line", "height", "surface",
                                     [Parameter("a", "1", -10.0, 10.0, 1.0, smooth=True),
                                      Parameter("b", "m", -10.0, 10.0, 1.0)],
                                     lambda h, v, s: h, "a straight line")}
    counts = {}
    for name, problem in (("plain", plain), ("smooth", smooth)):
        calls.clear()
        fitted, _, _ = dg.fit_effects(problem, {"line": np.zeros(2)}, ["line"])
        counts[name] = len(calls)
        coef, *_ = np.linalg.lstsq(np.column_stack([x, np.ones_like(x)]), y, rcond=None)
        np.testing.assert_allclose(fitted["line"], coef, rtol=1e-6)
    # Per Jacobian: 4 evaluations with both columns central, 3 with one forward column (its
    # base is the solver's last evaluation).
    assert counts["smooth"] < counts["plain"]
