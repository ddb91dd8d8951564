"""Process tolerance spec: a distribution for each process effect, per mask where it applies.

TOML schema (every table optional; lengths in the unit named by the key)::

    [etch_depth]            # depth error of each mask's etch
    sigma_rel = 0.02        # or sigma_nm / mean_nm / mean_rel; dist = "normal" (default)
    [etch_depth.mask.3]     # override for mask 3 only (masks count from 0, 75 nm first);
    sigma_nm = 5            # it replaces the shared sigma of any unit
    [mask_overlay]          # x and y placement of masks 1.. relative to mask 0
    sigma_um = 0.25
    [mask_rotation]         # rotation of masks 1.. about the design centre
    sigma_urad = 20
    [linewidth_bias]        # growth of every opening edge
    sigma_um = 0.1
    [proximity_blur]        # one value per run: contact-gap blur sigma
    dist = "uniform"
    low_um = 0.0
    high_um = 0.5
    [proximity_gap]         # one value per run: mask-to-resist gap of proximity printing
    mean_um = 30            # (wafer bow: sigma_um); masks.proximity prints through it
    sigma_um = 3
    [resist_threshold]      # added to the nominal clearing level (dose_to_clear / dose), a number
    [collimation_half_angle]  # added to the nominal illumination half-angle (2 deg), in deg
    [sidewall_slope]        # width of the etched step ramp (um)
    [etch_loading]          # fractional depth loss per unit open fraction (plain number)
    [roughness]             # rms (nm)
    [microtrenching]        # per mask: depth (nm) and
    sigma_nm = 3            # width (um) of the trench at the foot of each etched edge
    mean_um = 0.5
    [etch_gradient]         # x and y: relative depth change across the field, % per mm
    sigma_percent_per_mm = 0.5
    [thresholds]            # yield: every threshold must hold
    on_target_mean = ">= 0.15"
    [yield]                 # the share of elements that must meet them (default 0.9);
    goal = 0.95             # doe tolerance --yield-goal overrides it

Distributions: ``normal`` (``mean_*``, ``sigma_*``), ``uniform`` (``low_*``, ``high_*``),
``fixed`` (``value_*``). ``masks = [1, 2]`` restricts a per-mask effect to some masks.
Effects that cannot be negative (blur, sidewall, roughness) are clipped at 0 after drawing.
Sample k of a run seeded S draws from ``numpy.random.default_rng(SeedSequence([S, k]))``, so
it does not depend on which worker or scheduler computes it.
"""

from __future__ import annotations

import math
import re
from pathlib import Path
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy import stats

from doedesign.errors import DoeError
from doedesign.fileio import read_json, read_toml

from ..effects import effect_spec
from ..process import ProcessParams
from ..process_params import finite_float

__all__ = ["DEFAULT_SPEC", "EFFECTS", "Param", "ToleranceSpec", "YIELD_GOAL", "build_spec", "check_yield_goal",
           "default_spec", "load_spec", "meets", "nominal_process", "parse_threshold", "sample_seed",
           "spec_from_compare"]

#: The yield a process is judged against unless the spec or the command says otherwise: nine
#: elements in ten within the thresholds.
YIELD_GOAL = 0.9

# The effects of masks.effects, as a tolerance spec names them (mask_rotation in urad here,
# applied as the rotation in ProcessParams.mask_overlay).
# effect -> (per_mask, skip mask 0, units {suffix: factor to SI}, report unit, clip at 0)
_LEN_UM = {"um": 1e-6}
EFFECTS = {
    "etch_depth": (True, False, {"nm": 1e-9, "rel": None}, "nm", False),
    "mask_overlay": (True, True, _LEN_UM, "um", False),
    "mask_rotation": (True, True, {"urad": 1e-6, "mrad": 1e-3}, "urad", False),
    "linewidth_bias": (True, False, _LEN_UM, "um", False),
    "proximity_blur": (False, False, _LEN_UM, "um", True),
    "sidewall_slope": (False, False, _LEN_UM, "um", True),
    "etch_loading": (False, False, {"": 1.0}, "", True),
    "roughness": (False, False, {"nm": 1e-9}, "nm", True),
    "proximity_gap": (False, False, _LEN_UM, "um", True),
    "resist_threshold": (False, False, {"": 1.0}, "", False),
    "collimation_half_angle": (False, False, {"deg": math.pi / 180}, "deg", False),
}
# Fields of the proximity print that are no effect of masks.effects: their plausible ranges.
_FIELD_BOUNDS = {"proximity_gap": (0.0, 200e-6), "resist_threshold": (0.0, 1.0),
                 "collimation_half_angle": (0.0, math.radians(10))}
# Per-mask / whole-run arrays of the process model set component by component.
_ARRAYS = {
    "microtrenching": (True, False, {"nm": 1e-9, "um": 1e-6}, "", True),
    "etch_gradient": (False, False, {"percent_per_mm": 10.0}, "percent_per_mm", False),
}
EFFECTS.update(_ARRAYS)
# Effects with several components: component -> report unit (its keys use that unit).
COMPONENTS = {"mask_overlay": {"dx": "um", "dy": "um"}, "microtrenching": {"depth": "nm", "width": "um"},
              "etch_gradient": {"x": "percent_per_mm", "y": "percent_per_mm"}}
REPORT_SCALE = {"nm": 1e9, "um": 1e6, "urad": 1e6, "percent_per_mm": 0.1, "deg": 180 / math.pi, "": 1.0}
DISTRIBUTIONS = {"normal": ("mean", "sigma"), "uniform": ("low", "high"), "fixed": ("value",)}
#: The tolerance analysis's default process spread per effect (relative or absolute sigmas).
DEFAULT_SPEC = {
    "etch_depth": {"sigma_rel": 0.02},
    "mask_overlay": {"sigma_um": 0.25},
    "linewidth_bias": {"sigma_um": 0.1},
}
DEFAULT_SPEC_NOTE = ("built-in default: typical contact lithography and RIE control (etch depth sigma 2 % per "
                     "mask, overlay sigma 0.25 um per axis for masks 1.. relative to mask 0, linewidth bias "
                     "sigma 0.1 um per mask)")
# The masks.effects parameter bounding each (effect, component): a spec's errors must stay within
# the process model's plausible range (mask_rotation is the overlay's rotation in rad).
_BOUNDED_BY = {("mask_overlay", "dx"): ("mask_overlay", 0), ("mask_overlay", "dy"): ("mask_overlay", 1),
               ("mask_rotation", ""): ("mask_overlay", 2), ("microtrenching", "depth"): ("microtrenching", 0),
               ("microtrenching", "width"): ("microtrenching", 1), ("etch_gradient", "x"): ("etch_gradient", 0),
               ("etch_gradient", "y"): ("etch_gradient", 1)}
_OPS = {">=": np.greater_equal, "<=": np.less_equal, ">": np.greater, "<": np.less}


@dataclass(frozen=True)
class Param:
    """One scalar random process parameter, in SI units.

    ``dist`` is normal (a = mean, b = sigma), uniform (a = low, b = high) or fixed (a).
    """

    effect: str
    mask: int | None
    component: str
    dist: str
    a: float
    b: float = 0.0

    @property
    def unit(self) -> str:
        return COMPONENTS.get(self.effect, {}).get(self.component, EFFECTS[self.effect][3])

    @property
    def name(self) -> str:
        """Report key with its unit, e.g. ``mask_overlay.dx_um[mask 2]``."""
        unit = self.unit
        comp = f".{self.component}" if self.component else ""
        where = f"[mask {self.mask}]" if self.mask is not None else ""
        return f"{self.effect}{comp}{'_' + unit if unit else ''}{where}"

    @property
    def label(self) -> str:
        """Human label for plots naming the mask and effect."""
        where = f"mask {self.mask} " if self.mask is not None else ""
        comp = f" {self.component}" if self.component else ""
        return f"{where}{self.effect}{comp}"

    @property
    def group(self) -> str:
        """Sobol group: the effect on one mask (its components together, e.g. overlay x and y)."""
        where = f"mask {self.mask} " if self.mask is not None else ""
        return f"{where}{self.effect}"

    @property
    def spread(self) -> float:
        return self.b - self.a if self.dist == "uniform" else (self.b if self.dist == "normal" else 0.0)

    def ppf(self, u: float | np.ndarray) -> float | np.ndarray:
        """Value at quantile(s) ``u`` in (0, 1), clipped at 0 for non-negative effects."""
        u = np.asarray(u, float)
        if self.dist == "normal":
            v = stats.norm.ppf(u, self.a, self.b) if self.b > 0 else np.full(u.shape, self.a)
        elif self.dist == "uniform":
            v = self.a + u * (self.b - self.a)
        else:
            v = np.full(u.shape, self.a)
        return np.maximum(v, 0.0) if EFFECTS[self.effect][4] else v

    def to_report(self, value: float | np.ndarray) -> float:
        return float(value) * REPORT_SCALE[self.unit]


@dataclass
class ToleranceSpec:
    """The random parameters of a process and the yield thresholds.

    Attributes
    ----------
    params : list of Param
    thresholds : dict
        metric -> (operator, value), e.g. ``{"on_target_mean": (">=", 0.15)}``.
    source : str
        Where the spec came from (file, compare report or built-in default).
    table : dict
        The spec as given (for the report).
    yield_goal : float
        Share of elements that must meet every threshold, in (0, 1).
    """

    params: list
    thresholds: dict = field(default_factory=dict)
    source: str = "built-in default"
    table: dict = field(default_factory=dict)
    yield_goal: float = YIELD_GOAL

    @property
    def random_params(self) -> list[Param]:
        """Parameters with a non-zero spread (the ones sensitivity analysis varies)."""
        return [p for p in self.params if p.spread > 0]

    def draw(self, seed_root: int, index: int) -> tuple[dict, int]:
        """Parameter values (SI) of sample ``index`` and its integer seed."""
        seed = sample_seed(seed_root, index)
        u = np.random.default_rng(seed).random(len(self.params))
        return {p.name: float(p.ppf(ui)) for p, ui in zip(self.params, u)}, seed

    def nominal_values(self) -> dict:
        """Every parameter at its centre (mean, mid-range or fixed value)."""
        return {p.name: float(p.ppf(0.5)) for p in self.params}

    def params_for(self, values: dict, base: ProcessParams, seed: int | None = None) -> ProcessParams:
        """The :class:`~masks.process_params.ProcessParams` of one sample: ``base`` plus the drawn errors."""
        depth = np.array(base.etch_depth, float)
        overlay = np.array(base.mask_overlay, float)
        bias = np.array(base.linewidth_bias, float)
        scalars: dict[str, float] = {}
        arrays: dict[str, np.ndarray] = {}
        for p in self.params:
            v = values[p.name]
            if p.effect == "etch_depth":
                depth[p.mask] += v
            elif p.effect == "mask_overlay":
                overlay[p.mask, 0 if p.component == "dx" else 1] += v
            elif p.effect == "mask_rotation":
                overlay[p.mask, 2] += v
            elif p.effect == "linewidth_bias":
                bias[p.mask] += v
            elif p.effect in _ARRAYS:
                arrays.setdefault(p.effect, np.array(getattr(base, p.effect), float))
                index = {"depth": 0, "width": 1, "x": 0, "y": 1}[p.component]
                arrays[p.effect][(p.mask, index) if p.mask is not None else index] += v
            else:
                scalars[p.effect] = scalars.get(p.effect, getattr(base, p.effect)) + v
        if "microtrenching" in arrays:
            # A trench needs a positive width wherever it has a depth.
            arrays["microtrenching"][:, 1] = np.maximum(arrays["microtrenching"][:, 1], 1e-9)
        return base.copy(etch_depth=np.maximum(depth, 0.0), mask_overlay=overlay, linewidth_bias=bias,
                         seed=seed, **scalars, **arrays)

    def describe(self) -> dict:
        """JSON-friendly description (units in the keys)."""
        rows = []
        for p in self.params:
            keys = DISTRIBUTIONS[p.dist]
            row = {"name": p.name, "effect": p.effect, "mask": p.mask, "dist": p.dist}
            for k, v in zip(keys, (p.a, p.b)):
                row[f"{k}_{p.unit}" if p.unit else k] = p.to_report(v)
            rows.append(row)
        return {"source": self.source, "given": self.table, "parameters": rows,
                "thresholds": {k: f"{op} {v:g}" for k, (op, v) in self.thresholds.items()},
                "yield_goal": self.yield_goal}


def sample_seed(seed_root: int, index: int) -> int:
    """Integer seed of sample ``index`` of a run seeded ``seed_root`` (independent streams)."""
    return int(np.random.SeedSequence([int(seed_root), int(index)]).generate_state(1)[0])


def parse_threshold(text: str, source: str = "threshold") -> tuple[str, tuple[str, float]]:
    """``"metric >= 0.3"`` -> ``(metric, (">=", 0.3))``."""
    m = re.fullmatch(r"\s*([A-Za-z_][\w\[\]. ]*?)?\s*(>=|<=|>|<)\s*([-+0-9.eE]+)\s*", str(text))
    if not m:
        raise DoeError(f"{source}: threshold {text!r} must look like 'metric >= value'")
    try:
        value = float(m.group(3))
    except ValueError:
        raise DoeError(f"{source}: threshold {text!r}: {m.group(3)!r} is not a number") from None
    return (m.group(1) or "").strip(), (m.group(2), value)


def check_yield_goal(value: object, what: str) -> float:
    """``value`` as a yield goal: a share strictly between 0 and 1 (1 can never be shown by sampling)."""
    goal = finite_float(value, what)
    if not 0 < goal < 1:
        raise DoeError(f"{what} must lie strictly between 0 and 1 (a share of elements), got {goal:g}")
    return goal


def meets(value: float, threshold: tuple[str, float]) -> bool:
    """Whether ``value`` meets ``threshold``, an ``(operator, limit)`` pair such as ``(">=", 0.8)``."""
    op, limit = threshold
    return bool(_OPS[op](value, limit))


def build_spec(table: dict, nominal_depths_m: np.ndarray, source: str = "spec") -> ToleranceSpec:
    """Parse a spec dict (the TOML schema above) for a design with ``len(nominal_depths_m)`` masks."""
    if not isinstance(table, dict):
        raise DoeError(f"{source}: the spec must be a table")
    n = len(nominal_depths_m)
    params, thresholds, goal = [], {}, YIELD_GOAL
    for effect, entry in table.items():
        if effect == "thresholds":
            if not isinstance(entry, dict):
                raise DoeError(f"{source}: [thresholds] must be a table of metric = '>= value'")
            for metric, text in entry.items():
                _, thresholds[metric] = parse_threshold(f"{metric} {text}", source)
            continue
        if effect == "yield":
            if not isinstance(entry, dict) or set(entry) != {"goal"}:
                raise DoeError(f"{source}: [yield] must hold one key, goal = a share in (0, 1), e.g. goal = 0.9")
            goal = check_yield_goal(entry["goal"], f"{source}: [yield] goal")
            continue
        if effect not in EFFECTS:
            raise DoeError(f"{source}: unknown effect {effect!r}; known: {', '.join(EFFECTS)}")
        if not isinstance(entry, dict):
            raise DoeError(f"{source}: [{effect}] must be a table")
        params.extend(_effect_params(effect, entry, n, nominal_depths_m, source))
    return ToleranceSpec(params=params, thresholds=thresholds, source=source, table=table, yield_goal=goal)


def _effect_params(effect, entry, n, nominal_depths_m, source):
    per_mask, skip0, _, _, _ = EFFECTS[effect]
    entry = dict(entry)
    overrides = entry.pop("mask", {})
    first = 1 if skip0 else 0
    masks = entry.pop("masks", list(range(first, n)) if per_mask else None)
    if not per_mask:
        if overrides or masks is not None:
            raise DoeError(f"{source}: [{effect}] is one value per run; it takes no mask")
        return [_param(effect, None, comp, _for_component(effect, comp, entry), None, source)
                for comp in _components(effect)]
    if not isinstance(overrides, dict):
        raise DoeError(f"{source}: [{effect}.mask] must hold tables named by mask index")
    try:
        masks = sorted({int(m) for m in masks} | {int(k) for k in overrides})
    except (TypeError, ValueError):
        raise DoeError(f"{source}: [{effect}] masks must be integers, got {masks!r} / {list(overrides)}") from None
    for m in masks:
        if not first <= m < n:
            what = "mask 0 is the reference" if skip0 and m == 0 else f"the design has masks 0..{n - 1}"
            raise DoeError(f"{source}: [{effect}] names mask {m}, which does not exist ({what})")
    out = []
    for m in masks:
        # A per-mask key replaces the shared one of the same kind (sigma_nm replaces sigma_rel).
        own = overrides.get(str(m), overrides.get(m, {}))
        replaced = {k.partition("_")[0] for k in own}
        values = {**{k: v for k, v in entry.items() if k.partition("_")[0] not in replaced}, **own}
        for comp in _components(effect):
            out.append(_param(effect, m, comp, _for_component(effect, comp, values), nominal_depths_m[m], source))
    return out


def _components(effect):
    return tuple(COMPONENTS.get(effect, {"": None}))


def _for_component(effect, comp, values):
    """The keys of one component: all of them, or those in its own unit (microtrench depth nm, width um)."""
    unit = COMPONENTS.get(effect, {}).get(comp)
    if effect != "microtrenching":
        return values
    return {k: v for k, v in values.items() if k == "dist" or k.partition("_")[2] == unit}


def _param(effect, mask, component, values, nominal_depth_m, source):
    units = EFFECTS[effect][2]
    values = dict(values)
    bases = {k.partition("_")[0] for k in values}
    dist = values.pop("dist", "uniform" if bases & {"low", "high"} else "fixed" if "value" in bases else "normal")
    where = f"[{effect}]" + (f" mask {mask}" if mask is not None else "")
    if dist not in DISTRIBUTIONS:
        raise DoeError(f"{source}: {where}: unknown dist {dist!r}; choose {', '.join(DISTRIBUTIONS)}")
    got = {}
    for key, value in values.items():
        base, _, unit = key.partition("_")
        if base not in DISTRIBUTIONS[dist] or unit not in units:
            allowed = [f"{b}_{u}" if u else b for b in DISTRIBUTIONS[dist] for u in units]
            raise DoeError(f"{source}: {where}: unknown key {key!r} for dist {dist!r}; use {', '.join(allowed)}")
        value = finite_float(value, f"{source}: {where}: {key}")
        if base in got:
            raise DoeError(f"{source}: {where}: give {base} once (in one unit), got {sorted(values)}")
        factor = units[unit] if units[unit] is not None else nominal_depth_m
        got[base] = value * factor
    keys = DISTRIBUTIONS[dist]
    a = got.get(keys[0], 0.0)
    b = got.get(keys[1], 0.0) if len(keys) > 1 else 0.0
    if dist == "normal" and b < 0:
        raise DoeError(f"{source}: {where}: negative width (sigma {b:g} SI); a sigma must be >= 0")
    if dist == "uniform" and b < a:
        raise DoeError(f"{source}: {where}: negative width (high < low)")
    param = Param(effect, mask, component, dist, a, b)
    _check_plausible(param, keys, a, b, f"{source}: {where}")
    return param


def _check_plausible(param, keys, a, b, where):
    """Refuse values beyond the process model's plausible range (:data:`masks.effects.PROCESS_EFFECTS`).

    Offsets and bounds may reach the largest magnitude the range allows, a sigma its whole
    width: a sigma of 1e6 um is no process and would make the model allocate absurd grids.
    """
    if param.effect in _FIELD_BOUNDS:
        lower, upper = _FIELD_BOUNDS[param.effect]
    else:
        name, index = _BOUNDED_BY.get((param.effect, param.component), (param.effect, 0))
        bound = effect_spec(name).params[index]
        lower, upper = bound.lower, bound.upper
    reach, width = max(abs(lower), abs(upper)), upper - lower
    for key, value in zip(keys, (a, b)):
        limit = width if key == "sigma" else reach
        if abs(value) > limit:
            unit = param.unit
            raise DoeError(f"{where}: {key} {param.to_report(value):g}{' ' + unit if unit else ''} is beyond the "
                           f"process model's plausible range (|{key}| <= {param.to_report(limit):g}"
                           f"{' ' + unit if unit else ''})")


def load_spec(path: str | Path, nominal_depths_m: np.ndarray) -> ToleranceSpec:
    """Read a spec: a TOML file, or a ``doe compare`` report.json (what the fab delivered).

    The file's size is checked before it is read; a file nested too deeply or not UTF-8 is
    refused as one line.
    """
    path = Path(path)
    if path.suffix == ".json":
        report = read_json(path, "doe compare report")
        if not isinstance(report, dict):
            raise DoeError(f"{path}: not a doe compare report (a JSON object)")
        return spec_from_compare(report, nominal_depths_m, str(path))
    return build_spec(read_toml(path, "tolerance spec"), nominal_depths_m, str(path))


def default_spec(nominal_depths_m: np.ndarray) -> ToleranceSpec:
    """The built-in spec (:data:`DEFAULT_SPEC`)."""
    spec = build_spec(DEFAULT_SPEC, nominal_depths_m, "built-in default")
    spec.source = DEFAULT_SPEC_NOTE
    return spec


def spec_from_compare(report: dict, nominal_depths_m: np.ndarray,
                      source: str = "compare report") -> ToleranceSpec:
    """Spec centred on the values a ``doe compare`` measured, with their standard errors as sigma."""
    n = len(nominal_depths_m)
    try:
        depths = np.asarray(report["etch_depths_nm"], float)
        depths_err = np.asarray(report.get("etch_depths_err_nm", np.zeros(n)), float)
        overlay = np.asarray(report.get("overlay_um", np.zeros((n, 2))), float).reshape(-1, 2)
        overlay_err = np.asarray(report.get("overlay_err_um", np.zeros((n, 2))), float).reshape(-1, 2)
        bias = np.asarray(report.get("linewidth_bias_um", np.zeros(n)), float)
        bias_err = np.asarray(report.get("linewidth_bias_err_um", np.zeros(n)), float)
    except (KeyError, TypeError, ValueError) as exc:
        raise DoeError(f"{source}: not a doe compare report (need etch_depths_nm and friends): {exc}") from None
    if not (depths.shape == depths_err.shape == bias.shape == bias_err.shape == (n,)
            and overlay.shape == overlay_err.shape == (n, 2)):
        raise DoeError(f"{source}: the compare report describes {depths.size} masks, the design has {n}")
    nominal_nm = np.asarray(nominal_depths_m) * 1e9
    table: dict[str, dict[str, Any]] = {"etch_depth": {"mask": {str(j): {"mean_nm": float(depths[j] - nominal_nm[j]),
                                              "sigma_nm": float(depths_err[j])} for j in range(n)}},
             "mask_overlay": {"mask": {}},
             "linewidth_bias": {"mask": {str(j): {"mean_um": float(bias[j]), "sigma_um": float(bias_err[j])}
                                         for j in range(n)}}}
    params = build_spec(table, nominal_depths_m, source).params
    # Overlay x and y have their own means and errors; build them directly.
    table["mask_overlay"] = {"mask": {}}
    for j in range(1, n):
        for c, comp in enumerate(("dx", "dy")):
            params.append(Param("mask_overlay", j, comp, "normal", overlay[j, c] * 1e-6, overlay_err[j, c] * 1e-6))
            table["mask_overlay"]["mask"].setdefault(str(j), {})[f"{comp}_mean_um"] = float(overlay[j, c])
            table["mask_overlay"]["mask"][str(j)][f"{comp}_sigma_um"] = float(overlay_err[j, c])
    return ToleranceSpec(params=params, source=f"{source} (doe compare: measured values, standard errors as sigma)",
                         table=table)


def nominal_process(nominal_depths_m: np.ndarray) -> ProcessParams:
    """The ideal process for these mask depths."""
    return ProcessParams.ideal(depths_m=nominal_depths_m)
