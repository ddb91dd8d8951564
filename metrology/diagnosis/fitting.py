"""Least-squares fits of effects' parameters on a diagnosis problem, and their uncertainties.

Bounded ``scipy.optimize.least_squares`` in units of each parameter's scale, with
finite-difference Jacobians whose columns may be computed in worker threads
(:mod:`metrology.diagnosis.parallel`): SciPy's own differences take relative steps, which vanish
at a parameter of exactly zero, where most effects start. Uncertainties are
``cov = s^2 (J^T J)^-1 A`` with ``A`` the noise's correlation area.

A fit to convergence that ``trf`` does not finish in ``TRF_EVALS`` evaluations is finished
by ``dogbox``. Near a bound (a fill factor running to point sampling) ``trf``'s scaling by the
distance to the bound makes it zig-zag: on a coherence-scanning interferometer's file its
instrument fit stopped at the 60-evaluation cap 1580 cost units (17 criterion units) above the
optimum that ``dogbox`` reached in 28 evaluations, with the objective's NA, fill factor and
batwing at their true values. ``dogbox`` alone stalls elsewhere: on another such file it spent 60
evaluations 0.5 % above the cost ``trf`` reached in 8.

Tolerances are in the information criterion's units, which decide: a fit ends where a step
lowers the criterion by less than ``CRITERION_TOL``, or ``CRAWL_STEPS`` steps together by
less than ``CRAWL_TOL``. A limit the user asked for (``stop``) ends one under way.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING, Any

import numpy as np
from scipy.optimize import OptimizeResult, least_squares

from metrology.diagnosis.parallel import fit_workers, parallel_map

if TYPE_CHECKING:
    from metrology.diagnosis.problem import Problem

__all__ = ["JAC_STEP", "bic_eff", "fit_effects", "power_share", "standard_errors"]

log = logging.getLogger(__name__)

# Finite-difference step of the Jacobian, in units of each parameter's scale.
JAC_STEP = 0.02
# Evaluations of a fit to convergence, of which trf may spend the first TRF_EVALS.
MAX_EVALS, TRF_EVALS = 60, 12
# A fit has converged when a step lowers the information criterion (:func:`bic_eff`: ``n_eff ln
# RSS``, so a relative change of the cost times ``n_eff``) by less than this: a fifth of a unit,
# where an effect must earn ten; a parameter then sits within sqrt(0.2) = 0.45 of its standard
# error of the optimum. With a relative ``ftol`` of 1e-6 instead (a thousandth of a unit on a
# 160 px window), dogbox's finish of a CSI file's fits spent up to 7 Jacobians of 14-18 columns on
# their last 0.01-0.1 units. A fiftieth of a unit cost a CSI field its restart once the floor's
# correlation area came down to the noise's (40 px to 1 px: a fortieth of the tolerance in the cost).
CRITERION_TOL = 0.2
# A fit to convergence whose last CRAWL_STEPS iterations together lowered the criterion by less
# than CRAWL_TOL ends there: beside a bound (a fill factor or a batwing's reach on it) the solvers
# crawl. On a CSI file's refit with an etch gradient, dogbox spent 48 Jacobians of 18 columns (a
# third of the CPU budget) on its last 2 units, 0.03-0.1 per iteration.
CRAWL_STEPS, CRAWL_TOL = 5, 1.0
# A fit to convergence updates its Jacobian by Broyden's rank-one rule after a step its first
# trial took (one evaluation, where differences cost one or two per parameter), at most this many
# times running; after a rejected trial, differences again. In a curved valley (a CSI file's fill
# factor, NA and batwing beside an etch loading the instrument stage had not seen) the solvers
# take dozens of short accepted steps: that fit took 42 Jacobians of 11 columns, 45 CPU s.
BROYDEN_STEPS = 4


def bic_eff(rss: float, n: int, n_eff: float, k: int) -> float:
    """Information criterion with an effective sample count: ``n_eff ln(RSS/N) + k ln(n_eff)``."""
    return float(n_eff * np.log(rss / n) + k * np.log(n_eff))


def power_share(problem: Problem, r: np.ndarray, rss: float) -> float:
    """The share of the floor's power (per sample) that going from residual ``r`` to ``rss`` explains."""
    return (float(np.sum(r ** 2)) - rss) / (r.size * problem.noise.sigma ** 2)


def fit_effects(problem: Problem, model: dict[str, np.ndarray], free: Sequence[str],
                max_iter: int | None = None, central: bool | None = None,
                stop: Callable[[], bool] | None = None,
                precise: bool = False) -> tuple[dict[str, np.ndarray], float, dict[str, np.ndarray]]:
    """Least-squares fit of the ``free`` effects' parameters, others held at ``model``.

    Central-difference Jacobians where the residual has kinks (``problem.kinks``: area-coverage
    edges make a height residual piecewise smooth, with kinks where an edge crosses a grid line,
    at zero shift or bias, where one-sided differences stall a fit to convergence); forward ones
    where it is smooth in the parameters (a PSF stack), at half the evaluations, and in the
    parameters marked ``smooth`` (the instrument's transfer: each of its columns costs a new
    transfer and inverse FFTs, where a placement's costs a resampling).

    Parameters
    ----------
    problem : Problem
    model : dict
        Effect name -> parameter values; the free effects start from theirs.
    free : list of str
        Effects whose parameters are fitted.
    max_iter : int, optional
        Cap on function evaluations outside the Jacobian (a short fit to screen candidates;
        its standard errors are NaN: the Jacobian at its last point is not computed).
    central : bool, optional
        Central differences (else forward ones: half the evaluations, for a short screening fit
        whose score is conservative anyway); default ``problem.kinks``.
    stop : callable, optional
        Asked before each evaluation and each Jacobian once the start is evaluated (a limit the
        user asked for, spent): when it says true, the fit ends at its best evaluation so far, its
        standard errors NaN.
    precise : bool
        A measurement's fit (an instrument's calibration, then held in every diagnosis): a
        relative ``ftol`` of 1e-6, differences at every step, no crawl stop. With the tolerances in
        criterion units, a CSI artefact's calibrated NA was 2.3 sigma off (0.449 against 0.442;
        0.443 precise), and a diagnosis holding it named a false etch depth.

    Returns
    -------
    (dict, float, dict)
        Fitted model, residual sum of squares (in the problem's units squared), and the
        standard errors of the free effects' parameters (``cov = s^2 (J^T J)^-1 A``).
    """
    effs, scale, lo, hi, x0, unpack, residual = _fit_setup(problem, model, free)
    central = _central(effs, problem.kinks if central is None else central)
    sizes = []  # residual size of each solver evaluation
    last: dict[str, Any] = {}  # the last evaluation, the base of a forward-difference Jacobian there
    best: dict[str, Any] = {}  # the lowest-cost evaluation: where a fit that ``stop`` ends returns
    crawl = []  # the cost at each Jacobian's point
    held: dict[str, Any] = {}  # the last Jacobian: its point, residual, matrix, Broyden updates since a full one, evaluations
    workers = fit_workers(problem)

    def fun(x):
        if np.array_equal(last.get("x"), x):
            return last["r"]  # the start, evaluated below to size the tolerance
        if best and stop is not None and stop():
            raise _Stopped
        r = residual(x)
        sizes.append(r.size)
        last.update(x=x.copy(), r=r)
        cost = float(r @ r)
        if not best or cost < best["cost"]:
            best.update(x=x.copy(), cost=cost)
        return r

    def jac(x):
        if stop is not None and stop():
            raise _Stopped
        if max_iter and len(sizes) >= max_iter:
            # The solver stops right after this Jacobian, which would only serve the errors.
            sizes.append(-1)
            return np.zeros((sizes[-2], x.size))
        here = np.array_equal(last.get("x"), x)
        if (not max_iter and not precise and here and held and len(sizes) == held["n"] + 1
                and held["age"] < BROYDEN_STEPS):
            # One step accepted at its first trial since the last Jacobian: Broyden's update.
            dx = x - held["x"]
            j = held["j"] + np.outer(last["r"] - held["r"] - held["j"] @ dx, dx / (dx @ dx))
            age = held["age"] + 1
        else:
            f0 = last["r"] if not central.all() and here else None
            j, age = _jacobian(residual, x, lo, hi, central, workers, f0=f0, stop=stop), 0
        if here:
            held.update(x=x.copy(), r=last["r"], j=j, age=age, n=len(sizes))
        if here and not max_iter and not precise:
            crawl.append(float(last["r"] @ last["r"]))
            if (len(crawl) > CRAWL_STEPS
                    and crawl[-1 - CRAWL_STEPS] - crawl[-1] < CRAWL_TOL * crawl[-1] * problem.noise.corr_area_px
                    / last["r"].size):
                raise _Crawled(x.copy(), last["r"], j)
        return j

    try:
        # The cost's relative change that moves the information criterion by CRITERION_TOL.
        r0 = fun(x0)
        ftol = 1e-6 if precise else max(CRITERION_TOL * problem.noise.corr_area_px / max(r0.size, 1), 1e-10)
        opts = dict(jac=jac, bounds=(lo, hi), xtol=1e-6, ftol=ftol)
        res = least_squares(fun, x0, method="trf", max_nfev=max_iter or TRF_EVALS, **opts)
        if not max_iter and res.status == 0:
            # trf zig-zags beside a bound: dogbox finishes from where it stopped (alone it stalls
            # where the Jacobian is nearly rank-deficient, which trf crosses).
            more = least_squares(fun, _inside(res.x, lo, hi), method="dogbox", max_nfev=MAX_EVALS - res.nfev,
                                 **opts)
            res = more if more.cost <= res.cost else res
    except _Stopped:
        log.info("fit %s stopped by its budget after %d evaluations", free, len(sizes))
        rss = best["cost"] * problem.noise.sigma ** 2
        return unpack(best["x"]), rss, _split(effs, np.full(best["x"].size, np.nan))
    except _Crawled as crawled:
        log.debug("fit %s crawls: ended after %d evaluations", free, len(sizes))
        res = OptimizeResult(x=crawled.args[0], fun=crawled.args[1], jac=crawled.args[2])
    log.debug("fit %s: %d evaluations", free, len(sizes))
    rss = float(np.sum(res.fun ** 2)) * problem.noise.sigma ** 2
    if held.get("age") and not max_iter:
        # The errors need the differences' Jacobian, not an update's.
        res.jac = _jacobian(residual, res.x, lo, hi, central, workers)
    err = _errors(problem, res.fun, res.jac, scale)
    if sizes and sizes[-1] < 0:
        err = np.full(res.x.size, np.nan)
    return unpack(res.x), rss, _split(effs, err)


class _Stopped(Exception):
    """Raised in a fit's evaluation when its ``stop`` says so: ends the solver."""


class _Crawled(Exception):
    """Raised with ``(x, residual, Jacobian)`` at a point where the fit crawls (``CRAWL_STEPS``)."""


def standard_errors(problem: Problem, model: dict[str, np.ndarray], free: Sequence[str]) -> dict[str, np.ndarray]:
    """Standard errors of the ``free`` effects' parameters at ``model`` (a fitted optimum), the
    others held: one central-difference Jacobian, as :func:`fit_effects` reports them, without
    the solver's iterations."""
    effs, scale, lo, hi, x0, _, residual = _fit_setup(problem, model, free)
    jac = _jacobian(residual, x0, lo, hi, True, fit_workers(problem))
    return _split(effs, _errors(problem, residual(x0), jac, scale))


def _fit_setup(problem, model, free):
    """The free effects, their parameter scales and scaled bounds, the scaled start, and the
    maps from scaled parameters to a model and to the noise-weighted residual."""
    effs = [problem.effects[name] for name in free]
    scale = np.concatenate([e.scales() for e in effs])
    lo = np.concatenate([e.bounds()[0] for e in effs]) / scale
    hi = np.concatenate([e.bounds()[1] for e in effs]) / scale
    x0 = np.concatenate([np.asarray(model[e.name], dtype=float) for e in effs]) / scale
    x0 = _inside(x0, lo, hi)
    splits = np.cumsum([e.n_params for e in effs])[:-1]

    def unpack(x):
        trial = dict(model)
        for e, v in zip(effs, np.split(x * scale, splits)):
            trial[e.name] = v
        return trial

    def residual(x):
        return problem.residual(unpack(x)) / problem.noise.sigma

    return effs, scale, lo, hi, x0, unpack, residual


def _central(effs, central):
    """Per parameter, whether its Jacobian column takes central differences: where ``central``
    asks for them and the parameter is not marked smooth."""
    smooth = np.array([p.smooth for e in effs for p in e.params], bool)
    return np.asarray(central, bool) & ~smooth


def _inside(x, lo, hi):
    """``x`` moved strictly inside the bounds (a solver's start must not lie on one)."""
    return np.clip(x, lo + 1e-9 * (hi - lo), hi - 1e-9 * (hi - lo))


def _errors(problem, fun, jac, scale):
    """Standard errors (parameter units) from a weighted residual and its Jacobian (scaled
    parameters): ``cov = s^2 (J^T J)^-1 A``, ``A`` the noise's correlation area."""
    n, k = fun.size, jac.shape[1]
    try:
        cov = np.linalg.pinv(jac.T @ jac) * (np.sum(fun ** 2) / max(n - k, 1)) * problem.noise.corr_area_px
        return np.sqrt(np.clip(np.diag(cov), 0, None)) * scale
    except np.linalg.LinAlgError:
        return np.full(k, np.nan)


def _split(effs, values):
    """Per-effect parts of a vector over the effects' parameters."""
    return {e.name: v for e, v in zip(effs, np.split(values, np.cumsum([e.n_params for e in effs])[:-1]))}


def _jacobian(fun, x, lo, hi, central, workers=1, step=JAC_STEP, f0=None, stop=None):
    """Finite differences with an absolute step (in units of each parameter's scale); SciPy's
    relative steps vanish at a parameter of exactly zero, where most effects start.

    ``central``: per column, central differences (else forward ones). Central differences are
    one-sided against a bound; forward ones go backward against the upper bound, from
    ``f0 = fun(x)`` (computed when not given). The columns are computed in ``workers`` threads when more
    than one. ``stop`` (a fit's budget) is asked before each column: a Jacobian the deadline finds
    under way ends within one evaluation per thread, not after its last column (a CSI window's fit
    to convergence with a trenching frees 14 parameters: 14-28 evaluations of about 0.5 s).
    """
    central = np.broadcast_to(np.asarray(central, bool), x.shape)
    if not central.all() and f0 is None:
        f0 = fun(x)

    def column(i):
        if stop is not None and stop():
            raise _Stopped
        if central[i]:
            up, down = x.copy(), x.copy()
            up[i] = min(x[i] + step, hi[i])
            down[i] = max(x[i] - step, lo[i])
            return (fun(up) - fun(down)) / (up[i] - down[i])
        other = x.copy()
        other[i] = x[i] + step if x[i] + step <= hi[i] else max(x[i] - step, lo[i])
        return (fun(other) - f0) / (other[i] - x[i])

    return np.stack(list(parallel_map(column, range(x.size), workers)), axis=1)
