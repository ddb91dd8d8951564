"""The vocabulary of fabrication effects of the masks process model.

One table, :data:`PROCESS_EFFECTS`, lists every effect :mod:`masks.process` can print: its
name (also the :class:`~masks.process_params.ProcessParams` field that holds it), its physical
parameters with the unit in each name, their plausible bounds, whether they repeat per mask,
and a one-sentence description. Simulation, tolerance analysis and diagnosis read their
effect names and bounds from here. Conventions as in :mod:`masks.process`: x toward
increasing column, y up (toward row 0), rotations counter-clockwise about the centre of the
design grid (the field centre).
"""

from __future__ import annotations

from dataclasses import dataclass

__all__ = ["EffectParameter", "ProcessEffect", "PROCESS_EFFECTS", "EFFECTS", "effect_spec"]


@dataclass(frozen=True)
class EffectParameter:
    """One physical parameter of a process effect.

    Attributes
    ----------
    name : str
        Name with its unit (``dx_m``, ``rotation_deg``, ``per_m``).
    unit : str
        Unit as shown in reports (``"m"``, ``"deg"``, ``"1"`` for a fraction, ``"1/m"``).
    lower, upper : float
        Plausible bounds for a fit or a tolerance distribution.
    per_mask : bool
        One value per mask (else one value for the whole run).
    """

    name: str
    unit: str
    lower: float
    upper: float
    per_mask: bool = True


@dataclass(frozen=True)
class ProcessEffect:
    """A fabrication effect of the process model.

    Attributes
    ----------
    name : str
        Effect name, shared by masks, metrology and diagnosis; also the ProcessParams field.
    params : tuple of EffectParameter
        In the order of the field's last axis (per-mask arrays: one row per mask).
    description : str
        One sentence a user reads in a report.
    extra_fields : tuple of str
        Further ProcessParams fields the effect uses (held fixed when it is fitted).
    """

    name: str
    params: tuple
    description: str
    extra_fields: tuple = ()


def _p(name, unit, lower, upper, per_mask=True):
    return EffectParameter(name, unit, lower, upper, per_mask)


#: Every effect the process model can print, with its parameters, units and bounds (the module docstring).
PROCESS_EFFECTS = (
    ProcessEffect("etch_depth", (_p("depth_m", "m", 0.0, 5e-6),),
                  "Each mask's etch removes a depth that differs from its nominal value."),
    ProcessEffect("mask_overlay", (_p("dx_m", "m", -20e-6, 20e-6), _p("dy_m", "m", -20e-6, 20e-6),
                                   _p("rotation_rad", "rad", -0.02, 0.02)),
                  "A mask is printed shifted (and slightly rotated) relative to mask 0."),
    ProcessEffect("linewidth_bias", (_p("bias_m", "m", -5e-6, 5e-6),),
                  "Every opening edge of a mask moves outward (wider openings) or inward by the same amount."),
    ProcessEffect("proximity_blur", (_p("sigma_m", "m", 0.0, 20e-6, per_mask=False),),
                  "The contact-gap aerial image is blurred, so small openings shrink and corners round.",
                  extra_fields=("resist_threshold",)),
    ProcessEffect("sidewall_slope", (_p("width_m", "m", 0.0, 10e-6, per_mask=False),),
                  "Etched steps are ramps of this width instead of vertical walls."),
    ProcessEffect("etch_loading", (_p("loss_fraction", "1", -0.5, 0.5, per_mask=False),),
                  "The etch is shallower where more of the mask is open nearby (RIE loading).",
                  extra_fields=("loading_radius",)),
    ProcessEffect("roughness", (_p("rms_m", "m", 0.0, 50e-9, per_mask=False),),
                  "Random height noise of the etched surface."),
    ProcessEffect("mask_rotation", (_p("rotation_deg", "deg", -1.0, 1.0),),
                  "A mask is printed rotated about the field centre, so its overlay grows linearly "
                  "with the distance from the centre, opposite in sign on opposite sides."),
    ProcessEffect("microtrenching", (_p("depth_m", "m", 0.0, 200e-9), _p("width_m", "m", 0.0, 5e-6)),
                  "RIE etches deeper at the foot of a mask's etched edges, inside the opening: an extra "
                  "depth decaying exponentially over a width, in proportion to that step's etch."),
    ProcessEffect("etch_gradient", (_p("x_per_m", "1/m", -100.0, 100.0, per_mask=False),
                                    _p("y_per_m", "1/m", -100.0, 100.0, per_mask=False)),
                  "Plasma non-uniformity makes every etch deeper on one side of the field than on the "
                  "other by the same relative amount per metre (10 /m = 1 % per mm)."),
)

# Effect names shared by masks, metrology and diagnosis (CONTRIBUTING.md).
EFFECTS = tuple(e.name for e in PROCESS_EFFECTS)


def effect_spec(name: str) -> ProcessEffect:
    """The :class:`ProcessEffect` called ``name`` (KeyError if there is none)."""
    for effect in PROCESS_EFFECTS:
        if effect.name == name:
            return effect
    raise KeyError(f"unknown process effect {name!r}; known: {list(EFFECTS)}")
