"""The element's figure of merit for the design, the measured wafer and the corrected next wafer.

All three go through ``doe tolerance``'s machinery (:mod:`masks.tolerance`): the process model
on the whole element, the coded PSF and the design's own metrics (on-target light per colour
for a Bayer element, the light on the target pixels for others; :mod:`masks.tolerance.metrics`).

- design: the ideal process at the diagnosed nominal depths;
- measured wafer: every combined parameter at its mean, spread by its between-field spread;
- next wafer: the corrected parameters at what is left of them after the job sheet (zero for a
  shift, a rotation or a bias; for an etch, the measured error times the target's change), each
  spread by its between-field spread and its standard error (the correction is only as good as
  the mean it takes out); the rest as measured.

Each wafer is evaluated at its central values and at ``samples`` Monte Carlo draws (sample k
seeded from ``SeedSequence([seed, k])`` as in ``doe tolerance``).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

import numpy as np

from doedesign.design import Design
from doedesign.progress import Progress

from .systematic import Estimate, find_estimate

if TYPE_CHECKING:
    from masks.tolerance.evaluate import Evaluator
    from masks.tolerance.spec import ToleranceSpec

__all__ = ["change_percent", "merit_evaluator", "params_for_wafer", "predict_merit", "wafer_merit"]

# Diagnosis effect -> (tolerance-spec effect, component from the parameter name, factor to SI).
_COMPONENT = {"mask_overlay": lambda p: p[:2], "etch_gradient": lambda p: p[:1],
              "microtrenching": lambda p: p.split("_")[0]}


def _spec_param(e: Estimate, mean: float, sigma: float, nominal_depths_m: Sequence[float]):
    from masks.tolerance.spec import Param

    scale = 1.0
    if e.effect == "etch_depth":
        assert e.mask is not None  # a depth is per mask
        scale = nominal_depths_m[e.mask]
    elif e.effect == "mask_rotation":
        scale = math.pi / 180.0
    component = _COMPONENT.get(e.effect, lambda p: "")(e.param)
    mask = e.mask if e.effect not in ("etch_loading", "proximity_blur", "sidewall_slope", "etch_gradient") else None
    return Param(e.effect, mask, component, "normal", mean * scale, abs(sigma) * scale)


def _print_param(e: Estimate, corrected: bool):
    """A ``proximity_print`` parameter as the spec's ``proximity_gap`` or ``resist_threshold``
    (added to the nominal clearing level, the parameter's null); with ``corrected`` (masks
    pre-distorted for the gap, :mod:`metrology.correction.proximity`) the contact print they aim at: gap 0."""
    from masks.tolerance.spec import Param

    name = "proximity_gap" if e.param == "gap_m" else "resist_threshold"
    if corrected:
        return Param(name, None, "", "normal", 0.0, 0.0)
    return Param(name, None, "", "normal", e.mean - e.null, abs(e.spread))


def params_for_wafer(estimates: Sequence[Estimate], jobs: Sequence[dict], nominal_depths_m: Sequence[float],
                     corrected: bool) -> list:
    """Tolerance-spec parameters (:class:`masks.tolerance.spec.Param`) of the measured wafer or,
    with ``corrected``, of the next one made with the job sheet ``jobs``."""
    out = []
    gap = find_estimate(estimates, "proximity_print", None, "gap")  # corrected: the masks are pre-distorted
    for e in estimates:
        if e.effect == "proximity_print":
            out.append(_print_param(e, corrected and gap is not None))
            continue
        if e.effect not in ("etch_depth", "mask_overlay", "mask_rotation", "linewidth_bias", "etch_loading",
                            "proximity_blur", "sidewall_slope", "etch_gradient", "microtrenching"):
            continue
        mean, sigma = e.mean, e.spread
        if corrected and e.effect == "etch_depth":
            assert e.mask is not None  # a depth is per mask
            job = jobs[e.mask]
            # The etch aimed at the target removes (1 + error) target: relative to nominal, the error left.
            mean = (1.0 + e.mean) * job["etch_depth_target_nm"] / job["etch_depth_nm"] - 1.0
            if e.corrected or job["etch_loading_mean_loss_fraction"]:
                sigma = math.hypot(e.spread, e.standard_error)
        elif corrected and e.corrected and e.effect != "etch_loading":
            mean, sigma = e.null, math.hypot(e.spread, e.standard_error)
        out.append(_spec_param(e, mean, sigma, nominal_depths_m))
    if corrected:
        from masks.tolerance.spec import Param

        # A target moved only for the loading, on a mask whose depth error no field named.
        have = {e.mask for e in estimates if e.effect == "etch_depth"}
        for job in jobs:
            if job["mask"] not in have and job["etch_depth_target_nm"] != job["etch_depth_nm"]:
                shift = (job["etch_depth_target_nm"] - job["etch_depth_nm"]) * 1e-9
                out.append(Param("etch_depth", job["mask"], "", "normal", shift, 0.0))
    return out


def merit_evaluator(design: Design, nominal_depths_m: Sequence[float], source: str = "design", oversample: int = 2) -> Evaluator:
    """``doe tolerance``'s evaluator of ``design`` (its metrics set up on its ideal element) with
    the ideal process at the diagnosed nominal depths as the base every wafer's errors add to."""
    from masks.process import ProcessParams
    from masks.tolerance.analysis import build_evaluator
    from masks.tolerance.spec import ToleranceSpec

    ev, _, _ = build_evaluator(design, ToleranceSpec(params=[]), source=source, oversample=oversample)
    ev.base = ProcessParams.ideal(depths_m=nominal_depths_m)
    return ev


def wafer_merit(ev: Evaluator, spec: ToleranceSpec, samples: int, seed: int, key: str, bar: Progress | None = None) -> dict:
    """Metrics of one wafer: ``ev``'s element made with process ``spec`` at its central values and
    at ``samples`` draws (sample k from ``SeedSequence([seed, k])``).

    Returns
    -------
    dict
        ``central``, ``samples``, ``draws`` (``mean``, ``std``, ``worst`` per metric) and ``parameters``.
    """
    from masks.tolerance.metrics import DIRECTIONS

    ev.spec = spec
    central = ev({"id": "centre", "values": spec.nominal_values(), "seed": seed})["metrics"]
    if bar is not None:
        bar.update(1, status=f"{key} centre")
    draws = []
    for k in range(samples):
        values, s = spec.draw(seed, k)
        draws.append(ev({"id": k, "values": values, "seed": s})["metrics"])
        if bar is not None:
            bar.update(1, status=f"{key} {k + 1}/{samples}")
    stats = {}
    for name in central:
        v = np.array([d[name] for d in draws]) if draws else np.array([central[name]])
        worst = v.max() if DIRECTIONS.get(name) == "lower" else v.min()
        stats[name] = {"mean": float(v.mean()), "std": float(v.std(ddof=1)) if v.size > 1 else 0.0,
                       "worst": float(worst)}
    return {"central": central, "samples": samples, "draws": stats, "parameters": spec.describe()["parameters"]}


def change_percent(value: float, base: float, lower_better: bool) -> float:
    """``value`` against the design's ``base`` in percent, positive = better."""
    change = (value - base) / abs(base) * 100 if base else math.nan
    return -change if lower_better else change


def predict_merit(design: Design, estimates: Sequence[Estimate], jobs: Sequence[dict],
                  nominal_depths_m: Sequence[float], samples: int = 12, seed: int = 0, source: str = "design",
                  oversample: int = 2) -> dict:
    """Metrics of the design, the measured wafer and the corrected next wafer (see the module docstring).

    Returns
    -------
    dict
        ``primary_metric``, ``direction``, ``metric_unit``, and per wafer (``design``,
        ``measured_wafer``, ``corrected_wafer``): ``central`` (metrics at the central values),
        ``samples`` (number of draws), ``mean``, ``std`` and ``worst`` of each metric over the
        draws, and ``primary_change_percent`` (central primary metric against the design's,
        negative = worse).
    """
    from masks.tolerance.metrics import DIRECTIONS, metric_unit
    from masks.tolerance.spec import ToleranceSpec

    ev = merit_evaluator(design, nominal_depths_m, source, oversample)
    assert ev.metrics is not None  # build_evaluator sets it up
    primary = ev.metrics.primary
    lower_better = DIRECTIONS.get(primary) == "lower"
    nominal = ev.metrics(ev.coded_psf(ev.height({})))
    out: dict[str, Any] = {"primary_metric": primary, "direction": "lower" if lower_better else "higher",
           "metric_unit": metric_unit(primary), "oversample": int(oversample),
           "design": {"central": nominal, "samples": 0}}
    with Progress(2 * (samples + 1), desc="doe correct: merit") as bar:
        for key, corrected in (("measured_wafer", False), ("corrected_wafer", True)):
            spec = ToleranceSpec(params=params_for_wafer(estimates, jobs, nominal_depths_m, corrected),
                                 source=f"doe correct: {key}")
            out[key] = wafer_merit(ev, spec, samples, seed, key, bar)
    base = nominal[primary]
    for key in ("design", "measured_wafer", "corrected_wafer"):
        out[key]["primary_change_percent"] = change_percent(out[key]["central"][primary], base, lower_better)
    return out
