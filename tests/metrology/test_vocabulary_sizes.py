"""The diagnosis's vocabulary at the sizes fabrication produces (issue 25): a mask turned by a
tenth or two of a degree is named a rotation (not a linewidth bias or an overlay), an etch
gradient across the field is named without a false ``etch_depth``. Measured by the tests' own
instruments (``tests/metrology/instruments``), not the diagnosis's model."""

import json

import numpy as np
import pytest

import filegen
from doedesign.cli import main
from instruments import boxcar, point

# The confusers of a rotation (a bias, an overlay) and of a gradient (a depth error) compete.
EFFECTS = "etch_depth,mask_overlay,linewidth_bias,mask_rotation,etch_gradient"


def _case(module, truth, seed, design_px=40, field_px=120):
    rng = np.random.default_rng(seed)
    levels = filegen.random_levels((design_px, design_px), rng)
    surface = filegen.wafer_surface(levels, truth)
    # 1 um pixels: the field stays on the design at any rotation.
    height, inst = module.measure(surface, filegen.FINE_PER_PX, levels.shape, (field_px, field_px), rng,
                                  pixel_m=1.0e-6, header_pixel_m=1.0e-6)
    return filegen.FileCase(levels=levels, truth=truth, instrument=inst, height_m=height, seed=seed)


def _diagnose(case, tmp_path):
    design, measured = case.write(tmp_path)
    out = tmp_path / "diag"
    assert main(["diagnose", "--design", str(design), "--measured", str(measured), "--frame", "camera",
                 "--window-px", "96", "--effects", EFFECTS, "--out", str(out)]) == 0
    return json.loads((out / "report.json").read_text()), (out / "report.md").read_text()


def _fabrication(report):
    return {s["effect"]: s["params"] for s in report["steps"] if not s["measurement_artefact"]}


@pytest.mark.slow
def test_a_mask_turned_by_0_15_degrees_is_named_a_rotation(tmp_path):
    case = _case(point, {"mask_rotation": {"mask": 2, "angle_deg": 0.15}}, 12)
    report, text = _diagnose(case, tmp_path)
    fab = _fabrication(report)
    assert list(fab) == ["mask_rotation"], fab
    angles = [fab["mask_rotation"][f"rotation_mask{j}_deg"] for j in (1, 2, 3)]
    assert abs(angles[1] - 0.15) < 0.2 * 0.15
    assert max(abs(angles[0]), abs(angles[2])) < 0.2 * 0.15
    assert report["final_residual_rms"] <= 1.3 * report["noise_floor"]
    assert "rotated about the design's centre" in text


@pytest.mark.slow
def test_an_etch_gradient_is_named_without_a_false_depth_error_and_says_where_it_is_referred(tmp_path):
    # 3 % per mm toward 30 degrees (x right, y up): +-2 nm across the 600 nm step over the field.
    per_mm, direction = 0.03, 30.0
    case = _case(boxcar, {"etch_gradient": {"per_mm": per_mm, "direction_deg": direction}}, 14)
    report, text = _diagnose(case, tmp_path)
    fab = _fabrication(report)
    assert list(fab) == ["etch_gradient"], fab
    truth = 1e3 * per_mm * np.array([np.cos(np.radians(direction)), np.sin(np.radians(direction))])
    fit = np.array([fab["etch_gradient"]["x_per_m"], fab["etch_gradient"]["y_per_m"]])
    assert np.hypot(*(fit - truth)) < 0.2 * np.hypot(*truth)
    assert report["final_residual_rms"] <= 1.3 * report["noise_floor"]
    # The report says what the gradient is referred to: the design's centre (the generator's too).
    assert "referred to the design's centre" in text
