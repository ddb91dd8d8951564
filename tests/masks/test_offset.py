"""Edge offsets of mask polygons (masks.offset, masks.corrected): the drawn geometry is the
Chebyshev offset of the pixel mask, checked against gdstk's own point-in-polygon test, and the
read-back check catches a geometry off by one database unit."""

import gdstk
import numpy as np
import pytest

from doedesign.design import Design
from doedesign.errors import DoeError
from masks.corrected import narrowest_runs_px, offset_feasibility, write_offset_element
from masks.gds_read import read_boundaries
from masks.grid import PixelGrid
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


@pytest.mark.parametrize("offset", [0.3e-6, -0.3e-6, 0.0])
@pytest.mark.parametrize("mirrored", [False, True])
def test_offset_geometry_is_the_chebyshev_offset_of_the_pixels(tmp_path, offset, mirrored):
    mask = _mask()
    grid = PixelGrid.centred(mask.shape, PITCH, mirrored)
    polys = offset_polygons(mask, grid, offset, 1)
    # Independent of this package: gdstk's point-in-polygon test at random points, against the
    # distance of each point to the nearest open pixel (Chebyshev, in um).
    rng = np.random.default_rng(1)
    idx = rng.uniform(-1, mask.shape[1] + 1, (4000, 2))  # (col, row) in pixels
    xy = grid.to_um(idx)
    inside = np.array(gdstk.inside(xy, polys))
    col, row = idx[:, 0], idx[:, 1]
    rr, cc = np.nonzero(mask)
    dx = np.maximum(np.abs(col[:, None] - (cc + 0.5)) - 0.5, 0)
    dy = np.maximum(np.abs(row[:, None] - (rr + 0.5)) - 0.5, 0)
    dist_out = np.maximum(dx, dy).min(axis=1) * PITCH * 1e6  # to the openings, 0 inside
    rr, cc = np.nonzero(~np.pad(mask, 3))
    rr, cc = rr - 3, cc - 3
    dx = np.maximum(np.abs(col[:, None] - (cc + 0.5)) - 0.5, 0)
    dy = np.maximum(np.abs(row[:, None] - (rr + 0.5)) - 0.5, 0)
    dist_in = np.maximum(dx, dy).min(axis=1) * PITCH * 1e6  # to the closed areas, 0 outside
    want = (dist_out <= offset * 1e6) if offset >= 0 else (dist_in > -offset * 1e6)
    clear = np.minimum(np.abs(dist_out - max(offset, 0) * 1e6), np.abs(dist_in + min(offset, 0) * 1e6)) > 1e-3
    assert np.array_equal(inside[clear], want[clear])
    pts, counts = _written(tmp_path, mask, grid, offset)
    res = verify_offset_layer(pts, counts, mask, grid, offset)
    assert res["mismatched_samples"] == 0 and not res["problems"], res


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
