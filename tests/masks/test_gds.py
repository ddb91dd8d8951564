"""GDS export: merged Manhattan polygons, independent read-back, CLI."""

import json

import gdstk
import numpy as np
import pytest

from doedesign.cli import main
from doedesign.design import Design
from doedesign.errors import DoeError
from masks.decompose import levels_to_masks
from masks.gds import export_masks
from masks.gds_read import read_gds_boundaries, read_library
from masks.grid import PixelGrid, rasterize_layer
from masks.layout import aperture_polygons
from masks.plate import PlateDesign, plate_layout, write_plate
from masks.verify import verify_file
from masks.polygons import mask_polygons

PITCH = 5.4e-6


def _levels(kind, shape=(96, 120), seed=0):
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[:shape[0], :shape[1]]
    if kind == "random":
        return rng.integers(0, 16, shape).astype(np.int16)
    return ((((xx - shape[1] / 2) ** 2 + (yy - shape[0] / 2) ** 2) // 30) % 16).astype(np.int16)


def _pixel_scan(mask_polys, shape):
    """Pixel-centre point-in-polygon test with gdstk.inside (a second, slow rasterizer)."""
    rows, cols = shape
    yy, xx = np.mgrid[:rows, :cols]
    centres = np.stack([xx.ravel() + 0.5, yy.ravel() + 0.5], 1)
    if not mask_polys:
        return np.zeros(shape, bool)
    return np.array(gdstk.inside(centres, [gdstk.Polygon(p) for p in mask_polys])).reshape(shape)


@pytest.mark.parametrize("kind", ["random", "rings"])
def test_polygons_manhattan_on_grid_no_overlap(kind):
    mask = levels_to_masks(_levels(kind))[1]
    ps = mask_polygons(mask)
    polys = ps.split()
    assert ps.max_vertices <= 199
    area = 0
    for p in polys:
        q = np.roll(p, -1, axis=0)
        assert np.all((p[:, 0] == q[:, 0]) | (p[:, 1] == q[:, 1])), "diagonal edge"
        area += abs(np.sum(p[:, 0] * q[:, 1] - q[:, 0] * p[:, 1])) / 2
    assert p.dtype.kind == "i"  # integer pixel-corner indices: every vertex on the grid
    assert area == mask.sum()  # no overlaps: polygon area equals the open pixel count
    assert np.array_equal(_pixel_scan(polys, mask.shape), mask)
    assert ps.n_polygons < mask.sum() / 2  # merged, not per-pixel boxes


def test_long_chains_split_below_199_vertices():
    # a staircase 400 rows tall: one chain of runs whose outline needs ~1600 vertices
    rows = 400
    mask = np.zeros((rows, rows + 10), bool)
    for r in range(rows):
        mask[r, r:r + 8] = True
    ps = mask_polygons(mask)
    assert ps.max_vertices <= 199
    # every row steps both edges: 4 vertices per row, 1600 in all -> at least 9 pieces
    assert 9 <= ps.n_polygons <= 10
    assert np.array_equal(_pixel_scan(ps.split(), mask.shape), mask)


def test_merged_rectangle_is_four_vertices():
    mask = np.zeros((20, 30), bool)
    mask[3:17, 5:25] = True
    ps = mask_polygons(mask)
    assert ps.n_polygons == 1 and ps.n_vertices == 4
    assert sorted(map(tuple, ps.vertices.tolist())) == [(5, 3), (5, 17), (25, 3), (25, 17)]


@pytest.mark.parametrize("tone", ["dark", "clear"])
@pytest.mark.parametrize("mirrored", [False, True])
def test_export_reads_back_exactly(tmp_path, tone, mirrored):
    levels = _levels("random")
    masks = levels_to_masks(levels)
    path = tmp_path / "d.gds"
    rep = export_masks(path, masks, PITCH, tone=tone, mirrored=mirrored, clear_aperture_m=0.3e-3)
    assert rep["verification"] == {**rep["verification"], "passed": True, "mismatched_pixels": 0}
    grid = PixelGrid.centred(levels.shape, PITCH, mirrored)
    lib = read_library(path)
    elem = [c for c in lib.cells if c.name == "ELEMENT"][0]
    recovered = []
    for j, layer in enumerate((1, 2, 3, 4)):
        pts = [p.points for p in elem.polygons if p.layer == layer]
        assert max(len(p) for p in pts) <= 199
        idx = [grid.to_index(p) for p in pts]
        assert all(np.allclose(i, np.rint(i), atol=1e-6) for i in idx)
        drawn = _pixel_scan(idx, levels.shape)
        recovered.append(drawn if tone == "dark" else ~drawn)
    weights = np.array([1, 2, 4, 8])[:, None, None]
    assert np.array_equal((np.array(recovered) * weights).sum(0), levels)
    # pixel (0, 0) corner: x = -cols p / 2 (mirrored: +), y = +rows p / 2
    x0 = 120 * 5.4 / 2 * (1 if mirrored else -1)
    assert rep["pixel_grid"]["origin_um"] == pytest.approx([x0, 96 * 5.4 / 2])
    assert rep["pixel_grid"]["mirrored"] is mirrored
    assert rep["tone"]["name"] == tone


def test_rasterizer_catches_bad_polygons():
    grid = PixelGrid.centred((10, 10), PITCH)
    good = grid.to_um(np.array([[0, 0], [0, 2], [3, 2], [3, 0]]))
    cov, probs = rasterize_layer([good, good], grid)
    assert cov.max() == 2 and cov.sum() == 12 and probs == []
    diag = grid.to_um(np.array([[0, 0], [0, 2], [3, 0]]))
    assert any("axis-parallel" in p for p in rasterize_layer([diag], grid)[1])
    off = grid.to_um(np.array([[0, 0], [0, 2.5], [3, 2.5], [3, 0]]))
    assert any("off the pixel grid" in p for p in rasterize_layer([off], grid)[1])


def test_aperture_pieces_cover_die_minus_circle():
    pieces = aperture_polygons(8.64e-3, 10e-3)
    assert max(len(p.points) for p in pieces) <= 199
    area = sum(p.area() for p in pieces)
    r = 4320.0
    # inscribed 720-gon: area (n/2) r^2 sin(2 pi / n)
    assert area == pytest.approx(1e8 - 360 * r ** 2 * np.sin(2 * np.pi / 720), rel=1e-9)
    with pytest.raises(DoeError):
        aperture_polygons(12e-3, 10e-3)


def test_marks_and_tests_outside_element(tmp_path):
    rep = export_masks(tmp_path / "m.gds", levels_to_masks(_levels("rings", (64, 64))), PITCH)
    lib = read_library(tmp_path / "m.gds")
    names = {c.name for c in lib.cells}
    assert {"ELEMENT", "MARKS_design", "TEST_design"} <= names
    marks = [c for c in lib.cells if c.name == "MARKS_design"][0]
    # vernier: main pitch 10 um on layer 1, 9.75 um on the later mask -> 0.25 um reading
    bars2 = sorted({round(p.bounding_box()[0][0] + 2, 3) for p in marks.polygons
                    if p.layer == 2 and p.bounding_box()[1][1] - p.bounding_box()[0][1] in (40, 50)})
    assert np.any(np.isclose(np.diff(bars2), 9.75))
    assert rep["file_size_bytes"] > 0


def test_plate_layout_four_designs(tmp_path):
    designs = [PlateDesign(n, levels_to_masks(_levels("random", (40, 40), seed=i)), PITCH, 0.15e-3)
               for i, n in enumerate(["HDR", "hyperspectral", "depth", "Bayer"])]
    lib, dies = plate_layout(designs)
    res = write_plate(tmp_path / "plate.gds", lib, dies)
    assert all(r["passed"] for r in res.values()) and len(res) == 4
    with pytest.raises(DoeError, match="outside the wafer"):
        plate_layout(designs * 1 + [PlateDesign(f"x{i}", designs[0].masks, PITCH) for i in range(30)])


def _design_file(tmp_path, levels=None, height=None, name="lens"):
    step = 74.74e-9
    lv = _levels("rings", (64, 80)) if levels is None else levels
    h = -lv * step if height is None else height
    d = Design(h, PITCH, levels=lv if height is None else None,
               metadata={"name": name, "camera": {"aperture_diameter_m": 0.3e-3}})
    p = tmp_path / f"{name}.npz"
    d.save(p)
    return p


def test_cli_masks_writes_verified_outputs(tmp_path):
    p = _design_file(tmp_path)
    out = tmp_path / "out"
    assert main(["masks", str(p), "--out", str(out), "--mirror", "--tone", "clear", "--format", "both"]) == 0
    rep = json.loads((out / "report.json").read_text())
    assert rep["verification"]["passed"] and rep["verification"]["mismatched_pixels"] == 0
    assert [layer["layer"] for layer in rep["layers"]] == [1, 2, 3, 4]
    assert rep["layers"][3]["etch_depth_nm"] == pytest.approx(8 * 74.74, abs=0.1)
    assert all(layer["max_vertices"] <= 199 for layer in rep["layers"])
    assert rep["pixel_grid"]["rows"] == "toward decreasing y" and rep["pixel_grid"]["mirrored"]
    assert (out / "lens.gds").stat().st_size == rep["file_size_bytes"]
    assert (out / "lens.oas").exists() and (out / "masks.png").exists()


def test_cli_quantizes_heights(tmp_path):
    rng = np.random.default_rng(3)
    p = _design_file(tmp_path, height=-rng.uniform(0, 1.19e-6, (40, 40)), name="cont")
    out = tmp_path / "o"
    assert main(["masks", str(p), "--out", str(out), "--depths-nm", "75,150,300,600"]) == 0
    q = json.loads((out / "report.json").read_text())["quantization"]
    assert q["rms_error_nm"] == pytest.approx(74.74 / np.sqrt(12), rel=0.1)


@pytest.mark.parametrize("case", ["levels16", "nan", "layers", "missing"])
def test_cli_bad_input_exit_2_no_file(tmp_path, case, capsys):
    args = []
    if case == "levels16":
        lv = _levels("rings", (20, 20))
        lv[0, 0] = 16
        p = _design_file(tmp_path, levels=lv)
    elif case == "nan":
        p = tmp_path / "nan.npz"
        np.savez(p, height_m=np.full((4, 4), np.nan), pitch_m=PITCH, material="fused_silica",
                 design_wavelength_m=550e-9, metadata="{}")
    elif case == "layers":
        p = _design_file(tmp_path)
        args = ["--layers", "1,2,3"]
    else:
        p = tmp_path / "nothing.npz"
    out = tmp_path / "out"
    assert main(["masks", str(p), "--out", str(out)] + args) == 2
    err = capsys.readouterr().err
    assert "error" in err and "Traceback" not in err
    assert not out.exists() or not any(out.iterdir())


def test_verification_failure_leaves_no_file(tmp_path, monkeypatch):
    import masks.gds_records as g
    from masks.polygons import PolygonSet

    real = g.mask_polygons

    def drop_last(mask, max_vertices=199):
        ps = real(mask, max_vertices)
        return PolygonSet(ps.vertices[:ps.offsets[-2]], ps.offsets[:-1])

    monkeypatch.setattr(g, "mask_polygons", drop_last)
    with pytest.raises(DoeError, match="verification failed"):
        export_masks(tmp_path / "bad.gds", levels_to_masks(_levels("random", (30, 30))), PITCH)
    assert list(tmp_path.iterdir()) == []


def _shoelace_area(polys):
    return sum(abs(np.sum(p[:, 0] * np.roll(p[:, 1], -1) - np.roll(p[:, 0], -1) * p[:, 1])) / 2
               for p in polys)


@pytest.mark.parametrize("case, corners", [("edge", 4 + 4 + 3), ("corner_above", 6 + 4 + 2),
                                           ("corner_below", 6 + 4 + 2)])
def test_hole_joined_by_keyhole_cut(case, corners):
    # one component with one hole -> one polygon: outer + hole corners + the cut's vertices
    # (3 when the cut ends inside an edge, 2 when it ends at a concave corner)
    mask = np.zeros((10, 12), bool)
    if case == "edge":
        mask[0:10, 0:10] = True
    elif case == "corner_above":
        mask[0:3, 0:10] = True
        mask[3:8, 2:10] = True
    else:
        mask[0:3, 2:10] = True
        mask[3:8, 0:10] = True
    mask[3:5, 5:7] = False
    ps = mask_polygons(mask)
    assert ps.n_polygons == 1 and ps.n_vertices == corners
    p = ps.vertices
    q = np.roll(p, -1, axis=0)
    assert np.all((p[:, 0] == q[:, 0]) | (p[:, 1] == q[:, 1]))
    assert _shoelace_area(ps.split()) == mask.sum()
    assert np.array_equal(_pixel_scan(ps.split(), mask.shape), mask)


@pytest.mark.parametrize("density", [0.3, 0.5, 0.62, 0.8])
def test_full_merge_random_masks(density):
    from scipy import ndimage

    rng = np.random.default_rng(int(density * 100))
    mask = rng.random((70, 90)) < density
    # nested rings (islands inside holes inside islands), kept apart from the random pixels
    mask[19:51, 19:51] = False
    mask[20:50, 20:50] = True
    mask[24:46, 24:46] = False
    mask[28:42, 28:42] = True
    mask[31:39, 31:39] = False
    ps = mask_polygons(mask)
    polys = ps.split()
    assert ps.max_vertices <= 199
    for p in polys:
        q = np.roll(p, -1, axis=0)
        assert np.all((p[:, 0] == q[:, 0]) | (p[:, 1] == q[:, 1])), "diagonal edge"
    assert _shoelace_area(polys) == mask.sum()  # no overlaps, no gaps
    assert np.array_equal(_pixel_scan(polys, mask.shape), mask)
    labels, n_comp = ndimage.label(mask)
    if density <= 0.5:
        # every 4-connected component is small: exactly one polygon each, holes included
        assert ps.n_polygons == n_comp
    else:
        assert ps.n_polygons >= n_comp


def test_reader_ignores_header_lookalikes_in_coordinates(tmp_path):
    # coordinates whose bytes spell a complete fake BOUNDARY element (header, LAYER 1,
    # DATATYPE 0, XY of 4 points, ENDEL) inside a real polygon's XY record
    fake = [(0x00040800, 0x00060D02), (0x00010006, 0x0E020000), ((36 << 16) | 0x1003, 7),
            (1, 2), (3, 4), (5, 6), (7, 0x00041100), (9, 10)]
    lib = gdstk.Library(unit=1e-6, precision=1e-9)
    cell = gdstk.Cell("C")
    cell.add(gdstk.Polygon(np.array(fake, float) * 1e-3, layer=5, datatype=3))
    cell.add(gdstk.rectangle((0, 0), (2, 1), layer=7))
    lib.add(cell)
    path = tmp_path / "fake.gds"
    lib.write_gds(str(path))
    read = read_gds_boundaries(path)
    assert read.dbu_m == pytest.approx(1e-9)
    c = read.cells["C"]
    assert c["layer"].tolist() == [5, 7] and c["datatype"].tolist() == [3, 0]
    assert c["counts"].tolist() == [8, 4]
    pts = read.points("C")
    assert np.array_equal(pts[:8], np.array(fake))
    assert sorted(map(tuple, pts[8:].tolist())) == [(0, 0), (0, 1000), (2000, 0), (2000, 1000)]


def test_reader_matches_gdstk_and_klayout_on_export(tmp_path):
    masks = levels_to_masks(_levels("random", (80, 70), seed=5))
    path = tmp_path / "r.gds"
    export_masks(path, masks, PITCH, tone="dark", clear_aperture_m=0.3e-3)
    read = read_gds_boundaries(path)
    lib = read_library(path)
    for c in lib.cells:
        ours = read.cells[c.name]
        assert ours["counts"].size == len(c.polygons)
        theirs = sorted((p.layer, p.datatype, tuple(np.rint(p.points * 1000).astype(int).ravel()))
                        for p in c.polygons)
        pts = read.points(c.name)
        first = np.cumsum(ours["counts"]) - ours["counts"]
        mine = sorted((int(ly), int(dt), tuple(pts[f:f + k].ravel()))
                      for ly, dt, f, k in zip(ours["layer"], ours["datatype"], first, ours["counts"]))
        assert mine == theirs
    db = pytest.importorskip("klayout.db")
    ly = db.Layout()
    ly.read(str(path))
    elem = ly.cell("ELEMENT")
    p = int(round(PITCH * 1e9))
    for j in range(4):
        area = db.Region(elem.begin_shapes_rec(ly.layer(j + 1, 0))).area()
        assert area == int(masks[j].sum()) * p * p


def test_verify_catches_byte_level_corruption(tmp_path):
    masks = levels_to_masks(_levels("rings", (40, 50)))
    path = tmp_path / "c.gds"
    export_masks(path, masks, PITCH)
    grid = PixelGrid.centred((40, 50), PITCH)
    data = bytearray(path.read_bytes())
    # first element of the ELEMENT cell: shift its first x by 1 nm (off the pixel grid)
    at = data.index(b"ELEMENT")
    at = data.index(bytes([0, 4, 8, 0]), at) + 20
    x = int.from_bytes(data[at:at + 4], "big", signed=True) + 1
    data[at:at + 4] = x.to_bytes(4, "big", signed=True)
    bad = tmp_path / "bad.gds"
    bad.write_bytes(bytes(data))
    assert verify_file(path, masks, grid)["passed"]
    res = verify_file(bad, masks, grid)
    assert not res["passed"] and any("off the pixel grid" in p for p in res["problems"])


def test_skeleton_temporary_is_named_for_cleanup(tmp_path):
    """A killed run's GDS skeleton must be found by the next run's temporary cleanup."""
    import os
    from pathlib import Path

    from doedesign.fileio import remove_stale_temporaries
    from masks.gds_records import write_element_gds

    lib = gdstk.Library(unit=1e-6, precision=1e-9)
    lib.add(gdstk.Cell("ELEMENT"))
    seen = []

    class Recorder:  # the library, recording where the skeleton is written
        def write_gds(self, name, **kwargs):
            seen.append(name)
            lib.write_gds(name, **kwargs)

    masks = levels_to_masks(_levels("rings", (20, 20)))
    write_element_gds(Recorder(), tmp_path / "x.gds", masks, PixelGrid.centred((20, 20), PITCH))
    (skeleton,) = [Path(n).name for n in seen]
    assert not (tmp_path / skeleton).exists()  # removed after use
    # left behind by a dead process (above Linux's largest pid), the next run removes it
    dead = skeleton.replace(f".{os.getpid()}-", f".{2 ** 22 + 1}-")
    (tmp_path / dead).write_bytes(b"")
    assert remove_stale_temporaries(tmp_path) == [dead]
