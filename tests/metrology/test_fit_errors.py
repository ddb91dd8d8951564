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
