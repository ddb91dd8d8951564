"""Diagnosis on hidden effects: named, nothing named for noise alone, parameters and residual right.

The generator (:mod:`metrology.diagnosis.synthetic`) draws sizes, directions, affected masks and noise at
random from each case's seed; the workflow is not told what is hidden.
"""

import json

import numpy as np
import pytest

from doedesign.cli import main
from metrology.diagnosis import PsfProblem, bic_eff, diagnose_heights, estimate_noise, run_diagnosis
from metrology.diagnosis.budget import Deadline
from metrology.diagnosis.effects import effects_for
from metrology.diagnosis.synthetic import (
    HEIGHT_EFFECTS,
    PSF_EFFECTS,
    correlated_noise,
    make_height_case,
    make_psf_case,
    parameter_errors,
)

PARAM_TOL = 0.20
RESIDUAL_TOL = 1.3


def _diagnose_height_case(effects, seed, **kw):
    case = make_height_case(effects, seed)
    d = case.data
    kw.setdefault("region_px", 32)
    diag = diagnose_heights(d["levels"], d["pitch_m"], d["measured_height_m"], d["step_m"], **kw)
    return case, diag


def _diagnose_psf_case(effects, seed, stop_at_floor=True, **kw):
    case = make_psf_case(effects, seed)
    d = case.data
    problem = PsfProblem(d["design"].height_m, d["design"].pitch_m, d["camera"], d["measured_psf"], d["views"],
                         d["wavelengths_m"], d["camera"].focus_distance_m, effects_for("psf"),
                         renderer=d["renderer"], **kw)
    return case, run_diagnosis(problem, domain="psf", stop_at_floor=stop_at_floor)


def _check(case, diag):
    assert sorted(diag.named) == sorted(case.truth), (case.truth, diag.named)
    errors = parameter_errors(case, diag)
    assert all(e < PARAM_TOL for e in errors.values()), errors
    assert diag.final_residual_rms < RESIDUAL_TOL * diag.noise_floor
    assert not diag.unexplained
    for step in diag.steps:
        assert step.residual_rms_after < step.residual_rms_before
        assert step.criterion_change < -10


def test_noise_floor_and_correlation_area_from_flat_regions():
    rng = np.random.default_rng(4)
    shape = (200, 200)
    groups = np.zeros(shape, int)
    groups[10:190, 10:100] = 1
    groups[10:190, 110:190] = 2
    white = correlated_noise(shape, 2e-9, 0.0, rng) + np.where(groups == 2, 300e-9, 0.0)
    est = estimate_noise(white, groups)
    assert est.sigma == pytest.approx(2e-9, rel=0.05)
    assert est.corr_area_px == pytest.approx(1.0, abs=0.2)
    # Noise smoothed by a Gaussian of 1 px has autocorrelation exp(-r^2 / 4): summed over
    # lags |dx|, |dy| <= 3 that is (1 + 2 sum_k exp(-k^2 / 4))^2 = 12.28.
    smooth = correlated_noise(shape, 2e-9, 1.0, rng)
    est = estimate_noise(smooth, groups)
    expect = (1 + 2 * np.exp(-np.arange(1, 4) ** 2 / 4).sum()) ** 2
    assert est.corr_area_px == pytest.approx(expect, rel=0.15)
    assert est.sigma == pytest.approx(2e-9, rel=0.1)


def test_criterion_rewards_fit_and_penalizes_parameters():
    # Same RSS: each extra parameter costs ln(n_eff); halving the RSS gains n_eff ln 2.
    assert bic_eff(1.0, 100, 50, 3) - bic_eff(1.0, 100, 50, 0) == pytest.approx(3 * np.log(50))
    assert bic_eff(0.5, 100, 50, 0) - bic_eff(1.0, 100, 50, 0) == pytest.approx(-50 * np.log(2))


@pytest.mark.parametrize("effect", HEIGHT_EFFECTS)
def test_single_hidden_height_effect(effect):
    seed = 1000 + HEIGHT_EFFECTS.index(effect)
    case, diag = _diagnose_height_case([effect], seed)
    _check(case, diag)
    step = diag.steps[0]
    assert step.effect == effect
    assert (step.kind == "artefact") == (effect in ("instrument_blur", "batwing"))
    # Uncertainties from the Jacobian: positive, and the truth within 5 standard errors.
    idx = case.main[effect]
    err = np.array(list(step.uncertainties.values()))[idx]
    fit = np.asarray(diag.model[effect])[idx]
    assert np.all(err > 0)
    assert np.all(np.abs(fit - case.truth[effect][idx]) < 5 * err + 1e-3 * np.abs(case.truth[effect][idx]))


def test_pair_of_hidden_height_effects():
    case, diag = _diagnose_height_case(["mask_overlay", "instrument_blur"], 77)
    _check(case, diag)


@pytest.mark.parametrize("seed", [5, 6])
def test_null_height_case_names_nothing(seed):
    # Every candidate is fitted and scored (no early stop at the noise floor).
    case, diag = _diagnose_height_case([], seed, stop_at_floor=False)
    assert diag.named == []
    assert not diag.unexplained
    assert diag.final_residual_rms < RESIDUAL_TOL * diag.noise_floor
    assert diag.noise_floor == pytest.approx(case.noise_rms, rel=0.15)


def test_a_spent_time_limit_stops_the_selection_and_says_so():
    # The case of test_single_hidden_height_effect's overlay (named there without a budget).
    seed = 1000 + HEIGHT_EFFECTS.index("mask_overlay")
    case, diag = _diagnose_height_case(["mask_overlay"], seed, limit=Deadline.after(0.0))
    assert diag.named == [] and diag.incomplete
    stop = diag.to_dict()["stopped_early"]
    assert stop["reason"].startswith("time limit") and stop["limit"] == "cpu"
    assert stop["final_over_floor"] > RESIDUAL_TOL
    assert set(stop["untried"]) == set(diag.candidates) and "mask_overlay" in stop["untried"]
    assert diag.unexplained
    # Without a limit (the default) it runs to the criterion's end and has tested every candidate.
    _, free = _diagnose_height_case(["mask_overlay"], seed)
    assert free.named == ["mask_overlay"] and free.stopped_early is None and not free.incomplete
    assert free.tested == free.candidates and free.to_dict()["summary"].startswith("complete")


def test_missing_effect_is_reported_unexplained():
    # Etch loading hidden but not among the candidates: a structured residual must remain.
    case, diag = _diagnose_height_case(["etch_loading"], 31, candidates=["etch_depth", "mask_overlay"])
    assert diag.unexplained
    assert diag.final_residual_rms > RESIDUAL_TOL * diag.noise_floor


@pytest.mark.parametrize("effect", ["dual_pixel_crosstalk", "depth_scale"])
def test_single_hidden_psf_effect(effect):
    case, diag = _diagnose_psf_case([effect], 2000 + PSF_EFFECTS.index(effect))
    _check(case, diag)


@pytest.mark.parametrize("effect", ["dual_pixel_crosstalk", "depth_scale", "defocus", "source_bandwidth"])
def test_candidates_screened_on_a_crop_name_the_same_effect(effect):
    # A 24 x 24 crop of the 40 x 72 window: the crop holds the most ideal light; the named
    # effect is then fitted on the whole window, to the same accuracy.
    case, diag = _diagnose_psf_case([effect], 2000 + PSF_EFFECTS.index(effect), screen_window_px=24)
    _check(case, diag)


def test_screening_crop_holds_the_most_light_and_shares_the_noise():
    case = make_psf_case([], 5)
    d = case.data
    problem = PsfProblem(d["design"].height_m, d["design"].pitch_m, d["camera"], d["measured_psf"], d["views"],
                         d["wavelengths_m"], d["camera"].focus_distance_m, effects_for("psf"), screen_window_px=24)
    crop = problem.screening
    assert crop.measured.shape[-2:] == (24, 24) and crop.noise is problem.noise
    assert crop.screening is None and list(crop.effects) == list(problem.effects)
    # The axis moves with the crop; the crop lies inside the window.
    r0 = problem.axis_pixel[0] - crop.axis_pixel[0]
    c0 = problem.axis_pixel[1] - crop.axis_pixel[1]
    assert 0 <= r0 <= 40 - 24 and 0 <= c0 <= 72 - 24
    cut = problem.measured[..., r0:r0 + 24, c0:c0 + 24]
    np.testing.assert_allclose(crop.measured, cut / cut.sum(axis=(-2, -1), keepdims=True))
    # No other 24 x 24 window holds more ideal light (brute force).
    full = problem.render(problem.height_m, problem.wavelengths_m, problem.depth_m)
    light = (full / full.sum(axis=(-2, -1), keepdims=True)).sum(axis=(0, 1))
    best = max(light[r:r + 24, c:c + 24].sum() for r in range(40 - 23) for c in range(72 - 23))
    assert light[r0:r0 + 24, c0:c0 + 24].sum() == pytest.approx(best)
    # A window at most twice the crop's area is not cropped (every existing small case).
    small = PsfProblem(d["design"].height_m, d["design"].pitch_m, d["camera"], d["measured_psf"], d["views"],
                       d["wavelengths_m"], d["camera"].focus_distance_m, effects_for("psf"))
    assert small.screening is None



def test_psf_renderer_reuses_channels_and_matches_the_engine():
    """The renderer computes only the wavelengths it has not rendered for that height and distance
    (a wavelength-averaged model reuses the nominal ones), and its stacks are the engine's."""
    from doedesign.engine.psf import PSFEngine
    from metrology.diagnosis.psf import PsfRenderer
    from metrology.diagnosis.synthetic import psf_test_setup

    design, camera, wls = psf_test_setup(3)
    render = PsfRenderer(camera, design.pitch_m, design.shape, design.material)
    h, d = design.height_m, camera.focus_distance_m
    first = render(h, wls, d)
    shifted = np.array([wls[1], wls[1] + 7e-9, wls[2]])
    second = render(h, shifted, d)
    assert render.calls == 2 and [len(k[0]) for k in render._engines] == [3, 1]
    for stack, w in ((first, wls), (second, shifted)):
        ref = PSFEngine(camera, design.pitch_m, design.shape, design.material, w, (d,)).psf(h).psf[:, 0]
        np.testing.assert_allclose(stack, ref, rtol=0, atol=1e-12 * ref.max())
    # An equal map in another array is found by content; another height or distance is rendered anew.
    np.testing.assert_array_equal(render(h.copy(), wls, d), first)
    assert render.calls == 2
    render(h * 1.01, wls, d)
    render(h, wls, 2.0)
    assert render.calls == 4
    # Single precision (screening) stays within 1e-6 of the peak of the double-precision stack.
    single = PsfRenderer(camera, design.pitch_m, design.shape, design.material, precision="single")(h, wls, d)
    assert np.abs(single - first).max() < 1e-6 * first.max()

def test_psf_fits_take_forward_differences_to_the_central_optimum():
    """A PSF stack is smooth in every effect's parameters: its fits take forward-difference
    Jacobians (one render a column, not two) and reach the central-difference optimum to a
    small fraction of the standard error; a height problem keeps central ones (kinks)."""
    from metrology.diagnosis.fitting import fit_effects

    case = make_psf_case(["source_bandwidth", "defocus"], 2003)
    d = case.data
    fits = {}
    for central in (True, None):
        problem = PsfProblem(d["design"].height_m, d["design"].pitch_m, d["camera"], d["measured_psf"], d["views"],
                             d["wavelengths_m"], d["camera"].focus_distance_m, effects_for("psf"))
        start = {n: problem.effects[n].start_values() for n in ("source_bandwidth", "defocus")}
        calls = problem.render.calls
        fits[central] = fit_effects(problem, start, list(start), central=central) + (problem.render.calls - calls,)
    assert fits[None][3] < 0.8 * fits[True][3]
    for name in ("source_bandwidth", "defocus"):
        err = fits[True][2][name]
        assert np.all(np.abs(fits[None][0][name] - fits[True][0][name]) < 0.1 * err), name
        assert np.all(np.abs(fits[None][2][name] - err) < 0.05 * err)
        # The fit is right, not only the same (the hidden values; the comparison above can fail).
        assert np.all(np.abs(fits[None][0][name] - case.truth[name]) < 0.2 * np.abs(case.truth[name]))
    assert fits[None][1] == pytest.approx(fits[True][1], rel=1e-6)
    from metrology.diagnosis.camera import CameraHeightProblem
    from metrology.diagnosis.heights import HeightProblem
    from metrology.diagnosis.tiles import TiledCameraProblem

    assert not PsfProblem.kinks and HeightProblem.kinks and CameraHeightProblem.kinks and TiledCameraProblem.kinks


def test_whole_window_model_in_single_precision_only_far_below_the_noise():
    """The whole window's model is rendered in single precision when its measured error (against
    the double-precision ideal model) is below 1 % of the noise floor; a stack with little noise
    keeps double precision. The two models differ by that error, no more."""
    from doedesign.engine.psf import VIEWS
    from metrology.diagnosis.psf import SINGLE_PRECISION_NOISE_FRACTION, PsfRenderer

    case = make_psf_case([], 5)
    d = case.data
    head = (d["design"].height_m, d["design"].pitch_m, d["camera"])
    tail = (d["views"], d["wavelengths_m"], d["camera"].focus_distance_m, effects_for("psf"))
    ideal = PsfRenderer(d["camera"], d["design"].pitch_m, d["design"].shape)(
        d["design"].height_m, d["wavelengths_m"], d["camera"].focus_distance_m)[[VIEWS.index(v) for v in d["views"]]]
    ideal = ideal / ideal.sum(axis=(-2, -1), keepdims=True)
    rng = np.random.default_rng(1)
    problems = {}
    for rel in (1e-7, 3e-3):  # noise rms over the brightest pixel
        problems[rel] = PsfProblem(*head, ideal + rel * ideal.max() * rng.standard_normal(ideal.shape), *tail)
    quiet, noisy = problems[1e-7], problems[3e-3]
    assert quiet.render.precision == "double" and noisy.render.precision == "single"
    for p in (quiet, noisy):
        assert (p.render.precision == "single") == (p.single_precision_error
                                                    < SINGLE_PRECISION_NOISE_FRACTION * p.noise.sigma)
    a, b = noisy.stack({}), quiet.stack({})
    assert 0 < np.abs(a - b).max() <= 1.01 * noisy.single_precision_error


UNSEPARABLE_AT_MODEL_GRID = {"instrument_blur", "sidewall_slope"}


@pytest.mark.slow
@pytest.mark.parametrize("seed", range(6))
def test_random_sweep_height(seed):
    rng = np.random.default_rng(seed)
    singles = [[e] for e in HEIGHT_EFFECTS]
    pairs = [list(rng.choice(HEIGHT_EFFECTS, 2, replace=False)) for _ in range(2)]
    for effects in singles + pairs + [[]]:
        case, diag = _diagnose_height_case(effects, 10_000 + 97 * seed + len(effects))
        if set(effects) == UNSEPARABLE_AT_MODEL_GRID:
            # Known limit: at a ~1 um model grid a ramp and a blur give the same 3-tap edge
            # kernel. The method must not claim success: it flags the residual or the ambiguity.
            ambiguous = any(step.get("ambiguous_with") for step in diag.to_dict()["steps"])
            assert diag.unexplained or ambiguous
            continue
        _check(case, diag)


@pytest.mark.slow
@pytest.mark.parametrize("effect", PSF_EFFECTS)
def test_random_sweep_psf(effect):
    for seed in range(2):
        case, diag = _diagnose_psf_case([effect], 3000 + 11 * seed + PSF_EFFECTS.index(effect))
        _check(case, diag)


@pytest.mark.slow
def test_psf_pair_and_null():
    case, diag = _diagnose_psf_case(["dual_pixel_crosstalk", "background"], 41)
    _check(case, diag)
    case, diag = _diagnose_psf_case([], 42, stop_at_floor=False)
    assert diag.named == []


# -- CLI ---------------------------------------------------------------------------------------
def _psf_files(tmp_path, effects, seed):
    case = make_psf_case(effects, seed)
    d = case.data
    design = d["design"]
    design.metadata["camera"] = d["camera"].to_dict()
    design.save(tmp_path / "design.npz")
    np.savez(tmp_path / "psf.npz", psf=d["measured_psf"], views=np.array(d["views"]),
             wavelengths_m=d["wavelengths_m"], pixel_pitch_m=d["camera"].pixel_pitch_m,
             axis_pixel=np.array(d["camera"].axis_pixel))
    return case


def test_cli_psf_report(tmp_path):
    case = _psf_files(tmp_path, ["dual_pixel_crosstalk"], 7)
    out = tmp_path / "out"
    code = main(["diagnose", "--design", str(tmp_path / "design.npz"), "--measured-psf", str(tmp_path / "psf.npz"),
                 "--out", str(out), "--effects", "dual_pixel_crosstalk,background"])
    assert code == 0
    report = json.loads((out / "report.json").read_text())
    for key in ("steps", "noise_floor", "initial_residual_rms", "final_residual_rms", "unexplained"):
        assert key in report
    assert [s["effect"] for s in report["steps"]] == ["dual_pixel_crosstalk"]
    step = report["steps"][0]
    for key in ("effect", "params", "residual_rms_before", "residual_rms_after", "criterion_change"):
        assert key in step
    assert step["params"]["fraction"] == pytest.approx(case.truth["dual_pixel_crosstalk"][0], rel=0.05)
    assert report["final_residual_rms"] < RESIDUAL_TOL * report["noise_floor"]
    assert (out / "residual_steps.png").stat().st_size > 1000
    assert (out / "breakdown.png").stat().st_size > 1000


def test_cli_bad_inputs(tmp_path, capsys):
    _psf_files(tmp_path, [], 8)
    bad = tmp_path / "bad.npz"
    np.savez(bad, psf=np.ones((2, 3, 4, 5)), wavelengths_m=np.array([550e-9]), pixel_pitch_m=5.4e-6)
    code = main(["diagnose", "--design", str(tmp_path / "design.npz"), "--measured-psf", str(bad),
                 "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err
    assert code == 2 and "bad.npz" in err and "wavelengths" in err
    code = main(["diagnose", "--design", str(tmp_path / "nope.npz"), "--measured-psf", str(bad),
                 "--out", str(tmp_path / "o")])
    assert code == 2 and "nope.npz" in capsys.readouterr().err
    code = main(["diagnose", "--design", str(tmp_path / "design.npz"), "--measured-psf", str(tmp_path / "psf.npz"),
                 "--out", str(tmp_path / "o"), "--effects", "no_such_effect"])
    assert code == 2 and "no_such_effect" in capsys.readouterr().err
    assert not (tmp_path / "o" / "report.json").exists()
