"""Height-map optimization with nlopt and analytic gradients, then a quantization-aware finish.

Pipeline (:func:`design_doe`)
-----------------------------
1. Continuous stage: minimize the target loss (:mod:`doedesign.losses`) over the heights with
   nlopt (``LD_LBFGS`` by default; ``LD_MMA`` or ``LD_CCSAQ``), gradients from
   :meth:`doedesign.psf.PSFEngine.value_and_grad`. Heights are bounded, in the design file's
   convention (z up, 0 = unetched top, etched pixels negative):
   ``height_range="process"``: ``[-(N-1) step, 0]``, the deepest process level down to the top
   surface, so every height has a fabricable nearest level; ``"2pi"``: ``[-N step, 0]``, the
   full 2 pi height at the design wavelength, where a height rounding to level N wraps to
   level 0 (the same phase at the design wavelength only); ``"wrap"``: unbounded continuous
   heights wrapped modulo the 2 pi height at the end. Bounds cut a linear phase ramp into a
   clipped one, so single-wavelength designs (gratings, spot arrays) converge best with
   "wrap"; the wrap is exact at the design wavelength and approximate elsewhere.
2. Quantization-aware finish: penalty annealing toward the nearest level. The penalty
   ``mean sin^2(pi h / step)`` (zero on every level) is added with a growing weight and the
   heights re-optimized at each weight; finally each height is rounded (not floored) to the
   nearest level by the one level rule of :mod:`doedesign.levels` (the rule the masks,
   the comparison and the diagnosis use too). The plain rounding of the continuous optimum
   is evaluated as well and the better of the two is kept.
3. Optional fabrication regularizer (``fab_weight``) against one-pixel pillars and holes.

Uniform multi-spot targets: ``reweight_rounds`` > 0 adds rounds after the continuous stage
in which the target's pixel weights are updated from the current PSF,
``w_i <- w_i (mean a / a_i)^reweight_alpha`` with ``a_i`` = delivered / wanted light
(:func:`doedesign.losses.reweight_target`, the gradient analogue of weighted Gerchberg-Saxton),
and the heights re-optimized for ``reweight_iter`` evaluations. The weights keep being updated
before each annealing stage, so the quantized design stays balanced; the final weights are
in the report. On targets with one pixel per plane (Bayer) the update does nothing.

Robust design: ``perturbations`` (a list of functions ``h -> (h', vjp)``, e.g. process samples
from the ``doe.perturbations`` entry points) makes every stage minimize the mean loss over the
perturbed heights, or with ``robust_measure="cvar"`` the mean of the worst ``cvar_alpha`` share
(CVaR), through the same adjoint gradient pulled back by each ``vjp``. The list is fixed for the
whole run (common random numbers), so the objective stays deterministic for nlopt.


Balanced objectives (``objective``): ``"loss"`` minimizes the :class:`~doedesign.losses.LossSpec`
terms; ``"softmin"`` the negative soft minimum of the per-plane energies on target over their
``colour_weights``; ``"maxmin"`` runs the continuous stage as nlopt's auxiliary-variable max-min
(:func:`doedesign.objectives.maximize_min`, LD_MMA or LD_CCSAQ) and anneals with the soft-min.
``init="router"`` starts from the coherent pupil model's max-min (:mod:`doedesign.router`);
``starts`` adds initial designs for a multi-start (a short stage each, the best goes on; all
are in the report).

Metrics (energy on target per wavelength and depth, efficiency, L1, and each plane's energy
beside its single-colour bound, :mod:`doedesign.bounds`) are reported for the continuous, the
plainly rounded and the final quantized design.
"""

from __future__ import annotations

import logging
import time
from dataclasses import asdict, dataclass, field

import numpy as np

from .bounds import bound_report, spot_bound
from .design import Design
from .errors import DoeError
from .losses import LossSpec, make_loss, reweight_target, target_metrics
from .levels import N_LEVELS, level_step_m, quantize, wrap_height_m
from .materials import get_material
from .objectives import maxmin_stage, plane_weights, softmin_loss
from .progress import Progress
from .psf import PSFEngine
from .router import router_start

__all__ = ["ALGORITHMS", "ANNEAL_SCHEDULE", "DesignRun", "HEIGHT_RANGES", "INITS", "OptimizerSettings",
           "WRAP_SPAN", "coded_support", "design_doe", "height_bounds", "initial_height", "isolated_pixels",
           "isolation_penalty", "level_penalty", "minimize"]

log = logging.getLogger(__name__)

ALGORITHMS = ("LD_LBFGS", "LD_MMA", "LD_CCSAQ")
INITS = ("random", "zeros", "streak", "grating", "lens", "router")
OBJECTIVES = ("loss", "softmin", "maxmin")
HEIGHT_RANGES = ("process", "2pi", "wrap")
ROBUST_MEASURES = ("mean", "cvar")
# Bounds of the "wrap" range in 2 pi heights: wide enough never to bind, finite for nlopt.
WRAP_SPAN = 8
# Weights of the level penalty relative to the continuous loss, one re-optimization each.
ANNEAL_SCHEDULE = (0.03, 0.1, 0.3, 1.0, 3.0)


# -- levels and bounds ---------------------------------------------------------------------------
def height_bounds(step_m, n_levels=N_LEVELS, height_range="process"):
    """(lower, upper) height bounds in metres for ``height_range`` (see the module docstring)."""
    if height_range == "process":
        return -(n_levels - 1) * step_m, 0.0
    if height_range == "2pi":
        return -n_levels * step_m, 0.0
    if height_range == "wrap":
        return -WRAP_SPAN * n_levels * step_m, WRAP_SPAN * n_levels * step_m
    raise DoeError(f"height range must be one of {HEIGHT_RANGES}, got {height_range!r}")


def level_penalty(height_m, step_m, support=None):
    """``mean sin^2(pi h / step)`` over ``support`` (zero when every height is on a level) and its gradient."""
    h = np.asarray(height_m, dtype=float)
    s = np.ones(h.shape, bool) if support is None else support
    n = max(int(s.sum()), 1)
    x = np.pi * h / step_m
    value = float(np.sum(np.sin(x)[s] ** 2) / n)
    grad = np.where(s, np.pi / step_m * np.sin(2 * x) / n, 0.0)
    return value, grad


def _neighbour_differences(h):
    """``h - neighbour`` for the 4 neighbours (up, down, left, right), and where they exist.

    Returns (4, rows, cols) differences and a mask that is False for neighbours outside the
    array (an edge pixel is judged on the neighbours it has).
    """
    pad = np.pad(h, 1, mode="edge")
    nb = np.stack([pad[:-2, 1:-1], pad[2:, 1:-1], pad[1:-1, :-2], pad[1:-1, 2:]])
    inside = np.ones(nb.shape, dtype=bool)
    inside[0, 0, :] = inside[1, -1, :] = inside[2, :, 0] = inside[3, :, -1] = False
    return h[None] - nb, inside


_OFFSETS = ((-1, 0), (1, 0), (0, -1), (0, 1))


def isolation_penalty(height_m, step_m):
    """How far one-pixel pillars stick up and holes dig down, in levels, per pixel.

    A pixel higher than all its neighbours contributes ``min(h - neighbour) / step`` (the
    pillar's height above its tallest neighbour); one lower than all, ``min(neighbour - h) / step``.
    Returns the mean over pixels and its (sub)gradient.
    """
    h = np.asarray(height_m, dtype=float)
    d, inside = _neighbour_differences(h)
    d = d / step_m
    n = h.size
    kmin = np.where(inside, d, np.inf).argmin(axis=0)
    kmax = np.where(inside, d, -np.inf).argmax(axis=0)
    dmin = np.take_along_axis(d, kmin[None], 0)[0]
    dmax = np.take_along_axis(d, kmax[None], 0)[0]
    pillar, hole = dmin > 0, dmax < 0
    value = float((dmin[pillar].sum() - dmax[hole].sum()) / n)
    grad = (pillar.astype(float) - hole) / (step_m * n)
    for k, (dr, dc) in enumerate(_OFFSETS):
        # Neighbour k of pixel (i, j) is (i + dr, j + dc); never outside the array (masked above).
        c = -(pillar & (kmin == k)).astype(float) + (hole & (kmax == k))
        grad += np.roll(c, (dr, dc), axis=(0, 1)) / (step_m * n)
    return value, grad


def isolated_pixels(levels):
    """Number of one-pixel pillars and holes: pixels above (or below) all their in-array neighbours."""
    d, inside = _neighbour_differences(np.asarray(levels, dtype=float))
    up = np.all(np.where(inside, d > 0, True), axis=0)
    down = np.all(np.where(inside, d < 0, True), axis=0)
    return int(np.count_nonzero(up | down))


# -- initial height maps ------------------------------------------------------------------------
def _wrap_into(h, lower, step_m, n_levels):
    """Wrap heights modulo the 2 pi height into [lower, 0] (nearest end for the process gap)."""
    h = wrap_height_m(h, step_m, n_levels)
    return np.where(h < lower, np.where(h < lower - step_m / 2, 0.0, lower), h)


def initial_height(kind, shape, step_m, lower, rng, n_levels=N_LEVELS, period_px=16, arms="+",
                   pitch_m=5.4e-6, camera=None, design_wavelength_m=550e-9, material="fused_silica",
                   focus_depth_m=None):
    """A starting height map.

    Parameters
    ----------
    kind : {"random", "zeros", "streak", "grating", "lens"}
        ``random``: uniform in the bounds; ``zeros``: flat; ``streak``: rank-1 maps varying along
        one axis only (each spreads light along that axis), along columns in the top half and
        along rows in the bottom half for a "+" cross; ``grating``: a blazed staircase of
        ``period_px`` along columns, phase rising with column (first order toward higher
        column); ``lens``: the phase that refocuses the camera from its focus distance to
        ``focus_depth_m`` (a lens difference), wrapped into the bounds.
    """
    rows, cols = shape
    if kind == "random":
        return rng.uniform(lower, 0.0, shape)
    if kind == "zeros":
        return np.zeros(shape)
    if kind == "streak":
        along_cols = np.broadcast_to(rng.uniform(lower, 0.0, cols), shape)
        along_rows = np.broadcast_to(rng.uniform(lower, 0.0, rows)[:, None], shape)
        if arms == "h":
            return along_cols.copy()
        if arms == "v":
            return along_rows.copy()
        return np.where((np.arange(rows) < rows // 2)[:, None], along_cols, along_rows)
    if kind == "grating":
        level = (np.arange(cols) % period_px) * n_levels // period_px
        return np.tile(-(n_levels - 1 - level) * step_m, (rows, 1)).astype(float)
    if kind == "lens":
        if camera is None or focus_depth_m is None:
            raise DoeError("the lens initialization needs the camera and a depth to focus")
        y = (np.arange(rows) - (rows - 1) / 2) * pitch_m
        x = (np.arange(cols) - (cols - 1) / 2) * pitch_m
        r2 = y[:, None] ** 2 + x[None, :] ** 2

        def sag(d):
            return np.zeros_like(r2) if np.isinf(d) else r2 / (np.sqrt(r2 + d * d) + d)

        # The DOE cancels the defocus path of a point at focus_depth_m: that point comes to focus.
        opd = -(sag(focus_depth_m) - sag(camera.focus_distance_m))
        mat = get_material(material)
        h = opd / (mat.n(design_wavelength_m) - 1.0)
        return _wrap_into(h, lower, step_m, n_levels)
    raise DoeError(f"unknown initialization {kind!r}; choose from {', '.join(INITS)} or give a height map")


# -- the nlopt driver -----------------------------------------------------------------------------
@dataclass
class OptimizerSettings:
    """Settings of :func:`design_doe` (see the module docstring)."""

    algorithm: str = "LD_LBFGS"
    max_iter: int = 100
    ftol_rel: float = 1e-7
    max_time_s: float | None = None
    seed: int = 0
    init: str = "random"
    height_range: str = "process"
    n_levels: int = N_LEVELS
    quantize: bool = True
    anneal_iter: int = 20
    fab_weight: float = 0.0
    reweight_rounds: int = 0
    reweight_alpha: float = 1.0
    reweight_iter: int | None = None  # None: max_iter
    robust_measure: str = "mean"      # with perturbations: "mean" or "cvar" of the loss
    cvar_alpha: float = 0.25          # CVaR: share of the worst perturbations averaged
    objective: str = "loss"
    colour_weights: list | None = None  # per wavelength (or per plane) for softmin / maxmin
    softmin_tau: float = 0.01
    starts: tuple = ()  # further initial designs for a multi-start; the best after start_iter is kept
    start_iter: int | None = None  # None: max(max_iter // 4, 3)
    router_grid_px: int = 100
    router_iter: int = 150

    def __post_init__(self):
        if self.objective not in OBJECTIVES:
            raise DoeError(f"objective must be one of {', '.join(OBJECTIVES)}, got {self.objective!r}")
        self.starts = tuple(self.starts)
        for s in (self.init, *self.starts):
            if s not in INITS:
                raise DoeError(f"unknown initialization {s!r}; choose from {', '.join(INITS)}")
        if not self.softmin_tau > 0:
            raise DoeError(f"softmin_tau must be positive, got {self.softmin_tau}")
        if self.algorithm not in ALGORITHMS:
            raise DoeError(f"algorithm must be one of {', '.join(ALGORITHMS)}, got {self.algorithm!r}")
        if int(self.max_iter) < 1:
            raise DoeError(f"iterations must be at least 1, got {self.max_iter}")
        if self.height_range not in HEIGHT_RANGES:
            raise DoeError(f"height range must be one of {HEIGHT_RANGES}, got {self.height_range!r}")
        if self.max_time_s is not None and not self.max_time_s > 0:
            raise DoeError(f"time limit must be positive, got {self.max_time_s}")
        if self.fab_weight < 0:
            raise DoeError("fab_weight must be >= 0")
        if int(self.reweight_rounds) < 0 or not (np.isfinite(self.reweight_alpha) and self.reweight_alpha > 0):
            raise DoeError(f"reweight_rounds must be >= 0 and reweight_alpha > 0, got {self.reweight_rounds} "
                           f"and {self.reweight_alpha}")
        if self.reweight_iter is not None and int(self.reweight_iter) < 1:
            raise DoeError(f"reweight_iter must be at least 1, got {self.reweight_iter}")
        if self.robust_measure not in ROBUST_MEASURES or not 0 < self.cvar_alpha <= 1:
            raise DoeError(f"robust_measure must be one of {ROBUST_MEASURES} and cvar_alpha in (0, 1], got "
                           f"{self.robust_measure!r} and {self.cvar_alpha}")


def robust_value_and_grad(value_and_grad, h, perturbations, measure="mean", cvar_alpha=0.25):
    """Mean (or CVaR) of ``value_and_grad`` over perturbed heights, and its gradient in ``h``.

    Each perturbation maps ``h -> (h', vjp)``; the loss gradient at ``h'`` is pulled back by ``vjp``.
    CVaR averages the worst ``ceil(cvar_alpha K)`` of the K losses (a subgradient at ties).
    """
    values, grads = [], []
    for perturb in perturbations:
        hp, vjp = perturb(h)
        v, g = value_and_grad(hp)
        values.append(v)
        grads.append(vjp(g))
    values = np.asarray(values, float)
    weights = np.full(values.size, 1.0 / values.size)
    if measure == "cvar":
        k = int(np.ceil(cvar_alpha * values.size))
        weights = np.zeros(values.size)
        weights[np.argsort(values)[::-1][:k]] = 1.0 / k
    return float(weights @ values), sum(w * g for w, g in zip(weights, grads) if w)


def minimize(fun, x0, lower, upper, algorithm="LD_LBFGS", max_iter=100, ftol_rel=1e-7, max_time_s=None,
             callback=None, desc="optimize"):
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


# -- the whole design run --------------------------------------------------------------------------
@dataclass
class DesignRun:
    """Result of :func:`design_doe`: the design file object and the report figures."""

    design: Design
    continuous_height_m: np.ndarray
    history: dict
    report: dict = field(default_factory=dict)


def coded_support(camera, pitch_m, shape):
    """Boolean map of the design pixels that the coded half-aperture sees (any light at all)."""
    grid = camera.pupil_grid_shape(shape, pitch_m)
    coded = camera.view_weights(grid, pitch_m)[0]
    oy, ox = (grid[0] - shape[0]) // 2, (grid[1] - shape[1]) // 2
    return coded[oy:oy + shape[0], ox:ox + shape[1]] > 0


def design_doe(target, camera, pitch_m, shape, material="fused_silica", design_wavelength_m=550e-9,
               loss=None, settings=None, init_height_m=None, callback=None, doe_oversample=1, perturbations=None,
               full_window=False):
    """Optimize a DOE for ``target`` and quantize it to the process levels.

    Parameters
    ----------
    target : doedesign.targets.Target
    camera : doedesign.camera.Camera
        Its window and axis must match the target's.
    pitch_m : float
    shape : (int, int)
        Design grid (DOE pixels), centred on the axis.
    loss : doedesign.losses.LossSpec, optional
    settings : OptimizerSettings, optional
    init_height_m : ndarray, optional
        A user starting height map (overrides ``settings.init``).
    callback : callable, optional
        ``callback(evaluation, loss, height_m)``; True stops the current stage.
    perturbations : list of callable, optional
        ``h -> (h', vjp)`` each; the loss becomes their mean or CVaR (robust design).
    full_window : bool
        Compute the whole sensor window at every evaluation even when the loss reads only a
        few pixels and the window energy (same result, slower; for checks and benchmarks).

    Returns
    -------
    DesignRun
    """
    settings = settings or OptimizerSettings()
    loss = loss or LossSpec()
    if perturbations and settings.objective == "maxmin":
        raise DoeError("robust design: the maxmin objective has no robust form; use objective loss or softmin")
    if tuple(target.window_shape) != tuple(camera.window_shape) or target.axis_pixel != camera.axis_pixel:
        raise DoeError(f"target window {tuple(target.window_shape)} / axis {target.axis_pixel} does not match the "
                       f"camera's {camera.window_shape} / {camera.axis_pixel}")
    t0 = time.perf_counter()
    engine = PSFEngine(camera, pitch_m, shape, material, target.wavelengths_m, target.depths_m, doe_oversample)
    step = level_step_m(material, design_wavelength_m, settings.n_levels)
    lower, upper = height_bounds(step, settings.n_levels, settings.height_range)
    support = coded_support(camera, pitch_m, tuple(shape))
    rng = np.random.default_rng(settings.seed)
    report = {}

    def start_height(kind):
        if kind == "router":
            return router_start(target, camera, pitch_m, tuple(shape), material, lower, settings)
        period_m = target.meta.get("period_m")
        finite = target.depths_m[np.isfinite(target.depths_m)]
        return initial_height(kind, tuple(shape), step, lower, rng, settings.n_levels,
                              period_px=int(round(period_m / pitch_m)) if period_m else 16,
                              arms=target.meta.get("arms", "+"), pitch_m=pitch_m, camera=camera,
                              design_wavelength_m=design_wavelength_m, material=material,
                              focus_depth_m=float(np.median(finite)) if finite.size else None)

    if init_height_m is not None:
        h0 = np.asarray(init_height_m, dtype=float)
        if h0.shape != tuple(shape):
            raise DoeError(f"initial height map has shape {h0.shape}, the design is {tuple(shape)}")
        h0 = np.clip(h0, lower, upper)
    else:
        h0 = start_height(settings.init)
    h0 = np.where(support, h0, 0.0)
    # The reweighting rounds replace the target (its pixel weights) between stages.
    weights = plane_weights(target, settings.colour_weights)
    balanced = settings.objective != "loss"
    state = {"target": target, "loss": softmin_loss(target, weights, settings.softmin_tau) if balanced
             else make_loss(target, loss)}
    bound = spot_bound(camera, pitch_m, tuple(shape), target, material)

    def objective(h, extra=None):
        if perturbations:
            value, grad = robust_value_and_grad(lambda x: engine.value_and_grad(x, state["loss"], full_window=full_window), h, perturbations,
                                                settings.robust_measure, settings.cvar_alpha)
        else:
            value, grad = engine.value_and_grad(h, state["loss"], full_window=full_window)
        if settings.fab_weight:
            v, g = isolation_penalty(h, step)
            value += settings.fab_weight * v
            grad = grad + settings.fab_weight * g
        if extra is not None:
            v, g = extra(h)
            value += v
            grad = grad + g
        return value, grad

    def metrics(h):
        psf = engine.psf(h, views=("coded",)).psf[0]
        out = target_metrics(psf, target)
        out["loss"] = float(objective(h)[0])
        out["bound"] = bound_report(out["energy_on_target"], bound)
        return out

    def reweight(h):
        if settings.reweight_rounds and not balanced:
            psf = engine.psf(h, views=("coded",)).psf[0]
            state["target"] = reweight_target(state["target"], psf, settings.reweight_alpha)
            state["loss"] = make_loss(state["target"], loss)

    # Only the pixels the coded view sees are free; the others stay at 0 (unetched).
    def on_support(fun):
        def wrapped(x):
            value, grad = fun(full(x))
            return value, grad[support]
        return wrapped

    def full(x):
        h = np.zeros(support.shape)
        h[support] = x
        return h

    def stage_callback(i, value, x):
        return callback(i, value, full(x)) if callback is not None else False

    def run_stage(fun, h_start, max_iter, max_time, desc):
        x, hist = minimize(on_support(fun), h_start[support], lower, upper, settings.algorithm, max_iter,
                           settings.ftol_rel, max_time, stage_callback, desc=desc)
        return full(x), hist

    starts = list(dict.fromkeys((settings.init, *settings.starts))) if init_height_m is None else ["user"]
    if len(starts) > 1:
        # Multi-start: a short stage from each initial design, the best one goes on.
        start_iter = settings.start_iter or max(settings.max_iter // 4, 3)
        tried = []
        for kind in starts:
            hs, hist = run_stage(objective, h0 if kind == settings.init else np.where(support, start_height(kind), 0.0),
                                 start_iter, settings.max_time_s, f"start {kind}")
            tried.append({"init": kind, "loss": min(hist), "height": hs,
                          "energy_on_target": metrics(hs)["energy_on_target"]})
        best = min(tried, key=lambda r: r["loss"])
        h0 = best["height"]
        report["multistart"] = [{k: v for k, v in r.items() if k != "height"} for r in tried]
        report["multistart_best"] = best["init"]
    if settings.objective == "maxmin":
        h_cont, hist_cont = maxmin_stage(engine, target, weights, h0, support, lower, upper, settings)
    else:
        h_cont, hist_cont = run_stage(objective, h0, settings.max_iter, settings.max_time_s, "design")
    for r in range(int(settings.reweight_rounds)):
        reweight(h_cont)
        h_cont, hist = run_stage(objective, h_cont, settings.reweight_iter or settings.max_iter,
                                 settings.max_time_s, f"reweight {r + 1}")
        hist_cont = hist_cont + hist
    if settings.height_range == "wrap":
        lower, upper = height_bounds(step, settings.n_levels, "2pi")
        h_cont = wrap_height_m(h_cont, step, settings.n_levels)
    history = {"continuous": hist_cont}
    report["continuous"] = metrics(h_cont)
    q = quantize(h_cont, step, settings.n_levels)
    levels, h_final = q.levels, q.height_m
    if settings.quantize:
        h = h_cont
        scale = max(report["continuous"]["loss"], 1e-6)
        history["anneal"] = []
        # The annealing stages together get at most half the continuous stage's time limit.
        stage_time = settings.max_time_s / (2 * len(ANNEAL_SCHEDULE)) if settings.max_time_s else None
        for mu in ANNEAL_SCHEDULE:
            def penalized(x, mu=mu):
                v, g = level_penalty(x, step, support)
                return scale * mu * v, scale * mu * g

            reweight(h)
            h, hist = run_stage(lambda x, p=penalized: objective(x, p), h, settings.anneal_iter, stage_time,
                                f"anneal x{mu:g}")
            history["anneal"].extend(hist)
        q = quantize(h, step, settings.n_levels)
        lev_a, h_a = q.levels, q.height_m
        # Both candidates are scored with the same (final) weights.
        report["rounded"] = metrics(h_final)
        report["annealed"] = metrics(h_a)
        if report["annealed"]["loss"] <= report["rounded"]["loss"]:
            levels, h_final, report["quantized_from"] = lev_a, h_a, "annealed"
        else:
            report["quantized_from"] = "rounded"
        report["quantized"] = report[report["quantized_from"]]
    else:
        h_final, levels = h_cont, None
    report.update({
        "run_time_s": time.perf_counter() - t0,
        "evaluations": sum(len(v) for v in history.values()),
        "loss_history": history,
        "level_step_m": step,
        "height_bounds_m": [lower, upper],
        "isolated_pixels": isolated_pixels(levels) if levels is not None else None,
        "settings": asdict(settings),
        "loss_spec": asdict(loss),
        "objective": settings.objective,
        "plane_weights": weights.tolist(),
        "final_pixel_weight_range": [float(f(np.broadcast_to(state["target"].pixel_weight, target.intensity.shape)
                                              [target.mask])) for f in (np.min, np.max)],
        "target": target.summary(),
        "camera": camera.to_dict(),
        "shape": list(shape),
        "pitch_m": pitch_m,
        "sampling": engine.sampling,
        "robust_samples": len(perturbations or ()),
    })
    design = Design(height_m=h_final, pitch_m=pitch_m, material=str(material),
                    design_wavelength_m=design_wavelength_m,
                    levels=None if levels is None else levels.astype(np.int16), aperture=support,
                    metadata={"name": target.name, "target": target.summary(), "camera": camera.to_dict(),
                              "optimizer": asdict(settings), "n_levels": settings.n_levels})
    return DesignRun(design=design, continuous_height_m=h_cont, history=history, report=report)

