"""`doe diagnose` on files measured by the tests' own instruments (``tests/metrology/instruments``),
which are not the diagnosis's instrument model."""

import json

import numpy as np
import pytest

import filegen
from doedesign.cli import main
from instruments import point


def _point_case(truth, seed, design_px=40, field_px=130):
    rng = np.random.default_rng(seed)
    levels = filegen.random_levels((design_px, design_px), rng)
    surface = filegen.wafer_surface(levels, truth)
    height, inst = point.measure(surface, filegen.FINE_PER_PX, levels.shape, (field_px, field_px), rng)
    return filegen.FileCase(levels=levels, truth=truth, instrument=inst, height_m=height, seed=seed)


# Failed before the instrument's transfer was fitted (a false etch_loading beside the overlay).
@pytest.mark.slow
def test_point_sampling_camera_overlay_is_named_with_its_mask_and_shift(tmp_path):
    shift = 0.45e-6 * np.array([np.cos(2.2), np.sin(2.2)])
    case = _point_case({"mask_overlay": {"mask": 2, "shift_m": shift}}, 31)
    design, measured = case.write(tmp_path)
    out = tmp_path / "diag"
    assert main(["diagnose", "--design", str(design), "--measured", str(measured), "--out", str(out)]) == 0
    report = json.loads((out / "report.json").read_text())
    fab = {s["effect"]: s["params"] for s in report["steps"] if not s["measurement_artefact"]}
    assert list(fab) == ["mask_overlay"]
    params = fab["mask_overlay"]
    fit = np.array([[params[f"dx_mask{j}_m"], params[f"dy_mask{j}_m"]] for j in range(1, 4)])
    # The right mask moved by the right vector; the others stay within a tenth of it.
    assert np.hypot(*(fit[1] - shift)) < 0.1 * np.hypot(*shift)
    assert np.hypot(fit[[0, 2], 0], fit[[0, 2], 1]).max() < 0.1 * np.hypot(*shift)
    assert report["final_residual_rms"] <= 1.3 * report["noise_floor"]
