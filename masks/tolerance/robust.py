"""Process samples as height perturbations for robust design (``doe design --robust``).

Registered in the ``doe.perturbations`` entry-point group, so ``doedesign`` finds it without
importing ``masks``. Each perturbation takes the optimizer's continuous heights ``h``, rounds
them to levels, makes that element with one process sample (the process model at one sample
per design pixel: area coverage, so sub-pixel overlay and bias change heights continuously)
and returns ``h + (fabricated - ideal)``. The adjoint treats the process error as constant
(straight-through: ``vjp`` is the identity), exact for a height offset and first-order right
for a depth scale error (whose true factor 1 + eps is within a few % of 1).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from doedesign.levels import level_step_m, quantize

from ..decompose import binary_depths_m
from ..fabricated import fabricated_height
from ..process import ProcessParams
from .spec import default_spec, load_spec, nominal_process


@dataclass
class ProcessPerturbation:
    """One process sample acting on continuous heights: ``h -> (h', vjp)``."""

    params: ProcessParams
    step_m: float
    pitch_m: float
    n_levels: int = 16

    def __call__(self, height_m):
        levels = quantize(height_m, self.step_m, self.n_levels).levels
        made = fabricated_height(levels, self.pitch_m, self.params, oversample=1)
        return height_m + (made + levels * self.step_m), _identity


def _identity(g):
    return g


def process_perturbations(spec, n_samples, seed, pitch_m, material="fused_silica", design_wavelength_m=550e-9,
                          n_levels=16):
    """``n_samples`` process samples of ``spec`` (a TOML / compare-report path, or None for the default).

    Sample k is the tolerance run's sample k for the same seed (``SeedSequence([seed, k])``).
    """
    step = level_step_m(material, design_wavelength_m, n_levels)
    depths = binary_depths_m(step, int(round(math.log2(n_levels))))
    tol = load_spec(spec, depths) if spec else default_spec(depths)
    base = nominal_process(depths)
    out = []
    for k in range(int(n_samples)):
        values, s = tol.draw(seed, k)
        out.append(ProcessPerturbation(tol.params_for(values, base, seed=s), step, pitch_m, n_levels))
    return out


def nominal_vs_robust(size_px, window_px, spec_table, out_dir, robust_samples=4, eval_samples=64, iterations=40,
                      anneal_iterations=5, measure="mean", seed=0, eval_seed=1, scheduler="inline", workers=None,
                      warm_start=True):
    """Design the Bayer element plainly and robustly, then run both through the same tolerance study.

    The robust design sees process samples ``SeedSequence([seed, k])``, k < ``robust_samples``;
    the tolerance study draws ``eval_samples`` fresh ones from ``eval_seed``, so the comparison is
    out of sample. With ``warm_start`` the robust design starts from the plain one's continuous heights. Returns ``{"nominal": ..., "robust": ...}`` with the primary metric's nominal,
    mean and worst-decile values, the yield against a common threshold (90 % of the plain design's
    nominal figure) and the design times.
    """
    import time
    from pathlib import Path

    from doedesign import targets
    from doedesign.camera import Camera
    from doedesign.losses import LossSpec
    from doedesign.optimize import OptimizerSettings, design_doe

    from .analysis import nominal_depths, tolerance_analysis
    from .spec import build_spec

    pitch = 5.4e-6
    camera = Camera(aperture_diameter_m=size_px * pitch, focus_distance_m=math.inf,
                    window_shape=(window_px, window_px), axis_pixel=(window_px // 2, window_px // 2))
    target = targets.bayer(camera)
    settings = OptimizerSettings(max_iter=iterations, anneal_iter=anneal_iterations, init="zeros", seed=seed,
                                 robust_measure=measure)
    step = level_step_m("fused_silica", 550e-9, 16)
    depths = binary_depths_m(step, 4)
    spec = build_spec(spec_table, depths, "robust study spec")
    base = nominal_process(depths)
    perturbations = []
    for k in range(robust_samples):
        values, s = spec.draw(seed, k)
        perturbations.append(ProcessPerturbation(spec.params_for(values, base, seed=s), step, pitch))
    out = {}
    threshold = None
    start = None
    for name, pert in (("nominal", None), ("robust", perturbations)):
        t0 = time.perf_counter()
        run = design_doe(target, camera, pitch, (size_px, size_px), loss=LossSpec.parse("l1,energy"),
                         settings=settings, init_height_m=start, perturbations=pert)
        if warm_start:
            start = run.continuous_height_m
        t_design = time.perf_counter() - t0
        design = run.design
        spec_eval = build_spec(spec_table, nominal_depths(design), "robust study spec")
        rep = tolerance_analysis(design, spec_eval, eval_samples, Path(out_dir) / name, design_name=name,
                                 seed=eval_seed, scheduler=scheduler, workers=workers, sobol_base=0,
                                 one_at_a_time=False, thresholds=threshold)
        primary = rep["primary_metric"]
        if threshold is None:
            threshold = {primary: (">=", 0.9 * rep["nominal"][primary])}
            rep = tolerance_analysis(design, spec_eval, eval_samples, Path(out_dir) / name, design_name=name,
                                     seed=eval_seed, scheduler="inline", sobol_base=0, one_at_a_time=False,
                                     thresholds=threshold)
        m = rep["metrics"][primary]
        out[name] = {"metric": primary, "nominal": m["nominal"], "mean": m["mean"], "p10": m["p10"],
                     "worst_decile_mean": m["worst_decile_mean"], "yield": rep["yield"]["fraction"],
                     "yield_ci95": rep["yield"]["ci95"], "threshold": rep["yield"]["thresholds"],
                     "design_s": t_design, "per_colour_nominal": {k: v for k, v in rep["nominal"].items()
                                                                  if k.startswith("on_target_")}}
    return out
