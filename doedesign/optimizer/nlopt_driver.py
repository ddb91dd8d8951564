"""The nlopt driver: minimize ``fun(x) -> (value, grad)`` over a bounded array, keeping the best point.

Every stage of :func:`doedesign.optimizer.optimize.design_doe` (continuous, reweighting, multi-start,
annealing) runs through :func:`minimize`. The evaluation budget is enforced inside the objective,
because nlopt's L-BFGS can evaluate past ``maxeval``; round-off and nlopt's generic failures keep
the best point evaluated instead of raising, except a failure before any step (the start returned
unoptimized), which raises.

nlopt's LD_LBFGS (Luksan's PLIS) computes ``-999 * n`` in a C ``int`` before its first step
(nlopt issue #632, open in 2.11): above :data:`LBFGS_MAX_VARIABLES` free variables it overflows,
and every run fails after the first evaluation. :func:`choose_algorithm` runs those sizes with
LD_CCSAQ instead (the paper setting's 4500 px DOE has about 7.9 million free heights). At such
sizes nlopt's own work per evaluation, on the host, is what a GPU design waits on: on a 16-core
H100 host, 1 million variables cost LD_LBFGS about 0.2 s, LD_MMA 0.14 s and LD_CCSAQ 0.07 s per
evaluation, and at 1600 px both MMA and CCSAQ reach the same design (weakest colour 0.2622).
"""

from __future__ import annotations

import logging
from collections.abc import Callable

import numpy as np
from numpy.typing import ArrayLike

from ..errors import DoeError
from ..progress import Progress

__all__ = ["ALGORITHMS", "LARGE_ALGORITHM", "LBFGS_MAX_VARIABLES", "LBFGS_SHORT_MEMORY_FROM", "LBFGS_VECTOR_STORAGE",
           "StageCallback", "choose_algorithm", "minimize"]

log = logging.getLogger(__name__)

# Gradient algorithms of nlopt that take bounds.
ALGORITHMS = ("LD_LBFGS", "LD_MMA", "LD_CCSAQ")
#: The largest n for which PLIS's int product 999 * n does not overflow (2,149,633).
LBFGS_MAX_VARIABLES = (2**31 - 1) // 999
#: What runs LD_LBFGS's problems above that size: bounded, gradient-based, no O(n * m) int products,
#: and the cheapest per evaluation of nlopt's bounded gradient methods (see the module docstring).
LARGE_ALGORITHM = "LD_CCSAQ"
# L-BFGS's stored correction pairs from LBFGS_SHORT_MEMORY_FROM free variables on (nlopt's
# default, 10, below). Its own work per evaluation grows with them and runs on the host while a
# GPU waits: at 1600 px (1.0 M free heights) the demo's Bayer design took 22.9 s on a 2-core CPU
# with 10 and 20.3 s with 5, its weakest colour 0.2632 and 0.2635 (5 is liblbfgs's default; 3 to
# 20 the usual range). Small problems keep 10: there the evaluations cost more than nlopt, and
# a 32 x 32 spot array converged less far in its budget with 5.
LBFGS_VECTOR_STORAGE = 5
LBFGS_SHORT_MEMORY_FROM = 250_000
# callback(evaluation, loss, height_m); True stops the stage.
StageCallback = Callable[[int, float, np.ndarray], bool | None]


def choose_algorithm(algorithm: str, n: int) -> str:
    """The nlopt algorithm that can run ``algorithm``'s problem with ``n`` variables.

    LD_LBFGS above :data:`LBFGS_MAX_VARIABLES` becomes :data:`LARGE_ALGORITHM` (logged);
    everything else is returned unchanged.
    """
    if algorithm == "LD_LBFGS" and n > LBFGS_MAX_VARIABLES:
        log.info("%d free variables exceed nlopt LD_LBFGS's limit of %d (an int overflow, nlopt issue #632): "
                 "running %s instead", n, LBFGS_MAX_VARIABLES, LARGE_ALGORITHM)
        return LARGE_ALGORITHM
    return algorithm


def minimize(fun: Callable[[np.ndarray], tuple[float, np.ndarray]], x0: np.ndarray, lower: ArrayLike,
             upper: ArrayLike, algorithm: str = "LD_LBFGS", max_iter: int = 100, ftol_rel: float = 1e-7,
             max_time_s: float | None = None, callback: StageCallback | None = None,
             desc: str = "optimize") -> tuple[np.ndarray, list[float]]:
    """Minimize ``fun(x) -> (value, grad)`` over a bounded array with nlopt.

    Parameters
    ----------
    algorithm : str
        An nlopt gradient algorithm. LD_LBFGS above its size limit runs as LD_CCSAQ
        (:func:`choose_algorithm`) on the objective scaled to a unit mean gain per variable
        (``_unit_gain_scale``); the history and the callback see the unscaled values.
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
    requested, algorithm = algorithm, choose_algorithm(algorithm, n)
    opt = nlopt.opt(getattr(nlopt, algorithm), n)
    # One bound for every variable stays a number: nlopt fills its own arrays, and no host array
    # of millions of equal values is built and copied in.
    lo, hi = (np.asarray(b, float) for b in (lower, upper))
    lo, hi = (b if b.ndim == 0 else np.broadcast_to(b, shape).ravel() for b in (lo, hi))
    opt.set_lower_bounds(float(lo) if lo.ndim == 0 else lo)
    opt.set_upper_bounds(float(hi) if hi.ndim == 0 else hi)
    opt.set_maxeval(int(max_iter))
    if algorithm == "LD_LBFGS" and n >= LBFGS_SHORT_MEMORY_FROM:
        opt.set_vector_storage(LBFGS_VECTOR_STORAGE)
    if ftol_rel:
        opt.set_ftol_rel(float(ftol_rel))
    if max_time_s:
        opt.set_maxtime(float(max_time_s))
    history: list[float] = []
    best = {"value": np.inf, "x": np.clip(x0.ravel(), lo, hi).copy()}
    x_start = best["x"].copy()
    first, scale = None, 1.0
    # nlopt reports a ForcedStop raised in the objective as a generic failure: remember ours.
    stopped = {"budget": False}
    if algorithm != requested:
        first = fun(x_start.reshape(shape))
        scale = _unit_gain_scale(np.asarray(first[1], float).ravel(), lo, hi)
        log.info("%s: %s objective scaled by %.3g (unit mean gain per variable)", desc, algorithm, scale)

    with Progress(max_iter, desc=desc) as bar:
        def objective(x, grad):
            # nlopt's L-BFGS can evaluate past maxeval (in a line search, or after a failure that
            # it retries): the budget is enforced here, before any further evaluation.
            if len(history) >= max_iter:
                stopped["budget"] = True
                raise nlopt.ForcedStop
            # The switched run evaluated the start already (for its scale): nlopt's first call is there.
            value, g = first if first is not None and not history and np.array_equal(x, x_start) else fun(x.reshape(shape))
            if not np.isfinite(value):
                raise DoeError(f"{desc}: the loss became {value}")
            history.append(float(value))
            if value < best["value"]:
                best["value"] = float(value)
                np.copyto(best["x"], x)
            if grad.size:
                np.multiply(np.asarray(g, dtype=float).reshape(-1), scale, out=grad)
            bar.update(1, status=f"loss {value:.5g}")
            if callback is not None and callback(len(history), float(value), x.reshape(shape)):
                opt.force_stop()
            return scale * float(value)

        opt.set_min_objective(objective)
        try:
            opt.optimize(best["x"].copy())
        except nlopt.RoundoffLimited:
            log.info("%s: stopped by round-off; keeping the best point", desc)
        except nlopt.ForcedStop:
            log.info("%s: stopped by the callback or the evaluation budget", desc)
        except (RuntimeError, getattr(nlopt, "runtime_error", RuntimeError)) as exc:
            # nlopt's generic failure (e.g. a line search that cannot progress): keep the best point.
            if stopped["budget"]:
                log.info("%s: stopped by the evaluation budget", desc)
            elif len(history) <= 1:
                # No step was taken: returning the start would pass an unoptimized design as a result.
                raise DoeError(f"{desc}: nlopt {algorithm} failed after {len(history)} evaluation(s) with {n} "
                               f"variables, before any step ({exc})") from None
            else:
                log.warning("%s: nlopt stopped with a failure after %d evaluations; keeping the best point",
                            desc, len(history))
        result = opt.last_optimize_result()
    log.info("%s: %d evaluations, loss %.6g -> %.6g (nlopt result %s)", desc, len(history),
             history[0] if history else np.nan, best["value"], result)
    return best["x"].reshape(shape), history


def _unit_gain_scale(grad: np.ndarray, lower: np.ndarray, upper: np.ndarray) -> float:
    """The factor that makes the mean linear gain per variable, ``|g_j| (upper_j - lower_j) / 2``, one.

    MMA's curvature bound rho is absolute (objective units), starts at 1 and never falls below
    1e-5, while its step per variable is about ``g sigma^2 / (|g| sigma + rho / 2)`` with sigma half
    the bound range. Heights in metres over millions of pixels give gains near 1e-7: unscaled, MMA
    barely moves (the 4500 px design stopped by ftol after 2 evaluations with the loss unchanged).
    """
    gain = float(np.mean(np.abs(grad) * 0.5 * (upper - lower)))
    return 1.0 / gain if np.isfinite(gain) and gain > 0 else 1.0
