"""Diagnosis: where do model and measurement disagree, which effect explains it, by how much.

Method
------
1. Forward model: the design through the ideal process (height domain, :mod:`masks.process`)
   or the ideal PSF (PSF domain, :mod:`doedesign.psf`), with the effects of the current model
   (:mod:`metrology.diagnosis.effects`) applied.
2. Noise floor and correlation from the data alone: heights scatter about their own mean on
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
5. Parameter uncertainties: ``cov = s^2 (J^T J)^-1 A`` with ``J`` the Jacobian at the optimum,
   ``s^2 = RSS / (N - k)``; the factor ``A`` accounts for correlated pixels.

Arrays are row-major with row 0 at the top. Residuals are in the measurement's units: metres
for heights, fraction of each channel's light per pixel for PSFs.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import scipy.ndimage as ndi
from scipy.optimize import least_squares

from doedesign.errors import DoeError
from doedesign.fileio import save_figure
from doedesign.progress import Progress

from metrology.diagnosis.effects import Effect, Parameter, effects_for

log = logging.getLogger(__name__)

DEFAULT_THRESHOLD = 10.0
# Iterations of the short fit that screens each candidate.
SCREEN_ITER = 4
# Finite-difference step of the Jacobian, in units of each parameter's scale.
JAC_STEP = 0.02
# Lags (pixels) over which the noise autocorrelation is summed into the correlation area.
MAX_LAG_PX = 3
# Margin (m) around design edges excluded from the flat interiors used for the noise floor:
# wider than plausible overlay / bias slivers plus instrument blur.
INTERIOR_MARGIN_M = 1.6e-6


# Fraction of the noise floor above which a final residual is reported unexplained even when
# no binned pattern earns its parameters (the noise-floor estimate itself is good to ~5 %).
UNEXPLAINED_RATIO = 1.25


def _shift_all_masks(params, values):
    overlay = np.array(params.mask_overlay, dtype=float, copy=True)
    overlay[:, 0] += values[0]
    overlay[:, 1] += values[1]
    return params.copy(mask_overlay=overlay)


# A residual registration error of the measurement against the design moves every mask alike.
# It is a nuisance, always fitted (never named): registration is good to a fraction of a pixel.
REGISTRATION = Effect(
    "registration_shift", "height", "process",
    [Parameter(f"{ax}_m", "m", -2e-6, 2e-6, 0.2e-6) for ax in ("dx", "dy")], _shift_all_masks,
    "Residual shift of the registered measurement against the design (nuisance).", kind="calibration",
    order=-1)


# -- statistics -------------------------------------------------------------------------------
@dataclass
class NoiseEstimate:
    """Noise floor and correlation of the measurement, estimated from the data.

    Attributes
    ----------
    sigma : float
        Robust rms of the noise (measurement units).
    corr_area_px : float
        Correlation area ``A = sum of the autocorrelation over lags`` (pixels, >= 1).
    n_samples : int
        Pixels the estimate used.
    """

    sigma: float
    corr_area_px: float
    n_samples: int


def estimate_noise(values, groups, max_lag=MAX_LAG_PX):
    """Noise rms and correlation area from pixels scattering about a per-group constant.

    Parameters
    ----------
    values : ndarray (rows, cols)
    groups : ndarray of int (rows, cols)
        Label of each pixel's flat region; 0 excludes the pixel. Within a group the true
        signal is taken as constant, so the scatter about the group mean is noise.
    max_lag : int
        Largest lag (pixels) of the autocorrelation summed into the correlation area.

    Returns
    -------
    NoiseEstimate
    """
    groups = np.asarray(groups)
    valid = (groups > 0) & np.isfinite(values)
    n = int(valid.sum())
    labels = groups[valid]
    n_groups = np.unique(labels).size
    if n - n_groups < 50:
        raise DoeError(f"too few flat pixels ({n}) to estimate the noise floor; "
                       "the measurement must include feature interiors away from edges")
    sums = np.bincount(labels, weights=values[valid])
    counts = np.bincount(labels)
    dev = np.zeros(values.shape)
    dev[valid] = values[valid] - sums[labels] / counts[labels]
    area = _correlation_area(dev, valid, groups, max_lag)
    # Removing each group's mean also removes ~A pixels' worth of correlated noise variance;
    # undo that shrinkage per group (groups smaller than 3 A carry too little and are dropped).
    n_g = counts[labels]
    keep = n_g > 3 * area
    if keep.sum() < 50:
        raise DoeError(f"too few flat pixels in features wider than the noise correlation "
                       f"({int(keep.sum())}) to estimate the noise floor")
    scaled = dev[valid][keep] * np.sqrt(n_g[keep] / (n_g[keep] - area))
    # MAD is robust to spikes and to a few edge pixels left in the interiors.
    var = (1.4826 * np.median(np.abs(scaled - np.median(scaled)))) ** 2
    if not var > 0:
        var = float(np.mean(scaled ** 2))
    n = int(keep.sum())
    return NoiseEstimate(sigma=float(np.sqrt(var)), corr_area_px=area, n_samples=n)


def _correlation_area(dev, valid, groups, max_lag):
    """Sum of the autocorrelation of ``dev`` over lags up to ``max_lag`` (pairs within a group)."""
    var = np.mean(dev[valid] ** 2)
    clip = np.where(valid & (np.abs(dev) < 5 * np.sqrt(var)), dev, 0.0)
    ref = np.mean(clip[valid] ** 2)
    rows, cols = dev.shape
    area = 0.0
    for dy in range(-max_lag, max_lag + 1):
        for dx in range(-max_lag, max_lag + 1):
            a = (slice(max(0, -dy), rows - max(0, dy)), slice(max(0, -dx), cols - max(0, dx)))
            b = (slice(max(0, dy), rows + min(0, dy)), slice(max(0, dx), cols + min(0, dx)))
            same = valid[a] & valid[b] & (groups[a] == groups[b])
            if same.sum() < 20:
                continue
            area += max(np.mean(clip[a][same] * clip[b][same]) / ref, 0.0)
    return float(max(area, 1.0))


def bic_eff(rss, n, n_eff, k):
    """Information criterion with an effective sample count: ``n_eff ln(RSS/N) + k ln(n_eff)``."""
    return float(n_eff * np.log(rss / n) + k * np.log(n_eff))


# -- the generic fitting loop ------------------------------------------------------------------
@dataclass
class Step:
    """One named effect of a diagnosis."""

    effect: str
    kind: str
    description: str
    params: dict
    uncertainties: dict
    units: dict
    residual_rms_before: float
    residual_rms_after: float
    criterion_change: float
    candidates: dict
    ambiguous_with: list = field(default_factory=list)
    revised: str | None = None

    def to_dict(self):
        return {"effect": self.effect, "kind": self.kind, "description": self.description,
                "measurement_artefact": self.kind == "artefact",
                "params": self.params, "uncertainties": self.uncertainties, "units": self.units,
                "residual_rms_before": self.residual_rms_before, "residual_rms_after": self.residual_rms_after,
                "criterion_change": self.criterion_change, "candidates": self.candidates,
                "ambiguous_with": self.ambiguous_with, "revised": self.revised}


@dataclass
class Diagnosis:
    """Result of :func:`diagnose_heights` or :func:`diagnose_psf`.

    Attributes
    ----------
    domain : {"height", "psf"}
    steps : list of Step
        Named effects in the order found, each with the parameters of the final joint fit.
    model : dict
        Effect name -> fitted parameter values (final joint fit).
    noise_floor : float
    initial_residual_rms, final_residual_rms : float
    unexplained : bool
        Whether a significant structured residual remains (binned residual model earns its
        parameters under the same criterion).
    breakdown_initial, breakdown_final : dict
        Residual broken down by what may explain it (see :func:`residual_breakdown`).
    residual_maps : list of ndarray
        Residual map before the first step and after each step (row 0 at the top).
    """

    domain: str
    steps: list
    model: dict
    noise_floor: float
    corr_area_px: float
    n_samples: int
    n_eff: float
    initial_residual_rms: float
    final_residual_rms: float
    unexplained: bool
    structure_criterion: float
    units: str
    breakdown_initial: dict = field(default_factory=dict)
    breakdown_final: dict = field(default_factory=dict)
    residual_maps: list = field(default_factory=list)
    map_step_m: float | None = None

    @property
    def named(self):
        """Names of the effects found, in order."""
        return [s.effect for s in self.steps]

    def to_dict(self):
        return {"domain": self.domain, "units": self.units,
                "steps": [s.to_dict() for s in self.steps],
                "effects_found": self.named,
                "measurement_artefacts": [s.effect for s in self.steps if s.kind == "artefact"],
                "model": {k: np.asarray(v).tolist() for k, v in self.model.items()},
                "noise_floor": self.noise_floor, "corr_area_px": self.corr_area_px,
                "n_samples": self.n_samples, "n_eff": self.n_eff,
                "initial_residual_rms": self.initial_residual_rms,
                "final_residual_rms": self.final_residual_rms,
                "unexplained": self.unexplained, "structure_criterion": self.structure_criterion,
                "breakdown_initial": self.breakdown_initial, "breakdown_final": self.breakdown_final}

    def plot(self, out_dir):
        """Write ``residual_steps.png`` (residual map before and after each step) and
        ``breakdown.png`` (residual by edge distance, level, density, position, frequency).

        Returns
        -------
        list of Path
        """
        return [_plot_steps(self, Path(out_dir) / "residual_steps.png"),
                _plot_breakdown(self, Path(out_dir) / "breakdown.png")]


class _Problem:
    """What a domain supplies to the fitting loop.

    Subclasses set ``effects`` (candidate Effect objects), ``noise`` (NoiseEstimate) and
    implement ``residual(model) -> 1-D array`` (measured minus model, on the compared samples),
    ``residual_map(model) -> 2-D array`` and ``breakdown(residual_map) -> dict``.
    """

    effects: dict
    noise: NoiseEstimate
    units = "m"
    nuisance: dict = {}

    def residual(self, model):
        raise NotImplementedError

    def residual_map(self, model):
        raise NotImplementedError

    def breakdown(self, residual_map):
        return {}

    def structure_groups(self):
        """Label maps of bins for the structured-residual test (0 = excluded), one per way of
        grouping pixels that an unmodelled effect would show up in."""
        return []


def _fit(problem, model, free, max_iter=None):
    """Least-squares fit of the ``free`` effects' parameters, others held at ``model``.

    Central-difference Jacobians: area-coverage edges make the residual piecewise smooth with
    kinks where an edge crosses a grid line (at zero shift or bias), where one-sided differences
    stall the fit.

    Parameters
    ----------
    max_iter : int, optional
        Cap on function evaluations outside the Jacobian (a short fit to screen candidates).

    Returns (values dict, rss, stderr dict).
    """
    effs = [problem.effects[name] for name in free]
    scale = np.concatenate([e.scales() for e in effs])
    lo = np.concatenate([e.bounds()[0] for e in effs]) / scale
    hi = np.concatenate([e.bounds()[1] for e in effs]) / scale
    x0 = np.concatenate([np.asarray(model[e.name], dtype=float) for e in effs]) / scale
    x0 = np.clip(x0, lo + 1e-9 * (hi - lo), hi - 1e-9 * (hi - lo))
    splits = np.cumsum([e.n_params for e in effs])[:-1]
    sigma = problem.noise.sigma

    def unpack(x):
        trial = dict(model)
        for e, v in zip(effs, np.split(x * scale, splits)):
            trial[e.name] = v
        return trial

    def fun(x):
        return problem.residual(unpack(x)) / sigma

    def jac(x):
        return _central_jacobian(fun, x, lo, hi)

    res = least_squares(fun, x0, jac=jac, bounds=(lo, hi), method="trf", xtol=1e-6, ftol=1e-6,
                        max_nfev=max_iter or 60)
    fitted = unpack(res.x)
    rss = float(np.sum(res.fun ** 2)) * sigma ** 2
    n, k = res.fun.size, res.x.size
    jtj = res.jac.T @ res.jac
    try:
        cov = np.linalg.pinv(jtj) * (np.sum(res.fun ** 2) / max(n - k, 1)) * problem.noise.corr_area_px
        err = np.sqrt(np.clip(np.diag(cov), 0, None)) * scale
    except np.linalg.LinAlgError:
        err = np.full(k, np.nan)
    errors = {e.name: v for e, v in zip(effs, np.split(err, splits))}
    return fitted, rss, errors


def _central_jacobian(fun, x, lo, hi, step=JAC_STEP):
    """Central differences with an absolute step (in units of each parameter's scale),
    one-sided against a bound. SciPy's relative steps vanish at a parameter of exactly zero,
    where most effects start."""
    cols = []
    for i in range(x.size):
        up, down = x.copy(), x.copy()
        up[i] = min(x[i] + step, hi[i])
        down[i] = max(x[i] - step, lo[i])
        cols.append((fun(up) - fun(down)) / (up[i] - down[i]))
    return np.stack(cols, axis=1)


def _rms(r):
    return float(np.sqrt(np.mean(r ** 2)))


def _structure_test(problem, r_map, n_eff, n):
    """Most negative criterion change of a binned (piecewise-constant) model of the residual
    over the problem's groupings; below -threshold a structured residual remains."""
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


def _criterion(problem, model, n, n_eff):
    r = problem.residual(model)
    return bic_eff(float(np.sum(r ** 2)), n, n_eff, sum(problem.effects[m].n_params for m in model))


def _revise(problem, model, errors, steps, alternatives, nuisance, n, n_eff, threshold):
    """Backward pass of the stepwise selection, once all named effects are in the model.

    Nearly degenerate effects (a sub-pixel instrument blur and a narrow sidewall ramp) can only
    be told apart once everything else is explained: each named effect is tried against the
    alternatives that scored close to it when it was chosen (swap if better by the threshold,
    or if tied and the alternative is a measurement artefact), then each named effect is
    dropped if the criterion no longer needs it.
    """
    crit = _criterion(problem, model, n, n_eff)
    by_name = {st.effect: st for st in steps}
    for st in list(steps):
        for alt in alternatives.get(st.effect, []):
            if alt in model or st.effect not in model:
                continue
            trial = {k: v for k, v in model.items() if k != st.effect}
            trial[alt] = problem.effects[alt].start_values()
            fitted, rss, errs = _fit(problem, trial, list(trial))
            c_alt = bic_eff(rss, n, n_eff, sum(problem.effects[m].n_params for m in fitted))
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
    for st in list(steps):
        if len(model) - len(nuisance) <= 1:
            break
        trial = {k: v for k, v in model.items() if k != st.effect}
        fitted, rss, errs = _fit(problem, trial, list(trial))
        c_drop = bic_eff(rss, n, n_eff, sum(problem.effects[m].n_params for m in fitted))
        if c_drop < crit + threshold:
            log.info("revision: %s no longer needed (criterion %+.1f)", st.effect, c_drop - crit)
            model, errors, crit = fitted, errs, c_drop
    return model, errors, crit


def run_diagnosis(problem, threshold=DEFAULT_THRESHOLD, max_steps=6, domain="height", candidates=None,
                  screen_iter=SCREEN_ITER, stop_at_floor=True):
    """The greedy model-building loop on a prepared problem (see the module docstring).

    Parameters
    ----------
    problem : _Problem
    threshold : float
        Criterion drop a candidate must achieve to be named.
    max_steps : int
    domain : str
    candidates : list of str, optional
        Restrict the candidates (default: every registered effect of the domain).
    screen_iter : int
        Iterations of each candidate's screening fit (the candidate with the named effects).
        A short fit over-estimates the RSS, so its criterion change is conservative; the
        chosen effect is then fitted to convergence jointly with all effects and nuisances.
    stop_at_floor : bool
        Stop as soon as the residual rms reaches the noise floor (else only the criterion stops).

    Returns
    -------
    Diagnosis
    """
    nuisance = list(getattr(problem, "nuisance", {}))
    names = [n for n in (list(candidates) if candidates is not None else list(problem.effects)) if n not in nuisance]
    model = {}
    if nuisance:
        model, _, _ = _fit(problem, {n: problem.effects[n].start_values() for n in nuisance}, nuisance)
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
    while len(steps) < max_steps and (_rms(r) > problem.noise.sigma or not stop_at_floor):
        pending = [nm for nm in names if nm not in model]
        if not pending:
            break
        scores = {}
        fits = {}
        k_now = sum(problem.effects[m].n_params for m in model)
        with Progress(len(pending), desc=f"diagnosis step {len(steps) + 1}") as bar:
            for name in pending:
                eff = problem.effects[name]
                trial = dict(model)
                trial[name] = eff.start_values()
                # The named effects refit with the candidate: partly degenerate effects (a blur
                # and a sidewall ramp) must be able to share what one of them took alone.
                free = [m for m in model if m not in nuisance] + [name]
                fitted, rss_c, _ = _fit(problem, trial, free, max_iter=screen_iter)
                scores[name] = bic_eff(rss_c, n, n_eff, k_now + eff.n_params) - crit
                fits[name] = fitted
                bar.update(1, status=f"{name} {scores[name]:+.1f}")
        if not scores:
            break
        best = min(scores, key=scores.get)
        log.info("candidates: %s", {k: round(v, 1) for k, v in sorted(scores.items(), key=lambda kv: kv[1])})
        if scores[best] > -threshold:
            break
        # Candidates close to the best are fitted to convergence and compared again; those
        # within the threshold of the best cannot be told apart by the data. Among them a
        # measurement artefact is preferred: it is always present in a measurement, and a
        # fabrication effect must not be blamed for what the instrument does.
        close = [c for c in scores if scores[c] < scores[best] + max(threshold, 0.02 * abs(scores[best]))]
        refits = {}
        for c in close:
            refits[c] = _fit(problem, fits[c], list(model) + [c])
            scores[c] = bic_eff(refits[c][1], n, n_eff, k_now + problem.effects[c].n_params) - crit
        best = min(close, key=scores.get)
        tied = [c for c in close if scores[c] <= scores[best] + threshold]
        artefacts = [c for c in tied if problem.effects[c].kind == "artefact"]
        if artefacts:
            best = min(artefacts, key=scores.get)
        ambiguous = sorted(c for c in tied if c != best)
        alternatives[best] = [c for c in close if c != best]
        model, rss_new, errors = refits[best]
        new_crit = bic_eff(rss_new, n, n_eff, k_now + problem.effects[best].n_params)
        r_new = problem.residual(model)
        eff = problem.effects[best]
        steps.append(Step(
            effect=best, kind=eff.kind, description=eff.description,
            params={}, uncertainties={}, units={p.name: p.unit for p in eff.params},
            residual_rms_before=_rms(r), residual_rms_after=_rms(r_new),
            criterion_change=new_crit - crit, candidates={k: float(v) for k, v in scores.items()},
            ambiguous_with=ambiguous))
        maps.append(problem.residual_map(model))
        r, crit = r_new, new_crit
    if steps:
        model, errors, crit = _revise(problem, model, errors, steps, alternatives, nuisance, n, n_eff, threshold)
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
    return Diagnosis(domain=domain, steps=steps, model=model, noise_floor=problem.noise.sigma,
                     corr_area_px=problem.noise.corr_area_px, n_samples=n, n_eff=n_eff,
                     initial_residual_rms=initial_rms, final_residual_rms=_rms(r),
                     unexplained=unexplained, structure_criterion=struct, units=problem.units,
                     breakdown_initial=breakdown_initial, breakdown_final=problem.breakdown(final_map),
                     residual_maps=maps)


# -- residual breakdown -----------------------------------------------------------------------
def binned(values, key, edges):
    """Mean, rms and count of ``values`` in bins of ``key`` (NaN values ignored)."""
    ok = np.isfinite(values) & np.isfinite(key)
    idx = np.digitize(key[ok], edges) - 1
    inside = (idx >= 0) & (idx < len(edges) - 1)
    v, idx = values[ok][inside], idx[inside]
    nb = len(edges) - 1
    count = np.bincount(idx, minlength=nb)
    mean = np.bincount(idx, weights=v, minlength=nb) / np.maximum(count, 1)
    ms = np.bincount(idx, weights=v ** 2, minlength=nb) / np.maximum(count, 1)
    return {"edges": np.asarray(edges, dtype=float).tolist(), "mean": mean.tolist(),
            "rms": np.sqrt(ms).tolist(), "count": count.tolist()}


def radial_psd(residual_map, step_m):
    """Radially averaged power spectral density of a residual map (NaN set to 0).

    Returns a binned dict keyed by spatial frequency (cycles/m); ``mean`` holds the PSD
    (units^2 m^2), normalized so that its integral over the plane is the mean square.
    """
    r = np.nan_to_num(np.asarray(residual_map, dtype=float))
    rows, cols = r.shape
    spec = np.abs(np.fft.fft2(r)) ** 2 * step_m ** 2 / (rows * cols)
    fy = np.fft.fftfreq(rows, d=step_m)[:, None]
    fx = np.fft.fftfreq(cols, d=step_m)[None, :]
    f = np.hypot(fy, fx)
    edges = np.linspace(0, 0.5 / step_m, 16)
    out = binned(spec.ravel(), f.ravel(), edges)
    out.pop("rms")
    return out


# -- height domain ----------------------------------------------------------------------------
def signed_edge_distance_m(mask, step_m):
    """Distance (m) of each pixel centre to the nearest edge of a boolean mask; positive inside."""
    inside = ndi.distance_transform_edt(mask) - 0.5
    outside = ndi.distance_transform_edt(~mask) - 0.5
    return np.where(mask, inside, -outside) * step_m


class HeightProblem(_Problem):
    """A measured height map against the design through the process model.

    Parameters
    ----------
    levels : ndarray of int (rows, cols)
        Design levels, row 0 at the top.
    pitch_m : float
    measured_height_m : ndarray
        The measurement on the fine model grid of ``region``: shape
        ``((row1 - row0) * u, (col1 - col0) * u)`` with ``u = pitch_m / step_m``; NaN = no data.
    step_m : float
    region : (row0, row1, col0, col1)
        Design pixels the measurement covers (half-open).
    base_params : ProcessParams
        The ideal process (the nominal etch depths).
    effects : list of Effect
    border_m : float
        Width excluded at the edges of the map (spectral filters see mirrored data there).
    fit_registration : bool
        Fit a residual shift of the whole pattern as a nuisance in every model.
    """

    units = "m"

    def __init__(self, levels, pitch_m, measured_height_m, step_m, region, base_params, effects,
                 border_m=3e-6, fit_registration=True):
        from masks.decompose import levels_to_masks
        from masks.process import fine_upsample

        self.levels = np.asarray(levels)
        self.pitch_m = float(pitch_m)
        self.region = tuple(int(v) for v in region)
        u = fine_upsample(pitch_m, step_m)
        if abs(pitch_m / u - step_m) > 1e-6 * step_m:
            raise DoeError(f"model grid step {step_m * 1e6:.4g} um must divide the design pitch "
                           f"{pitch_m * 1e6:.4g} um (resample the measurement first)")
        self.step_m = pitch_m / u
        self.upsample = u
        row0, row1, col0, col1 = self.region
        shape = ((row1 - row0) * u, (col1 - col0) * u)
        meas = np.asarray(measured_height_m, dtype=float)
        if meas.shape != shape:
            raise DoeError(f"measurement of shape {meas.shape} does not match the model grid {shape} "
                           f"of design region {self.region} at {u} samples per pixel")
        self.measured = meas
        self.base = base_params
        self.effects = {e.name: e for e in effects}
        if fit_registration:
            self.effects[REGISTRATION.name] = REGISTRATION
            self.nuisance = {REGISTRATION.name: REGISTRATION}
        b = int(np.ceil(border_m / self.step_m))
        keep = np.zeros(shape, dtype=bool)
        keep[b:shape[0] - b, b:shape[1] - b] = True
        self.valid = keep & np.isfinite(meas)
        if self.valid.sum() < 100:
            raise DoeError("the measurement has fewer than 100 valid pixels in the diagnosed region")
        # Design quantities on the fine grid, for the noise floor and the breakdown.
        lev = self.levels[row0:row1, col0:col1]
        self.fine_levels = np.repeat(np.repeat(lev, u, axis=0), u, axis=1)
        masks = levels_to_masks(lev, len(base_params.etch_depth))
        self.fine_masks = np.repeat(np.repeat(masks, u, axis=1), u, axis=2)
        self.edge_m = np.stack([signed_edge_distance_m(m, self.step_m) for m in self.fine_masks])
        self.any_edge_m = np.min(np.abs(self.edge_m), axis=0)
        m = int(np.ceil(INTERIOR_MARGIN_M / self.step_m))
        flat = (ndi.maximum_filter(self.fine_levels, size=2 * m + 1)
                == ndi.minimum_filter(self.fine_levels, size=2 * m + 1)) & self.valid
        groups, _ = ndi.label(flat)
        self.noise = estimate_noise(meas, groups)

    def surface(self, model):
        """Model height map (m) on the fine grid with the effects in ``model`` applied."""
        from masks.process import simulate_surface

        chosen = sorted((self.effects[n] for n in model),
                        key=lambda e: (("process", "surface").index(e.stage), e.order))
        params = self.base
        for e in chosen:
            if e.stage == "process":
                params = e.apply(params, e.check(model[e.name]))
        h = simulate_surface(self.levels, self.pitch_m, params, step_m=self.step_m, region=self.region).height_m
        for e in chosen:
            if e.stage == "surface":
                h = e.apply(h, e.check(model[e.name]), self.step_m)
        return h

    def residual(self, model):
        r = self.measured[self.valid] - self.surface(model)[self.valid]
        # The measurement's height zero is arbitrary: a piston is always removed (1 dof).
        return r - r.mean()

    def residual_map(self, model):
        out = np.full(self.measured.shape, np.nan)
        out[self.valid] = self.residual(model)
        return out

    def structure_groups(self):
        """Level x distance to the nearest edge (edge effects), level x 4 x 4 tiles of the field
        (density and position effects), and signed distance to each mask's edges."""
        dist_bin = np.digitize(self.any_edge_m, np.array([0.25, 0.5, 1.0, 1.5, 2.5, 4.0]) * 1e-6)
        rows, cols = self.valid.shape
        tile = (np.arange(rows)[:, None] * 4 // rows) * 4 + (np.arange(cols)[None, :] * 4 // cols)
        signed = [np.digitize(d, np.linspace(-3e-6, 3e-6, 13)) for d in self.edge_m]
        maps = [self.fine_levels * 8 + dist_bin, self.fine_levels * 16 + tile]
        maps.append(sum(b * 14 ** j for j, b in enumerate(signed[::-1][:2])))
        return [np.where(self.valid, m + 1, 0) for m in maps]

    def breakdown(self, residual_map):
        """Residual by signed distance to each mask's edges, level, density, position, frequency."""
        out = {}
        edges_d = np.linspace(-4e-6, 4e-6, 17)
        for j, d in enumerate(self.edge_m):
            out[f"edge_distance_mask{j}_m"] = binned(residual_map, d, edges_d)
        out["level"] = binned(residual_map, self.fine_levels.astype(float), np.arange(-0.5, 16.5))
        sigma_px = 50e-6 / self.step_m
        density = ndi.gaussian_filter(self.fine_masks.mean(axis=0).astype(float), sigma_px, mode="reflect")
        out["pattern_density"] = binned(residual_map, density, np.linspace(0, 1, 11))
        rows, cols = residual_map.shape
        yy, xx = np.mgrid[:rows, :cols]
        radius = np.hypot(yy - (rows - 1) / 2, xx - (cols - 1) / 2) * self.step_m
        out["radius_from_centre_m"] = binned(residual_map, radius, np.linspace(0, radius.max() + 1e-12, 9))
        out["spatial_frequency_per_m"] = radial_psd(residual_map, self.step_m)
        return out


def _busiest_region(levels, region_px):
    """The window of ``region_px`` design pixels with the most level edges times flat
    interiors: the effects show at edges and between levels, the noise floor on interiors."""
    rows, cols = levels.shape
    h, w = min(region_px, rows), min(region_px, cols)
    edges = np.zeros(levels.shape)
    edges[:, :-1] += levels[:, 1:] != levels[:, :-1]
    edges[:-1, :] += levels[1:, :] != levels[:-1, :]
    # Design pixels whose 3 x 3 neighbourhood is one level: flat interiors for the noise floor.
    flat = (ndi.maximum_filter(levels, size=3) == ndi.minimum_filter(levels, size=3)).astype(float)

    def window_sums(a):  # summed-area table: the sum over every h x w window
        sat = np.pad(a.cumsum(0).cumsum(1), ((1, 0), (1, 0)))
        return sat[h:, w:] - sat[:-h, w:] - sat[h:, :-w] + sat[:-h, :-w]

    counts = window_sums(edges) * window_sums(flat)
    # Prefer the centre among equally busy windows (ties, e.g. a periodic design).
    rr, cc = np.mgrid[:counts.shape[0], :counts.shape[1]]
    centre = np.hypot(rr - (rows - h) / 2, cc - (cols - w) / 2)
    r0, c0 = np.unravel_index(np.argmax(counts - 1e-6 * centre), counts.shape)
    return (int(r0), int(r0) + h, int(c0), int(c0) + w)


def diagnose_heights(design_levels, pitch_m, measured_height_m, step_m, region=None, region_px=40,
                     depths_m=None, candidates=None, threshold=DEFAULT_THRESHOLD, max_steps=6, stop_at_floor=True):
    """Find, name and fit the effects that explain a measured height map.

    Parameters
    ----------
    design_levels : ndarray of int (rows, cols)
        The design's levels (0 = top surface), row 0 at the top.
    pitch_m : float
        Design pixel pitch.
    measured_height_m : ndarray
        Measured heights (m, z up) registered onto the fine model grid: fine pixel (a, b) of
        the map covers design coordinates ``row0 + (a + 0.5) / u - 0.5`` (likewise columns),
        ``u = pitch_m / step_m``. It covers either the whole design or ``region``.
    step_m : float
        Fine-grid spacing of the measurement; must divide ``pitch_m``.
    region : (row0, row1, col0, col1), optional
        Design pixels the measurement covers. Default: the whole design.
    region_px : int
        The diagnosis fits the window of at most this many design pixels per side that holds
        the most level edges (each model evaluation then costs milliseconds).
    depths_m : sequence of float, optional
        Nominal etch depths per mask (default: 75, 150, 300, 600 nm).
    candidates : list of str, optional
        Effects to try (default: every registered height-domain effect).
    threshold : float
        Criterion drop required to name an effect.
    max_steps : int
    stop_at_floor : bool
        Stop when the residual reaches the noise floor (default) or only on the criterion.

    Returns
    -------
    Diagnosis
    """
    from masks.process import ProcessParams, fine_upsample

    levels = np.asarray(design_levels)
    if levels.ndim != 2:
        raise DoeError(f"design levels must be a 2-D array, got shape {levels.shape}")
    u = fine_upsample(pitch_m, step_m)
    meas = np.asarray(measured_height_m, dtype=float)
    if region is None:
        region = (0, levels.shape[0], 0, levels.shape[1])
    row0, row1, col0, col1 = (int(v) for v in region)
    if meas.shape != ((row1 - row0) * u, (col1 - col0) * u):
        raise DoeError(f"measurement of shape {meas.shape} does not cover design region {tuple(region)} "
                       f"at {u} samples per {pitch_m * 1e6:.3g} um pixel (expected "
                       f"{((row1 - row0) * u, (col1 - col0) * u)})")
    sub = _busiest_region(levels[row0:row1, col0:col1], region_px)
    meas = meas[sub[0] * u:sub[1] * u, sub[2] * u:sub[3] * u]
    window = (row0 + sub[0], row0 + sub[1], col0 + sub[2], col0 + sub[3])
    base = ProcessParams.ideal(depths_m=depths_m) if depths_m is not None else ProcessParams.ideal()
    problem = HeightProblem(levels, pitch_m, meas, step_m, window, base, effects_for("height", candidates))
    diag = run_diagnosis(problem, threshold=threshold, max_steps=max_steps, domain="height",
                         stop_at_floor=stop_at_floor)
    diag.map_step_m = problem.step_m
    return diag


# -- PSF domain -------------------------------------------------------------------------------
class PsfRenderer:
    """Ideal PSFs of a design for any wavelengths and source distance, engines and results cached.

    ``render(height_m, wavelengths_m, depth_m)`` returns (views, wavelengths, rows, cols) for
    the views ``("coded", "uncoded")``.
    """

    def __init__(self, camera, pitch_m, shape, material="fused_silica", doe_oversample=1, cache_size=16):
        self.camera, self.pitch_m, self.shape = camera, float(pitch_m), tuple(shape)
        self.material, self.q = material, int(doe_oversample)
        self._engines = {}
        self._results = {}
        self.cache_size = cache_size
        self.calls = 0

    def __call__(self, height_m, wavelengths_m, depth_m):
        from doedesign.psf import VIEWS, PSFEngine

        wls = tuple(np.round(np.asarray(wavelengths_m, dtype=float), 15))
        key = (hash(np.asarray(height_m).tobytes()), wls, float(depth_m))
        if key in self._results:
            return self._results[key]
        ekey = (wls, float(depth_m))
        if ekey not in self._engines:
            if len(self._engines) > self.cache_size:
                self._engines.pop(next(iter(self._engines)))
            self._engines[ekey] = PSFEngine(self.camera, self.pitch_m, self.shape, self.material, wls,
                                            (float(depth_m),), self.q)
        self.calls += 1
        out = self._engines[ekey].psf(height_m, views=VIEWS).psf[:, 0]
        if len(self._results) > self.cache_size:
            self._results.pop(next(iter(self._results)))
        self._results[key] = out
        return out


def psf_forward(model, effects, render, height_m, wavelengths_m, depth_m, views):
    """Model PSF stack of the measured ``views`` with the effects of ``model`` applied.

    Each (view, wavelength) channel is normalized to unit sum over the window, as the measured
    stack is (its units are arbitrary).

    Parameters
    ----------
    model : dict
        Effect name -> values.
    effects : dict
        Effect name -> Effect (per-channel effects already expanded).
    render : callable
        ``render(height_m, wavelengths_m, depth_m) -> (2 views, wavelengths, rows, cols)``.
    views : sequence of str
        Measured views, a subset of ``("coded", "uncoded")``.
    """
    from doedesign.psf import VIEWS

    chosen = sorted((effects[n] for n in model), key=lambda e: (("height", "optics", "sensor").index(e.stage), e.order))
    h = np.asarray(height_m, dtype=float)
    info = {"depth_m": float(depth_m)}
    for e in chosen:
        if e.stage == "height":
            h = e.apply(h, e.check(model[e.name]))
    for e in chosen:
        if e.stage == "optics":
            render = e.apply(render, e.check(model[e.name]), info)
    full = render(h, wavelengths_m, depth_m)
    stack = full[[VIEWS.index(v) for v in views]]
    info.update(views=tuple(views), full=full, full_views=VIEWS)
    for e in chosen:
        if e.stage == "sensor":
            stack = e.apply(stack, e.check(model[e.name]), info)
    return stack / stack.sum(axis=(-2, -1), keepdims=True)


def _mosaic(stack):
    """Channels of a (views, wavelengths, rows, cols) stack one under another, separated by a
    row of NaN, as one 2-D map (row 0 at the top)."""
    v, w, rows, cols = stack.shape
    out = np.full((v * w, rows + 1, cols), np.nan)
    out[:, :rows] = stack.reshape(v * w, rows, cols)
    return out.reshape(v * w * (rows + 1), cols)[:-1]


class PsfProblem(_Problem):
    """A measured PSF stack against the design's PSFs through the camera.

    Parameters
    ----------
    design_height_m : ndarray (rows, cols)
    pitch_m : float
    camera : Camera
    measured : ndarray (views, wavelengths, rows, cols)
        Any units; each channel is normalized to unit sum.
    views : sequence of str
    wavelengths_m : sequence of float
    depth_m : float
        Point-source distance (default in :func:`diagnose_psf`: the camera's focus).
    effects : list of Effect
    """

    units = "fraction of the channel's light per pixel"

    def __init__(self, design_height_m, pitch_m, camera, measured, views, wavelengths_m, depth_m, effects,
                 material="fused_silica", doe_oversample=1, renderer=None):
        meas = np.asarray(measured, dtype=float)
        self.views = tuple(views)
        self.wavelengths_m = np.asarray(wavelengths_m, dtype=float)
        if meas.shape[:2] != (len(self.views), self.wavelengths_m.size) or meas.shape[2:] != tuple(camera.window_shape):
            raise DoeError(f"measured PSF stack of shape {meas.shape} does not match {len(self.views)} view(s), "
                           f"{self.wavelengths_m.size} wavelength(s) and the camera window {camera.window_shape}")
        sums = np.nansum(meas, axis=(-2, -1), keepdims=True)
        if np.any(sums <= 0):
            raise DoeError("a channel of the measured PSF stack holds no light (sum <= 0)")
        self.measured = meas / sums
        self.height_m = np.asarray(design_height_m, dtype=float)
        self.depth_m = float(depth_m)
        self.render = renderer or PsfRenderer(camera, pitch_m, self.height_m.shape, material, doe_oversample)
        self.channels = [f"{v}_{wl * 1e9:.0f}nm" for v in self.views for wl in self.wavelengths_m]
        self.effects = {e.name: e.for_channels(self.channels) for e in effects}
        self.axis_pixel = camera.axis_pixel
        self.valid = np.isfinite(self.measured)
        # Where no light of either view falls in the ideal model, the measurement is noise
        # (plus a smooth background): the noise floor comes from those pixels in 8 x 8 tiles.
        from doedesign.psf import VIEWS

        full = self.render(self.height_m, self.wavelengths_m, self.depth_m)
        light = full / full.sum(axis=(-2, -1), keepdims=True)
        lit = (light > 1e-3 * light.max(axis=(-2, -1), keepdims=True)).any(axis=0)
        lit = ndi.binary_dilation(lit, structure=np.ones((1, 7, 7), dtype=bool))
        self.ideal = light[[VIEWS.index(v) for v in self.views]]
        rows, cols = camera.window_shape
        tiles = (np.arange(rows)[:, None] // 8) * ((cols + 7) // 8) + np.arange(cols)[None, :] // 8 + 1
        n_tiles = int(tiles.max())
        groups = np.zeros(self.measured.shape, dtype=int)
        for vi in range(len(self.views)):
            for wi in range(self.wavelengths_m.size):
                ci = vi * self.wavelengths_m.size + wi
                groups[vi, wi] = np.where(~lit[wi] & self.valid[vi, wi], tiles + ci * n_tiles, 0)
        self.noise = estimate_noise(_mosaic(self.measured), np.nan_to_num(_mosaic(groups)).astype(int))

    def stack(self, model):
        return psf_forward(model, self.effects, self.render, self.height_m, self.wavelengths_m, self.depth_m,
                           self.views)

    def _residual_stack(self, model):
        # The measured channel sums carry noise and light outside the window: a free scale per
        # channel (least squares, closed form) is profiled out, like the piston for heights.
        p = np.where(self.valid, self.stack(model), 0.0)
        m = np.where(self.valid, self.measured, 0.0)
        scale = (m * p).sum(axis=(-2, -1), keepdims=True) / (p * p).sum(axis=(-2, -1), keepdims=True)
        return np.where(self.valid, m - scale * p, np.nan)

    def residual(self, model):
        return self._residual_stack(model)[self.valid]

    def residual_map(self, model):
        return _mosaic(self._residual_stack(model))

    def _radius(self):
        rows, cols = self.measured.shape[-2:]
        yy, xx = np.mgrid[:rows, :cols]
        return np.hypot(yy - self.axis_pixel[0], xx - self.axis_pixel[1])

    def structure_groups(self):
        """Radial rings about the axis per channel, and 8 x 8 pixel tiles per channel."""
        rows, cols = self.measured.shape[-2:]
        ring = np.minimum(self._radius() // 3, 40).astype(int)
        tiles = (np.arange(rows)[:, None] // 8) * ((cols + 7) // 8) + np.arange(cols)[None, :] // 8
        nch = len(self.channels)
        out = []
        for m in (ring, tiles):
            stack = np.broadcast_to(m, self.measured.shape).reshape(nch, rows, cols)
            labelled = stack + (np.arange(nch)[:, None, None] * (int(m.max()) + 1)) + 1
            out.append(np.nan_to_num(_mosaic(labelled.reshape(self.measured.shape))).astype(int))
        return out

    def breakdown(self, residual_map):
        """Residual by radius from the axis (pixels), by channel, and by spatial frequency."""
        nch = len(self.channels)
        rows, cols = self.measured.shape[-2:]
        r = np.full((nch, rows + 1, cols), np.nan)
        r.reshape(-1, cols)[:residual_map.shape[0]] = residual_map
        r = r[:, :rows]
        radius = np.broadcast_to(self._radius(), r.shape)
        out = {"radius_from_axis_px": binned(r, radius, np.linspace(0, radius.max() + 1e-9, 13)),
               "channel_rms": {c: float(np.sqrt(np.nanmean(r[i] ** 2))) for i, c in enumerate(self.channels)},
               "channel_mean": {c: float(np.nanmean(r[i])) for i, c in enumerate(self.channels)}}
        out["spatial_frequency_per_px"] = radial_psd(np.nanmean(r, axis=0), 1.0)
        return out


def diagnose_psf(design, camera, measured_stack, wavelengths_m, views=("coded",), depth_m=None, candidates=None,
                 threshold=DEFAULT_THRESHOLD, max_steps=5, doe_oversample=1):
    """Find, name and fit the effects that explain a measured PSF stack.

    Parameters
    ----------
    design : Design
        The element (its height map, pitch and material).
    camera : Camera
        Geometry of the measurement (window, axis pixel, DOE side).
    measured_stack : ndarray (views, wavelengths, rows, cols) or (wavelengths, rows, cols)
        Measured PSFs in any units, row 0 at the top, the axis at ``camera.axis_pixel``;
        a 3-D stack is one view (``views[0]``).
    wavelengths_m : sequence of float
    views : sequence of str
        Which views the stack holds, from ``("coded", "uncoded")``.
    depth_m : float, optional
        Point-source distance; default where the camera is focused.
    candidates : list of str, optional
        Effects to try (default every registered PSF-domain effect).

    Returns
    -------
    Diagnosis
    """
    stack = np.asarray(measured_stack, dtype=float)
    if stack.ndim == 3:
        stack = stack[None]
    if stack.ndim != 4:
        raise DoeError(f"measured PSF stack must be (views, wavelengths, rows, cols), got shape {stack.shape}")
    if len(views) != stack.shape[0] or any(v not in ("coded", "uncoded") for v in views):
        raise DoeError(f"views {tuple(views)} do not match a stack of {stack.shape[0]} view(s)")
    depth = camera.focus_distance_m if depth_m is None else float(depth_m)
    problem = PsfProblem(design.height_m, design.pitch_m, camera, stack, views, wavelengths_m, depth,
                         effects_for("psf", candidates), material=design.material, doe_oversample=doe_oversample)
    return run_diagnosis(problem, threshold=threshold, max_steps=max_steps, domain="psf")


# -- plots ------------------------------------------------------------------------------------
def _plot_steps(diag, path):
    import matplotlib.pyplot as plt

    maps = diag.residual_maps
    scale, unit = (1e9, "nm") if diag.domain == "height" else (1.0, "fraction")
    lim = np.nanpercentile(np.abs(maps[0]), 99) * scale or 1.0
    fig, axes = plt.subplots(1, len(maps), figsize=(3.2 * len(maps), 3.4), squeeze=False)
    if len(maps) == len(diag.steps) + 1:
        titles = ["ideal model"] + [f"+ {s.effect}" for s in diag.steps]
        rms = [diag.initial_residual_rms] + [s.residual_rms_after for s in diag.steps]
    else:  # the backward pass revised the steps: show the ideal and the final model
        titles = ["ideal model", "final: " + ", ".join(diag.named)]
        rms = [diag.initial_residual_rms, diag.final_residual_rms]
    for ax, m, t, r in zip(axes[0], maps, titles, rms):
        im = ax.imshow(m * scale, cmap="RdBu_r", vmin=-lim, vmax=lim, origin="upper", interpolation="nearest")
        ax.set_title(f"{t}\nrms {r * scale:.3g} {unit}", fontsize=9)
        ax.set_xticks([])
        ax.set_yticks([])
    fig.colorbar(im, ax=axes[0].tolist(), shrink=0.8, label=f"measured - model ({unit}); row 0 at top")
    return save_figure(fig, path)


def _plot_breakdown(diag, path):
    import matplotlib.pyplot as plt

    scale, unit = (1e9, "nm") if diag.domain == "height" else (1.0, "fraction")
    keys = [k for k, v in diag.breakdown_initial.items() if "rms" in v]
    fig, axes = plt.subplots(1, max(len(keys), 1), figsize=(3.4 * max(len(keys), 1), 3.0), squeeze=False)
    for ax, key in zip(axes[0], keys):
        for label, bd, style in (("before", diag.breakdown_initial, "o-"), ("after", diag.breakdown_final, "s--")):
            b = bd[key]
            centres = 0.5 * (np.asarray(b["edges"][1:]) + np.asarray(b["edges"][:-1]))
            x = centres * 1e6 if key.endswith("_m") else centres
            ax.plot(x, np.asarray(b["mean"]) * scale, style, ms=3, label=f"mean {label}")
        ax.axhline(0, color="k", lw=0.5)
        ax.set_xlabel(f"{key[:-2]} (um)" if key.endswith("_m") else key, fontsize=8)
        ax.set_ylabel(f"residual ({unit})", fontsize=8)
        ax.tick_params(labelsize=7)
    axes[0][0].legend(fontsize=7)
    return save_figure(fig, path)
