"""After the forward selection: the backward pass that swaps or drops named effects, and the refit
of what stays once effects are withheld.

Both stop at a limit the user asked for (:class:`~metrology.diagnosis.budget.Deadline`, which
records that it ended them: the diagnosis is then incomplete); without one they run to their end.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence

import numpy as np

from metrology.diagnosis.budget import Deadline, FitStop
from metrology.diagnosis.fitting import bic_eff, fit_effects, power_share
from metrology.diagnosis.problem import Problem

__all__ = ["refit_kept", "revise"]

log = logging.getLogger(__name__)


def revise(problem: Problem, model: dict[str, np.ndarray], errors: dict[str, np.ndarray], steps: list,
           alternatives: dict[str, list[str]], nuisance: Sequence[str], n: int, n_eff: float, threshold: float,
           deadline: Deadline, min_share: float = 0.0) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray], float]:
    """Backward pass of the stepwise selection, once all named effects are in the model.

    Nearly degenerate effects (a sub-pixel instrument blur and a narrow sidewall ramp) can only
    be told apart once everything else is explained: each named effect is tried against the
    alternatives that scored close to it when it was chosen and its rivals (another form of the
    same cause: :class:`~metrology.diagnosis.effect_model.Effect`) (swap if better by the threshold,
    or if tied and the alternative is a measurement artefact), then each named effect is
    dropped if the criterion no longer needs it or if, in the final model, it explains less than
    ``min_share`` of the noise floor's power (the forward selection's rule for naming one: less
    is within what the instrument model's mismatch leaves), the weakest first. Past ``deadline`` (:class:`~metrology.diagnosis.budget.Deadline`) the
    pass stops where it is (the model stays the forward pass's or its last revision; a fit the
    deadline cut short changes nothing).
    """
    r = problem.residual(model)
    crit = bic_eff(float(np.sum(r ** 2)), n, n_eff, sum(problem.effects[m].n_params for m in model))
    by_name = {st.effect: st for st in steps}
    budget = FitStop(deadline)
    for i, st in enumerate(list(steps)):
        rivals = [e for e in problem.effects[st.effect].rivals if e in problem.effects]
        for alt in dict.fromkeys([*alternatives.get(st.effect, []), *rivals]):
            if alt in model or st.effect not in model or deadline.past():
                continue
            trial = {k: v for k, v in model.items() if k != st.effect}
            if alt in rivals:
                # Another form of the same cause: what was named after this one was fitted around
                # the wrong form, a basin the rival's fit cannot leave; it restarts from null.
                later = {s.effect for s in steps[i + 1:]} - set(nuisance)
                trial = {k: problem.effects[k].null_values() if k in later else v for k, v in trial.items()}
            trial[alt] = problem.effects[alt].start_values()
            fitted, rss, errs = fit_effects(problem, trial, list(trial), stop=budget)
            if budget.fired:
                return model, errors, crit
            c_alt = bic_eff(rss, n, n_eff, sum(problem.effects[m].n_params for m in fitted))
            log.info("revision: %s in %s's place: criterion %+.1f", alt, st.effect, c_alt - crit)
            prefer = problem.effects[alt].kind == "artefact" and problem.effects[st.effect].kind != "artefact"
            if c_alt < crit - threshold or (prefer and c_alt <= crit + threshold):
                log.info("revision: %s replaces %s (criterion %+.1f)", alt, st.effect, c_alt - crit)
                old = st.effect
                eff = problem.effects[alt]
                st.effect, st.kind, st.description = alt, eff.kind, eff.description
                st.units = {p.name: p.unit for p in eff.params}
                st.ambiguous_with = sorted(set(st.ambiguous_with + [old]) - {alt})
                st.revised = f"replaced {old} in the backward pass"
                by_name[alt] = st
                model, errors, crit = fitted, errs, c_alt
    # The weakest first: the likeliest to go, before the deadline can stop the pass.
    for st in sorted(steps, key=lambda s: -s.criterion_change):
        if len(model) - len(nuisance) <= 1 or deadline.past():
            break
        trial = {k: v for k, v in model.items() if k != st.effect}
        fitted, rss, errs = fit_effects(problem, trial, list(trial), stop=budget)
        if budget.fired:
            break
        c_drop = bic_eff(rss, n, n_eff, sum(problem.effects[m].n_params for m in fitted))
        share = -power_share(problem, problem.residual(model), rss)
        if c_drop < crit + threshold or share < min_share:
            log.info("revision: %s no longer needed (criterion %+.1f, %.2f %% of the floor's power)", st.effect,
                     c_drop - crit, 100 * share)
            model, errors, crit = fitted, errs, c_drop
    return model, errors, crit


def refit_kept(problem: Problem, kept: dict[str, np.ndarray], errors: dict[str, np.ndarray],
               deadline: Deadline) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
    """The model ``kept`` (what stays once effects are withheld) refitted, and its uncertainties.

    Past ``deadline`` the fit stops where it is (at once, if already past): the kept parameters
    then stand as the joint fit left them, with that fit's uncertainties (``errors``).
    """
    if not kept:
        return {}, {}
    stop = FitStop(deadline)
    model, _, errs = fit_effects(problem, kept, list(kept), stop=stop)
    if stop.fired:
        log.info("refit of %s stopped at the deadline: the joint fit's uncertainties stand", sorted(kept))
        return model, {k: v for k, v in errors.items() if k in kept}
    return model, errs
