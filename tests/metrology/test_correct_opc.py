"""`doe correct` on fields whose diagnoses name a print through the aligner's gap (issue 56, must 4):
the masks come out pre-distorted for the diagnosed gap and threshold, with each mask's linewidth bias
folded in, verified, and what they print through that gap, computed by the tests' own proximity
simulator (:mod:`proximitygen`, written apart from the model), is closer to the design than what the
masks as drawn print.

The diagnoses are written here by hand (as in test_correct.py): the fine 16-level map of the
diagnosis tests (:func:`filegen.random_levels`), 12 px of 5.4 um, about one edge per pixel on its
shallow masks.
"""

import json

import numpy as np
import pytest

import filegen
import proximitygen
from doedesign.cli import main
from doedesign.design import Design
from metrology.correction.diagnoses import design_fingerprint

DEPTHS = list(filegen.DEPTHS_M)
GAP_M, THRESHOLD, BIAS3_M = 30e-6, 0.35, 0.15e-6


def _design(tmp_path, px=12):
    levels = filegen.random_levels((px, px), np.random.default_rng(0))
    height = -np.asarray(DEPTHS) @ filegen.masks_of(levels).reshape(4, -1)
    d = Design(height_m=height.reshape(levels.shape), pitch_m=filegen.PITCH_M, levels=levels)
    path = tmp_path / "fine.npz"
    d.save(path)
    return d, path, levels


def _field(tmp_path, name, design, path, gap_m, threshold, bias3_m):
    steps = [{"effect": "proximity_print", "kind": "fabrication", "measurement_artefact": False,
              "params": {"gap_m": gap_m, "threshold": threshold},
              "uncertainties": {"gap_m": 0.2e-6, "threshold": 0.002}},
             {"effect": "linewidth_bias", "kind": "fabrication", "measurement_artefact": False,
              "params": {"bias_mask0_m": 0.0, "bias_mask1_m": 0.0, "bias_mask2_m": 0.0, "bias_mask3_m": bias3_m},
              "uncertainties": {f"bias_mask{j}_m": 2e-9 for j in range(4)}}]
    folder = tmp_path / name
    folder.mkdir()
    report = {"domain": "height", "steps": steps, "unexplained": False, "noise_floor": 1e-9,
              "measurement_artefacts": [], "inputs": {"nominal_depths_m": DEPTHS, **design_fingerprint(design, path)}}
    (folder / "report.json").write_text(json.dumps(report))
    return folder


def _layout_masks(gds, shape, pitch_m, k):
    """The element cell's openings per layer (1..4) read with gdstk, sampled at the centres of a
    ``pitch / k`` grid (the element centred on (0, 0), row 0 at the top, y up)."""
    import gdstk

    from masks.grid import ELEMENT_CELL

    cell = next(c for c in gdstk.read_gds(str(gds)).cells if c.name == ELEMENT_CELL)
    rows, cols = shape[0] * k, shape[1] * k
    step_um = pitch_m / k * 1e6
    x = -cols * step_um / 2 + (np.arange(cols) + 0.5) * step_um
    y = rows * step_um / 2 - (np.arange(rows) + 0.5) * step_um
    points = np.stack(np.meshgrid(x, y), -1).reshape(-1, 2)
    out = []
    for layer in (1, 2, 3, 4):
        polygons = cell.get_polygons(layer=layer, datatype=0)
        out.append(np.array(gdstk.inside(points, polygons), bool).reshape(rows, cols))
    return out


def _printed_error_um2(mask_fine, target_fine, dx, gap_m, threshold):
    """|printed - target| area (um^2) of a mask on the 0.225 um grid, printed by the tests' own simulator."""
    pad = int(np.ceil((gap_m * (np.tan(np.radians(30)) + np.tan(np.radians(2))) + 4e-6) / dx))
    t = np.pad(mask_fine.astype(np.complex64), pad)
    inten = proximitygen.intensity_of(t, dx, gap_m)[pad:-pad, pad:-pad]
    return float(np.abs((inten > threshold).astype(float) - target_fine).sum() * dx * dx * 1e12)


def test_a_diagnosed_gap_gives_masks_pre_distorted_for_it_that_print_closer_to_the_design(tmp_path, capsys):
    design, path, levels = _design(tmp_path)
    fields = [_field(tmp_path, f"f{k}", design, path, GAP_M + d * 1e-6, THRESHOLD + d * 0.004, BIAS3_M + d * 5e-9)
              for k, d in enumerate((-1, 0, 1))]
    out = tmp_path / "next"
    argv = ["correct", "--design", str(path), "--out", str(out), "--samples", "0"]
    for f in fields:
        argv += ["--diagnosis", str(f)]
    assert main(argv) == 0
    capsys.readouterr()
    sheet = json.loads((out / "job.json").read_text())
    assert "proximity_print.gap_m" in sheet["corrected"]
    opc = sheet["proximity_correction"]
    assert opc["gap_um"] == pytest.approx(30.0) and opc["resist_threshold"] == pytest.approx(THRESHOLD)
    assert opc["linewidth_bias_um"] == pytest.approx([0, 0, 0, 0.15])
    # The process model's own print check through the diagnosed print, drawn against corrected.
    assert opc["field_overlap_corrected"] > opc["field_overlap_drawn"] + 0.1  # measured 0.727 -> 0.904
    # The merit: the measured wafer printed through the gap, the corrected one as a contact print.
    assert _param(sheet, "measured_wafer", "proximity_gap")["mean_um"] == pytest.approx(30.0)
    assert _param(sheet, "corrected_wafer", "proximity_gap")["mean_um"] == 0.0
    for job in sheet["masks"]:
        assert job["drawn_edge_offset_um"] == 0.0  # the bias is in the pre-distortion, not an offset on top
        assert job["opc"]["gap_um"] == pytest.approx(30.0)
        assert any("pre-distorted" in c for c in job["corrections"])
        assert not any(c.startswith("edges drawn") for c in job["corrections"])
    report = json.loads((out / "masks" / "report.json").read_text())
    assert report["verification"]["passed"]
    assert (out / "masks" / "print_check.json").exists()
    page = (out / "report.md").read_text()
    assert "Masks pre-distorted for the gap (OPC)" in page
    toml = (out / "process_spec.toml").read_text()
    assert "proximity_print: the corrected masks are pre-distorted" in toml

    # What the layout file holds, printed by the tests' own simulator against the masks as drawn.
    k = round(design.pitch_m / (opc["mask_grid_um"] * 1e-6))
    corrected = _layout_masks(out / "masks" / report["file"], levels.shape, design.pitch_m, k)
    dx = design.pitch_m / k
    drawn = [np.repeat(np.repeat(m, k, 0), k, 1) for m in filegen.masks_of(levels)]
    for j in (0, 1, 2):  # the unbiased masks: the simulator's print of the drawn and the corrected opening
        before = _printed_error_um2(drawn[j], drawn[j], dx, GAP_M, THRESHOLD)
        after = _printed_error_um2(corrected[j], drawn[j], dx, GAP_M, THRESHOLD)
        assert after < 0.5 * before, (j, before, after)  # measured 339 -> 106, 329 -> 123, 382 -> 142 um^2


def test_no_opc_draws_the_masks_uncorrected_for_the_gap_and_warns(tmp_path, capsys):
    design, path, _ = _design(tmp_path, px=8)
    fields = [_field(tmp_path, f"f{k}", design, path, GAP_M + d * 1e-6, THRESHOLD, 0.0) for k, d in enumerate((-1, 0, 1))]
    out = tmp_path / "next"
    argv = ["correct", "--design", str(path), "--out", str(out), "--samples", "0", "--no-opc"]
    for f in fields:
        argv += ["--diagnosis", str(f)]
    assert main(argv) == 0
    capsys.readouterr()
    sheet = json.loads((out / "job.json").read_text())
    assert "proximity_correction" not in sheet and "proximity_print.gap_m" not in sheet["corrected"]
    assert any("--no-opc" in w and "proximity_print" in w for w in sheet["warnings"])
    # The measured wafer's merit carries the print, and the corrected one too: nothing takes it out.
    for wafer in ("measured_wafer", "corrected_wafer"):
        gap = _param(sheet, wafer, "proximity_gap")
        assert gap["mean_um"] == pytest.approx(30.0) and gap["sigma_um"] == pytest.approx(1.0)
        assert _param(sheet, wafer, "resist_threshold")["mean"] == pytest.approx(THRESHOLD - 0.5)


def _param(sheet, wafer, effect):
    return next(p for p in sheet["merit"][wafer]["parameters"] if p["effect"] == effect)
