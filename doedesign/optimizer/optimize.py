"""Height-map optimization with nlopt and analytic gradients, then a quantization-aware finish.

Pipeline (:func:`design_doe`)
-----------------------------
1. Continuous stage: minimize the target loss (:mod:`doedesign.optimizer.losses`) over the heights with
   nlopt (:mod:`doedesign.optimizer.nlopt_driver`; ``LD_LBFGS`` by default, ``LD_MMA`` or ``LD_CCSAQ``),
   gradients from :meth:`doedesign.engine.psf.PSFEngine.value_and_grad`. Heights are bounded, in the design file's
   convention (z up, 0 = unetched top, etched pixels negative):
   ``height_range="process"``: ``[-(N-1) step, 0]``, the deepest process level down to the top
   surface, so every height has a fabricable nearest level; ``"2pi"``: ``[-N step, 0]``, the
   full 2 pi height at the design wavelength, where a height rounding to level N wraps to
   level 0 (the same phase at the design wavelength only); ``"wrap"``: unbounded continuous
   heights wrapped modulo the 2 pi height at the end. Bounds cut a linear phase ramp into a
   clipped one, so single-wavelength designs (gratings, spot arrays) converge best with
   "wrap"; the wrap is exact at the design wavelength and approximate elsewhere.
2. Quantization-aware finish: penalty annealing toward the nearest level (:mod:`doedesign.optimizer.anneal`).
   The penalty ``mean sin^2(pi h / step)`` (zero on every level) is added with a growing weight
   and the heights re-optimized at each weight; finally each height is rounded (not floored) to the
   nearest level by the one level rule of :mod:`doedesign.levels` (the rule the masks,
   the comparison and the diagnosis use too). The plain rounding of the continuous optimum
   is evaluated as well and the better of the two is kept.
3. Optional fabrication regularizer (``fab_weight``) against one-pixel pillars and holes
   (:mod:`doedesign.isolation`).

Uniform multi-spot targets: ``reweight_rounds`` > 0 adds rounds after the continuous stage
in which the target's pixel weights are updated from the current PSF,
``w_i <- w_i (mean a / a_i)^reweight_alpha`` with ``a_i`` = delivered / wanted light
(:func:`doedesign.optimizer.losses.reweight_target`, the gradient analogue of weighted Gerchberg-Saxton),
and the heights re-optimized for ``reweight_iter`` evaluations. The weights keep being updated
before each annealing stage, so the quantized design stays balanced; the final weights are
in the report. On targets with one pixel per plane (Bayer) the update does nothing.

Robust design: ``perturbations`` (a list of functions ``h -> (h', vjp)``, e.g. process samples
from the ``doe.perturbations`` entry points) makes every stage minimize the mean loss over the
perturbed heights, or with ``robust_measure="cvar"`` the mean of the worst ``cvar_alpha`` share
(CVaR), through the same adjoint gradient pulled back by each ``vjp`` (:mod:`doedesign.optimizer.robust_loss`).
The list is fixed for the whole run (common random numbers), so the objective stays
deterministic for nlopt.

Balanced objectives (``objective``): ``"loss"`` minimizes the :class:`~doedesign.optimizer.losses.LossSpec`
terms; ``"softmin"`` the negative soft minimum of the per-plane energies on target over their
``colour_weights``; ``"maxmin"`` runs the continuous stage as nlopt's auxiliary-variable max-min
(:func:`doedesign.optimizer.objectives.maximize_min`, LD_MMA or LD_CCSAQ) and anneals with the soft-min.
``init="router"`` starts from the coherent pupil model's max-min (:mod:`doedesign.optimizer.router`);
``starts`` adds initial designs for a multi-start (:mod:`doedesign.optimizer.starts`: a short stage each,
the best goes on; all are in the report).

Metrics (energy on target per wavelength and depth, efficiency, L1, and each plane's energy
beside its single-colour bound, :mod:`doedesign.bounds`) are reported for the continuous, the
plainly rounded and the final quantized design.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from ..bounds import bound_report, spot_bound
from ..design import Design
from ..engine.psf import PSFEngine
from ..errors import DoeError
from ..isolation import isolated_pixels, isolation_penalty
from ..levels import level_step_m, quantize, wrap_height_m
from .anneal import ANNEAL_SCHEDULE, anneal, level_penalty
from .losses import LossSpec, make_loss, reweight_target, target_metrics
from .nlopt_driver import ALGORITHMS, StageCallback, minimize
from .objectives import maxmin_stage, plane_weights, softmin_loss
from .robust_loss import Perturbation, robust_value_and_grad
from .router import router_start
from .settings import HEIGHT_RANGES, OBJECTIVES, WRAP_SPAN, OptimizerSettings, height_bounds
from .starts import INITS, initial_height, multistart

if TYPE_CHECKING:
    from ..camera import Camera
    from ..targets import Target

# The optimizer's public names, wherever they are defined (callers import them from here).
__all__ = ["ALGORITHMS", "ANNEAL_SCHEDULE", "DesignRun", "HEIGHT_RANGES", "INITS", "OBJECTIVES", "OptimizerSettings",
           "WRAP_SPAN", "coded_support", "design_doe", "height_bounds", "initial_height", "isolated_pixels",
           "isolation_penalty", "level_penalty", "minimize", "robust_value_and_grad"]

# -- the whole design run --------------------------------------------------------------------------
@dataclass
class DesignRun:
    """Result of :func:`design_doe`: the design file object and the report figures."""

    design: Design
    continuous_height_m: np.ndarray
    history: dict
    report: dict = field(default_factory=dict)


def coded_support(camera: Camera, pitch_m: float, shape: tuple[int, int]) -> np.ndarray:
    """Boolean map of the design pixels that the coded half-aperture sees (any light at all)."""
    grid = camera.pupil_grid_shape(shape, pitch_m)
    coded = camera.view_weights(grid, pitch_m)[0]
    oy, ox = (grid[0] - shape[0]) // 2, (grid[1] - shape[1]) // 2
    return coded[oy:oy + shape[0], ox:ox + shape[1]] > 0


def design_doe(target: Target, camera: Camera, pitch_m: float, shape: tuple[int, int], material: str = "fused_silica",
               design_wavelength_m: float = 550e-9, loss: LossSpec | None = None,
               settings: OptimizerSettings | None = None, init_height_m: np.ndarray | None = None,
               callback: StageCallback | None = None, doe_oversample: int = 1,
               perturbations: Sequence[Perturbation] | None = None, full_window: bool = False) -> DesignRun:
    """Optimize a DOE for ``target`` and quantize it to the process levels.

    Parameters
    ----------
    target : doedesign.targets.Target
    camera : doedesign.camera.Camera
        Its window and axis must match the target's.
    pitch_m : float
    shape : (int, int)
        Design grid (DOE pixels), centred on the axis.
    loss : doedesign.optimizer.losses.LossSpec, optional
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
    shape = (int(shape[0]), int(shape[1]))
    engine = PSFEngine(camera, pitch_m, shape, material, target.wavelengths_m, target.depths_m, doe_oversample,
                       device=settings.device)
    step = level_step_m(material, design_wavelength_m, settings.n_levels)
    lower, upper = height_bounds(step, settings.n_levels, settings.height_range)
    support = coded_support(camera, pitch_m, shape)
    rng = np.random.default_rng(settings.seed)
    report: dict[str, Any] = {}

    def start_height(kind):
        if kind == "router":
            return router_start(target, camera, pitch_m, shape, material, lower, settings)
        period_m = target.meta.get("period_m")
        finite = target.depths_m[np.isfinite(target.depths_m)]
        return initial_height(kind, shape, step, lower, rng, settings.n_levels,
                              period_px=int(round(period_m / pitch_m)) if period_m else 16,
                              arms=target.meta.get("arms", "+"), pitch_m=pitch_m, camera=camera,
                              design_wavelength_m=design_wavelength_m, material=material,
                              focus_depth_m=float(np.median(finite)) if finite.size else None)

    if init_height_m is not None:
        h0 = np.asarray(init_height_m, dtype=float)
        if h0.shape != shape:
            raise DoeError(f"initial height map has shape {h0.shape}, the design is {shape}")
        h0 = np.clip(h0, lower, upper)
    else:
        h0 = start_height(settings.init)
    h0 = np.where(support, h0, 0.0)
    # The reweighting rounds replace the target (its pixel weights) between stages.
    weights = plane_weights(target, settings.colour_weights)
    balanced = settings.objective != "loss"
    state: dict[str, Any] = {"target": target, "loss": softmin_loss(target, weights, settings.softmin_tau) if balanced
             else make_loss(target, loss)}
    bound = spot_bound(camera, pitch_m, shape, target, material, device=engine.backend)

    def objective(h):
        if perturbations:
            value, grad = robust_value_and_grad(
                lambda x: engine.value_and_grad(x, state["loss"], full_window=full_window), h, perturbations,
                settings.robust_measure, settings.cvar_alpha)
        else:
            value, grad = engine.value_and_grad(h, state["loss"], full_window=full_window)
        if settings.fab_weight:
            v, g = isolation_penalty(h, step)
            value += settings.fab_weight * v
            grad = grad + settings.fab_weight * g
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

    # Only the pixels the coded view sees are free; the others stay at 0 (unetched). The plain
    # loss is evaluated from the free heights alone (only they cross to a GPU, only their
    # gradient comes back); a penalty on them (the annealing's) is added where they live.
    plain = not perturbations and not settings.fab_weight

    def on_support(penalty=None):
        def wrapped(x):
            if plain:
                x = engine.backend.asarray(x)
                value, grad = engine.value_and_grad_free(x, support, state["loss"], full_window=full_window)
            else:
                value, grad = objective(full(x))
                grad = grad[support]
            if penalty is not None:
                v, g = penalty(x)
                value += v
                grad += g
            return value, engine.backend.to_host(grad)
        return wrapped

    def full(x):
        h = np.zeros(support.shape)
        h[support] = x
        return h

    def stage_callback(i, value, x):
        return callback(i, value, full(x)) if callback is not None else False

    def run_stage(h_start, max_iter, max_time, desc, penalty=None):
        x, hist = minimize(on_support(penalty), h_start[support], lower, upper, settings.algorithm, max_iter,
                           settings.ftol_rel, max_time, stage_callback, desc=desc)
        return full(x), hist

    starts = list(dict.fromkeys((settings.init, *settings.starts))) if init_height_m is None else ["user"]
    if len(starts) > 1:
        def start(kind, first=h0):
            return first if kind == settings.init else np.where(support, start_height(kind), 0.0)

        h0, report["multistart"], report["multistart_best"] = multistart(
            starts, start, run_stage,
            lambda h: metrics(h)["energy_on_target"], settings.start_iter or max(settings.max_iter // 4, 3),
            settings.max_time_s)
    if settings.objective == "maxmin":
        h_cont, hist_cont = maxmin_stage(engine, target, weights, h0, support, lower, upper, settings)
    else:
        h_cont, hist_cont = run_stage(h0, settings.max_iter, settings.max_time_s, "design")
    for r in range(int(settings.reweight_rounds)):
        reweight(h_cont)
        h_cont, hist = run_stage(h_cont, settings.reweight_iter or settings.max_iter,
                                 settings.max_time_s, f"reweight {r + 1}")
        hist_cont = hist_cont + hist
    if settings.height_range == "wrap":
        lower, upper = height_bounds(step, settings.n_levels, "2pi")
        h_cont = wrap_height_m(h_cont, step, settings.n_levels)
    history = {"continuous": hist_cont}
    report["continuous"] = metrics(h_cont)
    q = quantize(h_cont, step, settings.n_levels)
    levels: np.ndarray | None = q.levels
    h_final = q.height_m
    if settings.quantize:
        scale = max(report["continuous"]["loss"], 1e-6)
        h, history["anneal"] = anneal(run_stage, h_cont,
                                      step, scale, settings.anneal_iter,
                                      settings.max_time_s, before_stage=reweight)
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

