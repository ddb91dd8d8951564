"""The model-selection engine: fit candidate effects, score them, name the best, revise.

Method
------
1. Forward model: the design through the ideal process (height domain, :mod:`masks.process`)
   or the ideal PSF (PSF domain, :mod:`doedesign.engine.psf`), with the effects of the current model
   (:mod:`metrology.diagnosis.effects`) applied.
2. Noise floor (:mod:`metrology.diagnosis.noise`) and correlation from the data alone: heights scatter about their own mean on
   the flat interiors of features (edges excluded); PSF pixels scatter about a local mean where
   no model light falls. The autocorrelation of that scatter gives the correlation area ``A``
   (pixels) and the effective sample count ``n_eff = N / A``.
3. For every candidate effect, fit its parameters (scipy ``least_squares``, bounded, in units of
   each parameter's scale) starting from the current model, and score it with
   ``BIC_eff = n_eff ln(RSS / N) + k ln(n_eff)``; a richer model must lower it by more than
   ``threshold`` (10: "very strong" evidence) to be named.
4. Add the best candidate, refit all named effects jointly, repeat until no candidate is
   significant or the residual reaches the noise floor. Candidates within the threshold of
   the best cannot be told apart by the data; they are listed as ``ambiguous_with`` and a
   measurement artefact is preferred among them. A backward pass then swaps or drops named
   effects that the final model no longer needs (forward-backward stepwise selection).
   A residual shift of the whole pattern (registration) is fitted in every height model.
   Nothing else stops it: no default time limit or CPU budget decides what is tried or named.
   A limit the user asks for (:class:`~metrology.diagnosis.budget.Deadline`) ends it where it is,
   and the diagnosis says INCOMPLETE (:mod:`~metrology.diagnosis.result`).
5. Parameter uncertainties: ``cov = s^2 (J^T J)^-1 A`` with ``J`` the Jacobian at the optimum
   (the fits and their uncertainties: :mod:`metrology.diagnosis.fitting`).

A domain (:mod:`~metrology.diagnosis.heights`, :mod:`~metrology.diagnosis.psf`) supplies a
:class:`~metrology.diagnosis.problem.Problem`: the candidate effects, the noise estimate and the residual of a model.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
import numpy as np

from doedesign.progress import Progress
from metrology.diagnosis import budget as clock
from metrology.diagnosis.budget import Deadline, FitStop
from metrology.diagnosis.fitting import JAC_STEP, bic_eff, fit_effects, power_share, standard_errors
from metrology.diagnosis.parallel import fit_workers, parallel_map
from metrology.diagnosis.locate import locate_residual, partial_matches
from metrology.diagnosis.problem import Problem
from metrology.diagnosis.result import Diagnosis, Step
from metrology.diagnosis.revision import refit_kept, revise

__all__ = ["DEFAULT_THRESHOLD", "Diagnosis", "JAC_STEP", "Problem",
           "SCREEN_ITER", "Step", "UNEXPLAINED_RATIO", "bic_eff", "excess_share", "fit_effects", "run_diagnosis",
           "standard_errors"]

log = logging.getLogger(__name__)

DEFAULT_THRESHOLD = 10.0
# Iterations of the short fit that screens each candidate (on a screening crop: fewer, the
# close candidates are refitted on the whole problem anyway).
SCREEN_ITER = 4
SCREEN_ITER_CROP = 2
# Fraction of the noise floor above which a final residual is reported unexplained even when
# no binned pattern earns its parameters (the noise-floor estimate itself is good to ~5 %).
UNEXPLAINED_RATIO = 1.25
# Share of the shared edge profile's power in its odd part (about the edge) above which an
# instrument residual left by the instrument's own fit stops the diagnosis before any candidate:
# a wrong lateral transfer leaves an odd profile, a linewidth bias (the one fabrication effect
# the same at every mask's edges) an even one.
EARLY_ODD_SHARE = 0.8
# ... and the share of the residual's power above the noise floor that profile must hold: an
# instrument residual beside a larger one it does not explain (an etch's depth varying across
# the field, on the interiors) leaves candidates to screen.
EARLY_EXCESS_SHARE = 0.5
# ... and above which a final unexplained residual shared by every mask's edges is the
# instrument's (fabrication names then withheld).
FINAL_ODD_SHARE = 0.5
# Share of the noise floor's power (per sample) the best candidate must explain to be named: less
# is within what the instrument model's own mismatch to a real instrument leaves (a CSI null
# through its fitted transfer: 0.18 nm rms on a 1.2 nm floor, 2 % of its power), however well the
# data resolve it. At the instruments' true floors, false names bought 0.2-3.2 % (a 0.04 % etch
# loading beside an overlay; etch depths beside a bias, beside a loading, and on a null, on CSI and
# blurred-pixel files); the smallest true second effect measured, 9.9 % (a 2.8 % per mm gradient
# beside a depth).
MIN_POWER_SHARE = 0.05
# Share of the best screening score (a short fit) within which a candidate is fitted to convergence,
# and within which the backward pass tries it in the named one's place (one fit at the end; screening
# scores against screening scores): a true gradient on a 512 px point field screened 3.3 % behind the
# loading named, one on a 560 px pixel-integrating field 12.3 % behind an etch depth (the short fit
# of its smooth parameters is far from converged), and each replaces the named one there.
CLOSE_SHARE, ALTERNATIVE_SHARE = 0.02, 0.2


def _screen_one(rd, name):
    """Screen candidate ``name`` in the round ``rd``: (name, fitted model, score).

    The named effects refit with the candidate: partly degenerate effects (a blur and a
    sidewall ramp) must be able to share what one of them took alone. The criterion change on
    a screening crop is scaled by the ratio of effective sample counts. A candidate an earlier
    pass fitted starts from that value or from its start values, whichever leaves the smaller
    residual: beside effects this pass named that took part of it, the earlier value counts that
    part twice (a rerun's etch loading beside a depth and a gradient screened at +7789 from its
    first pass's 8.3 %, and was not named).
    """
    screen = rd["screen"]
    eff = rd["effects"][name]
    trial = dict(rd["model"])
    trial[name] = eff.start_values()
    if name in rd["prior"]:
        earlier = {**trial, name: rd["prior"][name]}
        if _cost(screen, earlier) < _cost(screen, trial):
            trial = earlier
    free = rd["named"] + [name]
    iters = rd["iters"]
    first = min(iters, 2) if rd["quick"] else iters

    def score(rss):
        return (bic_eff(rss, rd["n_s"], rd["n_eff_s"], rd["k_now"] + eff.n_params) - rd["crit_s"]) \
            * rd["n_eff"] / rd["n_eff_s"]

    fitted, rss_c, _ = fit_effects(screen, trial, free, max_iter=first, central=False if rd["quick"] else None,
                                   stop=rd["stop"])
    if first < iters and score(rss_c) < 0:
        # The first step paid for the candidate's parameters: finish the short fit.
        fitted, rss_c, _ = fit_effects(screen, fitted, free, max_iter=iters - 1, central=False, stop=rd["stop"])
    log.debug("screen %s: %.3f %% of the floor's power", name,
              100 * (rd["power_s"] - rss_c) / (rd["n_s"] * rd["floor_s"] ** 2))
    return name, fitted, score(rss_c)


def _cost(problem, model):
    r = problem.residual(model)
    return float(r @ r)


def _rms(r):
    return float(np.sqrt(np.mean(r ** 2)))


def excess_share(explained_power: float, power: float, sigma: float) -> float:
    """Share of a residual's mean power above the noise floor that a model of it explains.

    Parameters
    ----------
    explained_power : float
        Mean power (m^2 per sample) the model explains.
    power : float
        The residual's mean power (m^2 per sample).
    sigma : float
        Noise floor, rms (m).

    Returns
    -------
    float
        ``explained_power / (power - sigma**2)``; 1 where the residual is at the floor.
    """
    excess = power - sigma ** 2
    return 1.0 if excess <= 0 else explained_power / excess


def _excess_share(signature, r, sigma):
    """Share of the residual's excess over the floor that an instrument signature's shared edge
    profile holds."""
    return excess_share(signature["explained_rms_m"] ** 2, _rms(r) ** 2, sigma)


def _structure_test(problem, r_map, n_eff, n):
    """Most negative criterion change of a binned (piecewise-constant) model of the residual
    over the problem's groupings; below -threshold a structured residual remains."""
    if problem.fits_part_of_map:
        n = int(np.count_nonzero(np.isfinite(r_map)))
        n_eff = max(n / problem.noise.corr_area_px, 2.0)
    best = np.inf
    for groups in problem.structure_groups():
        valid = np.isfinite(r_map) & (groups > 0)
        r = r_map[valid]
        lab = groups[valid]
        counts = np.bincount(lab)
        means = np.bincount(lab, weights=r) / np.maximum(counts, 1)
        rss0 = float(np.sum(r ** 2))
        rss1 = float(np.sum((r - means[lab]) ** 2))
        k = int(np.count_nonzero(counts))
        best = min(best, bic_eff(rss1, n, n_eff, k) - bic_eff(rss0, n, n_eff, 0))
    return float(best)


def _close(scores, best, threshold, share=CLOSE_SHARE):
    """The candidates scored within ``share`` of ``best`` (at least ``threshold``)."""
    return [c for c in scores if scores[c] < scores[best] + max(threshold, share * abs(scores[best]))]


def _converge(problem, screen, start, free, stop):
    """``free`` fitted to convergence on ``problem`` (:func:`fit_effects`'s result). Converged on
    the cheap ``screen`` crop first, the fit on the whole problem starts near its optimum and needs
    a few of its expensive evaluations, not a dozen. A crop's fit that ``stop`` ended is returned
    as it is: the round names nothing from it, and the whole problem's first evaluation would only
    run past the deadline (on a CSI file with a trenching, 1.8 s: the fit stopped at 57.1 s of a
    selection that ends at 55 s)."""
    if screen is not problem:
        fitted = fit_effects(screen, start, free, stop=stop)
        if stop is not None and stop():
            return fitted
        start = fitted[0]
    return fit_effects(problem, start, free, stop=stop)


def _step(problem, name, r_before, r_after, change, scores, ambiguous):
    """The :class:`Step` that names ``name`` (its parameters are filled from the final joint fit)."""
    eff = problem.effects[name]
    return Step(effect=name, kind=eff.kind, description=eff.description, params={}, uncertainties={},
                units={p.name: p.unit for p in eff.params}, residual_rms_before=_rms(r_before),
                residual_rms_after=_rms(r_after), criterion_change=change,
                candidates={k: float(v) for k, v in scores.items()}, ambiguous_with=ambiguous)


def _cut_short(what, candidates):
    """``stopped_early`` of a selection whose round the user's limit cut short in ``what``."""
    log.info("diagnosis stopped: the time limit ended %s of %s", what, candidates)
    return {"reason": f"time limit: the round was cut short in {what} of {', '.join(sorted(candidates))} "
                      "(best so far), and nothing is named from it", "cut_short": sorted(candidates)}


def run_diagnosis(problem: Problem, threshold: float = DEFAULT_THRESHOLD, max_steps: int = 6, domain: str = "height",
                  candidates: Sequence[str] | None = None, screen_iter: int = SCREEN_ITER,
                  stop_at_floor: bool = True, quick_screen: bool = False,
                  prior: dict[str, np.ndarray] | None = None, limit: Deadline | None = None,
                  after_step: Callable[[dict[str, np.ndarray], list[Step]], None] | None = None,
                  carried: Sequence[Step] = ()) -> Diagnosis:
    """The greedy model-building loop on a prepared problem (see the module docstring).

    Candidates of a problem with ``parallel_fits`` are screened, and Jacobian columns computed,
    in up to :data:`~metrology.diagnosis.parallel.WORKERS` threads (the same fits, so
    the same result as in one process).

    Parameters
    ----------
    problem : Problem
    threshold : float
        Criterion drop a candidate must achieve to be named.
    max_steps : int
    domain : str
    candidates : list of str, optional
        Restrict the candidates (default: every registered effect of the domain).
    screen_iter : int
        Iterations of each candidate's screening fit (the candidate with the named effects),
        on ``problem.screening`` when the problem offers a cheaper crop of itself.
        A short fit over-estimates the RSS, so its criterion change is conservative; the
        chosen effect is then fitted to convergence jointly with all effects and nuisances.
    stop_at_floor : bool
        Stop as soon as the residual rms reaches the noise floor (else only the criterion stops).
    quick_screen : bool
        Screen with forward-difference Jacobians (half the model evaluations), and stop a
        candidate's screening fit after one step that does not pay for its parameters (its
        score stays that step's). The close candidates are refitted in full either way.
    prior : dict, optional
        A model of the same data from an earlier pass (e.g. before the robust rule re-admitted
        pixels, or the instrument stage's joint fit): the nuisances and each candidate start
        from its values instead of the null ones. The selection itself is made afresh.
    limit : Deadline, optional
        A limit the user asked for (default none: the criterion alone stops): past it no further
        round of candidates and no further revision starts, a round or revision under way stops at
        its fit's next evaluation and names nothing from it, and the diagnosis is incomplete
        (``stopped_early``, with the candidates not tried).
    after_step : callable, optional
        Called with the model (nuisances included) and the steps so far after each named step;
        a caller that learns from it that the problem itself must change (the camera's
        instrument stage) raises, and continues on the new problem (``carried``).
    carried : sequence of Step
        What an earlier pass on the same data named before its problem changed: these effects
        enter first, in their order, each refitted jointly from ``prior`` and kept while it still
        pays the threshold and the resolution rule; the screening rounds that chose them are not
        repeated, and the backward pass judges them with the rest.

    Returns
    -------
    Diagnosis
    """
    cpu0 = clock.cpu_seconds()
    deadline = limit if limit is not None else Deadline()
    stopped = small = None
    nuisance = list(getattr(problem, "nuisance", {}))
    screen = getattr(problem, "screening", None) or problem
    names = [n for n in (list(candidates) if candidates is not None else list(problem.effects)) if n not in nuisance]
    tested = []  # the candidates the round that ended the selection by the criterion scored
    entered = set()  # every candidate the selection named at some point (revised or withheld later)
    model: dict[str, np.ndarray] = {}
    if nuisance:
        model, _, _ = fit_effects(problem, {n: (prior or {}).get(n, problem.effects[n].start_values())
                                            for n in nuisance}, nuisance)
    r = problem.residual(model)
    n = r.size
    n_eff = max(n / problem.noise.corr_area_px, 2.0)
    rss = float(np.sum(r ** 2))
    initial_rms = _rms(r)
    k_base = sum(problem.effects[m].n_params for m in nuisance)
    crit = bic_eff(rss, n, n_eff, k_base)
    maps = [problem.residual_map(model)]
    breakdown_initial = problem.breakdown(maps[0])
    steps = []
    errors = {}
    alternatives = {}
    log.info("diagnosis: %d samples, n_eff %.0f, noise floor %.3g, initial rms %.3g",
             n, n_eff, problem.noise.sigma, initial_rms)
    # A fit that cannot close stops here and says so: what the instrument's own fit leaves is
    # the instrument's (the same odd profile at every mask's edges), and no candidate may be
    # named on it.
    early = (problem.instrument_signature(maps[0]) if _rms(r) > UNEXPLAINED_RATIO * problem.noise.sigma
             else None)
    if early is not None:
        excess_share = _excess_share(early, r, problem.noise.sigma)
        if early["odd_share"] < EARLY_ODD_SHARE or excess_share < EARLY_EXCESS_SHARE:
            log.info("an instrument residual (odd share %.2f) holds %.0f %% of the residual's excess over "
                     "the floor: candidates screened", early["odd_share"], 100 * excess_share)
            early = None
    if early is not None:
        log.info("the instrument's fit leaves an instrument residual (odd share %.2f, %.0f %% of the excess "
                 "over the floor): no candidate screened", early["odd_share"], 100 * excess_share)
    for old in carried if early is None else ():
        if old.effect not in problem.effects or old.effect in model:
            continue
        budget = FitStop(deadline)
        free = list(model) + [old.effect]
        start = {**model, old.effect: (prior or {}).get(old.effect, problem.effects[old.effect].start_values())}
        fitted, rss_new, errs = _converge(problem, screen, start, free, budget)
        if budget.fired:
            stopped = _cut_short("its refit (carried from before the instrument stage ran again)", [old.effect])
            break
        new_crit = bic_eff(rss_new, n, n_eff, sum(problem.effects[m].n_params for m in fitted))
        share = power_share(problem, r, rss_new)
        log.info("carried %s: criterion %+.1f, %.1f %% of the floor's power", old.effect, new_crit - crit, 100 * share)
        if new_crit - crit > -threshold or share < MIN_POWER_SHARE:
            break
        model, errors = fitted, errs
        r_new = problem.residual(model)
        entered.add(old.effect)
        steps.append(_step(problem, old.effect, r, r_new, new_crit - crit, old.candidates, list(old.ambiguous_with)))
        alternatives[old.effect] = [c for c in _close(old.candidates, old.effect, threshold, ALTERNATIVE_SHARE)
                                    if c != old.effect]
        maps.append(problem.residual_map(model))
        r, crit = r_new, new_crit
    while (early is None and stopped is None and len(steps) < max_steps
           and (_rms(r) > problem.noise.sigma or not stop_at_floor)):
        pending = [nm for nm in names if nm not in model]
        if not pending:
            break
        if deadline.past():
            stopped = {"reason": "time limit: no further candidates were tried"}
            log.info("diagnosis stopped: the time limit was reached after %d step(s)", len(steps))
            break
        scores = {}
        fits = {}
        k_now = sum(problem.effects[m].n_params for m in model)
        # Candidates are screened on the problem's cheaper crop when it has one; the criterion
        # change there is scaled by the ratio of effective sample counts (the best candidates
        # are then refitted on the whole problem).
        n_s, n_eff_s, crit_s, iters, r_s = n, n_eff, crit, screen_iter, r
        if screen is not problem:
            iters = min(screen_iter, SCREEN_ITER_CROP)
            r_s = screen.residual(model)
            n_s = r_s.size
            n_eff_s = max(n_s / screen.noise.corr_area_px, 2.0)
            crit_s = bic_eff(float(np.sum(r_s ** 2)), n_s, n_eff_s, k_now)
        # The budget stops the round's fits under way (a round costs 5-10 CPU s, a whole window's
        # fit to convergence 15-30), and nothing is named from a round it stopped: a screening
        # fit's parameters are not a diagnosis (on a CSI file an etch loading so named paid for a
        # gradient whose fit the loading's refit had not yet finished).
        budget = FitStop(deadline)
        rd = dict(screen=screen, effects=problem.effects, model=model, named=[m for m in model if m not in nuisance],
                  iters=iters, quick=quick_screen, n_s=n_s, n_eff_s=n_eff_s, crit_s=crit_s, k_now=k_now, n_eff=n_eff,
                  power_s=float(np.sum(r_s ** 2)), floor_s=screen.noise.sigma,
                  prior=prior or {}, stop=budget)
        workers = fit_workers(problem)
        # Those with the most parameters first (the longest fits): the workers then finish together.
        by_size = sorted(pending, key=lambda c: -problem.effects[c].n_params)
        with Progress(len(pending), desc=f"diagnosis step {len(steps) + 1}") as bar:
            for name, fitted, score in parallel_map(lambda c: _screen_one(rd, c), by_size, workers, ordered=False):
                scores[name], fits[name] = score, fitted
                bar.update(1, status=f"{name} {score:+.1f}")
        scores = {c: scores[c] for c in pending}  # in the candidates' order, however they finished
        if not scores:
            break
        best = min(scores, key=scores.__getitem__)
        log.info("candidates: %s", {k: round(v, 1) for k, v in sorted(scores.items(), key=lambda kv: kv[1])})
        if budget.fired:
            stopped = _cut_short("its screening", [best])
            break
        if scores[best] > -threshold:
            tested = list(scores)
            break
        # Candidates close to the best are fitted to convergence and compared again; those
        # within the threshold of the best cannot be told apart by the data. Among them a
        # measurement artefact is preferred: it is always present in a measurement, and a
        # fabrication effect must not be blamed for what the instrument does.
        close = _close(scores, best, threshold)
        screened = dict(scores)
        # Side by side, as the screening: each refit is computed alone (the same result in one
        # thread or two), and two fits overlap each other's serial steps.
        refits = dict(zip(close, parallel_map(lambda c: _converge(problem, screen, fits[c], list(model) + [c], budget),
                                              close, workers)))
        for c in close:
            scores[c] = bic_eff(refits[c][1], n, n_eff, k_now + problem.effects[c].n_params) - crit
        if budget.fired:
            stopped = _cut_short("its fit to convergence", close)
            break
        best = min(close, key=scores.__getitem__)
        if scores[best] > -threshold:  # a screening crop's scaled estimate was too hopeful
            tested = list(scores)
            break
        share = power_share(problem, r, refits[best][1])
        if share < MIN_POWER_SHARE:
            small = {"effect": best, "criterion_change": float(scores[best]), "floor_power_share": share}
            log.info("%s would explain %.2f %% of the floor's power: below the model's resolution, not named",
                     best, 100 * share)
            tested = list(scores)
            break
        tied = [c for c in close if scores[c] <= scores[best] + threshold]
        artefacts = [c for c in tied if problem.effects[c].kind == "artefact"]
        if artefacts:
            best = min(artefacts, key=scores.__getitem__)
        ambiguous = sorted(c for c in tied if c != best)
        alternatives[best] = [c for c in _close(screened, min(screened, key=screened.__getitem__), threshold,
                                                ALTERNATIVE_SHARE) if c != best]
        model, rss_new, errors = refits[best]
        new_crit = bic_eff(rss_new, n, n_eff, k_now + problem.effects[best].n_params)
        r_new = problem.residual(model)
        entered.add(best)
        steps.append(_step(problem, best, r, r_new, new_crit - crit, scores, ambiguous))
        maps.append(problem.residual_map(model))
        r, crit = r_new, new_crit
        if after_step is not None:
            after_step(model, steps)
    if stopped is None and early is None and _rms(r) <= problem.noise.sigma and stop_at_floor:
        tested = list(names)  # at the floor: nothing is left for any candidate to explain
    if steps:
        model, errors, crit = revise(problem, model, errors, steps, alternatives, nuisance, n, n_eff, threshold,
                                      deadline, min_share=MIN_POWER_SHARE)
        r = problem.residual(model)
        steps = [st for st in steps if st.effect in model]
        if len(maps) > len(steps) + 1 or any(st.revised for st in steps):
            # After a revision the per-step maps no longer describe the final model; keep the
            # ideal and the final residual maps.
            maps = maps[:1] + [problem.residual_map(model)]
    # Report every step's parameters from the final joint fit, with their uncertainties.
    for s in steps:
        eff = problem.effects[s.effect]
        s.params = {p.name: float(v) for p, v in zip(eff.params, model[s.effect])}
        s.uncertainties = {p.name: float(v) for p, v in zip(eff.params, errors.get(s.effect, []))}
    final_map = maps[-1]
    struct = _structure_test(problem, final_map, n_eff, n)
    unexplained = bool(struct < -threshold or _rms(r) > UNEXPLAINED_RATIO * problem.noise.sigma)
    partial = []
    if unexplained and steps and problem.judges_partial_matches:
        partial = partial_matches(problem, model, final_map, nuisance, UNEXPLAINED_RATIO)
        if partial:
            dropped = {p["effect"] for p in partial}
            kept = {k: v for k, v in model.items() if k not in dropped}
            model, errors = refit_kept(problem, kept, errors, deadline)
            steps = [st for st in steps if st.effect not in dropped]
            for s in steps:
                s.uncertainties = {p.name: float(v) for p, v in zip(problem.effects[s.effect].params,
                                                                    errors.get(s.effect, []))}
                s.params = {p.name: float(v) for p, v in zip(problem.effects[s.effect].params, model[s.effect])}
            r = problem.residual(model)
            final_map = problem.residual_map(model)
            maps = maps[:1] + [final_map]
            struct = _structure_test(problem, final_map, n_eff, n)
    inadequate = early if early is not None else problem.instrument_signature(final_map) if unexplained else None
    if inadequate is not None and inadequate["odd_share"] < FINAL_ODD_SHARE:
        inadequate = None
    final_share = (_excess_share(inadequate, r, problem.noise.sigma)
                   if inadequate is not None and early is None else 1.0)
    if final_share < EARLY_EXCESS_SHARE:
        # An edge profile beside a larger residual it does not explain is not the whole story:
        # the fabrication names fitted beside it stand.
        log.info("a shared edge profile holds %.0f %% of the final residual's excess over the floor: "
                 "not an inadequate instrument model", 100 * final_share)
        inadequate = None
    if inadequate is not None:
        # The residual is the instrument's (the same at every mask's edges): its model's family
        # cannot close it, and no fabrication effect may be named on what it leaves.
        fab = {st.effect for st in steps if st.kind != "artefact"}
        inadequate["withheld"] = sorted(fab)
        log.info("instrument model inadequate (shared edge profile holds %.0f %% of the edge residual); "
                 "withheld: %s", 100 * inadequate["explained_share"], sorted(fab))
        if fab:
            kept = {k: v for k, v in model.items() if k not in fab}
            model, errors = refit_kept(problem, kept, errors, deadline)
            steps = [st for st in steps if st.effect not in fab]
            for s in steps:
                eff = problem.effects[s.effect]
                s.uncertainties = {p.name: float(v) for p, v in zip(eff.params, errors.get(s.effect, []))}
                s.params = {p.name: float(v) for p, v in zip(eff.params, model[s.effect])}
            r = problem.residual(model)
            final_map = problem.residual_map(model)
            maps = maps[:1] + [final_map]
            struct = _structure_test(problem, final_map, n_eff, n)
    breakdown_final = problem.breakdown(final_map)
    where = (locate_residual(breakdown_final, final_map, problem.noise.sigma, problem.noise.corr_area_px)
             if unexplained else None)
    if inadequate is not None:
        where = dict(where or {})
        where["instrument_model_inadequate"] = dict(
            inadequate, message="the residual is the same at every mask's edges (per unit step), on both sides: "
                                "the instrument's lateral transfer, which its model's family (pixel fill factor, "
                                "Gaussian blur, NA-limited objective, batwing) cannot close; no fabrication "
                                "effect is named")
    if stopped is None and deadline.hit is not None:  # the limit ended the backward pass or a refit
        stopped = {"reason": "time limit: the selection finished, but the revision or refit after it was cut short"}
    if stopped is not None:
        tested = []  # an incomplete diagnosis tested only what it named
        stopped = dict(stopped, limit=deadline.hit, untried=[c for c in names if c not in model and c not in entered],
                       final_over_floor=_rms(r) / problem.noise.sigma, cpu_s=clock.cpu_seconds() - cpu0)
    tested = [c for c in names if c in tested or c in model or c in entered]
    return Diagnosis(domain=domain, steps=steps, model=model, noise_floor=problem.noise.sigma,
                     corr_area_px=problem.noise.corr_area_px, n_samples=n, n_eff=n_eff,
                     initial_residual_rms=initial_rms, final_residual_rms=_rms(r),
                     unexplained=unexplained, structure_criterion=struct, units=problem.units,
                     breakdown_initial=breakdown_initial, breakdown_final=breakdown_final,
                     residual_maps=maps, unexplained_where=where, partial_matches=partial, below_resolution=small,
                     stopped_early=stopped, candidates=names, tested=tested)
