"""Edge offsets of mask polygons (masks.offset, masks.corrected): the drawn geometry is the
Chebyshev offset of the pixel mask, checked against gdstk's own point-in-polygon test, and the
read-back check catches a geometry off by one database unit."""

from pathlib import Path

import gdstk
import numpy as np
import pytest

from doedesign.design import Design
from doedesign.errors import DoeError
from masks.corrected import narrowest_runs_px, offset_feasibility, write_offset_element
from masks.gds_read import read_boundaries
from masks.grid import MAX_VERTICES, PixelGrid
from masks.offset import offset_polygons, verify_offset_layer

PITCH = 5.4e-6


def _mask(seed=0, shape=(24, 24)):
    rng = np.random.default_rng(seed)
    m = rng.random(shape) < 0.5
    m[8:16, 8:16] = True
    m[10:13, 10:13] = False  # a hole
    return m


def _written(tmp_path, mask, grid, offset):
    lib = gdstk.Library(unit=1e-6, precision=1e-9)
    lib.new_cell("ELEMENT").add(*offset_polygons(mask, grid, offset, 1))
    lib.write_gds(str(tmp_path / "t.gds"), max_points=199)
    read = read_boundaries(tmp_path / "t.gds")
    return read.points("ELEMENT"), read.cells["ELEMENT"]["counts"]


def _random(seed, shape):
    return np.random.default_rng(seed).random(shape) < 0.5


def _chebyshev_inside(mask, grid, offset, polys, n=4000, seed=1):
    """gdstk's point-in-polygon test at random points against the Chebyshev distance of each
    point to the nearest open / closed pixel (in um): independent of this package. Half the
    points lie within 1.5 |offset| of a pixel line (where a slit or a missing strip would be)."""
    rng = np.random.default_rng(seed)
    rows, cols = mask.shape
    idx = rng.uniform(-1, (cols + 1, rows + 1), (n, 2))  # (col, row) in pixels
    near = np.arange(n) < n // 2
    axis = rng.integers(0, 2, n)
    line = rng.integers(0, cols + 1, n), rng.integers(0, rows + 1, n)
    band = 1.5 * max(abs(offset), 1e-7) / PITCH
    idx[near & (axis == 0), 0] = line[0][near & (axis == 0)] + rng.uniform(-band, band, (near & (axis == 0)).sum())
    idx[near & (axis == 1), 1] = line[1][near & (axis == 1)] + rng.uniform(-band, band, (near & (axis == 1)).sum())
    inside = np.array(gdstk.inside(grid.to_um(idx), polys))
    col, row = idx[:, 0], idx[:, 1]
    padded = np.pad(mask, 2)
    dist_out = np.full(n, np.inf)  # to the openings, 0 inside (only pixels within one matter)
    dist_in = np.full(n, np.inf)  # to the closed areas, 0 outside
    for dr in (-1, 0, 1):
        for dc in (-1, 0, 1):
            rr, cc = np.floor(row).astype(int) + dr, np.floor(col).astype(int) + dc
            dx = np.maximum(np.abs(col - (cc + 0.5)) - 0.5, 0)
            dy = np.maximum(np.abs(row - (rr + 0.5)) - 0.5, 0)
            d = np.maximum(dx, dy) * PITCH * 1e6
            is_open = padded[rr + 2, cc + 2]
            dist_out = np.where(is_open, np.minimum(dist_out, d), dist_out)
            dist_in = np.where(~is_open, np.minimum(dist_in, d), dist_in)
    want = (dist_out <= offset * 1e6) if offset >= 0 else (dist_in > -offset * 1e6)
    clear = np.abs(dist_out - dist_in - offset * 1e6) > 1e-3  # more than 1 nm from the offset edge
    assert clear.sum() > 0.9 * n
    return inside[clear], want[clear]


@pytest.mark.parametrize("offset", [0.3e-6, -0.3e-6, 0.0])
@pytest.mark.parametrize("mirrored", [False, True])
def test_offset_geometry_is_the_chebyshev_offset_of_the_pixels(tmp_path, offset, mirrored):
    mask = _mask()
    grid = PixelGrid.centred(mask.shape, PITCH, mirrored)
    polys = offset_polygons(mask, grid, offset, 1)
    inside, want = _chebyshev_inside(mask, grid, offset, polys)
    assert np.array_equal(inside, want)
    pts, counts = _written(tmp_path, mask, grid, offset)
    res = verify_offset_layer(pts, counts, mask, grid, offset)
    assert res["mismatched_samples"] == 0 and not res["problems"], res


@pytest.mark.parametrize("mask", [_random(4, (60, 60)), _random(5, (97, 120)), _random(6, (120, 83)),
                                  np.pad(_mask(7), 40)], ids=["60", "97x120", "120x83", "hole"])
@pytest.mark.parametrize("offset", [-0.05e-6, -0.173e-6, -0.3e-6, 0.211e-6])
@pytest.mark.parametrize("mirrored", [False, True])
def test_shrunk_openings_have_no_slits_on_large_random_masks(tmp_path, mask, offset, mirrored):
    # Random 50 % masks: holes, diagonal pixels, components split at the vertex limit. Shrinking
    # the merged pixel polygons opened their keyhole cuts and splits into slits.
    grid = PixelGrid.centred(mask.shape, PITCH, mirrored)
    polys = offset_polygons(mask, grid, offset, 1)
    assert max(p.points.shape[0] for p in polys) <= MAX_VERTICES
    inside, want = _chebyshev_inside(mask, grid, offset, polys, n=6000, seed=mask.shape[0])
    assert np.array_equal(inside, want), int((inside != want).sum())
    pts, counts = _written(tmp_path, mask, grid, offset)
    res = verify_offset_layer(pts, counts, mask, grid, offset)
    assert res["mismatched_samples"] == 0 and not res["problems"], res


def test_offset_of_half_the_pitch_is_refused():
    grid = PixelGrid.centred((4, 4), PITCH)
    with pytest.raises(DoeError, match="half the 5.4 um pixel"):
        offset_polygons(np.ones((4, 4), bool), grid, -2.7e-6, 1)
    assert "half the 5.4 um pixel" in offset_feasibility(np.ones((4, 4), bool), PITCH, 2.7e-6)


def test_read_back_check_catches_one_database_unit(tmp_path):
    mask = _mask(2)
    grid = PixelGrid.centred(mask.shape, PITCH)
    pts, counts = _written(tmp_path, mask, grid, -0.25e-6)
    assert verify_offset_layer(pts, counts, mask, grid, -0.25e-6)["problems"] == []
    off = verify_offset_layer(pts, counts, mask, grid, -0.251e-6)
    assert off["mismatched_samples"] > 0 and off["vertices_off_lines"] > 0
    moved = pts.copy()
    moved[counts[0]:counts[0] + counts[1], 0] += 1  # one polygon shifted by 1 nm
    assert verify_offset_layer(moved, counts, mask, grid, -0.25e-6)["mismatched_samples"] > 0


def test_narrowest_features_and_feasibility():
    m = np.zeros((10, 10), bool)
    m[2, 2:4] = True   # 1 px tall opening, 2 px wide
    m[2, 5:9] = True   # 1 px gap between the two at column 4
    assert narrowest_runs_px(m) == (1, 1)
    assert offset_feasibility(m, PITCH, -0.3e-6) is None
    assert "openings" in offset_feasibility(m, PITCH, -2.3e-6)
    assert "gaps" in offset_feasibility(m, PITCH, 2.3e-6)
    assert "cross" in offset_feasibility(m, PITCH, 2.8e-6)


def test_offset_element_writes_the_doe_masks_layout_and_labels(tmp_path):
    levels = np.random.default_rng(3).integers(0, 16, (20, 20)).astype(np.int16)
    levels[5:12, 5:12] = 15
    design = Design(height_m=-levels * 75e-9, pitch_m=PITCH, levels=levels)
    rep = write_offset_element(design, tmp_path, [-0.2e-6, 0.0, 0.1e-6, -0.3e-6], notes={0: "edges -0.200 um"})
    assert rep["verification"]["passed"] and (tmp_path / "design.lyp").is_file()
    lib = gdstk.read_gds(rep["file"])
    names = {c.name for c in lib.cells}
    assert {"ELEMENT", "DIE_design"} <= names
    layers = {(p.layer, p.datatype) for c in lib.cells if c.name == "ELEMENT" for p in c.polygons}
    assert layers == {(1, 0), (2, 0), (3, 0), (4, 0)}
    assert [entry["edge_offset_um"] for entry in rep["layers"]] == pytest.approx([-0.2, 0.0, 0.1, -0.3])
    with pytest.raises(DoeError, match="mask 0.*cannot be drawn"):
        write_offset_element(design, tmp_path / "bad", [-2.5e-6, 0, 0, 0])


def test_offset_element_with_shrunk_masks_on_a_110_px_random_design(tmp_path):
    levels = np.random.default_rng(8).integers(0, 16, (110, 110)).astype(np.int16)
    design = Design(height_m=-levels * 75e-9, pitch_m=PITCH, levels=levels)
    rep = write_offset_element(design, tmp_path, [-0.194e-6, -0.05e-6, 0.1e-6, -0.3e-6], mirrored=True)
    assert rep["verification"]["passed"] and Path(rep["file"]).is_file()
    assert all(c["mismatched_samples"] == 0 and c["polygons"] > 100 for c in rep["verification"]["layers"])
