"""The terrace fit (metrology.matching.terrace): level heights from flat interiors, step by step,
against analytic terraces, and beside the camera-frame fit of `doe compare` on generated files."""

import numpy as np
import pytest

import filegen
from doedesign.errors import DoeError
from metrology.matching.depths import LEVEL_REPEATABILITY_M, binary_code_matrix
from metrology.matching.terrace import check_against, fit_terraces, flat_interiors

STEP_M = 75e-9


def _staircase(rng, noise_m=1e-9, blur_px=0.0, tilt=(0.0, 0.0), n_levels=4, block=12, blocks=8, truth=None):
    """Random blocks of ``n_levels`` levels, heights known exactly (level k: -k * step + a bias)."""
    levels = rng.integers(0, n_levels, (blocks, blocks))
    labels = np.kron(levels, np.ones((block, block), int))
    if truth is None:
        truth = -np.arange(n_levels) * STEP_M + rng.normal(0, 3e-9, n_levels)
    h = truth[labels]
    if blur_px:
        from scipy import ndimage
        h = ndimage.gaussian_filter(h, blur_px, mode="nearest")
    r, c = np.mgrid[:h.shape[0], :h.shape[1]]
    h = h + tilt[0] * (c - (h.shape[1] - 1) / 2) + tilt[1] * (r - (h.shape[0] - 1) / 2)
    return h + noise_m * rng.standard_normal(h.shape), labels, truth


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_analytic_terraces_recovered_within_their_uncertainty(seed):
    rng = np.random.default_rng(seed)
    h, labels, truth = _staircase(rng, blur_px=1.0, tilt=(2e-10, -1e-10))
    fit = fit_terraces(h, labels, 4, margin_px=3, step_m=STEP_M, pitch_px=12)
    ok = np.isfinite(fit.heights_m)
    assert ok.all()
    # Heights in the field's own frame (the tilt is fitted, with no constant term).
    err = fit.heights_m - truth
    assert np.all(np.abs(err) < 3 * fit.heights_err_m)
    steps_true = truth[:-1] - truth[1:]
    assert np.all(np.abs(fit.steps_m - steps_true) < 3 * fit.steps_err_m)
    # The blurred edges are not on any terrace: the residual is the noise (1 nm).
    assert fit.rms_residual_m == pytest.approx(1e-9, rel=0.1)
    np.testing.assert_allclose(fit.background_m_per_px, [2e-10, -1e-10], atol=2e-12)
    # The uncertainty is the statistical part with the repeatability floor in quadrature.
    assert np.all(fit.heights_err_m >= LEVEL_REPEATABILITY_M)


def test_uncertainty_follows_the_scatter_between_terraces():
    """A level whose terraces sit at different heights (correlated error) is as uncertain as
    their scatter says, not as the many pixels would say."""
    rng = np.random.default_rng(5)
    h, labels, truth = _staircase(rng, noise_m=0.2e-9)
    from scipy import ndimage
    comp, n = ndimage.label(labels == 1)
    offsets = rng.normal(0, 2e-9, n + 1)
    offsets[0] = 0
    h = h + offsets[comp]
    fit = fit_terraces(h, labels, 4, margin_px=3, step_m=STEP_M, pitch_px=12, degree=0)
    w = np.bincount(comp[fit.mask & (labels == 1)], minlength=n + 1)[1:].astype(float)
    spread = np.sqrt(np.sum(w ** 2 * (offsets[1:] - np.sum(w * offsets[1:]) / w.sum()) ** 2) * n / (n - 1)) / w.sum()
    assert fit.heights_err_m[1] == pytest.approx(np.hypot(spread, LEVEL_REPEATABILITY_M), rel=0.05)
    assert fit.heights_err_m[1] > 2 * fit.heights_err_m[2]


def test_a_line_keeps_its_central_third():
    """ISO 5436-1: on a line too narrow for the margin, the central third of its width is kept."""
    labels = np.zeros((40, 60), int)
    labels[:, 24:33] = 1          # a 9 px line
    h = -STEP_M * labels.astype(float)
    mask = flat_interiors(h, labels, margin_px=6, step_m=STEP_M, pitch_px=9)
    cols = np.flatnonzero(mask[20] & (labels[20] == 1))
    assert cols.tolist() == [27, 28, 29]      # the central 3 of 9
    wide = np.flatnonzero(mask[20] & (labels[20] == 0))
    # The wide level keeps all but 6 px from the step and the field's border.
    assert wide.min() == 6 and wide.max() == 53 and 17 in wide and 18 not in wide


def test_a_pit_that_the_design_lacks_is_kept_off_the_terraces():
    rng = np.random.default_rng(7)
    labels = np.zeros((60, 60), int)
    labels[:, 30:] = 1
    h = -STEP_M * labels.astype(float) + 0.5e-9 * rng.standard_normal(labels.shape)
    h[:, 10:20] -= 50e-9          # a flat-bottomed pit the design does not have
    mask = flat_interiors(h, labels, margin_px=3, step_m=STEP_M, pitch_px=10)
    # Its walls are steps: nothing within 3 px of them is flat.
    assert not mask[:, 8:13].any() and not mask[:, 17:23].any()
    fit = fit_terraces(h, labels, 2, margin_px=3, step_m=STEP_M, pitch_px=10, degree=0)
    # Its bottom is flat but more than half a step off level 0: left out, level 0 unbiased.
    assert not fit.mask[:, 10:20].any()
    assert fit.heights_m[0] == pytest.approx(0.0, abs=0.1e-9)
    assert fit.steps_m[0] == pytest.approx(STEP_M, abs=0.2e-9)


def test_all_edges_is_refused():
    labels = np.indices((20, 20)).sum(0) % 2
    with pytest.raises(DoeError, match="no flat terrace"):
        fit_terraces(-STEP_M * labels, labels, 2, margin_px=3, step_m=STEP_M, pitch_px=1)


def test_check_warns_naming_the_step_and_mask_that_differ():
    rng = np.random.default_rng(3)
    depths = np.array([76e-9, 148e-9])
    h, labels, truth = _staircase(rng, truth=-binary_code_matrix(4) @ depths)
    fit = fit_terraces(h, labels, 4, margin_px=3, step_m=STEP_M, pitch_px=12)
    good = check_against(fit, depths, np.full(2, 0.05e-9))
    assert good["agree"] and not good["warnings"]
    bad = check_against(fit, depths + [0.0, 3e-9], np.full(2, 0.05e-9))
    assert not bad["agree"]
    # Mask 1 is deeper by 3 nm: step 1 -> 2 (mask 1 opens, mask 0 closes) and mask 1 warn; steps 0 -> 1
    # and 2 -> 3 (mask 0 alone) do not.
    assert [s["agree"] for s in bad["steps"]] == [True, False, True]
    assert any(w.startswith("step level 1 -> 2") for w in bad["warnings"])
    assert any(w.startswith("mask 1 etch depth") for w in bad["warnings"])


@pytest.mark.slow
def test_an_edge_artefact_makes_the_two_fits_differ_and_the_report_warn(tmp_path):
    """A batwing at every edge (the profilometer's overshoot): the camera-frame fit finds it (the
    diagnosis's instrument stage chooses it) and agrees with the terrace fit; held to a transfer
    without one (a calibration that has none), it is pulled off the depths, the terrace fit,
    which reads the flat interiors, stays, and the report warns."""
    from doedesign.cli import main
    from metrology.calibration.instrument import FORMAT
    import json

    case = filegen.make_case(["etch_depth"], 4, design_px=24, field_px=80,
                             instrument={"batwing": (0.15, 0.5e-6)})
    design, measured = case.write(tmp_path)
    truth = np.array(filegen.DEPTHS_M) * (1 + case.truth["etch_depth"]["error"]) * 1e9

    def compare(out, *extra):
        assert main(["compare", str(measured), "--design", str(design), "--out", str(out), "--no-psf",
                     "--no-render", *extra]) == 0
        return json.loads((out / "report.json").read_text())

    rep = compare(tmp_path / "fitted")
    frame = rep["instrument_frame"]
    # Before the camera-frame fit chose its transfer's member, it modelled no batwing and
    # missed the deepest step by more than the terrace fit did.
    assert frame["family"]["stage"]["members"] == ["batwing"] and frame["batwing"]["amplitude"] > 0.05
    assert rep["terrace_fit"]["against_camera_frame"]["agree"] is True
    np.testing.assert_allclose(rep["etch_depths_nm"], truth, atol=1.0)
    assert frame["rms_residual_flat_nm"] < 1.2 * case.instrument["noise_m"] * 1e9
    cal = tmp_path / "instrument.json"
    cal.write_text(json.dumps({"format": FORMAT, "lateral_transfer": {
        "blur_sigma_m": case.instrument["blur_sigma_m"], "fill_factor": 1.0, "na": 0.0, "wavelength_m": 0.57e-6}}))
    held = compare(tmp_path / "held", "--instrument", str(cal))
    terr = held["terrace_fit"]
    check = terr["against_camera_frame"]
    assert check["agree"] is False and check["warnings"]
    # The terrace fit is the nearer to the truth on the deepest mask.
    assert abs(terr["etch_depths_nm"][3] - truth[3]) < abs(held["etch_depths_nm"][3] - truth[3])
    page = (tmp_path / "held" / "report.md").read_text()
    assert "Terrace fit beside the camera-frame fit" in page and "WARNING: differ" in page
