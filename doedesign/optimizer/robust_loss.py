"""Robust design's loss: the mean, or the CVaR, of the loss over perturbed height maps.

A perturbation maps ``h -> (h', vjp)``: a perturbed height map (a process sample, e.g. from the
``doe.perturbations`` entry points) and the pullback of a gradient at ``h'`` to ``h``, so the
adjoint gradient of the PSF engine carries through every sample. The list is fixed for a whole
run (common random numbers): the objective stays deterministic for nlopt.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np

__all__ = ["Perturbation", "ROBUST_MEASURES", "robust_value_and_grad"]

ROBUST_MEASURES = ("mean", "cvar")
# h -> (h', vjp): a perturbed height map and the pullback of a gradient at h' to h.
Perturbation = Callable[[np.ndarray], tuple[np.ndarray, Callable[[np.ndarray], np.ndarray]]]


def robust_value_and_grad(value_and_grad: Callable[[np.ndarray], tuple[float, np.ndarray]], h: np.ndarray,
                          perturbations: Sequence[Perturbation], measure: str = "mean",
                          cvar_alpha: float = 0.25) -> tuple[float, np.ndarray]:
    """Mean (or CVaR) of ``value_and_grad`` over perturbed heights, and its gradient in ``h``.

    Each perturbation maps ``h -> (h', vjp)``; the loss gradient at ``h'`` is pulled back by ``vjp``.
    CVaR averages the worst ``ceil(cvar_alpha K)`` of the K losses (a subgradient at ties).
    """
    samples: list[float] = []
    grads = []
    for perturb in perturbations:
        hp, vjp = perturb(h)
        v, g = value_and_grad(hp)
        samples.append(v)
        grads.append(vjp(g))
    values = np.asarray(samples, float)
    weights = np.full(values.size, 1.0 / values.size)
    if measure == "cvar":
        k = int(np.ceil(cvar_alpha * values.size))
        weights = np.zeros(values.size)
        weights[np.argsort(values)[::-1][:k]] = 1.0 / k
    return float(weights @ values), sum(w * g for w, g in zip(weights, grads) if w)
