"""The quantization-aware finish: penalty annealing toward the nearest process level.

The penalty ``mean sin^2(pi h / step)`` (zero on every level) is added to the loss with the
growing weights of :data:`ANNEAL_SCHEDULE`, relative to the continuous loss, and the heights are
re-optimized at each weight; :func:`doedesign.optimizer.optimize.design_doe` then rounds the result to the
nearest level and keeps it or the plainly rounded continuous optimum, whichever scores better.
"""

from __future__ import annotations

from collections.abc import Callable

from array_api_compat import array_namespace, is_array_api_obj
import numpy as np
from numpy.typing import ArrayLike

from ..engine.backend import Array

__all__ = ["ANNEAL_SCHEDULE", "anneal", "level_penalty"]

#: Weights of the level penalty relative to the continuous loss, one re-optimization each.
ANNEAL_SCHEDULE = (0.03, 0.1, 0.3, 1.0, 3.0)



def level_penalty(height_m: ArrayLike, step_m: float,
                  support: np.ndarray | None = None) -> tuple[float, np.ndarray]:
    """``mean sin^2(pi h / step)`` over ``support`` (zero when every height is on a level) and its gradient.

    Computed where ``height_m`` lives (NumPy, or a GPU array beside the design's PSF engine)."""
    h: Array = height_m if is_array_api_obj(height_m) else np.asarray(height_m, dtype=float)
    xp = array_namespace(h)
    # On the support only, one sine and one cosine: sin 2x = 2 sin x cos x.
    x = (np.pi / step_m) * xp.astype(h if support is None else h[support], xp.float64)
    n = max(int(x.size), 1)
    sin = xp.sin(x)
    value = float(xp.sum(sin * sin)) / n
    g = xp.cos(x)
    g *= sin
    g *= 2 * np.pi / step_m / n
    if support is None:
        return value, g
    grad = xp.zeros(h.shape, dtype=xp.float64)
    grad[support] = g
    return value, grad


def anneal(run_stage: Callable[..., tuple[np.ndarray, list[float]]], height_m: np.ndarray, step_m: float,
           scale: float, iterations: int, max_time_s: float | None = None,
           before_stage: Callable[[np.ndarray], None] | None = None) -> tuple[np.ndarray, list[float]]:
    """Re-optimize ``height_m`` once per weight of :data:`ANNEAL_SCHEDULE` with the level penalty added.

    Parameters
    ----------
    run_stage : callable
        ``run_stage(h_start, max_iter, max_time_s, desc, penalty) -> (h, history)``, one nlopt stage
        of the design loss plus ``penalty(x) -> (value, grad)`` on its free heights ``x`` (a vector:
        the penalty is separable, so it never needs the whole map).
    scale : float
        The continuous loss, so the penalty weights are relative to it.
    iterations : int
        Evaluations per stage.
    max_time_s : float, optional
        Time limit of the continuous stage; the annealing stages together get at most half of it.
    before_stage : callable, optional
        ``before_stage(h)``, e.g. a target reweighting, before each stage.

    Returns
    -------
    height_m : ndarray, the annealed (still continuous) heights
    history : list of float, the objective at every evaluation of every stage
    """
    history = []
    stage_time = max_time_s / (2 * len(ANNEAL_SCHEDULE)) if max_time_s else None
    h = height_m
    for mu in ANNEAL_SCHEDULE:
        def penalized(x, mu=mu):
            v, g = level_penalty(x, step_m)
            g *= scale * mu
            return scale * mu * v, g

        if before_stage is not None:
            before_stage(h)
        h, hist = run_stage(h, iterations, stage_time, f"anneal x{mu:g}", penalized)
        history.extend(hist)
    return h, history
