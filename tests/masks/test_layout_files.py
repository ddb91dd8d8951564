"""The files a mask shop and a layout engineer ask for: OASIS beside GDSII, a vertex limit with
fracturing, and KLayout layer properties; each checked by KLayout, independent of gdstk."""

import json
import xml.etree.ElementTree as ET

import gdstk
import numpy as np
import pytest

from doedesign.cli import main
from doedesign.design import Design
from doedesign.errors import DoeError
from masks.decompose import levels_to_masks
from masks.gds import export_masks
from masks.grid import DEFAULT_LAYERS, PixelGrid, vertex_limits
from masks.polygons import mask_polygons
from masks.verify import verify_file

db = pytest.importorskip("klayout.db")

PITCH = 5.4e-6
P_DBU = 5400
STEP_M = 74.74e-9


def _rings(n=120, seed=0):
    """Fresnel-like rings (outlines of several hundred vertices) with random pixels sprinkled in."""
    yy, xx = np.mgrid[:n, :n] - n / 2
    levels = ((xx ** 2 + yy ** 2) // (n // 2) % 16).astype(np.int16)
    rng = np.random.default_rng(seed)
    spots = rng.random((n, n)) < 0.03
    levels[spots] = rng.integers(0, 16, int(spots.sum()))
    return levels


def _layout(path):
    ly = db.Layout()
    ly.read(str(path))
    return ly


def _region(ly, layer, datatype=0, merged=True, cell=None):
    top = ly.top_cell() if cell is None else ly.cell(cell)
    r = db.Region(top.begin_shapes_rec(ly.layer(layer, datatype)))
    r.merged_semantics = merged
    return r


def _polygons(ly, layer):
    """Every polygon KLayout reads on a layer (all cells, as written, not merged)."""
    li = ly.layer(layer, 0)
    polys = [s.polygon for c in ly.each_cell() for s in c.shapes(li).each()
             if s.is_polygon() or s.is_simple_polygon() or s.is_box()]
    assert polys, f"no polygons on layer {layer}"
    return polys


def _same_geometry(ly_a, ly_b, layers):
    for layer in layers:
        a, b = _region(ly_a, layer), _region(ly_b, layer)
        assert (a ^ b).is_empty(), f"layer {layer}: XOR not empty"
        assert a.area() == b.area()


@pytest.mark.parametrize("tone, mirrored", [("dark", False), ("clear", True)])
def test_oasis_holds_the_gds_geometry_and_is_smaller(tmp_path, tone, mirrored):
    levels = _rings()
    masks = levels_to_masks(levels)
    rep = export_masks(tmp_path / "d.gds", masks, PITCH, tone=tone, mirrored=mirrored, clear_aperture_m=0.5e-3,
                       formats=("gds", "oasis"), name="d")
    gds, oas = rep["files"]
    assert (gds["format"], gds["max_vertices"], oas["format"], oas["max_vertices"]) == ("gds", 199, "oasis", None)
    assert gds["verification"]["passed"] and oas["verification"]["passed"]
    assert oas["file"].endswith("d.oas") and oas["file_size_bytes"] < gds["file_size_bytes"] / 2
    ly_g, ly_o = _layout(gds["file"]), _layout(oas["file"])
    # every layer, marks, labels, aperture and outline included, is the same set of points
    _same_geometry(ly_g, ly_o, list(DEFAULT_LAYERS) + [10, 11])
    # the mask layers are the design's pixels: area = open pixels x pixel area
    for j, layer in enumerate(DEFAULT_LAYERS):
        drawn = masks[j] if tone == "dark" else ~masks[j]
        elem = db.Region(ly_o.cell("ELEMENT").begin_shapes_rec(ly_o.layer(layer, 0)))
        assert elem.area() == int(drawn.sum()) * P_DBU ** 2
    # unlimited OASIS: each ring is one polygon, where the GDSII needs pieces of <= 199
    most_o = max(p.num_points() for p in _polygons(ly_o, DEFAULT_LAYERS[3]))
    most_g = max(p.num_points() for layer in DEFAULT_LAYERS for p in _polygons(ly_g, layer))
    assert most_o > 199 >= most_g


@pytest.mark.parametrize("limit", [5, 8, 40])
def test_fractured_polygons_union_identical(tmp_path, limit):
    masks = levels_to_masks(_rings(96, seed=1))
    ref = export_masks(tmp_path / "ref.oas", masks, PITCH, formats=("oasis",), clear_aperture_m=0.4e-3)
    rep = export_masks(tmp_path / "lim.gds", masks, PITCH, formats=("gds", "oasis"), max_vertices=limit,
                       clear_aperture_m=0.4e-3)
    assert [f["max_vertices"] for f in rep["files"]] == [limit, limit]
    ly_ref = _layout(ref["files"][0]["file"])
    for f in rep["files"]:
        ly = _layout(f["file"])
        _same_geometry(ly, ly_ref, list(DEFAULT_LAYERS) + [10, 11])
        for layer in list(DEFAULT_LAYERS) + [10, 11]:
            polys = _polygons(ly, layer)
            assert max(p.num_points() for p in polys) <= limit, (f["format"], layer)
        for layer in DEFAULT_LAYERS:
            pieces = _region(ly, layer, merged=False, cell="ELEMENT")
            # Manhattan, every vertex on the pixel lattice (the grid's corner sits at -48 px) and
            # every piece whole pixels: so none is narrower than a pixel (no slivers; a keyhole
            # cut joining a hole has zero width and no area)
            for p in pieces.each():
                assert p.is_rectilinear()
                assert all(pt.x % P_DBU == 0 and pt.y % P_DBU == 0 for pt in p.each_point_hull())
                assert p.area() > 0 and p.area() % P_DBU ** 2 == 0
        assert all(st["max_vertices"] <= limit for st in f["layers"])
    n_lim = sum(st["polygons"] for st in rep["files"][0]["layers"])
    n_ref = sum(st["polygons"] for st in ref["files"][0]["layers"])
    assert n_lim > n_ref  # something was fractured


def test_polygon_limit_down_to_rectangles():
    rng = np.random.default_rng(4)
    mask = rng.random((50, 60)) < 0.6
    mask[10:40, 10:40] = True
    mask[20:30, 20:30] = False  # a hole
    for limit in (4, 5, 6, 7, 12):
        ps = mask_polygons(mask, limit)
        assert ps.max_vertices <= limit
        polys = ps.split()
        area = sum(abs(np.sum(p[:, 0] * np.roll(p[:, 1], -1) - np.roll(p[:, 0], -1) * p[:, 1])) / 2
                   for p in polys)
        assert area == mask.sum()
        yy, xx = np.mgrid[:50, :60]
        centres = np.stack([xx.ravel() + 0.5, yy.ravel() + 0.5], 1)
        inside = np.array(gdstk.inside(centres, [gdstk.Polygon(p) for p in polys])).reshape(mask.shape)
        assert np.array_equal(inside, mask)
    assert mask_polygons(mask, None).n_polygons < mask_polygons(mask, 199).n_polygons
    with pytest.raises(DoeError, match="at least 4"):
        mask_polygons(mask, 3)


def test_vertex_limits_rules():
    assert vertex_limits(("gds",)) == {"gds": 199}
    assert vertex_limits(("gds", "oasis")) == {"gds": 199, "oasis": None}
    assert vertex_limits(("oasis",), None) == {"oasis": None}
    assert vertex_limits(("gds", "oasis"), 64) == {"gds": 64, "oasis": 64}
    for formats, limit, msg in [(("gds",), None, "8190"), (("gds", "oasis"), 9000, "8190"),
                                (("oasis",), 4, ">= 5"), (("svg",), 10, "formats")]:
        with pytest.raises(DoeError, match=msg):
            vertex_limits(formats, limit)


def test_verify_refuses_polygons_over_the_limit(tmp_path):
    masks = levels_to_masks(_rings(80))
    rep = export_masks(tmp_path / "a.gds", masks, PITCH)
    grid = PixelGrid.centred((80, 80), PITCH)
    assert verify_file(rep["file"], masks, grid)["passed"]
    res = verify_file(rep["file"], masks, grid, max_vertices=6)
    assert not res["passed"] and any("exceed 6 vertices" in p for p in res["problems"])


def test_oasis_verification_failure_leaves_no_file(tmp_path, monkeypatch):
    import masks.gds as g
    from masks.polygons import PolygonSet

    real = g.mask_polygons

    def drop_last(mask, max_vertices=None):
        ps = real(mask, max_vertices)
        return PolygonSet(ps.vertices[:ps.offsets[-2]], ps.offsets[:-1])

    monkeypatch.setattr(g, "mask_polygons", drop_last)
    with pytest.raises(DoeError, match="verification failed"):
        export_masks(tmp_path / "bad.gds", levels_to_masks(_rings(40)), PITCH, formats=("oasis",))
    assert list(tmp_path.iterdir()) == []


def _lyp_entries(path):
    root = ET.parse(path).getroot()
    assert root.tag == "layer-properties"
    return [{c.tag: c.text for c in props} for props in root.findall("properties")]


def test_layer_properties_name_depths_and_load_in_klayout(tmp_path):
    masks = levels_to_masks(_rings(40))
    depths = (75e-9, 150e-9, 300e-9, 600e-9)
    rep = export_masks(tmp_path / "e.gds", masks, PITCH, layers=(7, 4, 5, 6), depths_m=depths,
                       etch_order=(3, 2, 1, 0), clear_aperture_m=0.1e-3)
    lyp = tmp_path / "e.lyp"
    assert rep["layer_properties_file"] == str(lyp)
    entries = _lyp_entries(lyp)
    for j, (layer, depth_nm) in enumerate(zip((7, 4, 5, 6), (75, 150, 300, 600))):
        mine = [e for e in entries if e["source"] == f"{layer}/0@1"]
        assert len(mine) == 1, layer
        assert mine[0]["name"] == f"mask {j + 1}: {depth_nm:.1f} nm etch, step {4 - j} (L{layer}/0)"
    colours = [e["fill-color"] for e in entries]
    assert len(set(colours)) == len(colours)  # every layer its own colour
    assert {e["source"] for e in entries} >= {"10/0@1", "11/0@1", "20/0@1"}
    lay = pytest.importorskip("klayout.lay")
    view = lay.LayoutView()
    view.load_layout(rep["file"], True)
    view.load_layer_props(str(lyp))
    loaded = {}
    it = view.begin_layers()
    while not it.at_end():
        node = it.current()
        loaded[(node.source_layer, node.source_datatype)] = (node.name, node.fill_color & 0xFFFFFF,
                                                             node.dither_pattern)
        it.next()
    assert loaded[(7, 0)][0].startswith("mask 1: 75.0 nm etch")
    assert loaded[(6, 0)] == (entries[3]["name"], int(entries[3]["fill-color"][1:], 16),
                              int(entries[3]["dither-pattern"][1:]))
    assert len(loaded) == len(entries)


def _design_file(tmp_path, n=64, name="lens"):
    levels = _rings(n)
    d = Design(-levels * STEP_M, PITCH, levels=levels, metadata={"name": name, "camera": {"aperture_diameter_m": 0.2e-3}})
    return d.save(tmp_path / f"{name}.npz")


def test_cli_oasis_only(tmp_path, capsys):
    out = tmp_path / "out"
    assert main(["masks", str(_design_file(tmp_path)), "--out", str(out), "--format", "oasis"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert sorted(p.name for p in out.iterdir()) == ["lens.lyp", "lens.oas", "masks.png", "report.json"]
    assert summary["file"] == str(out / "lens.oas")
    assert summary["files"] == [{"format": "oasis", "file": str(out / "lens.oas"),
                                 "file_size_bytes": (out / "lens.oas").stat().st_size, "max_vertices": None}]
    rep = json.loads((out / "report.json").read_text())
    assert rep["verification"]["passed"] and rep["layer_properties_file"] == str(out / "lens.lyp")


def test_cli_both_with_limit_and_plate(tmp_path):
    out = tmp_path / "out"
    assert main(["masks", str(_design_file(tmp_path)), "--out", str(out), "--format", "both",
                 "--max-vertices", "12", "--plate"]) == 0
    rep = json.loads((out / "report.json").read_text())
    assert [(f["format"], f["max_vertices"]) for f in rep["files"]] == [("gds", 12), ("oasis", 12)]
    assert all(st["max_vertices"] <= 12 for f in rep["files"] for st in f["layers"])
    plate = rep["plate"]
    assert [f["format"] for f in plate["files"]] == ["gds", "oasis"] and plate["verification"]["passed"]
    assert (out / "lens_plate.lyp").exists()
    ly_g, ly_o = _layout(out / "lens_plate.gds"), _layout(out / "lens_plate.oas")
    for ly in (ly_g, ly_o):
        placed = sum(i.na * i.nb for i in ly.cell("PLATE").each_inst() if i.cell.name.startswith("DIE_"))
        assert placed == plate["dies"]
    _same_geometry(ly_g, ly_o, DEFAULT_LAYERS)
    names = [e["name"] for e in _lyp_entries(out / "lens_plate.lyp")]
    assert any("wafer" in n for n in names) and sum(n.startswith("mask ") for n in names) == 4


@pytest.mark.parametrize("args, msg", [
    (["--max-vertices", "3"], ">= 5"), (["--max-vertices", "abc"], "'abc'"), (["--max-vertices", "nan"], "'nan'"),
    (["--max-vertices", "none"], "8190"), (["--format", "both", "--max-vertices", "none"], "8190"),
    (["--max-vertices", "9000"], "8190"), (["--format", "svg"], "invalid choice")])
def test_cli_bad_format_options_exit_2(tmp_path, capsys, args, msg):
    out = tmp_path / "out"
    assert main(["masks", str(_design_file(tmp_path, 16)), "--out", str(out)] + args) == 2
    err = capsys.readouterr().err
    # the error is one line (argparse prints the usage above its own)
    assert msg in err.strip().splitlines()[-1] and "Traceback" not in err, err
    assert not out.exists()
