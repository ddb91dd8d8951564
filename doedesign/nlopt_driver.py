"""The nlopt driver: minimize ``fun(x) -> (value, grad)`` over a bounded array, keeping the best point.

Every stage of :func:`doedesign.optimize.design_doe` (continuous, reweighting, multi-start,
annealing) runs through :func:`minimize`. The evaluation budget is enforced inside the objective,
because nlopt's L-BFGS can evaluate past ``maxeval``; round-off and nlopt's generic failures keep
the best point evaluated instead of raising.
"""

from __future__ import annotations

import logging
from collections.abc import Callable

import numpy as np
from numpy.typing import ArrayLike

from .errors import DoeError
from .progress import Progress

__all__ = ["ALGORITHMS", "StageCallback", "minimize"]

log = logging.getLogger(__name__)

# Gradient algorithms of nlopt that take bounds.
ALGORITHMS = ("LD_LBFGS", "LD_MMA", "LD_CCSAQ")
# callback(evaluation, loss, height_m); True stops the stage.
StageCallback = Callable[[int, float, np.ndarray], bool | None]


def minimize(fun: Callable[[np.ndarray], tuple[float, np.ndarray]], x0: np.ndarray, lower: ArrayLike,
             upper: ArrayLike, algorithm: str = "LD_LBFGS", max_iter: int = 100, ftol_rel: float = 1e-7,
             max_time_s: float | None = None, callback: StageCallback | None = None,
             desc: str = "optimize") -> tuple[np.ndarray, list[float]]:
    """Minimize ``fun(x) -> (value, grad)`` over a bounded array with nlopt.

    Parameters
    ----------
    callback : callable, optional
        ``callback(evaluation, value, x)``; returning True stops the run.

    Returns
    -------
    x_best : ndarray, the best point evaluated
    history : list of float, the objective at every evaluation
    """
    import nlopt

    shape = x0.shape
    n = x0.size
    opt = nlopt.opt(getattr(nlopt, algorithm), n)
    lo = np.broadcast_to(np.asarray(lower, float), shape).ravel()
    hi = np.broadcast_to(np.asarray(upper, float), shape).ravel()
    opt.set_lower_bounds(lo)
    opt.set_upper_bounds(hi)
    opt.set_maxeval(int(max_iter))
    if ftol_rel:
        opt.set_ftol_rel(float(ftol_rel))
    if max_time_s:
        opt.set_maxtime(float(max_time_s))
    history = []
    best = {"value": np.inf, "x": np.clip(x0.ravel(), lo, hi).copy()}

    with Progress(max_iter, desc=desc) as bar:
        def objective(x, grad):
            # nlopt's L-BFGS can evaluate past maxeval (in a line search, or after a failure that
            # it retries): the budget is enforced here, before any further evaluation.
            if len(history) >= max_iter:
                raise nlopt.ForcedStop
            value, g = fun(x.reshape(shape))
            if not np.isfinite(value):
                raise DoeError(f"{desc}: the loss became {value}")
            history.append(float(value))
            if value < best["value"]:
                best["value"], best["x"] = float(value), x.copy()
            if grad.size:
                grad[:] = np.asarray(g, dtype=float).ravel()
            bar.update(1, status=f"loss {value:.5g}")
            if callback is not None and callback(len(history), float(value), x.reshape(shape)):
                opt.force_stop()
            return float(value)

        opt.set_min_objective(objective)
        try:
            opt.optimize(best["x"].copy())
        except nlopt.RoundoffLimited:
            log.info("%s: stopped by round-off; keeping the best point", desc)
        except nlopt.ForcedStop:
            log.info("%s: stopped by the callback or the evaluation budget", desc)
        except (RuntimeError, getattr(nlopt, "runtime_error", RuntimeError)) as exc:
            # nlopt's generic failure (e.g. a line search that cannot progress): keep the best point.
            if not history:
                raise DoeError(f"{desc}: nlopt failed before the first evaluation ({exc})") from None
            log.warning("%s: nlopt stopped with a failure after %d evaluations; keeping the best point",
                        desc, len(history))
        result = opt.last_optimize_result()
    log.info("%s: %d evaluations, loss %.6g -> %.6g (nlopt result %s)", desc, len(history),
             history[0] if history else np.nan, best["value"], result)
    return best["x"].reshape(shape), history
