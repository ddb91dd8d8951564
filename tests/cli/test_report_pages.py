"""The Markdown pages a person reads: a summary at the top, tables whose number columns carry a
unit, verdicts in words, figures inline and a link to the JSON beside the page. The demo page's
colour table gives each colour's energy with its single-colour bound and the fraction of it."""

from __future__ import annotations

import re

import numpy as np
import pytest

from doedesign.bounds import bound_report
from metrology import report_pages as pages
from metrology.pipeline import markdown_report

# Columns that name things or count them (no unit to give).
LABEL_COLUMNS = {"colour", "mask", "step", "effect", "kind", "verdict", "quantity", "metric", "parameter",
                 "GDS layer", "polygons", "vertices", "yield", "better", "dist", "values", "mask and effect"}
NUMBER = re.compile(r"^[-+]?(\d+\.?\d*|\.\d+)(e[-+]?\d+)?( ± \S+)?( \S+)?$")


def _tables(text):
    """Each Markdown table of ``text`` as (header cells, rows of cells)."""
    out, block = [], []
    for line in text.splitlines() + [""]:
        if line.startswith("|"):
            block.append([c.strip() for c in line.strip("|").split(" | ")])
        elif block:
            out.append((block[0], block[2:]))
            block = []
    return out


def page_problems(text, folder):
    """What keeps ``text`` from being a page an engineer reads in two minutes (empty when none)."""
    problems = []
    lines = [line for line in text.splitlines() if line.strip()]
    if not lines[0].startswith("# ") or lines[1] != "## Summary":
        problems.append("no '## Summary' right under the title")
    if "[report.json](report.json)" not in text:
        problems.append("no link to report.json")
    if not re.search(r"\*\*(OK|CHECK|NOT JUDGED)\*\*", text):
        problems.append("no verdict in words")
    figures = re.findall(r"!\[[^\]]*\]\(([^)]+)\)", text)
    if not figures:
        problems.append("no inline figure")
    problems += [f"figure {f} missing" for f in figures if not (folder / f).is_file()]
    if "```" in text or "{" in text:
        problems.append("raw JSON or code pasted into the page")
    for header, rows in _tables(text):
        if rows and all(re.search(r"\([^)]+\)$", r[0]) for r in rows):
            continue  # the unit is given per row, in the quantity's name
        for i, name in enumerate(header):
            cells = [r[i] for r in rows if i < len(r) and r[i] != "n/a"]
            numeric = cells and all(NUMBER.match(c) for c in cells)
            if numeric and "(" not in name and "/" not in name and name not in LABEL_COLUMNS:
                problems.append(f"number column {name!r} names no unit")
    return problems


def test_the_page_check_can_fail(tmp_path):
    bad = "# T\n\nintro\n\n| depth |\n|---|\n| 75 |\n"
    found = page_problems(bad, tmp_path)
    assert {"no '## Summary' right under the title", "no link to report.json", "no verdict in words",
            "no inline figure", "number column 'depth' names no unit"} <= set(found)


def _demo_report(energy_c, energy_q, bound):
    stage = lambda e: {"energy_on_target": [e], "bound": bound_report([e], [bound])}  # noqa: E731
    return {"config": {"doe_px": 64, "measurement_pixel_m": 1.1e-6},
            "design": {"continuous": stage(energy_c), "quantized": stage(energy_q), "run_time_s": 1.0},
            "masks": {"layers": [{"mask": j, "layer": j + 1, "etch_depth_nm": 75.0 * 2 ** j, "polygons": 3,
                                  "vertices": 12} for j in range(4)], "verification": {"passed": True}},
            "comparison": {"etch_depths_nominal_nm": [75.0, 150.0, 300.0, 600.0],
                           "etch_depths_nm": [75.1, 150.0, 300.0, 600.4], "etch_depths_err_nm": [0.1] * 4,
                           "etch_depths_error_percent": [0.1, 0.0, 0.0, 0.07],
                           "overlay_um": [[0, 0], [0, 0], [0, 0], [0.4, 0.0]], "overlay_err_um": [[0.01, 0.01]] * 4,
                           "match": {"readout_correlation": 0.999, "edges_found": 0.99, "design_edges": 800,
                                     "confidence": "high"}},
            "diagnosis": {"effects_found": ["mask_overlay"], "units": "m", "initial_residual_rms": 4e-9,
                          "final_residual_rms": 1e-9, "noise_floor": 1e-9,
                          "steps": [{"effect": "mask_overlay", "kind": "fabrication",
                                     "params": {"dx_mask3_m": 0.38e-6}, "units": {"dx_mask3_m": "m"},
                                     "residual_rms_before": 4e-9, "residual_rms_after": 1e-9,
                                     "criterion_change": -500.0}]},
            "hidden_error": {"mask_overlay": {"mask": 3, "dx_um": 0.4, "dy_um": 0.0}},
            "tolerance": {"samples": 4, "spec": "built-in default", "sampling": "coded view",
                          "primary_metric": "on_target_mean",
                          "metrics": {"on_target_mean": {"nominal": 0.22, "mean": 0.21, "worst_decile_mean": 0.2}},
                          "yield": {"passed": 4, "samples": 4, "ci95": [0.3976, 1.0], "goal": 0.9}},
            "timings": [{"step": "design", "seconds": 1.0}]}


def test_demo_colour_table_gives_energy_bound_and_fraction(tmp_path):
    (tmp_path / "psf.png").write_bytes(b"png")
    bound = [0.489, 0.548, 0.644]
    cont, quant = [0.224, 0.221, 0.223], [0.221, 0.219, 0.221]
    text = markdown_report(_demo_report(cont, quant, bound), tmp_path)
    assert not page_problems(text, tmp_path), page_problems(text, tmp_path)
    table = next((h, rows) for h, rows in _tables(text) if h[0] == "colour")
    header, rows = table
    assert header == ["colour", "wavelength (nm)", "bound (fraction of light)", "continuous (fraction of light)",
                      "continuous / bound", "16 levels (fraction of light)", "16 levels / bound",
                      "quantization change (%)"]
    for row, c, q, b in zip(rows, cont, quant, bound):
        got = dict(zip(header, row))
        assert float(got["bound (fraction of light)"]) == pytest.approx(b, rel=1e-3)
        assert float(got["16 levels / bound"]) == pytest.approx(q / b, rel=2e-3)
        assert float(got["continuous / bound"]) == pytest.approx(c / b, rel=2e-3)
    # The summary says how far each colour is from its bound, in the same order.
    summary = text.split("## Light on target")[0]
    assert "/".join(f"{q / b:.2g}" for q, b in zip(quant, bound)) + " of each colour's single-colour bound" \
        in summary
    # The closing tolerance run: its unit and its yield judged in words (4 of 4 cannot show 90 %).
    tolerance = text.split("## Tolerance")[1]
    assert "| on_target_mean (fraction of light) |" in tolerance
    assert "Yield: **NOT JUDGED**: 4 samples cannot tell whether the yield reaches 90 %" in tolerance


def test_demo_colour_table_without_a_bound_says_so(tmp_path):
    rep = _demo_report([0.2] * 3, [0.2] * 3, [0.5] * 3)
    for stage in rep["design"].values():
        if isinstance(stage, dict):
            stage.pop("bound")
    text = markdown_report(rep, tmp_path)
    rows = next(rows for h, rows in _tables(text) if h[0] == "colour")
    assert all(r[2] == "n/a" and r[4] == "n/a" for r in rows)


def test_compare_and_diagnose_pages_read_as_reports(tmp_path):
    rep = _demo_report([0.2] * 3, [0.2] * 3, [0.5] * 3)
    for name, _ in pages.COMPARE_FIGURES + pages.DIAGNOSE_FIGURES:
        (tmp_path / name).write_bytes(b"png")
    comp = {**rep["comparison"], "measurement": "m.datx", "design": "d.npz",
            "psf": {"wavelengths_nm": [656, 589, 486], "design_on_target": [0.2] * 3,
                    "measured_on_target": [0.19] * 3}}
    text = pages.compare_page(comp, tmp_path).read_text()
    assert not page_problems(text, tmp_path), page_problems(text, tmp_path)
    assert "**CHECK**: mask 3 overlay dx" in text
    diag = {**rep["diagnosis"], "inputs": {"measured": "m.datx", "design": "d.npz"}}
    text = pages.diagnose_page(diag, tmp_path).read_text()
    assert not page_problems(text, tmp_path), page_problems(text, tmp_path)


def test_an_empty_diagnosis_claims_agreement_only_when_the_residual_is_noise(tmp_path):
    """Nothing named at 17x the floor (a user's limit stopped it, partial matches dropped) is no agreement."""
    base = {"steps": [], "initial_residual_rms": 62e-9, "final_residual_rms": 62e-9, "noise_floor": 3.7e-9,
            "inputs": {"measured": "m.datx", "design": "d.npz"}}
    stuck = {**base, "unexplained": True, "partial_matches": [{"effect": "linewidth_bias"}],
             "unexplained_where": {"summary": "at the edges of mask 3"},
             "stopped_early": {"reason": "time limit: no further candidates were tried", "final_over_floor": 17.0,
                               "limit": "wall"},
             "summary": "INCOMPLETE: the limit asked for (--wall-limit-s) ended the diagnosis; not tried: etch_depth"}
    text = "\n".join(pages.diagnose_sections(stuck, tmp_path))
    assert "agrees with the ideal model" not in text and "does not agree with the ideal model" in text
    assert "Rerun without `--wall-limit-s`" in text
    # The summary's first line says INCOMPLETE, and what was not tried.
    assert text.split("\n")[1].startswith("- INCOMPLETE:") and "not tried: etch_depth" in text.split("\n")[1]
    judged = {**stuck, "partial_matches": [{"effect": "etch_depth", "residual_on_footprint_over_floor": 1.62,
                                            "footprint_excess_explained": 0.946, "footprint_px": 900}]}
    text = "\n".join(pages.diagnose_sections(judged, tmp_path))
    assert "etch_depth (1.62x the floor there, 95 % of its excess explained)" in text
    quiet = {**base, "unexplained": False, "final_residual_rms": 3.6e-9}
    text = "\n".join(pages.diagnose_sections(quiet, tmp_path))
    assert "agrees with the ideal model" in text and "Rerun without" not in text


def test_a_candidate_below_the_models_resolution_is_said_not_named(tmp_path):
    rep = {"steps": [], "effects_found": ["mask_overlay"], "initial_residual_rms": 22e-9,
           "final_residual_rms": 0.63e-9, "noise_floor": 0.62e-9, "unexplained": False,
           "below_resolution": {"effect": "etch_loading", "criterion_change": -57.1, "floor_power_share": 0.0031},
           "inputs": {"measured": "m.datx", "design": "d.npz"}}
    text = "\n".join(pages.diagnose_sections(rep, tmp_path))
    assert "Fabrication effects named: mask_overlay;" in text
    assert "below the model's resolution: etch_loading would explain 0.31 % of the noise floor's power" in text


def test_tolerance_page_reads_as_a_report(tmp_path):
    from masks.tolerance.analysis import nominal_depths, tolerance_analysis
    from masks.tolerance.spec import build_spec

    from doedesign.camera import Camera
    from doedesign.design import Design
    from doedesign.levels import level_step_m

    n = 16
    levels = np.random.default_rng(3).integers(0, 16, (n, n)).astype(np.int16)
    cam = Camera(aperture_diameter_m=n * 5.4e-6, focus_distance_m=np.inf, window_shape=(16, 16), axis_pixel=(8, 8))
    meta = {"camera": cam.to_dict(), "n_levels": 16,
            "target": {"kind": "bayer", "wavelengths_nm": [656.0, 589.0, 486.0], "depths_m": ["inf"]}}
    design = Design(-levels * level_step_m("fused_silica", 550e-9, 16), 5.4e-6, levels=levels, metadata=meta)
    spec = build_spec({"etch_depth": {"sigma_rel": 0.03}}, nominal_depths(design), "t")
    rep = tolerance_analysis(design, spec, 3, tmp_path, scheduler="inline", sobol_base=0,
                             thresholds={"on_target_R": (">=", 0.0)})
    text = (tmp_path / "report.md").read_text()
    assert not page_problems(text, tmp_path), page_problems(text, tmp_path)
    # The summary: what was toleranced, how many samples, the yield with its interval, what matters
    # most (the largest one-sigma swing), and a verdict: 3 of 3 passing cannot show a 90 % yield.
    summary = text.split("## Summary")[1].split("\n## ")[0]
    top = rep["sensitivity"]["one_at_a_time"]["rows"][0]["label"]
    assert "varying etch_depth on masks 0, 1, 2, 3" in summary and "3 Monte Carlo process samples" in summary
    assert "100 % (3 of 3 samples), 95 % interval 29.2 % to 100 %" in summary
    assert f"**Matters most**: {top}: one sigma of it moves on_target_mean" in summary
    assert "**NOT JUDGED**: 3 samples cannot tell whether the yield reaches 90 %" in summary
    assert "at least 36 samples" in summary
    # A yield whose whole interval lies below the goal is a CHECK that names what to tighten first.
    from masks.tolerance.report import tolerance_page, yield_summary

    rep["yield"] = yield_summary([{"metrics": {"on_target_R": v}} for v in [1.0] * 70 + [0.0] * 30],
                                 {"on_target_R": (">=", 0.5)})
    text = tolerance_page(rep, tmp_path).read_text()
    assert not page_problems(text, tmp_path), page_problems(text, tmp_path)
    assert f"**CHECK**: the yield is below 90 % (95 % interval 60 % to 78.8 %); tighten the process on {top}" in text


def test_yield_verdict_follows_the_exact_interval():
    from masks.tolerance import report as tol

    # All n passing: the Clopper-Pearson lower bound is 0.025 ** (1 / n), which first reaches 0.9 at n = 36.
    assert tol.samples_to_show(0.9) == 36
    assert tol.clopper_pearson(36, 36)[0] == pytest.approx(0.025 ** (1 / 36), rel=1e-9)
    assert tol.meets_goal(tol.clopper_pearson(36, 36)) is True
    assert tol.meets_goal(tol.clopper_pearson(35, 35)) is None
    # 70 of 100 passing: the whole interval (about 0.60-0.79) lies below 0.9.
    assert tol.meets_goal(tol.clopper_pearson(70, 100)) is False
    samples = [{"metrics": {"m": v}} for v in [1.0] * 70 + [0.0] * 30]
    y = tol.yield_summary(samples, {"m": (">=", 0.5)})
    assert y["meets_goal"] is False and y["goal"] == 0.9 and y["passed"] == 70
