"""The effect registry: named, parametrized departures of the real part from the ideal model.

Each :class:`Effect` has a name, parameters with physical units and bounds, a function that
applies it to the model, a one-sentence explanation, and the *stage* of the forward model it
acts on. The diagnosis (:mod:`metrology.diagnosis.engine`) fits every candidate's parameters to a
measurement and keeps those that earn their parameters.

Stages, in the order the forward model applies them::

    height domain (a height map on the fine model grid, row 0 at the top)
        "process"  apply(params: ProcessParams, values) -> ProcessParams (masks stage model)
        "surface"  apply(height_m, values, step_m) -> height_m (instrument artefacts)
    PSF domain (a PSF stack shaped (views, wavelengths, rows, cols))
        "height"   apply(height_m, values) -> height_m (the DOE heights before the optics)
        "optics"   apply(render, values, info) -> render where render(height_m,
                   wavelengths_m, depth_m) returns the stack; effects wrap it (defocus,
                   spectral bandwidth). info holds focus_distance_m and depth_m.
        "sensor"   apply(stack, values, info) -> stack on the measured views (crosstalk,
                   background); info holds views (of stack), full (the stack of
                   every view before sensor effects) and full_views.

Users add their own effect from a script::

    @register_effect(name="depth_nonlinearity", domain="height", stage="surface",
                     params=[Parameter("k_per_m", "1/m", -1e5, 1e5, 5e3)],
                     description="The etch rate changed with depth: every height h became h + k h**2.")
    def depth_nonlinearity(height_m, values, step_m):
        return height_m + values[0] * height_m ** 2

and rerun: the library's ``candidates`` (``None`` = every registered effect of the domain) or
``doe diagnose --effects-file mine.py`` (the file registers them). A ``"surface"`` effect acts on
the model heights (m) on the fine grid in the design frame, before the instrument's blur and
pixels; a ``"process"`` effect maps :class:`masks.process.ProcessParams` to new ones.
``kind="artefact"`` marks a measurement artefact. :func:`unregister_effect` removes it. When no
registered effect explains a structured residual, the diagnosis names none and reports where
the residual lives (:mod:`metrology.diagnosis.locate`): that is when to write one.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import scipy.ndimage as ndi
from scipy.special import erf

from doedesign.errors import DoeError
from masks.process_params import ProcessParams

__all__ = ["DOMAINS", "Effect", "EffectError", "FWHM_PER_SIGMA", "KINDS", "Parameter", "REGISTRY", "STAGES",
           "apply_process", "batwing_profile", "batwing_transfer", "effects_for", "gaussian_blur", "get_effect",
           "register_effect", "unregister_effect"]

DOMAINS = ("height", "psf")
STAGES = {"height": ("process", "surface"), "psf": ("height", "optics", "sensor")}
KINDS = ("fabrication", "artefact", "calibration")
# Peak of sigma^2 d/dx G_sigma(x) for a unit step, at x = sigma: 1 / sqrt(2 pi e). Batwing
# amplitudes are quoted as the peak overshoot as a fraction of the step height.
_DOG_PEAK = 1.0 / np.sqrt(2.0 * np.pi * np.exp(1.0))


class EffectError(DoeError):
    """An effect is unknown, badly defined, or given the wrong number of values."""


class _Draft(ProcessParams):
    """A process between two effects' ``apply``: its checks wait for the last one. ``copy`` still
    copies its arrays as floats, and the checks only convert what they accept, so the process
    checked once at the end holds the values a check after every effect would give."""

    def __post_init__(self) -> None:
        pass


def apply_process(base: ProcessParams, effects: Sequence[Effect], model: dict[str, np.ndarray]) -> ProcessParams:
    """``base`` with the ``"process"``-stage ``effects`` applied in their order, each with its
    values in ``model``, checked once (a fit's model evaluation costs well under a millisecond; a
    check per effect would take half of it)."""
    params = base
    for e in effects:
        if e.stage == "process":
            if params is base:
                params = _Draft(**{f.name: getattr(base, f.name) for f in dataclasses.fields(base)})
            params = e.apply(params, e.check(model[e.name]))
    if params is base:
        return base
    return ProcessParams(**{f.name: getattr(params, f.name) for f in dataclasses.fields(params)})


@dataclass(frozen=True)
class Parameter:
    """One fitted parameter of an effect.

    Parameters
    ----------
    name : str
        Name with its unit where it helps (``shift_m``).
    unit : str
        Physical unit shown in reports (``"m"``, ``"rad"``, ``"1"`` for a fraction).
    lower, upper : float
        Bounds of the fit.
    scale : float
        Typical size; the fit works in units of ``scale`` (its ``x_scale``).
    null : float
        The value at which the effect vanishes (the ideal model).
    smooth : bool
        The residual is smooth in this parameter (a transfer's width, a trench's decay width) or
        linear in it (an etch depth, loading or gradient, a trench's depth: the heights scale),
        not an edge's position, which area coverage makes kink where the edge crosses a grid
        line: a fit's Jacobian takes forward differences in it, at half the evaluations of
        central ones (exact where the residual is linear).
    """

    name: str
    unit: str
    lower: float
    upper: float
    scale: float
    null: float = 0.0
    smooth: bool = False

    def __post_init__(self):
        if not (self.lower <= self.null <= self.upper) or not self.scale > 0:
            raise EffectError(f"parameter {self.name}: need lower <= null <= upper and scale > 0")


@dataclass(frozen=True)
class Effect:
    """A named effect: parameters, the function applying it, and what it means.

    Attributes
    ----------
    name : str
    domain : {"height", "psf"}
    stage : str
        Where in the forward model ``apply`` acts (see the module docstring).
    params : tuple of Parameter
    apply : callable
        Signature depends on ``stage`` (module docstring).
    description : str
        One sentence a user reads in the report.
    kind : {"fabrication", "artefact", "calibration"}
        ``"artefact"`` marks a measurement artefact, never to be blamed on fabrication.
    order : int
        Order within a stage (lower first).
    linear : bool
        A ``"surface"`` effect that is a linear, shift-invariant filter of the heights (a blur,
        a batwing): it may then act on each mask's etch alone, so that the camera model can move
        masks by sampling (:meth:`metrology.diagnosis.camera.CameraHeightProblem.render`).
        False, the safe default, for any other effect.
    fourier : callable, optional
        For a linear surface effect, its transfer on a fine grid's FFT:
        ``fourier(values, step_m, wr, wc, reach_px)`` with the angular frequencies (radians per
        fine cell) along rows (full) and columns (half spectrum) returns the factor to multiply
        the surface's spectrum by (broadcast to ``(wr.size, wc.size)``), or None when its taps
        reach further than ``reach_px`` cells (beyond, the FFT would wrap them around onto the
        pixels read), where ``apply`` on the fine grid must serve. The camera model then
        changes the effect's values at the cost of an inverse FFT, not of a new surface.
    beside_objective : bool
        A linear surface effect that is the instrument's own response at edges (a batwing),
        whose fitted width already is its lateral reach in the measurement: its part
        (transfer - 1) is added to the objective's optical transfer instead of imaged through it
        again (:meth:`metrology.matching.instrument.InstrumentModel.map_of`). Without an
        objective both are the same.
    mask_params : callable, optional
        For a per-mask effect, ``mask_params(n_masks) -> list of Parameter``: its parameters for
        an element of that many masks (:meth:`for_masks`); ``params`` holds those of four.
    """

    name: str
    domain: str
    stage: str
    params: tuple
    apply: object
    description: str
    kind: str = "fabrication"
    order: int = 0
    start: tuple | None = field(default=None)
    per_channel: bool = False
    linear: bool = False
    fourier: object = None
    beside_objective: bool = False
    mask_params: object = None

    def __post_init__(self):
        if self.domain not in DOMAINS:
            raise EffectError(f"effect {self.name}: domain must be one of {DOMAINS}, got {self.domain!r}")
        if self.stage not in STAGES[self.domain]:
            raise EffectError(f"effect {self.name}: stage of a {self.domain} effect must be one of "
                              f"{STAGES[self.domain]}, got {self.stage!r}")
        if self.kind not in KINDS:
            raise EffectError(f"effect {self.name}: kind must be one of {KINDS}, got {self.kind!r}")
        if not callable(self.apply):
            raise EffectError(f"effect {self.name}: apply must be callable")
        object.__setattr__(self, "params", tuple(self.params))
        if not self.params:
            raise EffectError(f"effect {self.name}: needs at least one parameter")

    @property
    def n_params(self) -> int:
        return len(self.params)

    def for_channels(self, channels: Sequence[str]) -> Effect:
        """This effect with its parameters repeated per channel (``per_channel`` effects).

        Parameters
        ----------
        channels : list of str
            Channel labels, e.g. ``"coded_550nm"``; one copy of every parameter per channel.
        """
        if not self.per_channel:
            return self
        params = [Parameter(f"{p.name}_{c}", p.unit, p.lower, p.upper, p.scale, p.null, p.smooth)
                  for c in channels for p in self.params]
        start = None if self.start is None else tuple(self.start) * len(channels)
        return Effect(self.name, self.domain, self.stage, params, self.apply, self.description,
                      self.kind, self.order, start, per_channel=False)

    def for_masks(self, n_masks: int) -> Effect | None:
        """This effect for an element of ``n_masks`` binary masks (``mask_params`` effects).

        A per-mask effect (``mask_params(n_masks)`` gives its parameters: one set per mask, or per
        mask after the first for an overlay or a rotation against mask 0) gets the parameters of
        that many masks; every other effect is returned as it is. None when the element has no
        mask the effect acts on (an overlay of a one-mask, binary element).
        """
        if self.mask_params is None:
            return self
        params = tuple(self.mask_params(int(n_masks)))
        if params == self.params:
            return self
        if not params:
            return None
        return dataclasses.replace(self, params=params, start=None)

    def null_values(self) -> np.ndarray:
        """Parameter values of the ideal model (the effect absent)."""
        return np.array([p.null for p in self.params], dtype=float)

    def start_values(self) -> np.ndarray:
        """Where a fit starts: ``start`` if given (for effects degenerate at null), else null."""
        return np.array(self.start, dtype=float) if self.start is not None else self.null_values()

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        return (np.array([p.lower for p in self.params], dtype=float),
                np.array([p.upper for p in self.params], dtype=float))

    def scales(self) -> np.ndarray:
        return np.array([p.scale for p in self.params], dtype=float)

    def check(self, values: float | Sequence[float] | np.ndarray) -> np.ndarray:
        """Values as a float array of the right length (raises :class:`EffectError`)."""
        v = np.atleast_1d(np.asarray(values, dtype=float))
        if v.shape != (self.n_params,):
            raise EffectError(f"effect {self.name} takes {self.n_params} values "
                              f"({', '.join(p.name for p in self.params)}), got {v.size}")
        return v

    def describe(self) -> dict[str, Any]:
        """Dictionary for reports."""
        return {"name": self.name, "domain": self.domain, "stage": self.stage, "kind": self.kind,
                "description": self.description,
                "params": [{"name": p.name, "unit": p.unit, "lower": p.lower, "upper": p.upper}
                           for p in self.params]}


REGISTRY: dict = {}


def register_effect(effect: Effect | None = None, *, replace: bool = False,
                    **kwargs: Any) -> Effect | Callable[[Callable], Callable]:
    """Add an effect to the registry; usable as a function or as a decorator.

    ``register_effect(Effect(...))`` registers an effect object.
    ``@register_effect(name=..., domain=..., stage=..., params=[...], description=...)``
    decorates the ``apply`` function.

    Parameters
    ----------
    effect : Effect, optional
    replace : bool
        Allow replacing an existing effect of the same name.
    **kwargs
        The :class:`Effect` fields except ``apply`` (decorator form).

    Returns
    -------
    Effect, or a decorator returning the decorated function unchanged.
    """
    def add(eff):
        if eff.name in REGISTRY and not replace:
            raise EffectError(f"an effect named {eff.name!r} is already registered (pass replace=True)")
        REGISTRY[eff.name] = eff
        return eff

    if effect is not None:
        if not isinstance(effect, Effect):
            raise EffectError(f"register_effect needs an Effect, got {type(effect).__name__}")
        return add(effect)

    def decorator(func):
        add(Effect(apply=func, **kwargs))
        return func

    return decorator


def unregister_effect(name: str) -> None:
    """Remove a (user) effect from the registry."""
    REGISTRY.pop(name, None)


def get_effect(name: str) -> Effect:
    try:
        return REGISTRY[name]
    except KeyError:
        raise EffectError(f"unknown effect {name!r}; registered: {', '.join(sorted(REGISTRY))}") from None


def effects_for(domain: str, names: Sequence[str] | None = None, n_masks: int | None = None) -> list[Effect]:
    """Registered effects of ``domain`` (optionally only ``names``), in forward-model order.

    With ``n_masks``, per-mask effects carry the parameters of that many masks
    (:meth:`Effect.for_masks`); one that no mask of such an element can show (an overlay of a
    binary element) is left out, or refused when ``names`` asks for it.
    """
    if domain not in DOMAINS:
        raise EffectError(f"domain must be one of {DOMAINS}, got {domain!r}")
    if names is None:
        chosen = [e for e in REGISTRY.values() if e.domain == domain]
    else:
        chosen = [get_effect(n) for n in names]
        for e in chosen:
            if e.domain != domain:
                raise EffectError(f"effect {e.name!r} belongs to the {e.domain} domain, not {domain}")
    if n_masks is not None:
        sized = [(e, e.for_masks(n_masks)) for e in chosen]
        absent = [e.name for e, s in sized if s is None]
        if absent and names is not None:
            raise EffectError(f"effect(s) {', '.join(absent)} need at least two masks; this element has {n_masks}")
        chosen = [s for _, s in sized if s is not None]
    stages = STAGES[domain]
    return sorted(chosen, key=lambda e: (stages.index(e.stage), e.order))


# -- array helpers ---------------------------------------------------------------------------
def _gaussian_taps(sigma_m, step_m):
    """Pixel-integrated Gaussian and Gaussian-second-derivative taps (per axis).

    For pixel-averaged heights ``h_k`` the blurred value at pixel ``j`` is
    ``sum_k h_k * integral over pixel k of G(x_j - x)``: taps ``Phi((m + 1/2) s / sigma) -
    Phi((m - 1/2) s / sigma)``; likewise ``G'(m s + s/2) - G'(m s - s/2)`` for ``G''``. They tend
    to the identity as sigma -> 0 (continuous for a least-squares fit) and do not depend on
    the size of the map (an FFT filter's band edge does).
    """
    half = int(np.ceil(5.0 * sigma_m / step_m)) + 1
    edges = (np.arange(-half, half + 2) - 0.5) * step_m
    cdf = 0.5 * (1.0 + erf(edges / (np.sqrt(2.0) * sigma_m)))
    smooth = np.diff(cdf)
    dens = np.exp(-0.5 * (edges / sigma_m) ** 2) / (np.sqrt(2.0 * np.pi) * sigma_m)
    first = -edges / sigma_m ** 2 * dens  # G'(x)
    second = np.diff(first)  # integral of G'' over each pixel (1/m^2 * m)
    return smooth / smooth.sum(), second


def gaussian_blur(height_m: np.ndarray, sigma_m: float, step_m: float) -> np.ndarray:
    """Gaussian blur of standard deviation ``sigma_m`` of a pixel-averaged map (separable)."""
    h = np.asarray(height_m, dtype=float)
    if sigma_m <= 0:
        return h
    smooth, _ = _gaussian_taps(sigma_m, step_m)
    out = ndi.correlate1d(h, smooth, axis=0, mode="nearest")
    return ndi.correlate1d(out, smooth, axis=1, mode="nearest")


def batwing_profile(height_m: np.ndarray, amplitude: float, sigma_m: float, step_m: float) -> np.ndarray:
    """Edge overshoot of a white-light interferometer: ``-a sigma^2 lap(G_sigma * h) / peak``.

    Across a step of height H the added profile is a derivative of Gaussian of width
    ``sigma_m``: an overshoot of ``amplitude * H`` at the top corner and an undershoot as deep
    at the bottom corner, zero on flat areas.
    """
    h = np.asarray(height_m, dtype=float)
    if sigma_m <= 0 or amplitude == 0:
        return np.zeros_like(h)
    smooth, second = _gaussian_taps(sigma_m, step_m)
    lap = (ndi.correlate1d(ndi.correlate1d(h, second, axis=0, mode="nearest"), smooth, axis=1, mode="nearest")
           + ndi.correlate1d(ndi.correlate1d(h, smooth, axis=0, mode="nearest"), second, axis=1, mode="nearest"))
    return -amplitude * sigma_m ** 2 / _DOG_PEAK * lap


# -- built-in height-domain effects ----------------------------------------------------------
def _etch_depth(params, values):
    depths = np.asarray(params.etch_depth, dtype=float) * (1.0 + values)
    return params.copy(etch_depth=tuple(depths))


def _mask_overlay(params, values):
    overlay = np.array(params.mask_overlay, dtype=float, copy=True)
    overlay[1:, 0] += values[0::2]
    overlay[1:, 1] += values[1::2]
    return params.copy(mask_overlay=overlay)


def _linewidth_bias(params, values):
    return params.copy(linewidth_bias=np.asarray(params.linewidth_bias, dtype=float) + values)


def _proximity_blur(params, values):
    return params.copy(proximity_blur=float(values[0]))


def _sidewall_slope(params, values):
    return params.copy(sidewall_slope=float(values[0]))


def _etch_loading(params, values):
    return params.copy(etch_loading=float(values[0]))


def _mask_rotation(params, values):
    rotation = np.array(params.mask_rotation, dtype=float, copy=True)
    rotation[1:] += values
    return params.copy(mask_rotation=rotation)


def _microtrenching(params, values):
    trench = np.array(params.microtrenching, dtype=float, copy=True)
    trench[:, 0] += values[0::2]
    # The width is a fitted value, not an increment: at zero depth it is free and harmless.
    trench[:, 1] = values[1::2]
    return params.copy(microtrenching=trench)


def _etch_gradient(params, values):
    return params.copy(etch_gradient=np.asarray(params.etch_gradient, dtype=float) + values)


def _instrument_blur(height_m, values, step_m):
    return gaussian_blur(height_m, float(values[0]), step_m)


def _batwing(height_m, values, step_m):
    return height_m + batwing_profile(height_m, float(values[0]), float(values[1]), step_m)


def batwing_transfer(values: Sequence[float], step_m: float, wr: np.ndarray, wc: np.ndarray,
                     reach_px: int) -> np.ndarray | None:
    """Fourier factor of ``h + batwing_profile(h)``: the same separable taps' responses (they
    are symmetric, so real: ``sum_k t_k cos(w k)``), or None beyond ``reach_px`` cells."""
    amplitude, sigma_m = float(values[0]), float(values[1])
    if sigma_m <= 0 or amplitude == 0:
        return np.ones((1, 1), np.float32)
    smooth, second = _gaussian_taps(sigma_m, step_m)
    half = smooth.size // 2
    if half > reach_px:
        return None
    k = np.arange(-half, half + 1)

    def response(taps, w):
        return np.cos(np.outer(w, k)) @ taps

    # The factor is kept in single precision: its two outer products are formed in it too.
    c = -amplitude * sigma_m ** 2 / _DOG_PEAK
    out = np.outer((c * response(second, wr)).astype(np.float32), response(smooth, wc).astype(np.float32))
    out += np.outer((c * response(smooth, wr)).astype(np.float32), response(second, wc).astype(np.float32))
    out += np.float32(1.0)
    return out


_UM = 1e-6


def _depth_params(n):
    return [Parameter(f"depth_error_mask{j}", "1", -0.3, 0.3, 0.02, smooth=True) for j in range(n)]


def _overlay_params(n):
    return [Parameter(f"{ax}_mask{j}_m", "m", -3 * _UM, 3 * _UM, 0.2 * _UM) for j in range(1, n) for ax in ("dx", "dy")]


def _bias_params(n):
    return [Parameter(f"bias_mask{j}_m", "m", -1.5 * _UM, 1.5 * _UM, 0.1 * _UM) for j in range(n)]


def _rotation_params(n):
    return [Parameter(f"rotation_mask{j}_deg", "deg", -0.5, 0.5, 0.005) for j in range(1, n)]


def _trench_params(n):
    return [Parameter(f"{q}_mask{j}_m", "m", lo, hi, sc, null, smooth=True) for j in range(n)
            for q, lo, hi, sc, null in (("depth", 0.0, 150e-9, 5e-9, 0.0),
                                        ("width", 0.05 * _UM, 3 * _UM, 0.1 * _UM, 0.4 * _UM))]


# The registry holds the per-mask effects of the four-mask (16-level) process; a diagnosis of an
# element of another mask count resizes them (effects_for(..., n_masks)).
_N = 4
_BUILTIN_HEIGHT = [
    Effect("etch_depth", "height", "process", _depth_params(_N), _etch_depth,
           "Each mask's etch went deeper or shallower than its target by a fraction: the 16 level "
           "heights stop being multiples of one step.", mask_params=_depth_params),
    Effect("mask_overlay", "height", "process",
           _overlay_params(_N), _mask_overlay,
           "A mask was printed shifted against the first one (x toward +column, y up): one-signed slivers "
           "of that mask's depth appear on opposite edges of its features.", mask_params=_overlay_params),
    Effect("linewidth_bias", "height", "process",
           _bias_params(_N), _linewidth_bias,
           "A mask's openings printed wider (positive) or narrower than drawn, from exposure dose or "
           "development: same-sign slivers on every edge of its features.", mask_params=_bias_params),
    Effect("proximity_blur", "height", "process",
           [Parameter("sigma_m", "m", 0.0, 4 * _UM, 0.5 * _UM)], _proximity_blur,
           "The contact-print gap blurs the mask's aerial image before the resist threshold: corners round "
           "and small isolated features shrink.", start=(0.8 * _UM,)),
    Effect("sidewall_slope", "height", "process",
           [Parameter("ramp_width_m", "m", 0.0, 3 * _UM, 0.3 * _UM)], _sidewall_slope,
           "The etch leaves sloped sidewalls: steps become ramps of a finite width.", start=(1.5 * _UM,)),
    Effect("etch_loading", "height", "process",
           [Parameter("loading", "1", -0.5, 0.5, 0.02, smooth=True)], _etch_loading,
           "The etch rate depends on the local open fraction of the mask: depth follows pattern density."),
    Effect("mask_rotation", "height", "process",
           _rotation_params(_N), _mask_rotation,
           "A mask was printed rotated about the design's centre (design pixel ((rows - 1) / 2, (cols - 1) / 2), "
           "not the camera field's) against the first one: its overlay grows linearly with the distance from "
           "that centre, opposite in sign on opposite sides.", mask_params=_rotation_params),
    Effect("microtrenching", "height", "process",
           _trench_params(_N), _microtrenching,
           "Ions reflected from the sidewalls etched deeper at the foot of a mask's etched edges: a trench "
           "inside each opening along its edges, decaying over a width, in proportion to that etch.",
           mask_params=_trench_params),
    Effect("etch_gradient", "height", "process",
           [Parameter(f"{ax}_per_m", "1/m", -100.0, 100.0, 5.0, smooth=True) for ax in ("x", "y")], _etch_gradient,
           "Plasma non-uniformity made every etch deeper on one side of the field by the same relative "
           "amount per metre (x toward +column, y up; 10 /m = 1 % per mm), referred to the design's centre "
           "(depths nominal there, not at the camera field's centre)."),
    Effect("instrument_blur", "height", "surface",
           [Parameter("sigma_m", "m", 0.0, 3 * _UM, 0.2 * _UM)], _instrument_blur,
           "Measurement artefact: the profilometer's finite lateral resolution (about 0.8 um at NA 0.4) "
           "smooths every step.", kind="artefact", order=20, start=(0.4 * _UM,), linear=True),
    Effect("batwing", "height", "surface",
           [Parameter("amplitude", "1", -1.0, 1.0, 0.05, smooth=True),
            Parameter("sigma_m", "m", 0.1 * _UM, 3 * _UM, 0.2 * _UM, 0.1 * _UM, smooth=True)],
           _batwing,
           "Measurement artefact: a white-light interferometer overshoots at steps shorter than its coherence "
           "length, a signed edge spike proportional to the step height.", kind="artefact", order=10,
           start=(0.05, 0.6 * _UM), linear=True, fourier=batwing_transfer, beside_objective=True),
]
for _e in _BUILTIN_HEIGHT:
    register_effect(_e)


# -- built-in PSF-domain effects -------------------------------------------------------------
# Gauss-Hermite nodes for averaging over a Gaussian source spectrum (exact for polynomials of
# degree 5 in wavelength, enough for a smear of a few pixels).
_GH_NODES, _GH_WEIGHTS = np.polynomial.hermite_e.hermegauss(3)
_GH_WEIGHTS = _GH_WEIGHTS / _GH_WEIGHTS.sum()
FWHM_PER_SIGMA = 2.0 * np.sqrt(2.0 * np.log(2.0))


def _depth_scale(height_m, values):
    return height_m * (1.0 + float(values[0]))


def _defocus(render, values, info):
    inv = 1.0 / info["depth_m"] + float(values[0])
    depth = np.inf if inv <= 0 else 1.0 / inv

    def shifted(height_m, wavelengths_m, depth_m):
        return render(height_m, wavelengths_m, depth)

    return shifted


def _source_bandwidth(render, values, info):
    sigma = float(values[0]) / FWHM_PER_SIGMA
    if sigma <= 0:
        return render

    def averaged(height_m, wavelengths_m, depth_m):
        wl = np.asarray(wavelengths_m, dtype=float)
        samples = (wl[None, :] + sigma * _GH_NODES[:, None]).ravel()
        stack = render(height_m, samples, depth_m)
        stack = stack.reshape(stack.shape[0], _GH_NODES.size, wl.size, *stack.shape[-2:])
        return np.tensordot(stack, _GH_WEIGHTS, axes=([1], [0]))

    return averaged


def _dual_pixel_crosstalk(stack, values, info):
    views, full, full_views = list(info["views"]), info["full"], list(info["full_views"])
    if "coded" not in views:
        return stack
    c = float(values[0])
    out = stack.copy()
    out[views.index("coded")] = ((1.0 - c) * full[full_views.index("coded")]
                                 + c * full[full_views.index("uncoded")])
    return out


def _background(stack, values, info):
    return stack + np.asarray(values, dtype=float).reshape(stack.shape[:2])[..., None, None]


_BUILTIN_PSF = [
    Effect("dual_pixel_crosstalk", "psf", "sensor",
           [Parameter("fraction", "1", 0.0, 0.5, 0.02)], _dual_pixel_crosstalk,
           "The dual-pixel sensor leaks a fraction of the uncoded view's light into the coded view.",
           kind="calibration", start=(0.02,)),
    Effect("source_bandwidth", "psf", "optics",
           [Parameter("fwhm_m", "m", 0.0, 60e-9, 3e-9)], _source_bandwidth,
           "The calibration source is not monochromatic: each PSF is averaged over a band of wavelengths, "
           "smearing diffraction orders radially.", kind="calibration", start=(4e-9,)),
    Effect("defocus", "psf", "optics",
           [Parameter("inverse_distance_change_per_m", "1/m", -0.19, 5.0, 0.1)], _defocus,
           "The point source was not where the camera is focused (or the sensor moved): a change of "
           "1/distance adds a spherical phase that blurs the PSF symmetrically.", kind="calibration",
           start=(0.3,)),
    Effect("depth_scale", "psf", "height",
           [Parameter("scale_error", "1", -0.3, 0.3, 0.02)], _depth_scale,
           "All heights are off by one factor (index or depth calibration): light moves into the zero "
           "and second orders.", kind="fabrication"),
    Effect("background", "psf", "sensor",
           [Parameter("offset", "1", -1e-3, 1e-3, 1e-6)], _background,
           "A constant offset per view and wavelength (dark level, stray light), as a fraction of the "
           "channel's light per pixel.", kind="calibration", per_channel=True, order=10),
]
for _e in _BUILTIN_PSF:
    register_effect(_e)
