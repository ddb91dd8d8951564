"""A user's time limit stops a fit under way, and nothing is named from a fit it stopped; a fit to
convergence ends where further steps cannot change a decision (criterion units)."""

import numpy as np

from metrology.diagnosis import diagnose_heights
from metrology.diagnosis import budget
from metrology.diagnosis import engine as dg
from metrology.diagnosis import fitting
from metrology.diagnosis.effects import Effect, Parameter
from metrology.diagnosis.noise import NoiseEstimate
from metrology.diagnosis.synthetic import HEIGHT_EFFECTS, make_height_case


class _Decay(dg.Problem):
    """y = a exp(-x / t) with white noise of known sigma (correlation area 1): nonlinear in t."""

    def __init__(self, x, y, sigma):
        self.x, self.y, self.calls = x, y, []
        self.noise = NoiseEstimate(sigma, 1.0, x.size)
        self.effects = {"decay": Effect("decay", "height", "surface",
                                        [Parameter("a", "1", 0.0, 10.0, 1.0), Parameter("t", "1", 0.05, 10.0, 1.0, 1.0)],
                                        lambda h, v, s: h, "an exponential decay")}

    def residual(self, model):
        a, t = model["decay"]
        r = self.y - a * np.exp(-self.x / t)
        self.calls.append(float(r @ r))
        return r


def _decay(seed=5):
    rng = np.random.default_rng(seed)
    x = np.linspace(0.0, 4.0, 500)
    return _Decay(x, 3.0 * np.exp(-x / 0.7) + 0.02 * rng.standard_normal(x.size), 0.02)


def test_a_stopped_fit_ends_at_its_best_evaluation_with_no_uncertainties():
    problem = _decay()
    asked = []

    def stop():  # the budget runs out after the solver's first step (a Jacobian is 4 evaluations)
        asked.append(1)
        return len(problem.calls) >= 7

    start = {"decay": np.array([1.0, 2.0])}
    fitted, rss, errors = fitting.fit_effects(problem, start, ["decay"], stop=stop)
    stopped_at = len(problem.calls)
    assert asked and stopped_at == 7  # under way: asked before each evaluation
    # The model is the evaluation it returns the RSS of, the best the solver saw (below the start's).
    np.testing.assert_allclose(np.sum(problem.residual(fitted) ** 2), rss)
    assert rss < np.sum(problem.residual(start) ** 2)
    assert np.all(np.isnan(errors["decay"]))
    problem.calls.clear()
    _, full, _ = fitting.fit_effects(problem, start, ["decay"])
    assert len(problem.calls) > 2 * stopped_at and full < rss


class _Poly(dg.Problem):
    """y = sum_k c_k x^k, six coefficients (a Jacobian of six central-difference columns, twelve
    evaluations), white noise of known sigma."""

    def __init__(self, parallel):
        rng = np.random.default_rng(4)
        self.x, self.calls, self.parallel_fits = np.linspace(-1.0, 1.0, 400), [], parallel
        self.y = np.polyval([0.5, -1.0, 0.3, 2.0, -0.7, 1.0], self.x) + 0.01 * rng.standard_normal(400)
        self.noise = NoiseEstimate(0.01, 1.0, self.x.size)
        self.effects = {"poly": Effect("poly", "height", "surface",
                                       [Parameter(f"c{k}", "1", -10.0, 10.0, 1.0) for k in range(6)],
                                       lambda h, v, s: h, "a polynomial")}

    def residual(self, model):
        self.calls.append(1)
        return self.y - np.polyval(model["poly"], self.x)


def test_a_jacobian_under_way_ends_at_its_next_column_once_the_budget_is_spent():
    # The budget runs out in the first Jacobian (after its first column's two evaluations): the
    # fit returns its start at once, not after the other ten evaluations of that Jacobian. With
    # two threads the columns already under way finish (two of them at most).
    for parallel, most in ((False, 3), (True, 5)):
        problem = _Poly(parallel)
        start = {"poly": np.zeros(6)}
        fitted, rss, errors = fitting.fit_effects(problem, start, ["poly"],
                                                  stop=lambda: len(problem.calls) >= 3)
        assert 3 <= len(problem.calls) <= most
        np.testing.assert_array_equal(fitted["poly"], start["poly"])
        assert np.all(np.isnan(errors["poly"]))


def test_a_fit_to_convergence_lands_within_the_criterion_tolerance_of_the_optimum():
    problem = _decay()
    fitted, rss, errors = fitting.fit_effects(problem, {"decay": np.array([1.0, 2.0])}, ["decay"])
    # The optimum, independently: scipy's own solver with tight tolerances and its own Jacobian.
    from scipy.optimize import least_squares

    exact = least_squares(lambda p: problem.y - p[0] * np.exp(-problem.x / p[1]), [1.0, 2.0], method="lm",
                          xtol=1e-14, ftol=1e-14)
    n = problem.x.size
    gap = dg.bic_eff(rss, n, n, 2) - dg.bic_eff(float(np.sum(exact.fun ** 2)), n, n, 2)
    assert 0.0 <= gap < fitting.CRITERION_TOL + 1e-9
    # Within the reach of that tolerance in its uncertainty (a criterion within d of the
    # optimum holds every parameter within sqrt(d) standard errors).
    assert np.all(np.abs(fitted["decay"] - exact.x) < np.sqrt(fitting.CRITERION_TOL) * errors["decay"])


def test_no_effect_is_named_from_a_refit_the_budget_cut_short(monkeypatch):
    # The overlay case that test_diagnose names without a budget. The budget runs out as the
    # candidate's fit to convergence starts (after its screening fit scored it): the fit stops
    # at its start, and the screening fit's parameters are not a diagnosis.
    case = make_height_case(["mask_overlay"], 1000 + HEIGHT_EFFECTS.index("mask_overlay"))
    d = case.data
    clock = [0.0]
    real_fit = dg.fit_effects

    def fit(problem, model, free, max_iter=None, **kw):
        if max_iter is None and set(free) - set(getattr(problem, "nuisance", {})):
            clock[0] = 1e9  # a refit with a candidate starts: the budget is spent
        return real_fit(problem, model, free, max_iter=max_iter, **kw)

    monkeypatch.setattr(budget, "cpu_seconds", lambda: clock[0])
    monkeypatch.setattr(dg, "fit_effects", fit)
    diag = diagnose_heights(d["levels"], d["pitch_m"], d["measured_height_m"], d["step_m"], region_px=32,
                            limit=budget.Deadline.after(100.0))
    assert diag.named == []
    report = diag.to_dict()
    stop = report["stopped_early"]
    assert "cut short" in stop["reason"] and stop["cut_short"] == ["mask_overlay"] and stop["limit"] == "cpu"
    # Incomplete: it tested nothing (it named nothing), so every candidate is listed as not tried.
    assert report["incomplete"] and report["summary"].startswith("INCOMPLETE")
    assert report["tested"] == [] and "mask_overlay" in report["untried"] == stop["untried"]
    assert diag.unexplained


class _Valley(dg.Problem):
    """Rosenbrock's curved valley as least squares, ``r = (10 (b - a^2), 1 - a)``, plus a
    hundred noisy samples of ``a`` (so the optimum has uncertainties)."""

    def __init__(self):
        self.calls = 0
        self.noise = NoiseEstimate(0.1, 1.0, 102)
        self.samples = 1.0 + 0.1 * np.random.default_rng(2).standard_normal(100)
        self.effects = {"v": Effect("v", "height", "surface",
                                    [Parameter("a", "1", -3.0, 3.0, 1.0), Parameter("b", "1", -3.0, 3.0, 1.0)],
                                    lambda h, v, s: h, "a curved valley")}

    def residual(self, model):
        self.calls += 1
        a, b = model["v"]
        return np.concatenate([[10 * (b - a * a), 1 - a], a - self.samples])


def test_broyden_updates_cross_a_curved_valley_in_fewer_evaluations(monkeypatch):
    counts = {}
    for steps in (0, fitting.BROYDEN_STEPS):
        monkeypatch.setattr(fitting, "BROYDEN_STEPS", steps)
        problem = _Valley()
        fitted, rss, errors = fitting.fit_effects(problem, {"v": np.array([-1.2, 1.0])}, ["v"])
        a = (1.0 + problem.samples.sum()) / 101  # the optimum, in closed form: b = a^2
        np.testing.assert_allclose(fitted["v"], [a, a * a], atol=1e-4)
        counts[steps] = problem.calls
        # The uncertainties are the differences' at the optimum, however the fit got there.
        at_optimum = fitting.standard_errors(problem, fitted, ["v"])
        np.testing.assert_allclose(errors["v"], at_optimum["v"], rtol=0.05)
    assert counts[fitting.BROYDEN_STEPS] < counts[0]


class _Ripples(dg.Problem):
    """A large ramp and a weak ripple over white noise (sigma 1, correlation area 1): each effect
    one amplitude, the data as many samples as a 500 x 500 field."""

    def __init__(self, ripple, seed=3):
        rng = np.random.default_rng(seed)
        self.x = np.linspace(0.0, 1.0, 250_000)
        self.shapes = {"ramp": self.x - 0.5, "ripple": np.sqrt(2) * np.sin(40 * np.pi * self.x)}
        self.y = 30.0 * self.shapes["ramp"] + ripple * self.shapes["ripple"] + rng.standard_normal(self.x.size)
        self.noise = NoiseEstimate(1.0, 1.0, self.x.size)
        self.effects = {k: Effect(k, "height", "process", [Parameter("a", "1", -100.0, 100.0, 1.0, smooth=True)],
                                  lambda h, v, s: h, f"a {k}") for k in self.shapes}

    def residual(self, model):
        return self.y - sum(v[0] * self.shapes[k] for k, v in model.items())

    def residual_map(self, model):
        return self.residual(model)[None, :]


def test_an_effect_under_the_models_resolution_is_not_named_however_well_resolved():
    # A ripple of 0.05 rms on a floor of 1 explains 0.25 % of its power: over 250,000 samples the
    # criterion resolves it (about -600), but an instrument model good to a few per cent of the
    # floor's power cannot tell it from its own error. Six times larger (9 %) it is named.
    weak = dg.run_diagnosis(_Ripples(0.05))
    assert weak.named == ["ramp"]
    small = weak.below_resolution
    assert small["effect"] == "ripple" and small["criterion_change"] < -100
    assert abs(small["floor_power_share"] - 0.0025) < 0.001
    assert weak.to_dict()["below_resolution"] == small
    strong = dg.run_diagnosis(_Ripples(0.3))
    assert strong.named == ["ramp", "ripple"] and strong.below_resolution is None


def test_what_stays_after_a_withheld_effect_is_refitted_only_within_the_deadline(monkeypatch):
    # A partial match withheld once the selection spent its time: the refit of what stays would run
    # past the command's limit, so the joint fit's values and uncertainties stand.
    from metrology.diagnosis.revision import refit_kept

    problem = _Ripples(0.2)
    joint, _, errors = fitting.fit_effects(problem, {"ramp": np.array([1.0]), "ripple": np.array([0.0])},
                                           ["ramp", "ripple"])
    kept = {"ramp": joint["ramp"] + 0.5}  # off its optimum, as the joint fit can leave it
    cpu = [0.0]
    monkeypatch.setattr(budget, "cpu_seconds", lambda: cpu[0])
    spent = budget.Deadline.after(10.0)
    cpu[0] = 11.0
    model, errs = refit_kept(problem, kept, errors, spent)
    assert model["ramp"] == kept["ramp"] and errs == {"ramp": errors["ramp"]}
    model, errs = refit_kept(problem, kept, errors, budget.Deadline())
    assert abs(model["ramp"][0] - 30.0) < 0.05 and np.all(np.isfinite(errs["ramp"]))


class _Orthogonal(_Ripples):
    """:class:`_Ripples` with a cosine ripple, orthogonal to the ramp (a sine's projection on it
    cancels a 0.3 ripple: fitted alone it explains nothing)."""

    def __init__(self, ripple):
        super().__init__(0.0)
        self.shapes["ripple"] = np.sqrt(2) * np.cos(40 * np.pi * self.x)
        self.y = self.y + ripple * self.shapes["ripple"]


def _carried(name, candidates):
    return dg.Step(effect=name, kind="process", description=f"a {name}", params={}, uncertainties={}, units={},
                   residual_rms_before=0.0, residual_rms_after=0.0, criterion_change=candidates[name],
                   candidates=candidates)


def test_what_an_earlier_pass_named_enters_first_without_its_screening_and_must_still_pay():
    # The camera's restart after the instrument stage chose more of the family: what the first
    # pass named is refitted on the new problem, not screened again. A fresh selection names the
    # ramp first (it holds 99 % of the residual); carried, the ripple comes first, with the
    # candidates of the round that chose it, and the ramp is still found after it.
    carried = [_carried("ripple", {"ripple": -600.0, "ramp": 50.0})]
    fresh = dg.run_diagnosis(_Orthogonal(0.3))
    assert fresh.named == ["ramp", "ripple"]
    again = dg.run_diagnosis(_Orthogonal(0.3), carried=carried, prior={"ripple": np.array([0.25])})
    assert again.named == ["ripple", "ramp"]
    assert again.steps[0].candidates == {"ripple": -600.0, "ramp": 50.0}
    assert abs(again.model["ripple"][0] - fresh.model["ripple"][0]) < 1e-3
    # Where the new problem holds no ripple, the carried name does not pay and is not kept.
    none = dg.run_diagnosis(_Orthogonal(0.0), carried=carried)
    assert none.named == ["ramp"]


def test_a_crops_fit_the_budget_stopped_does_not_start_the_whole_problems():
    # A fit to convergence runs on the screening crop, then on the whole field from the crop's
    # optimum. Stopped on the crop, it is cut short: the whole field's first evaluation (seconds
    # on a camera window) is not paid past the deadline.
    crop, whole = _Poly(False), _Poly(False)
    stop = budget.FitStop(budget.Deadline())
    spent = budget.FitStop(budget.Deadline(wall=0.0))
    dg._converge(whole, crop, {"poly": np.zeros(6)}, ["poly"], stop)
    assert crop.calls and whole.calls and not stop.fired
    crop.calls.clear()
    whole.calls.clear()
    dg._converge(whole, crop, {"poly": np.zeros(6)}, ["poly"], spent)
    assert spent.fired and len(crop.calls) == 1 and not whole.calls
