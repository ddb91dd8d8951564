"""`doe masks` on 2-, 8- and 32-level designs: M = log2(N) masks, M GDS layers, read back and
verified, the level map rebuilt from the masks' bits and the etch depths 2**j level steps."""

import json

import gdstk
import numpy as np
import pytest

from doedesign.cli import main
from doedesign.design import Design
from masks.decompose import levels_to_masks, masks_to_levels


@pytest.mark.parametrize("n_levels", [2, 8, 32])
def test_doe_masks_writes_log2_n_verified_layers(tmp_path, n_levels):
    rng = np.random.default_rng(n_levels)
    levels = np.kron(rng.integers(0, n_levels, (12, 12)), np.ones((3, 3), int)).astype(np.int16)
    probe = Design(np.zeros(levels.shape), 5.4e-6, metadata={"n_levels": n_levels})
    design = Design(-levels * probe.level_step_m(), 5.4e-6, levels=levels,
                    metadata={"n_levels": n_levels, "name": f"g{n_levels}"})
    path = tmp_path / "d.npz"
    design.save(path)
    assert Design.load(path).n_levels == n_levels
    out = tmp_path / "m"
    assert main(["masks", str(path), "--out", str(out)]) == 0
    rep = json.loads((out / "report.json").read_text())
    n_masks = int(np.log2(n_levels))
    assert rep["n_levels"] == n_levels
    assert rep["verification"]["passed"] and rep["verification"]["mismatched_pixels"] == 0
    step = probe.level_step_m()
    layers = {lay["layer"]: lay for lay in rep["layers"]}
    assert sorted(layers) == list(range(1, n_masks + 1))
    assert [lay["etch_depth_nm"] for lay in rep["layers"]] == pytest.approx([step * 2 ** j * 1e9 for j in range(n_masks)])
    lib = gdstk.read_gds(str(out / "g{}.gds".format(n_levels)))
    drawn = {(p.layer) for cell in lib.cells for p in cell.polygons}
    assert set(range(1, n_masks + 1)) <= drawn
    assert np.array_equal(masks_to_levels(levels_to_masks(levels, n_masks)), levels)


def test_a_level_beyond_the_count_or_a_bad_count_is_refused(tmp_path):
    levels = np.array([[0, 1], [2, 1]], np.int16)
    bad = Design(-levels * 598e-9, 5.4e-6, levels=levels, metadata={"n_levels": 2})
    bad.save(tmp_path / "bad.npz")
    assert main(["masks", str(tmp_path / "bad.npz"), "--out", str(tmp_path / "o")]) == 2
    assert not (tmp_path / "o" / "report.json").exists()
    with pytest.raises(Exception, match="2, 4, 8, 16, 32"):
        Design(np.zeros((2, 2)), 5.4e-6, metadata={"n_levels": 12})
    with pytest.raises(Exception, match="mask_depths_m must list 3"):
        Design(np.zeros((2, 2)), 5.4e-6, metadata={"n_levels": 8, "mask_depths_m": [1e-7, 2e-7]})
