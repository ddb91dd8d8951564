"""`doe compare` on an 8-level and a binary element made by the tests' own wafer generator
(tests/metrology/filegen.py, which shares no code with the model): the comparison fits the
design's own masks (3 and 1) and names the hidden depth error of the mask that carries it.

The generator etches masks of 75, 150, 300 and 600 nm; an 8-level design (step 149.5 nm,
fused silica at 550 nm) is made of its masks 1-3 (levels 0, 2, .., 14 of the generator), a
binary one (step 598 nm) of its mask 3 alone.
"""

import json

import numpy as np
import pytest

from doedesign.cli import main
from doedesign.design import Design

from . import filegen


def _case(tmp_path, n_levels, error, seed):
    rng = np.random.default_rng(seed)
    gen16 = filegen.random_levels((48, 48), rng)
    factor = 16 // n_levels
    design_levels = (gen16 // factor).astype(np.int16)
    truth_err = np.zeros(4)
    first = 4 - int(np.log2(n_levels))  # generator mask of the design's mask 0
    truth_err[first:] = error
    case = filegen.make_case([], seed, levels=design_levels * factor, truth={"etch_depth": {"error": truth_err}})
    depths = [filegen.DEPTHS_M[first + j] for j in range(4 - first)]
    height = -np.array(depths) @ filegen.masks_of(design_levels * factor)[first:].reshape(4 - first, -1)
    meta = {"n_levels": n_levels, "mask_depths_m": depths, "name": f"e{n_levels}"}
    design = Design(height.reshape(design_levels.shape), filegen.PITCH_M, levels=design_levels, metadata=meta)
    d = tmp_path / "design.npz"
    design.save(d)
    m = tmp_path / "measured.datx"
    from metrology.formats.writers import write_datx
    write_datx(m, case.height_m, case.instrument["header_pixel_m"])
    return d, m, depths


@pytest.mark.parametrize("n_levels, error", [(8, [0.0, 0.06, 0.0]), (2, [-0.05])])
def test_compare_fits_the_designs_own_masks_and_names_the_depth_error(tmp_path, n_levels, error):
    d, m, depths = _case(tmp_path, n_levels, error, seed=5)
    out = tmp_path / "cmp"
    assert main(["compare", str(m), "--design", str(d), "--out", str(out), "--no-psf", "--no-render"]) == 0
    rep = json.loads((out / "report.json").read_text())
    fitted = np.array(rep["etch_depths_nm"])
    assert fitted.size == int(np.log2(n_levels))
    truth = np.array(depths) * (1 + np.array(error)) * 1e9
    assert fitted == pytest.approx(truth, abs=4.0)


def _diagnose(tmp_path, d, m, effects):
    from .fabloop import diagnose, named_params
    return named_params(diagnose(main, d, m, tmp_path / "diag", window_px=72, effects=effects))


def test_diagnose_names_a_hidden_overlay_of_an_8_level_elements_own_mask(tmp_path):
    rng = np.random.default_rng(11)
    gen16 = filegen.random_levels((48, 48), rng)
    design_levels = (gen16 // 2).astype(np.int16)
    shift = np.array([0.45e-6, -0.2e-6])
    # The generator's mask 3 is the 8-level design's mask 2.
    case = filegen.make_case([], 11, levels=design_levels * 2, truth={"mask_overlay": {"mask": 3, "shift_m": shift}})
    depths = list(filegen.DEPTHS_M[1:])
    height = -np.array(depths) @ filegen.masks_of(design_levels * 2)[1:].reshape(3, -1)
    Design(height.reshape(design_levels.shape), filegen.PITCH_M, levels=design_levels,
           metadata={"n_levels": 8, "mask_depths_m": depths, "name": "e8"}).save(tmp_path / "design.npz")
    from metrology.formats.writers import write_datx
    write_datx(tmp_path / "measured.datx", case.height_m, case.instrument["header_pixel_m"])
    named = _diagnose(tmp_path, tmp_path / "design.npz", tmp_path / "measured.datx", "mask_overlay,linewidth_bias")
    assert set(named) == {"mask_overlay"}
    p = named["mask_overlay"]
    assert set(p) == {"dx_mask1_m", "dy_mask1_m", "dx_mask2_m", "dy_mask2_m"}
    assert p["dx_mask2_m"][0] == pytest.approx(shift[0], abs=0.08e-6)
    assert p["dy_mask2_m"][0] == pytest.approx(shift[1], abs=0.08e-6)
    assert abs(p["dx_mask1_m"][0]) < 0.08e-6 and abs(p["dy_mask1_m"][0]) < 0.08e-6


def test_diagnose_names_the_depth_error_of_a_binary_element(tmp_path):
    d, m, depths = _case(tmp_path, 2, [0.05], seed=7)
    named = _diagnose(tmp_path, d, m, "etch_depth,linewidth_bias")
    assert set(named) == {"etch_depth"}
    assert set(named["etch_depth"]) == {"depth_error_mask0"}
    assert named["etch_depth"]["depth_error_mask0"][0] == pytest.approx(0.05, abs=0.01)
