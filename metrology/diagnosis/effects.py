"""The effect registry: named, parametrized departures of the real part from the ideal model.

Each :class:`~metrology.diagnosis.effect_model.Effect` has a name, parameters with physical units and bounds, a function that
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
pixels; a ``"process"`` effect maps :class:`masks.process_params.ProcessParams` to new ones.
``kind="artefact"`` marks a measurement artefact. :func:`unregister_effect` removes it. When no
registered effect explains a structured residual, the diagnosis names none and reports where
the residual lives (:mod:`metrology.diagnosis.locate`): that is when to write one.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from masks.process_params import ProcessParams
from metrology.diagnosis.effect_model import DOMAINS, KINDS, STAGES, Effect, EffectError, Parameter
from metrology.diagnosis.height_effects import BUILTIN_HEIGHT, batwing_profile, batwing_transfer, gaussian_blur
from metrology.diagnosis.psf_effects import BUILTIN_PSF, FWHM_PER_SIGMA

__all__ = ["DOMAINS", "Effect", "EffectError", "FWHM_PER_SIGMA", "KINDS", "Parameter", "REGISTRY", "STAGES",
           "apply_process", "batwing_profile", "batwing_transfer", "effects_for", "gaussian_blur", "get_effect",
           "register_effect", "unregister_effect"]


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
        The :class:`~metrology.diagnosis.effect_model.Effect` fields except ``apply`` (decorator form).

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
    """The registered effect called ``name``; an ``EffectError`` naming the registered ones if none is."""
    try:
        return REGISTRY[name]
    except KeyError:
        raise EffectError(f"unknown effect {name!r}; registered: {', '.join(sorted(REGISTRY))}") from None


def effects_for(domain: str, names: Sequence[str] | None = None, n_masks: int | None = None) -> list[Effect]:
    """Registered effects of ``domain`` (optionally only ``names``), in forward-model order.

    With ``n_masks``, per-mask effects carry the parameters of that many masks
    (:meth:`Effect.for_masks <metrology.diagnosis.effect_model.Effect.for_masks>`); one that no mask of such an element can show (an overlay of a
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


for _e in (*BUILTIN_HEIGHT, *BUILTIN_PSF):
    register_effect(_e)
