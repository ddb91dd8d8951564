"""What an effect is: a named departure of the real part from the ideal model, with its parameters.

:class:`Parameter` is one fitted value with its unit, bounds and scale; :class:`Effect` holds the
parameters, the function that applies them, the stage of the forward model it acts on and the
sentence a report shows. The registry that holds them, and the stages' signatures, are in
:mod:`metrology.diagnosis.effects`; the built-in effects are in
:mod:`metrology.diagnosis.height_effects` and :mod:`metrology.diagnosis.psf_effects`.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from doedesign.errors import DoeError

__all__ = ["DOMAINS", "Effect", "EffectError", "KINDS", "Parameter", "STAGES"]

DOMAINS = ("height", "psf")
STAGES = {"height": ("process", "surface"), "psf": ("height", "optics", "sensor")}
KINDS = ("fabrication", "artefact", "calibration")


class EffectError(DoeError):
    """An effect is unknown, badly defined, or given the wrong number of values."""


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
        Where in the forward model ``apply`` acts (the stages are listed in :mod:`metrology.diagnosis.effects`).
    params : tuple of Parameter
    apply : callable
        Signature depends on ``stage`` (:mod:`metrology.diagnosis.effects`).
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
    rivals : tuple of str
        Effects that model the same physical cause in another form (the aligner's gap: a Gaussian
        blur of the aerial image, or the Fresnel print through it). The selection's first pick
        between them can be the wrong form, which then leaves what the other would have explained
        to false names; the backward pass always tries each rival in this one's place
        (:func:`metrology.diagnosis.revision.revise`), and the criterion chooses.
    """

    name: str
    domain: str
    stage: str
    params: Sequence[Parameter]  # stored as a tuple (__post_init__)
    apply: Callable[..., Any]
    description: str
    kind: str = "fabrication"
    order: int = 0
    start: tuple | None = field(default=None)
    per_channel: bool = False
    linear: bool = False
    fourier: Callable[..., Any] | None = None
    beside_objective: bool = False
    mask_params: Callable[[int], Sequence[Parameter]] | None = None
    rivals: tuple[str, ...] = ()

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
