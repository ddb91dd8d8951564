"""`doe correct` on diagnosis reports written here by hand (fast): systematic against random,
the job sheet's signs and units, the corrected masks, the merit, the process spec, bad input.

The end-to-end proof on generated wafers is tests/metrology/test_fab_loop.py."""

import json
import math
import tomllib

import numpy as np
import pytest

import filegen
from doedesign.cli import main
from doedesign.design import Design
from metrology.correction.diagnoses import design_fingerprint
from metrology.correction.systematic import combine_fields, DETECTION_LIMITS
from metrology.correction.diagnoses import FieldDiagnosis

DEPTHS = [75e-9, 150e-9, 300e-9, 600e-9]


def _design(tmp_path, seed=3, px=24):
    from doedesign.camera import Camera

    levels = filegen.random_levels((px, px), np.random.default_rng(seed))
    cam = Camera(aperture_diameter_m=None, focus_distance_m=np.inf, window_shape=(64, 64), axis_pixel=(32, 32),
                 doe_side="full")
    height = -np.asarray(DEPTHS) @ filegen.masks_of(levels).reshape(4, -1)
    d = Design(height_m=height.reshape(levels.shape), pitch_m=filegen.PITCH_M, levels=levels,
               metadata={"camera": cam.to_dict()})
    path = tmp_path / f"design{seed}.npz"
    d.save(path)
    return d, path


def _step(effect, params, errs):
    return {"effect": effect, "kind": "fabrication", "measurement_artefact": False, "params": params,
            "uncertainties": errs}


def _field(tmp_path, name, design, path, dx1, bias, depth3, rot2, depths=DEPTHS):
    steps = [_step("mask_overlay", {"dx_mask1_m": dx1, "dy_mask1_m": -0.2e-6, "dx_mask2_m": 1e-9, "dy_mask2_m": -2e-9,
                                    "dx_mask3_m": 0.0, "dy_mask3_m": 0.0},
                   {k: 2e-9 for k in ("dx_mask1_m", "dy_mask1_m", "dx_mask2_m", "dy_mask2_m", "dx_mask3_m",
                                      "dy_mask3_m")}),
             _step("linewidth_bias", {f"bias_mask{j}_m": bias for j in range(4)}, {f"bias_mask{j}_m": 1e-9 for j in range(4)}),
             _step("etch_depth", {"depth_error_mask0": 0.001, "depth_error_mask1": -0.001, "depth_error_mask2": 0.0,
                                  "depth_error_mask3": depth3}, {f"depth_error_mask{j}": 5e-4 for j in range(4)}),
             _step("mask_rotation", {"rotation_mask1_deg": 0.0, "rotation_mask2_deg": rot2, "rotation_mask3_deg": 0.0},
                   {f"rotation_mask{j}_deg": 0.002 for j in (1, 2, 3)})]
    folder = tmp_path / name
    folder.mkdir()
    report = {"domain": "height", "steps": steps, "unexplained": False, "noise_floor": 1e-9,
              "measurement_artefacts": [], "inputs": {"nominal_depths_m": depths, **design_fingerprint(design, path)}}
    (folder / "report.json").write_text(json.dumps(report))
    return folder


def _three_fields(tmp_path, design, path):
    return [_field(tmp_path, "f0", design, path, 0.41e-6, 0.30e-6, 0.050, 0.031),
            _field(tmp_path, "f1", design, path, 0.39e-6, 0.31e-6, 0.052, 0.029),
            _field(tmp_path, "f2", design, path, 0.40e-6, 0.29e-6, 0.048, 0.030)]


def test_fields_combine_into_mean_standard_error_and_spread():
    fields = [FieldDiagnosis("a", {"mask_overlay": {"dx_mask1_m": v, "dy_mask1_m": w}},
                             {"mask_overlay": {"dx_mask1_m": 1e-9, "dy_mask1_m": 1e-9}}, DEPTHS)
              for v, w in ((0.41e-6, 0.01e-6), (0.39e-6, -0.02e-6), (0.40e-6, 0.015e-6))]
    est = {e.param: e for e in combine_fields(fields)}
    dx = est["dx_mask1_m"]
    assert dx.mean == pytest.approx(0.40e-6)
    assert dx.spread == pytest.approx(0.01e-6)  # sample sd of 0.41, 0.39, 0.40
    assert dx.standard_error == pytest.approx(0.01e-6 / math.sqrt(3))
    assert dx.systematic and dx.corrected
    dy = est["dy_mask1_m"]  # mean 1.7 nm: below the 0.05 um limit and within 3 standard errors
    assert not dy.systematic and not dy.corrected
    # Masks 2 and 3 were never named: null values, the detection limit as their uncertainty.
    assert est["dx_mask2_m"].mean == 0 and est["dx_mask2_m"].uncertainties == [DETECTION_LIMITS["mask_overlay"]] * 3


def test_job_sheet_masks_merit_and_spec(tmp_path):
    design, path = _design(tmp_path)
    out = tmp_path / "out"
    diags = _three_fields(tmp_path, design, path)
    sheet = _correct(path, diags, out, samples=3)
    m = {e["mask"]: e for e in sheet["masks"]}
    assert [e["layer"] for e in sheet["masks"]] == [1, 2, 3, 4] and all(e["datatype"] == 0 for e in sheet["masks"])
    # The dials are the negative of the measured errors, relative to mask 0.
    assert m[1]["align_offset_um"] == pytest.approx([-0.40, 0.20])
    assert m[0]["align_offset_um"] == [0.0, 0.0] and m[2]["align_offset_um"] == [0.0, 0.0]
    assert m[2]["align_rotation_deg"] == pytest.approx(-0.030)
    # The etch aimed at the target lands on nominal: target (1 + error) = nominal.
    assert m[3]["etch_depth_target_nm"] * 1.05 == pytest.approx(600.0)
    assert m[0]["etch_depth_target_nm"] == pytest.approx(75.0)  # 0.1 % is below the limit: not corrected
    assert all(e["linewidth_bias_um"] == pytest.approx(0.30) and e["drawn_edge_offset_um"] == pytest.approx(-0.30)
               for e in sheet["masks"])
    assert "etch_depth.depth_error_mask0" in sheet["spread_only"]
    assert sheet["masks_verification"]["passed"] and (out / sheet["masks_file"]).is_file()
    assert (out / "masks" / "masks.png").is_file() and (out / "report.md").is_file()
    assert "mask 4" in (out / "report.md").read_text() or "| 3 |" in (out / "report.md").read_text()
    # Merit: the corrected wafer is predicted closer to the design than the measured one.
    merit = sheet["merit"]
    assert merit["measured_wafer"]["primary_change_percent"] < merit["corrected_wafer"]["primary_change_percent"]
    assert abs(merit["corrected_wafer"]["primary_change_percent"]) < 0.5 * abs(merit["measured_wafer"]["primary_change_percent"])
    # The process spec reads as a doe tolerance spec; its sigmas are the spreads between the fields.
    from masks.tolerance.spec import load_spec

    spec = load_spec(out / "process_spec.toml", DEPTHS)
    by = {p.name: p for p in spec.params}
    assert by["linewidth_bias_um[mask 1]"].b == pytest.approx(0.01e-6)
    assert by["etch_depth_nm[mask 3]"].b == pytest.approx(0.002 * 600e-9)
    assert by["etch_depth_nm[mask 3]"].a == pytest.approx(0.0, abs=1e-15)  # taken out by the target
    assert tomllib.loads((out / "process_spec.toml").read_text())


def _correct(path, diags, out, samples=0):
    # doe correct through its command line; the job sheet it wrote.
    assert main(["correct", "--design", str(path), *[a for d in diags for a in ("--diagnosis", str(d))],
                 "--out", str(out), "--samples", str(samples)]) == 0
    return json.loads((out / "job.json").read_text())


def _fails(argv, capsys):
    code = main(argv)
    err = capsys.readouterr().err.strip()
    return code, err


def test_bad_input_is_refused_in_one_line_with_no_output(tmp_path, capsys):
    design, path = _design(tmp_path)
    other, other_path = _design(tmp_path, seed=4)
    good = _three_fields(tmp_path, design, path)
    foreign = _field(tmp_path, "foreign", other, other_path, 0.4e-6, 0.3e-6, 0.05, 0.03)
    cases = {
        "another design": [foreign],
        "nominal etch depths": [_field(tmp_path, "depths", design, path, 0.4e-6, 0.3e-6, 0.05, 0.03,
                                       depths=[80e-9, 160e-9, 320e-9, 640e-9]), good[0]],
        "cannot be drawn": [_field(tmp_path, "huge", design, path, 0.4e-6, 2.4e-6, 0.05, 0.03)] * 2,
    }
    for what, diags in cases.items():
        out = tmp_path / f"out_{what.replace(' ', '_')}"
        code, err = _fails(["correct", "--design", str(path), *[a for d in diags for a in ("--diagnosis", str(d))],
                            "--out", str(out), "--samples", "0"], capsys)
        assert code == 2, what
        assert what in err and len(err.splitlines()) == 1, err
        assert not out.exists(), what


def test_fields_that_disagree_are_a_warning_in_the_job_sheet(tmp_path):
    design, path = _design(tmp_path)
    diags = [_field(tmp_path, "a", design, path, 0.60e-6, 0.30e-6, 0.05, 0.03),
             _field(tmp_path, "b", design, path, 0.20e-6, 0.30e-6, 0.05, 0.03),
             _field(tmp_path, "c", design, path, -0.05e-6, 0.30e-6, 0.05, 0.03)]
    out = tmp_path / "out"
    sheet = _correct(path, diags, out)
    # 0.25 +- 0.19 um: not significant; the scatter is named and reported as spread.
    assert any("dx_mask1_m" in w and "scatter beyond their fitted uncertainties" in w and "not corrected" in w
               for w in sheet["warnings"])
    assert "mask_overlay.dx_mask1_m" in sheet["spread_only"]
    assert sheet["masks"][1]["align_offset_um"][0] == 0.0
    # Fields that disagree in sign about a significant mean: corrected by the mean, with a warning.
    diags = [_field(tmp_path, "d", design, path, 0.90e-6, 0.30e-6, 0.05, 0.03),
             _field(tmp_path, "e", design, path, 0.80e-6, 0.30e-6, 0.05, 0.03),
             _field(tmp_path, "f", design, path, -0.05e-6, 0.30e-6, 0.05, 0.03),
             _field(tmp_path, "g", design, path, 0.85e-6, 0.30e-6, 0.05, 0.03),
             _field(tmp_path, "h", design, path, 0.95e-6, 0.30e-6, 0.05, 0.03)]
    out = tmp_path / "out2"
    sheet = _correct(path, diags, out)
    assert any("dx_mask1_m" in w and "disagree in sign" in w and "corrected by the mean" in w
               for w in sheet["warnings"])
    assert sheet["masks"][1]["align_offset_um"][0] == pytest.approx(-0.69)


def test_loading_compensation_is_the_mean_loss_over_each_masks_openings():
    """The etch target takes out the mean depth a loading L costs over a mask's openings:
    L times the mean local open fraction there (a Gaussian of 50 um over the drawn mask, closed
    outside the design), computed here with scipy directly."""
    import scipy.ndimage as ndi

    from metrology.correction.jobsheet import mean_loading_loss

    levels = filegen.random_levels((40, 40), np.random.default_rng(5))
    masks = filegen.masks_of(levels)
    loss = mean_loading_loss(masks, filegen.PITCH_M, DEPTHS, 0.08)
    for j, m in enumerate(masks):
        rho = ndi.gaussian_filter(m.astype(float), 50e-6 / filegen.PITCH_M, mode="constant", truncate=4.0)
        assert loss[j] == pytest.approx(0.08 * rho[m].mean(), rel=1e-4)


def test_loading_is_compensated_in_the_mean_and_the_rest_is_a_warning(tmp_path):
    """A systematic loading of 8 % on three fields: every etch target takes out the mean loss over
    its mask's openings (independently: L times the mean 50 um Gaussian open fraction there), the
    measured mean depth error per mask is (1 + e)(1 - L rho_mean) - 1, the masks' labels say the
    targets include the loading, and what varies with the density is a warning with the values."""
    import scipy.ndimage as ndi

    design, path = _design(tmp_path)
    diags = []
    for k, (load, d3) in enumerate(((0.081, 0.050), (0.079, 0.052), (0.080, 0.048))):
        folder = _field(tmp_path, f"L{k}", design, path, 0.40e-6, 0.30e-6, d3, 0.03)
        rep = json.loads((folder / "report.json").read_text())
        rep["steps"].append(_step("etch_loading", {"loading": load}, {"loading": 0.003}))
        (folder / "report.json").write_text(json.dumps(rep))
        diags.append(folder)
    out = tmp_path / "out"
    sheet = _correct(path, diags, out)
    assert "etch_loading.loading" in sheet["corrected"]
    masks = filegen.masks_of(design.levels)
    errors = [0.001, -0.001, 0.0, 0.05]  # means over the fields; only mask 3's is significant
    for j, m in enumerate(sheet["masks"]):
        rho = ndi.gaussian_filter(masks[j].astype(float), 50e-6 / filegen.PITCH_M, mode="constant", truncate=4.0)
        loss = 0.080 * rho[masks[j]].mean()
        rest_nm = 0.080 * rho[masks[j]].std() * DEPTHS[j] * 1e9
        assert m["etch_loading_mean_loss_fraction"] == pytest.approx(loss, rel=1e-3)
        assert m["etch_loading_residual_rms_nm"] == pytest.approx(rest_nm, rel=1e-3)
        corrected_error = errors[j] if j == 3 else 0.0
        assert m["etch_depth_target_nm"] == pytest.approx(DEPTHS[j] * 1e9 / (1 + corrected_error) / (1 - loss), rel=1e-6)
        assert m["etch_mean_error_measured"] == pytest.approx((1 + errors[j]) * (1 - loss) - 1, rel=1e-4)
        assert any("etch loading 0.080" in c for c in m["corrections"])
    warn = [w for w in sheet["warnings"] if w.startswith("etch_loading loading = 0.08 ")]
    assert len(warn) == 1 and "cannot be corrected" in warn[0]
    assert f"mask 3 {sheet['masks'][3]['etch_loading_residual_rms_nm']:.2f} nm" in warn[0]
    labels = json.loads((out / "masks" / "report.json").read_text())["layers"]
    assert all("loading mean loss" in layer["note"] for layer in labels)
    page = (out / "report.md").read_text()
    assert "mean loss corrected (etch targets)" in page and "measured mean etch error over the openings (%)" in page
    # The corrected wafer keeps the loading (no knob removes it) with the means taken out.
    from masks.tolerance.spec import load_spec

    spec = load_spec(out / "process_spec.toml", DEPTHS)
    assert {p.name: p for p in spec.params}["etch_loading"].a == pytest.approx(0.080)


def test_the_demo_fab_follows_the_job_sheet():
    """The demo's next wafer: the dials cancel the hidden overlay and rotation, the drawn edges
    add to the bias, the etch aimed at the target scales the actual depth by target / nominal."""
    from masks.process import ProcessParams
    from metrology.demo_loop import next_wafer_params

    overlay = np.zeros((4, 3))
    overlay[3, :2] = [0.4e-6, -0.1e-6]
    hidden = ProcessParams.ideal().copy(mask_overlay=overlay, linewidth_bias=np.full(4, 0.2e-6),
                                        etch_depth=np.array(DEPTHS) * [1, 1, 1, 1.05])
    sheet = {"masks": [{"mask": j, "align_offset_um": [-0.4, 0.1] if j == 3 else [0.0, 0.0],
                        "align_rotation_deg": -0.01 if j == 2 else 0.0, "drawn_edge_offset_um": -0.2,
                        "etch_depth_target_nm": DEPTHS[j] * 1e9 / (1.05 if j == 3 else 1.0),
                        "etch_depth_nm": DEPTHS[j] * 1e9} for j in range(4)]}
    nxt = next_wafer_params(hidden, sheet)
    assert np.abs(nxt.mask_overlay[:, :2]).max() < 1e-15
    assert nxt.mask_rotation[2] == pytest.approx(-0.01) and np.count_nonzero(nxt.mask_rotation) == 1
    assert np.abs(nxt.linewidth_bias).max() < 1e-15
    assert nxt.etch_depth == pytest.approx(DEPTHS, rel=1e-12)
    assert hidden.mask_overlay[3, 0] == 0.4e-6  # the measured wafer's process is left as it was


def test_a_field_that_did_not_test_an_effect_has_no_vote_on_it():
    # Field c's diagnosis was not given mask_overlay as a candidate: it says nothing about it, and
    # the overlay is the mean of the two that tested it (not dragged towards zero by a third).
    named = [FieldDiagnosis(k, {"mask_overlay": {"dx_mask1_m": v}}, {"mask_overlay": {"dx_mask1_m": 1e-9}}, DEPTHS)
             for k, v in (("a", 0.40e-6), ("b", 0.42e-6))]
    blind = FieldDiagnosis("c", {}, {}, DEPTHS, tested=["etch_depth"])
    absent = FieldDiagnosis("c", {}, {}, DEPTHS, tested=["etch_depth", "mask_overlay"])
    dx = {e.param: e for e in combine_fields(named + [blind])}["dx_mask1_m"]
    assert dx.mean == pytest.approx(0.41e-6) and dx.tested_in == 2 and dx.fields == 3 and len(dx.values) == 2
    dx = {e.param: e for e in combine_fields(named + [absent])}["dx_mask1_m"]
    assert dx.mean == pytest.approx(0.82e-6 / 3) and dx.tested_in == 3  # tested and absent: a vote for zero


def test_a_partial_match_is_no_vote_for_zero(tmp_path):
    """A field whose report names mask 3's etch depth on two fields, and on the third lists it as
    a partial match (the CSI field of the large fab loop): that field did not find the depth error
    absent, so the mean is the two fields' and the correction keeps it."""
    design, path = _design(tmp_path)
    fields = [_field(tmp_path, f"f{k}", design, path, 0.40e-6, 0.30e-6, 0.05 + 0.001 * k, 0.03) for k in range(3)]
    rep = json.loads((fields[2] / "report.json").read_text())
    rep["steps"] = [s for s in rep["steps"] if s["effect"] != "etch_depth"]
    rep["tested"] = ["mask_overlay", "linewidth_bias", "etch_depth", "mask_rotation", "etch_loading"]
    rep["unexplained"] = True
    rep["partial_matches"] = [{"effect": "etch_depth", "residual_on_footprint_over_floor": 3.0,
                               "footprint_px": 20000, "footprint_excess_explained": 0.97}]
    (fields[2] / "report.json").write_text(json.dumps(rep))
    job = _correct(path, fields, tmp_path / "out")
    est = {e["param"]: e for e in job["estimates"]}
    depth3 = est["depth_error_mask3"]
    assert depth3["tested_in"] == 2 and depth3["fields"] == 3
    assert depth3["mean"] == pytest.approx(0.0505)
    assert "etch_depth.depth_error_mask3" in job["corrected"]
    assert est["dx_mask1_m"]["tested_in"] == 3  # what the third field named still counts
    assert any("combined only over the fields whose diagnosis tested them" in w and "etch_depth (2 of 3)" in w
               for w in job["warnings"])


def test_a_field_cut_by_a_wall_limit_leaves_the_job_sheet_of_the_complete_ones_and_warns(tmp_path):
    from doedesign.camera import Camera

    # The third field: a real file of the design, diagnosed with a limit that ends it at once.
    case = filegen.make_case(["mask_overlay"], 3, design_px=32, field_px=100)
    cam = Camera(aperture_diameter_m=None, focus_distance_m=np.inf, window_shape=(64, 64), axis_pixel=(32, 32),
                 doe_side="full")
    path, measured = case.write(tmp_path / "wafer", metadata={"camera": cam.to_dict()})
    design = Design.load(path)
    cut = tmp_path / "cut"
    assert main(["diagnose", "--design", str(path), "--measured", str(measured), "--window-px", "64",
                 "--out", str(cut), "--wall-limit-s", "0.001"]) == 3
    assert json.loads((cut / "report.json").read_text())["summary"].startswith("INCOMPLETE")
    complete = [_field(tmp_path, "f0", design, path, 0.41e-6, 0.30e-6, 0.050, 0.031),
                _field(tmp_path, "f1", design, path, 0.39e-6, 0.31e-6, 0.052, 0.029)]
    two = _correct(path, complete, tmp_path / "two")
    three = _correct(path, complete + [cut], tmp_path / "three")
    assert three["masks"] == two["masks"] and three["corrected"] == two["corrected"]
    assert [e["mean"] for e in three["estimates"]] == [e["mean"] for e in two["estimates"]]
    assert {e["tested_in"] for e in three["estimates"]} == {2} and {e["fields"] for e in three["estimates"]} == {3}
    # Said first: in job.json and on the page, below its title.
    assert three["incomplete_diagnoses"] == [str(cut)] and not two["incomplete_diagnoses"]
    assert three["warnings"][0].startswith(f"INCOMPLETE diagnosis {cut}")
    assert "combined only over the fields whose diagnosis tested them" in three["warnings"][1]
    page = (tmp_path / "three" / "report.md").read_text().splitlines()
    assert next(line for line in page[1:] if line.strip()).startswith("**INCOMPLETE diagnosis")
    # Only incomplete diagnoses: refused, nothing written.
    code = main(["correct", "--design", str(path), "--diagnosis", str(cut), "--out", str(tmp_path / "none")])
    assert code == 2 and not (tmp_path / "none" / "job.json").exists()


def test_a_map_sets_the_aligner_dials_it_names_and_states_the_mask_scale(tmp_path):
    # Whole-element overlay models fitted on 25 tile values: mask 2 printed 10 ppm large, mask 3
    # moved 50 nm and turned 10 urad; the radial etch term 3 % from centre to edge.
    from metrology.diagnosis.map_models import fit_depth_model, fit_overlay_model

    design, path = _design(tmp_path)
    rng = np.random.default_rng(5)
    x, y = rng.uniform(-4e-3, 4e-3, (2, 25))
    s = np.full(25, 1e-9)
    noise = lambda: 0.5e-9 * rng.standard_normal(25)  # noqa: E731
    models = {"overlay_mask1": fit_overlay_model(x, y, noise(), noise(), s, s),
              "overlay_mask2": fit_overlay_model(x, y, 10e-6 * x + noise(), 10e-6 * y + noise(), s, s),
              "overlay_mask3": fit_overlay_model(x, y, 50e-9 - 10e-6 * y + noise(), 10e-6 * x + noise(), s, s),
              "depth_all": fit_depth_model(x, y, -0.03 * (x ** 2 + y ** 2) / 4.3e-3 ** 2 + 1e-4 * rng.standard_normal(25),
                                           np.full(25, 1e-4), 4.3e-3)}
    (tmp_path / "map.json").write_text(json.dumps({"n_tiles": 25, "models": models}))
    out = tmp_path / "out"
    diags = _three_fields(tmp_path, design, path)
    assert main(["correct", "--design", str(path), *[a for d in diags for a in ("--diagnosis", str(d))],
                 "--out", str(out), "--samples", "0", "--map", str(tmp_path / "map.json")]) == 0
    sheet = json.loads((out / "job.json").read_text())
    m = {e["mask"]: e for e in sheet["masks"]}
    # Mask 3: the map's dial (the negative of its translation and rotation), the fields' kept beside it.
    assert m[3]["align_source"] == "map" and m[3]["align_offset_um"][0] == pytest.approx(-0.050, rel=0.05)
    assert m[3]["align_rotation_deg"] == pytest.approx(-math.degrees(10e-6), rel=0.05)
    assert m[3]["align_offset_um_fields"] == [0.0, 0.0]
    # Mask 1: the map names nothing there, so the fields' dial stays; mask 2: a stated scale.
    assert m[1]["align_source"] == "fields" and m[1]["align_offset_um"] == pytest.approx([-0.40, 0.20])
    assert m[2]["mask_scale"] == pytest.approx(1 - 10e-6, abs=0.3e-6) and m[1]["mask_scale"] == 1.0
    assert sheet["map"]["source"].endswith("map.json")
    assert any("ppm" in w and "mask 2" in w for w in sheet["warnings"])
    assert any(w.startswith("etch depth -3.0") for w in sheet["warnings"])
    page = (out / "report.md").read_text()
    head = page.split("## Per mask")[0]
    assert "map" in head and "mask(s) 3" in head and "From the whole-element map" in page


def test_a_positive_bias_shrinks_the_openings_of_a_110_px_design_and_verifies(tmp_path):
    # The user's path: a measured linewidth bias of +0.194 um is drawn as a -0.194 um edge
    # offset; the inward offset of merged polygons (holes, splits) used to fail the read-back.
    design, path = _design(tmp_path, seed=5, px=110)
    diags = [_field(tmp_path, f"f{i}", design, path, 0.0, b, 0.0, 0.0) for i, b in enumerate((0.193e-6, 0.194e-6, 0.195e-6))]
    out = tmp_path / "out"
    sheet = _correct(path, diags, out)
    assert all(e["drawn_edge_offset_um"] == pytest.approx(-0.194) for e in sheet["masks"])
    assert sheet["masks_verification"]["passed"] and (out / sheet["masks_file"]).is_file()
