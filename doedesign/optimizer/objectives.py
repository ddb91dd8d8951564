"""Balanced objectives over several colours (planes): the weakest one counts.

- :func:`plane_energies`: light on each (depth, wavelength) plane's target pixels.
- :func:`softmin_loss`: a smooth max-min for the PSF engine, ``tau log sum exp(-E_p / (w_p tau))``
  (the negative soft minimum of the weighted energies ``E_p / w_p``; ``tau -> 0`` is the hard
  minimum). One forward and one adjoint pass serve all planes.
- :func:`maximize_min`: the hard max-min through nlopt in its auxiliary-variable form:
  maximize ``t`` subject to ``t <= E_p(x) / w_p`` for every plane, with ``LD_MMA`` or
  ``LD_CCSAQ`` (the algorithms that take inequality constraints with gradients).

Weights ``w_p`` (default 1) trade colours: the max-min of ``E_p / w_p`` lands where the
energies are proportional to the weights, which is how a weight sweep traces the Pareto front.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import TYPE_CHECKING

import numpy as np

from ..engine.psf import PSFEngine
from ..errors import DoeError
from ..progress import Progress
from .losses import MAX_READ_LINES, PixelReads

if TYPE_CHECKING:
    from numpy.typing import ArrayLike

    from ..targets import Target
    from .settings import OptimizerSettings

__all__ = ["MAXMIN_ALGORITHMS", "PlaneLoss", "maximize_min", "maxmin_stage", "plane_energies", "plane_weights",
           "softmin_loss"]

log = logging.getLogger(__name__)

MAXMIN_ALGORITHMS = ("LD_MMA", "LD_CCSAQ")
# Tolerance of the CCSA methods' inner dual solve (nlopt's default 1e-14). The dual has one
# variable per constraint and each of its evaluations is a pass over all n heights; at 1e-14 it
# took 80 % of the router's time (4.8 of 5.0 s for 4,004 heights, 150 evaluations); at 1e-8 the
# router took 1.1 s and reached the same weakest energy (0.2703).
DUAL_FTOL_REL = 1e-8


def plane_weights(target: Target, weights: ArrayLike | None = None) -> np.ndarray:
    """Weights (depths, wavelengths) of the planes; ``weights`` per wavelength or per plane, default 1."""
    shape = target.intensity.shape[:2]
    if weights is None:
        return np.ones(shape)
    w = np.asarray(weights, dtype=float)
    if w.shape == (shape[1],):
        w = np.broadcast_to(w, shape)
    if w.shape != shape or not np.all(np.isfinite(w)) or np.any(w <= 0):
        raise DoeError(f"colour weights must be {shape[1]} (one per wavelength) or {shape} positive numbers, "
                       f"got {weights!r}")
    return np.array(w, dtype=float)


def plane_energies(psf: np.ndarray, target: Target) -> np.ndarray:
    """Light (fraction of the coded view's) on each plane's target pixels, (depths, wavelengths)."""
    return np.sum(np.asarray(psf) * target.mask, axis=(-2, -1))


class PlaneLoss:
    """Engine loss ``f(E)`` of the plane energies ``E`` (depths, wavelengths) on ``mask``.

    Reads only the target pixels: ``reads`` and :meth:`sparse` let the engine evaluate it
    from those pixels alone (:mod:`doedesign.engine.reads`) when they lie on few rows and columns.

    Parameters
    ----------
    mask : ndarray (depths, wavelengths, rows, cols) of bool
    fn : callable
        ``fn(E) -> (value, dvalue_dE)``.
    """

    def __init__(self, mask: np.ndarray, fn: Callable[[np.ndarray], tuple[float, np.ndarray]]) -> None:
        self.mask = np.asarray(mask, dtype=bool)
        self.fn = fn
        rows, cols = np.nonzero(self.mask.any(axis=(0, 1)))
        self.reads = None
        if rows.size and max(np.unique(rows).size, np.unique(cols).size) <= MAX_READ_LINES:
            self.reads = PixelReads(rows=rows, cols=cols, energy=False)
            self._mask = self.mask[..., rows, cols]

    def __call__(self, psf: np.ndarray) -> tuple[float, np.ndarray]:
        value, d_e = self.fn(np.sum(np.asarray(psf) * self.mask, axis=(-2, -1)))
        return float(value), np.asarray(d_e, dtype=float)[..., None, None] * self.mask

    def sparse(self, values: np.ndarray, energy: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
        """The loss from the target pixels' values (depths, wavelengths, pixels); see :class:`doedesign.optimizer.losses.Loss`."""
        value, d_e = self.fn(np.sum(values * self._mask, axis=-1))
        return float(value), np.asarray(d_e, dtype=float)[..., None] * self._mask, np.zeros_like(energy)


def softmin_loss(target: Target, weights: ArrayLike | None = None, tau: float = 0.01) -> PlaneLoss:
    """Engine loss ``psf -> (value, dvalue/dpsf)``: the negative soft minimum of ``E_p / w_p``.

    ``value = tau log sum_p exp(-E_p / (w_p tau))`` lies within ``tau log(planes)`` of
    ``-min_p E_p / w_p``; its gradient puts the soft-max share ``s_p`` of each plane on its
    target pixels, ``-s_p / w_p``.
    """
    w = plane_weights(target, weights)
    if not tau > 0:
        raise DoeError(f"soft-min temperature must be positive, got {tau}")

    def fn(e):
        u = -e / w / tau
        top = u.max()
        s = np.exp(u - top)
        return tau * (top + np.log(s.sum())), -(s / s.sum()) / w

    return PlaneLoss(target.mask, fn)


def maximize_min(fun: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]], x0: np.ndarray, lower: ArrayLike,
                 upper: ArrayLike, weights: ArrayLike, algorithm: str = "LD_MMA", max_iter: int = 100,
                 max_time_s: float | None = None, xtol_rel: float = 1e-6,
                 desc: str = "max-min") -> tuple[np.ndarray, list]:
    """Maximize ``min_p E_p(x) / w_p`` with nlopt's auxiliary-variable form.

    Parameters
    ----------
    fun : callable
        ``fun(x) -> (E, G)``: energies (m,) and their gradients (m, x.size).
    weights : array (m,)

    Returns
    -------
    x_best : ndarray, the evaluated point with the largest weighted minimum
    history : list of float, the weighted minimum at every evaluation
    """
    import nlopt

    if algorithm not in MAXMIN_ALGORITHMS:
        raise DoeError(f"max-min needs an algorithm with constraints ({', '.join(MAXMIN_ALGORITHMS)}), got {algorithm!r}")
    w = np.asarray(weights, dtype=float).ravel()
    x0 = np.asarray(x0, dtype=float).ravel()
    n, m = x0.size, w.size
    lo = np.broadcast_to(np.asarray(lower, float), x0.shape)
    hi = np.broadcast_to(np.asarray(upper, float), x0.shape)
    opt = nlopt.opt(getattr(nlopt, algorithm), n + 1)
    opt.set_lower_bounds(np.r_[lo, 0.0])
    opt.set_upper_bounds(np.r_[hi, 1.0 / w.min()])
    opt.set_maxeval(int(max_iter))
    opt.set_xtol_rel(xtol_rel)
    opt.set_param("dual_ftol_rel", DUAL_FTOL_REL)
    if max_time_s:
        opt.set_maxtime(float(max_time_s))
    best = {"value": -np.inf, "x": np.clip(x0, lo, hi)}
    history = []

    def objective(x, grad):
        if grad.size:
            grad[:] = 0.0
            grad[-1] = 1.0
        return float(x[-1])

    with Progress(max_iter, desc=desc) as bar:
        def constraints(result, x, grad):
            e, g = fun(x[:-1])
            e = np.asarray(e, dtype=float).ravel()
            value = float(np.min(e / w))
            history.append(value)
            if value > best["value"]:
                best["value"], best["x"] = value, x[:-1].copy()
            result[:] = x[-1] - e / w
            if grad.size:
                grad[:, :n] = -np.asarray(g, dtype=float).reshape(m, n) / w[:, None]
                grad[:, n] = 1.0
            bar.update(1, status=f"weakest {value:.4f}")

        opt.set_max_objective(objective)
        opt.add_inequality_mconstraint(constraints, np.full(m, 1e-9))
        e0, _ = fun(best["x"])
        try:
            opt.optimize(np.r_[best["x"], max(float(np.min(np.ravel(e0) / w)), 0.0)])
        except (nlopt.RoundoffLimited, RuntimeError) as exc:
            if not history:
                raise DoeError(f"{desc}: nlopt failed before the first evaluation ({exc})") from None
            log.info("%s: nlopt stopped (%s); keeping the best point", desc, exc)
    log.info("%s: %d evaluations, weakest weighted energy %.4f", desc, len(history), best["value"])
    return best["x"], history


def _single_plane_loss(mask, d, w):
    """Loss of a one-wavelength engine: the energy on plane (d, w)'s target pixels."""
    one = np.zeros((mask.shape[0], 1) + mask.shape[2:], dtype=bool)
    one[d, 0] = mask[d, w]
    pick = np.zeros((mask.shape[0], 1))
    pick[d, 0] = 1.0
    return PlaneLoss(one, lambda e: (float(e[d, 0]), pick))


def maxmin_stage(engine: PSFEngine, target: Target, weights: np.ndarray, h0: np.ndarray, support: np.ndarray, lower: float,
                 upper: float, settings: OptimizerSettings) -> tuple[np.ndarray, list]:
    """Continuous max-min of the plane energies through nlopt (auxiliary variable, LD_MMA or LD_CCSAQ).

    Each plane's energy and gradient come from a one-wavelength engine sharing the camera and
    grid, so all planes together cost one forward and one adjoint pass, as one loss would.
    """
    engines = [PSFEngine(engine.camera, engine.pitch_m, engine.shape, engine.material, [wl], target.depths_m,
                         engine.q, device=engine.backend) for wl in target.wavelengths_m]
    nd, nw = target.intensity.shape[:2]
    losses = [[_single_plane_loss(target.mask, d, w) for w in range(nw)] for d in range(nd)]

    def fun(x):
        h = np.zeros(support.shape)
        h[support] = x
        e, g = np.empty(nd * nw), np.empty((nd * nw, x.size))
        for w, eng in enumerate(engines):
            for d in range(nd):
                e[d * nw + w], gh = eng.value_and_grad(h, losses[d][w])
                g[d * nw + w] = gh[support]
        return e, g

    # The constraints need LD_MMA or LD_CCSAQ; with another algorithm set, LD_MMA runs this stage.
    algorithm = settings.algorithm if settings.algorithm in MAXMIN_ALGORITHMS else "LD_MMA"
    x, hist = maximize_min(fun, h0[support], lower, upper, weights.ravel(),
                           algorithm, settings.max_iter, settings.max_time_s, desc="max-min")
    h = np.zeros(support.shape)
    h[support] = x
    # The loss history is the negative weighted minimum, so "lower is better" holds throughout.
    return h, [-v for v in hist]
