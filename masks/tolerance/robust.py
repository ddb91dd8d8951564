"""Process samples as height perturbations for robust design (``doe design --robust``).

Registered in the ``doe.perturbations`` entry-point group, so ``doedesign`` finds it without
importing ``masks``. Each perturbation is a :class:`masks.tolerance.smooth.SmoothProcess`:
the process sample acts on the optimizer's *continuous* heights through soft mask bits, so
the robust objective (the mean or CVaR of the loss over the K samples, which stay fixed for
the run: common random numbers) is differentiable and its adjoint gradient exact; heights
are quantized only at the end of the design, as without ``--robust``.
"""

from __future__ import annotations

import logging
import math
from pathlib import Path

import numpy as np

from doedesign.camera import Camera
from doedesign.levels import level_step_m

from ..decompose import binary_depths_m
from .smooth import SmoothProcess
from .spec import ToleranceSpec, default_spec, load_spec, nominal_process

__all__ = ["PITCH_M", "SMOOTH_EFFECTS", "nominal_vs_robust", "process_perturbations", "spec_perturbations",
           "study_camera"]

log = logging.getLogger(__name__)

PITCH_M = 5.4e-6
#: Spec effects the robust perturbation models; the others act in ``doe tolerance`` only.
SMOOTH_EFFECTS = ("etch_depth", "etch_gradient", "linewidth_bias", "mask_overlay", "mask_rotation")


def process_perturbations(spec: str | None, n_samples: int, seed: int, pitch_m: float, material: str = "fused_silica",
                          design_wavelength_m: float = 550e-9, n_levels: int = 16) -> list[SmoothProcess]:
    """``n_samples`` process samples of ``spec`` (a TOML / compare-report path, or None for the default).

    Sample k is the tolerance run's sample k for the same seed (``SeedSequence([seed, k])``).
    """
    step = level_step_m(material, design_wavelength_m, n_levels)
    depths = np.asarray(binary_depths_m(step, int(round(math.log2(n_levels)))))
    tol = load_spec(spec, depths) if spec else default_spec(depths)
    return spec_perturbations(tol, n_samples, seed, depths, step, pitch_m, n_levels)


def spec_perturbations(tol: ToleranceSpec, n_samples: int, seed: int, depths_m: np.ndarray, step_m: float,
                       pitch_m: float, n_levels: int = 16) -> list[SmoothProcess]:
    """Samples ``SeedSequence([seed, k])``, k < ``n_samples``, of a built spec as smooth perturbations."""
    ignored = sorted({p.effect for p in tol.params if p.effect not in SMOOTH_EFFECTS})
    if ignored:
        log.warning("robust design: %s act in doe tolerance only (not modelled on continuous heights)",
                    ", ".join(ignored))
    base = nominal_process(depths_m)
    out = []
    for k in range(int(n_samples)):
        values, s = tol.draw(seed, k)
        out.append(SmoothProcess(tol.params_for(values, base, seed=s), depths_m, step_m, pitch_m, n_levels))
    return out


def study_camera(size_px: int, window_px: int, pitch_m: float = PITCH_M) -> Camera:
    """The paper's camera scaled to a ``size_px`` aperture at the same f-number (spot size in pixels)."""
    full = Camera()
    assert full.aperture_diameter_m is not None  # the paper's camera has its aperture
    scale = size_px * pitch_m / full.aperture_diameter_m
    return Camera(aperture_diameter_m=size_px * pitch_m, focus_distance_m=math.inf,
                  sensor_distance_m=full.sensor_distance_m * scale, window_shape=(window_px, window_px),
                  axis_pixel=(window_px // 2, window_px // 2))


def nominal_vs_robust(size_px: int, window_px: int, spec_table: dict, out_dir: str | Path, robust_samples: int = 4,
                      eval_samples: int = 64, iterations: int = 40, anneal_iterations: int = 5,
                      measure: str = "mean", seed: int = 0, eval_seed: int = 1, scheduler: str = "inline",
                      workers: int | None = None, keep: float = 0.9, init: str = "router",
                      warm_start: bool = False) -> dict:
    """Design the Bayer element plainly and robustly, then run both through the same tolerance study.

    Both designs start from the same initial design (``init``) and run the same stages (soft-min
    objective, ``iterations`` continuous + annealing; with ``warm_start`` the robust design starts
    from the plain one's continuous heights instead); the robust one minimizes the mean (or
    CVaR) over process samples ``SeedSequence([seed, k])``, k < ``robust_samples``. The
    tolerance study draws ``eval_samples`` fresh ones from ``eval_seed`` (out of sample) with the
    full process model at oversample 2. Yield: ``on_target_mean`` >= ``keep`` x the plain
    design's nominal value, for both. Returns ``{"nominal": ..., "robust": ...}`` with the
    primary metric's nominal, mean, p10 and worst-decile mean, the yield and its 95 % interval,
    the per-sample values and the design times, and ``"paired"``: the share of evaluation samples
    (the same for both designs) in which the robust design is better, and the mean difference
    with its standard error.
    """
    import time

    from doedesign import targets
    from doedesign.optimizer.losses import LossSpec
    from doedesign.optimizer.optimize import OptimizerSettings, design_doe

    from .analysis import nominal_depths, tolerance_analysis
    from .spec import build_spec

    camera = study_camera(size_px, window_px)
    target = targets.bayer(camera)
    settings = OptimizerSettings(max_iter=iterations, anneal_iter=anneal_iterations, init=init, seed=seed,
                                 objective="softmin", robust_measure=measure)
    step = level_step_m("fused_silica", 550e-9, 16)
    depths = np.asarray(binary_depths_m(step, 4))
    spec = build_spec(spec_table, depths, "robust study spec")
    perturbations = spec_perturbations(spec, robust_samples, seed, depths, step, PITCH_M)
    out = {}
    threshold = start = None
    for name, pert in (("nominal", None), ("robust", perturbations)):
        t0 = time.perf_counter()
        run = design_doe(target, camera, PITCH_M, (size_px, size_px), loss=LossSpec.parse("l1,energy"),
                         settings=settings, init_height_m=start, perturbations=pert)
        if warm_start:
            start = run.continuous_height_m
        t_design = time.perf_counter() - t0
        design = run.design
        spec_eval = build_spec(spec_table, nominal_depths(design), "robust study spec")
        if threshold is None:
            nominal = tolerance_analysis(design, spec_eval, 1, Path(out_dir) / "probe", seed=eval_seed,
                                         scheduler="inline", sobol_base=0, one_at_a_time=False)
            threshold = {"on_target_mean": (">=", keep * nominal["nominal"]["on_target_mean"])}
        rep = tolerance_analysis(design, spec_eval, eval_samples, Path(out_dir) / name, design_name=name,
                                 seed=eval_seed, scheduler=scheduler, workers=workers, sobol_base=0,
                                 one_at_a_time=False, thresholds=threshold)
        m = rep["metrics"]["on_target_mean"]
        out[name] = {"metric": "on_target_mean", "nominal": m["nominal"], "mean": m["mean"], "p10": m["p10"],
                     "worst_decile_mean": m["worst_decile_mean"], "yield": rep["yield"]["fraction"],
                     "yield_ci95": rep["yield"]["ci95"], "threshold": rep["yield"]["thresholds"],
                     "design_s": t_design, "evaluations": run.report["evaluations"],
                     "per_colour_nominal": {k: v for k, v in rep["nominal"].items() if k.startswith("on_target_")},
                     "samples": [s["metrics"]["on_target_mean"]
                                 for s in sorted(rep["samples"], key=lambda s: s["index"])]}
    # Both designs saw the same evaluation samples, so the comparison can be paired.
    diff = np.subtract(out["robust"]["samples"], out["nominal"]["samples"])
    out["paired"] = {"robust_better_fraction": float(np.mean(diff > 0)), "mean_difference": float(diff.mean()),
                     "difference_se": float(diff.std(ddof=1) / np.sqrt(diff.size)) if diff.size > 1 else None}
    return out
