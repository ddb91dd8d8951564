"""doe tolerance: spec parsing, physics of a sample, reproducibility across schedulers, resume."""

import json
import math
import re

import numpy as np
import pytest

from doedesign.camera import Camera
from doedesign.design import Design
from doedesign.errors import DoeError
from doedesign.levels import level_step_m
from masks.tolerance.analysis import nominal_depths, tolerance_analysis
from masks.tolerance.report import clopper_pearson
from masks.tolerance.spec import build_spec, default_spec, sample_seed, spec_from_compare

DEPTHS = (75e-9, 150e-9, 300e-9, 600e-9)
PITCH = 5.4e-6


def grating_design(n=64, window=(16, 160), wavelengths_nm=(550.0,)):
    """16-level blazed grating of period 16 px along the columns, full square pupil."""
    # Level falls (height rises, phase rises) toward higher columns: the first order goes right.
    levels = np.tile(15 - np.arange(n) % 16, (n, 1)).astype(np.int16)
    step = level_step_m("fused_silica", 550e-9, 16)
    cam = Camera(aperture_diameter_m=None, focus_distance_m=math.inf, window_shape=window,
                 axis_pixel=(window[0] // 2, window[1] // 2 - 60), doe_side="full")
    meta = {"camera": cam.to_dict(), "n_levels": 16,
            "target": {"kind": "hyperspectral", "wavelengths_nm": list(wavelengths_nm), "depths_m": ["inf"],
                       "period_m": 16 * PITCH, "orders": [1]}}
    return Design(height_m=-levels * step, pitch_m=PITCH, levels=levels, metadata=meta)


def tiny_bayer(n=24):
    """A small random-level element with Bayer metadata (fast; the figures need not be good)."""
    rng = np.random.default_rng(3)
    levels = rng.integers(0, 16, (n, n)).astype(np.int16)
    step = level_step_m("fused_silica", 550e-9, 16)
    cam = Camera(aperture_diameter_m=n * PITCH, focus_distance_m=math.inf, window_shape=(24, 24),
                 axis_pixel=(12, 12))
    meta = {"camera": cam.to_dict(), "n_levels": 16,
            "target": {"kind": "bayer", "wavelengths_nm": [656.0, 589.0, 486.0], "depths_m": ["inf"], "rggb": False}}
    return Design(height_m=-levels * step, pitch_m=PITCH, levels=levels, metadata=meta)


# -- spec -----------------------------------------------------------------------------------------
def test_spec_errors_name_the_problem():
    with pytest.raises(DoeError, match="unknown effect 'overlay'"):
        build_spec({"overlay": {"sigma_um": 0.2}}, DEPTHS, "p.toml")
    with pytest.raises(DoeError, match="mask 5, which does not exist"):
        build_spec({"linewidth_bias": {"mask": {"5": {"sigma_um": 0.1}}}}, DEPTHS, "p.toml")
    with pytest.raises(DoeError, match="mask 0 is the reference"):
        build_spec({"mask_overlay": {"masks": [0, 1], "sigma_um": 0.2}}, DEPTHS, "p.toml")
    with pytest.raises(DoeError, match="negative width"):
        build_spec({"etch_depth": {"sigma_nm": -2}}, DEPTHS, "p.toml")
    with pytest.raises(DoeError, match="negative width"):
        build_spec({"proximity_blur": {"dist": "uniform", "low_um": 0.5, "high_um": 0.1}}, DEPTHS, "p.toml")
    with pytest.raises(DoeError, match="give sigma once"):
        build_spec({"etch_depth": {"sigma_nm": 2, "sigma_rel": 0.01}}, DEPTHS, "p.toml")
    with pytest.raises(DoeError, match="unknown key 'sigma_mm'"):
        build_spec({"mask_overlay": {"sigma_mm": 0.2}}, DEPTHS, "p.toml")
    with pytest.raises(DoeError, match=r"^p.toml: \[etch_depth\] mask 0: sigma_nm must be a number, got 'two'$"):
        build_spec({"etch_depth": {"sigma_nm": "two"}}, DEPTHS, "p.toml")
    with pytest.raises(DoeError, match=r"^p.toml: \[roughness\]: sigma_nm must be finite, got inf$"):
        build_spec({"roughness": {"sigma_nm": float("inf")}}, DEPTHS, "p.toml")


def test_spec_units_and_per_mask_override():
    spec = build_spec({"etch_depth": {"sigma_rel": 0.02, "mask": {"3": {"sigma_nm": 5}}},
                       "mask_overlay": {"sigma_um": 0.25}, "roughness": {"value_nm": 1.0, "dist": "fixed"}},
                      DEPTHS, "p.toml")
    by = {p.name: p for p in spec.params}
    assert by["etch_depth_nm[mask 1]"].b == pytest.approx(0.02 * 150e-9)
    # The per-mask sigma replaces the shared one.
    assert by["etch_depth_nm[mask 3]"].b == pytest.approx(5e-9)
    assert "mask_overlay.dx_um[mask 0]" not in by and by["mask_overlay.dy_um[mask 3]"].b == pytest.approx(0.25e-6)
    assert by["roughness_nm"].a == pytest.approx(1e-9)


def test_draws_are_seeded_per_sample_and_follow_the_distribution():
    spec = default_spec(DEPTHS)
    a, seed_a = spec.draw(7, 12)
    b, _ = spec.draw(7, 12)
    c, _ = spec.draw(7, 13)
    assert a == b and a != c and seed_a == sample_seed(7, 12)
    dx = np.array([spec.draw(0, k)[0]["mask_overlay.dx_um[mask 2]"] for k in range(2000)])
    assert abs(dx.mean()) < 4 * 0.25e-6 / math.sqrt(2000)
    assert dx.std() == pytest.approx(0.25e-6, rel=0.05)


def test_spec_from_compare_report_centres_on_the_measurement():
    report = {"etch_depths_nm": [76, 150, 297, 605], "etch_depths_err_nm": [0.5, 0.5, 1, 2],
              "overlay_um": [[0, 0], [0.1, -0.2], [0, 0], [0.4, 0]], "overlay_err_um": [[0, 0]] + [[0.05, 0.05]] * 3,
              "linewidth_bias_um": [0.1, 0, 0, 0], "linewidth_bias_err_um": [0.02] * 4}
    spec = spec_from_compare(report, DEPTHS)
    by = {p.name: p for p in spec.params}
    assert by["etch_depth_nm[mask 3]"].a == pytest.approx(5e-9)
    assert by["mask_overlay.dy_um[mask 1]"].a == pytest.approx(-0.2e-6)
    assert by["mask_overlay.dx_um[mask 3]"].b == pytest.approx(0.05e-6)
    with pytest.raises(DoeError, match="describes 3 masks"):
        spec_from_compare({**report, "etch_depths_nm": [1, 2, 3]}, DEPTHS)


def test_clopper_pearson_matches_closed_forms():
    # k = 0: upper = 1 - (alpha/2)^(1/n); k = n: lower = (alpha/2)^(1/n).
    assert clopper_pearson(0, 10) == pytest.approx([0.0, 1 - 0.025 ** 0.1])
    assert clopper_pearson(10, 10) == pytest.approx([0.025 ** 0.1, 1.0])


# -- physics ----------------------------------------------------------------------------------------
@pytest.mark.parametrize("eps", [0.1, 0.25])
def test_depth_scale_error_follows_the_multilevel_grating_formula(tmp_path, eps):
    """All etches (1 + eps) deep: first-order power of an N-level blazed grating scales by
    [sin(pi eps) / (N sin(pi eps / N))]^2 (phase steps 2 pi (1 + eps) / N)."""
    design = grating_design()
    spec = build_spec({"etch_depth": {"dist": "fixed", "value_rel": eps}}, nominal_depths(design), "t")
    rep = tolerance_analysis(design, spec, 1, tmp_path, scheduler="inline", sobol_base=0, one_at_a_time=False)
    ratio = rep["samples"][0]["metrics"]["first_order_efficiency"] / rep["nominal"]["first_order_efficiency"]
    expected = (math.sin(math.pi * eps) / (16 * math.sin(math.pi * eps / 16))) ** 2
    assert ratio == pytest.approx(expected, rel=2e-3)
    assert rep["samples"][0]["metrics"]["zero_order_leak"] > 10 * rep["nominal"]["zero_order_leak"]


# -- runs -------------------------------------------------------------------------------------------
def _strip(report):
    return [(s["index"], s["seed"], s["effects"], s["metrics"]) for s in report["samples"]]


def test_two_worker_cluster_matches_the_in_process_run_and_resumes(tmp_path):
    design = tiny_bayer()
    spec = default_spec(nominal_depths(design))
    inline = tolerance_analysis(design, spec, 6, tmp_path / "a", scheduler="inline", sobol_base=0, one_at_a_time=False)
    dask2 = tolerance_analysis(design, spec, 6, tmp_path / "b", scheduler="processes", workers=2, sobol_base=0,
                               one_at_a_time=False)
    assert _strip(inline) == _strip(dask2)
    assert dask2["run"]["workers"] == 2
    # Resume: lost files are recomputed, kept ones are not touched.
    done = sorted((tmp_path / "a" / "samples").glob("mc-*.json"))
    stamp = done[0].stat().st_mtime_ns
    done[-1].unlink()
    again = tolerance_analysis(design, spec, 6, tmp_path / "a", scheduler="threads", workers=2, sobol_base=0,
                               one_at_a_time=False)
    assert _strip(again) == _strip(inline) and done[0].stat().st_mtime_ns == stamp
    with pytest.raises(DoeError, match="another run"):
        tolerance_analysis(design, spec, 6, tmp_path / "a", seed=1, scheduler="inline", sobol_base=0,
                           one_at_a_time=False)


KILLER = """
import os
from pathlib import Path

def metric_worker_alive(psf, info):
    marker = Path(os.environ["DOE_TEST_KILL_MARKER"])
    if not marker.exists():
        marker.write_text("killed once")
        os._exit(1)
    return 1.0
"""


def test_a_killed_worker_does_not_lose_the_run(tmp_path, monkeypatch):
    """The first sample a worker evaluates kills it (os._exit); the nanny restarts it, the scheduler
    reruns the batch, and the run ends with the same samples as in process."""
    from masks.tolerance import analysis

    design = tiny_bayer()
    spec = default_spec(nominal_depths(design))
    script = tmp_path / "killer.py"
    script.write_text(KILLER)
    parent_marker = tmp_path / "parent-marker"
    parent_marker.write_text("this test process must never exit")
    monkeypatch.setenv("DOE_TEST_KILL_MARKER", str(parent_marker))
    ref = tolerance_analysis(design, spec, 4, tmp_path / "ref", scheduler="inline", sobol_base=0,
                             one_at_a_time=False, metric_script=script)
    worker_marker = tmp_path / "worker-marker"
    real_make_client = analysis.make_client

    def make_client_with_killer(*args, **kwargs):
        # Workers inherit the environment when the cluster starts.
        monkeypatch.setenv("DOE_TEST_KILL_MARKER", str(worker_marker))
        return real_make_client(*args, **kwargs)

    monkeypatch.setattr(analysis, "make_client", make_client_with_killer)
    rep = tolerance_analysis(design, spec, 4, tmp_path / "run", scheduler="processes", workers=2,
                             sobol_base=0, one_at_a_time=False, metric_script=script)
    assert worker_marker.exists()
    assert _strip(rep) == _strip(ref)


def test_report_holds_samples_yield_and_sensitivity(tmp_path):
    design = tiny_bayer()
    spec = build_spec({"etch_depth": {"sigma_rel": 0.03}, "mask_overlay": {"masks": [3], "sigma_um": 0.3}},
                      nominal_depths(design), "t")
    rep = tolerance_analysis(design, spec, 5, tmp_path, scheduler="inline", sobol_base=2,
                             thresholds={"on_target_R": (">=", 0.0)})
    data = json.loads((tmp_path / "report.json").read_text())
    assert set(data) >= {"samples", "nominal", "yield", "sensitivity", "spec", "metrics"}
    assert data["samples"][0].keys() >= {"index", "seed", "effects", "metrics"}
    assert data["yield"]["fraction"] == 1.0 and data["yield"]["ci95"][1] == 1.0
    labels = [r["label"] for r in rep["sensitivity"]["one_at_a_time"]["rows"]]
    assert "mask 3 mask_overlay dx" in labels and "mask 0 etch_depth" in labels
    assert rep["sensitivity"]["sobol"]["groups"][-1] == "mask 3 mask_overlay"
    for name in ("report.md", "distributions.png", "tornado.png"):
        assert (tmp_path / name).is_file()


def test_cli_errors_exit_2_with_one_line(tmp_path, capsys):
    from doedesign.cli import main

    path = tmp_path / "d.npz"
    tiny_bayer().save(path)
    bad = tmp_path / "bad.toml"
    bad.write_text("[sidewall]\nsigma_um = 0.1\n")
    assert main(["tolerance", str(path), "--spec", str(bad), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip()
    assert "unknown effect 'sidewall'" in err and "\n" not in err
    assert not (tmp_path / "o" / "report.json").exists()


def test_every_process_effect_can_be_toleranced():
    from masks.effects import EFFECTS as MODEL_EFFECTS
    from masks.process import ProcessParams
    from masks.tolerance.spec import EFFECTS as SPEC_EFFECTS

    # Every effect, plus the proximity print's fields (gap, threshold, collimation).
    assert set(SPEC_EFFECTS) == set(MODEL_EFFECTS) | {"proximity_gap", "resist_threshold", "collimation_half_angle"}
    spec = build_spec({"microtrenching": {"masks": [3], "sigma_nm": 3, "mean_um": 0.5},
                       "etch_gradient": {"sigma_percent_per_mm": 0.5}}, DEPTHS, "t")
    by = {p.name: p for p in spec.params}
    assert by["microtrenching.width_um[mask 3]"].a == pytest.approx(0.5e-6)
    assert by["etch_gradient.x_percent_per_mm"].b == pytest.approx(5.0)  # 0.5 %/mm = 5 /m
    values = {**spec.nominal_values(), "microtrenching.depth_nm[mask 3]": 4e-9, "etch_gradient.y_percent_per_mm": 2.0}
    params = spec.params_for(values, ProcessParams.ideal(depths_m=DEPTHS))
    assert params.microtrenching[3].tolist() == pytest.approx([4e-9, 0.5e-6])
    assert params.etch_gradient.tolist() == pytest.approx([0.0, 2.0])


def _tolerance_cli(tmp_path, name, *extra):
    """``doe tolerance`` on the tiny element, 5 samples that all pass (on_target_R >= 0)."""
    from doedesign.cli import main

    design = tmp_path / "d.npz"
    if not design.exists():
        tiny_bayer().save(design)
    out = tmp_path / name
    code = main(["tolerance", str(design), "--out", str(out), "--samples", "5", "--scheduler", "inline",
                 "--sobol-base", "0", "--no-oat", "--threshold", "on_target_R>=0", *extra])
    return code, out


def test_yield_goal_comes_from_the_spec_file_and_the_option_overrides_it(tmp_path):
    # 5 of 5 passing: the Clopper-Pearson lower bound is 0.025 ** (1 / 5) = 0.4782 (closed form),
    # above a goal of 0.4 (met) and below 0.5 (undecided: 6 passing samples are needed, since
    # 0.025 ** (1 / 6) = 0.541 >= 0.5 > 0.025 ** (1 / 5)).
    spec = tmp_path / "spec.toml"
    spec.write_text("[etch_depth]\nsigma_rel = 0.02\n[yield]\ngoal = 0.4\n")
    code, out = _tolerance_cli(tmp_path, "from_file", "--spec", str(spec))
    assert code == 0
    y = json.loads((out / "report.json").read_text())["yield"]
    assert y["passed"] == 5 and y["ci95"][0] == pytest.approx(0.025 ** 0.2, rel=1e-9)
    assert y["goal"] == 0.4 and y["meets_goal"] is True
    verdict = [line for line in (out / "report.md").read_text().splitlines() if line.startswith("- Verdict")]
    assert len(verdict) == 1 and "at least 40 % of elements meet the thresholds" in verdict[0]

    code, out = _tolerance_cli(tmp_path, "from_option", "--spec", str(spec), "--yield-goal", "0.5")
    assert code == 0
    y = json.loads((out / "report.json").read_text())["yield"]
    assert y["goal"] == 0.5 and y["meets_goal"] is None
    verdict = [line for line in (out / "report.md").read_text().splitlines() if line.startswith("- Verdict")]
    assert "cannot tell whether the yield reaches 50 %" in verdict[0] and "at least 6 samples" in verdict[0]


def test_yield_goal_defaults_to_nine_in_ten():
    assert build_spec({"etch_depth": {"sigma_rel": 0.02}}, DEPTHS, "t").yield_goal == 0.9
    assert default_spec(np.array(DEPTHS)).yield_goal == 0.9


@pytest.mark.parametrize("table, match", [
    ("[yield]\ngoal = 1.0\n", r"spec.toml: \[yield\] goal must lie strictly between 0 and 1 .*got 1$"),
    ("[yield]\ngoal = 0\n", r"spec.toml: \[yield\] goal must lie strictly between 0 and 1 .*got 0$"),
    ("[yield]\ngoal = 'most'\n", r"spec.toml: \[yield\] goal must be a number, got 'most'$"),
    ("[yield]\ngoal = nan\n", r"spec.toml: \[yield\] goal must be finite, got nan$"),
    ("[yield]\nshare = 0.9\n", r"spec.toml: \[yield\] must hold one key, goal"),
])
def test_a_bad_yield_goal_in_the_spec_file_exits_2_with_one_line(tmp_path, capsys, table, match):
    spec = tmp_path / "spec.toml"
    spec.write_text(table)
    code, out = _tolerance_cli(tmp_path, "o", "--spec", str(spec))
    err = capsys.readouterr().err.strip()
    assert code == 2 and "\n" not in err and "Traceback" not in err
    assert re.search(match, err), err
    assert not out.exists()


@pytest.mark.parametrize("value", ["1", "0", "1.5", "-0.1", "nan"])
def test_a_bad_yield_goal_option_exits_2_with_one_error_line(tmp_path, capsys, value):
    code, out = _tolerance_cli(tmp_path, "o", "--yield-goal", value)
    errors = [line for line in capsys.readouterr().err.splitlines() if "error" in line]
    assert code == 2 and len(errors) == 1 and "argument --yield-goal" in errors[0] and "< 1" in errors[0]
    assert not out.exists()
