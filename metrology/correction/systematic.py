"""Systematic against random: the effects of several diagnosed fields combined per parameter.

For every parameter of every fabrication effect the diagnoses could name, with ``v_i`` the
value fitted on field ``i`` and ``s_i`` its standard error, over the n fields whose diagnosis
tested the effect (:meth:`~metrology.correction.diagnoses.FieldDiagnosis.tested_effect`; a field
that did not try it, because a limit ended its diagnosis or the effect was not a candidate,
carries no information about it and has no vote):

- ``mean`` = the plain mean of ``v_i`` (every field one vote: the correction is for all of them);
- ``spread`` = the sample standard deviation of ``v_i`` (ddof 1): how much fields differ,
  measurement error included; with one field, its ``s_1``;
- ``standard_error`` = ``sqrt(max(spread**2, mean(s_i**2)) / n)``: the between-field scatter
  when it exceeds what the fits' own uncertainties allow, else those (three fields estimate a
  scatter poorly, and the fits bound it from below);
- ``excess_spread`` = ``sqrt(max(spread**2 - mean(s_i**2), 0))``: the part of the spread the
  fits' uncertainties do not explain, the field-to-field variation of the process;
- ``chi2_per_dof`` = ``sum((v_i - mean)**2 / s_i**2) / (n - 1)``: above
  :data:`DISAGREEMENT_CHI2` the fields disagree beyond their uncertainties (a warning).

A field whose diagnosis tested an effect and did not name it (or gives no value for a parameter)
counts with the parameter's null value and the effect's detection limit as its uncertainty (the
diagnosis would have named anything larger).

A parameter is *systematic* when ``|mean| > SIGNIFICANCE * standard_error`` and
``|mean| >`` its detection limit (:data:`DETECTION_LIMITS`: the smallest change the fab's
knobs make and the diagnosis resolves on one field). Only systematic parameters that a knob
acts on (:data:`KNOBS`) are corrected; everything else is reported as spread.
"""

from __future__ import annotations

import math
import re
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field

import numpy as np

from metrology.diagnosis.effects import get_effect

from .diagnoses import FieldDiagnosis

__all__ = ["DETECTION_LIMITS", "DISAGREEMENT_CHI2", "Estimate", "KNOBS", "SIGNIFICANCE", "combine_fields",
           "find_estimate", "parameter_mask"]

SIGNIFICANCE = 3.0
#: chi2 per degree of freedom above which fields disagree beyond their fitted uncertainties
#: (p < 1e-4 for 2 degrees of freedom, three fields).
DISAGREEMENT_CHI2 = 9.0
#: Smallest systematic value worth correcting, in the diagnosis's units: the aligner's dial
#: (0.05 um, 0.002 deg = 35 urad), the mask writer's edge placement (0.02 um), etch-depth control
#: (0.5 % of the depth), a 1 % loading, 0.1 um of blur or sidewall, 2 nm of trench, 0.1 %/mm of
#: gradient, a 2 um gap (an aligner's gap setting). Each is also above what one diagnosed field
#: resolves (its fitted uncertainty).
DETECTION_LIMITS = {
    "proximity_print": 2e-6,
    "etch_depth": 0.005, "mask_overlay": 0.05e-6, "mask_rotation": 0.002, "linewidth_bias": 0.02e-6,
    "etch_loading": 0.01, "proximity_blur": 0.1e-6, "sidewall_slope": 0.1e-6, "microtrenching": 2e-9,
    "etch_gradient": 1.0,
}
#: The knob that takes a systematic effect out of the next run.
KNOBS = {"etch_depth": "etch target depth", "mask_overlay": "aligner offset", "mask_rotation": "aligner rotation",
         "linewidth_bias": "drawn edges offset", "etch_loading": "etch target depth (mean loss over the openings)",
         "proximity_print": "masks pre-distorted for the gap (OPC)"}
_MASK = re.compile(r"mask(\d+)")


def parameter_mask(name: str) -> int | None:
    """The mask a diagnosis parameter belongs to (``dx_mask2_m`` -> 2), None for whole-run ones."""
    m = _MASK.search(name)
    return int(m.group(1)) if m else None


@dataclass
class Estimate:
    """One parameter combined over the fields (units of the diagnosis's parameter)."""

    effect: str
    param: str
    unit: str
    mask: int | None
    values: list
    uncertainties: list
    named_in: int
    tested_in: int
    fields: int
    mean: float
    standard_error: float
    spread: float
    excess_spread: float
    chi2_per_dof: float | None
    detection_limit: float
    systematic: bool
    knob: str | None
    corrected: bool
    null: float = 0.0
    notes: list = field(default_factory=list)

    def to_dict(self) -> dict:
        return asdict(self)


def find_estimate(estimates: Sequence[Estimate], effect: str, mask: int | None, prefix: str,
                  corrected_only: bool = True) -> Estimate | None:
    """The first estimate of ``effect`` on ``mask`` (None: a whole-run parameter) whose parameter
    name starts with ``prefix``; only a corrected one unless ``corrected_only`` is False."""
    for e in estimates:
        if e.effect == effect and e.mask == mask and e.param.startswith(prefix) and (e.corrected or not corrected_only):
            return e
    return None


def combine_fields(fields: Sequence[FieldDiagnosis]) -> list[Estimate]:
    """Per parameter of every fabrication effect named on any field: mean, errors, spread, verdict."""
    named = []
    for f in fields:
        named += [e for e in f.params if e not in named]
    out = []
    for effect in named:
        eff = get_effect(effect)
        limit = DETECTION_LIMITS.get(effect, math.inf)
        for p in eff.params:
            # A microtrench's width and a print's threshold are shapes, not sizes: the trench's depth
            # and the print's gap carry the significance.
            shape = (effect == "microtrenching" and p.name.startswith("width")) or (
                effect == "proximity_print" and p.name == "threshold")
            p_limit = math.inf if shape else limit
            vals, errs, n_named = [], [], 0
            tested = [f for f in fields if f.tested_effect(effect)]
            for f in tested:
                if p.name in f.params.get(effect, {}):
                    vals.append(f.params[effect][p.name])
                    err = f.uncertainties[effect].get(p.name, math.nan)
                    errs.append(err if math.isfinite(err) and err > 0 else (limit if math.isfinite(limit) else 0.0))
                    n_named += 1
                else:
                    vals.append(p.null)
                    errs.append(limit if math.isfinite(limit) else 0.0)
            v, s = np.array(vals), np.array(errs)
            n = v.size
            mean = float(v.mean())
            spread = float(v.std(ddof=1)) if n > 1 else float(s[0])
            fit_var = float(np.mean(s ** 2))
            se = math.sqrt(max(spread ** 2, fit_var) / n)
            excess = math.sqrt(max(spread ** 2 - fit_var, 0.0)) if n > 1 else 0.0
            chi2 = float(np.sum((v - mean) ** 2 / np.maximum(s, 1e-300) ** 2) / (n - 1)) if n > 1 else None
            size = abs(mean - p.null)
            systematic = bool(size > SIGNIFICANCE * se and size > p_limit)
            knob = KNOBS.get(effect)
            out.append(Estimate(effect=effect, param=p.name, unit=p.unit, mask=parameter_mask(p.name), values=vals,
                                uncertainties=errs, named_in=n_named, tested_in=len(tested), fields=len(fields), mean=mean, standard_error=se, spread=spread,
                                excess_spread=excess, chi2_per_dof=chi2, detection_limit=p_limit,
                                systematic=systematic, knob=knob, corrected=systematic and knob is not None,
                                null=p.null))
    return out
