"""`doe masks --plate`: a full 4-inch wafer of one die by array references, global marks."""

import json
from itertools import combinations

import gdstk
import numpy as np
import pytest

from doedesign.cli import main
from doedesign.design import Design

PITCH = 5.4e-6
LAYERS = (1, 2, 3, 4)
USABLE_R_UM = 45_000.0  # 100 mm wafer minus a 5 mm edge exclusion
WAFER_R_UM = 50_000.0


def _records(data):
    """(record type, payload) of every record of a GDSII byte string (a plain walk)."""
    pos = 0
    while pos + 4 <= len(data):
        length = int.from_bytes(data[pos:pos + 2], "big")
        if length < 4:
            return
        yield int.from_bytes(data[pos + 2:pos + 4], "big"), data[pos + 4:pos + length]
        pos += length


def _lattice_count(w, h, pitch_x, pitch_y):
    """Most footprints w x h on a lattice of the given pitch that fit the usable circle (any phase)."""
    best = 0
    for fx in (0.0, 0.5):
        for fy in (0.0, 0.5):
            i = np.arange(-10, 11) + fx
            cx, cy = np.meshgrid(i * pitch_x, (np.arange(-10, 11) + fy) * pitch_y)
            far = np.hypot(np.abs(cx) + w / 2, np.abs(cy) + h / 2)
            best = max(best, int((far <= USABLE_R_UM).sum()))
    return best


@pytest.fixture(scope="module")
def plate(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("plate")
    yy, xx = np.mgrid[:300, :300] - 150
    levels = ((xx ** 2 + yy ** 2) // 400 % 16).astype(np.int16)
    Design(-levels * 74.74e-9, PITCH, levels=levels, metadata={"name": "lens"}).save(tmp / "lens.npz")
    assert main(["masks", str(tmp / "lens.npz"), "--plate", "--out", str(tmp / "out")]) == 0
    report = json.loads((tmp / "out" / "report.json").read_text())
    return tmp / "out" / "lens_plate.gds", report["plate"]


def test_plate_places_dies_by_array_reference(plate):
    path, rep = plate
    assert rep["verification"]["passed"] and rep["dies"] >= 20
    records = list(_records(path.read_bytes()))
    arefs = [r for r in records if r[0] == 0x0B00]
    assert len(arefs) == rep["array_references"] >= 3  # one AREF per row of dies
    assert sum(1 for r in records if r[0] == 0x0A00) <= 10  # a few SREFs inside the die, not a die each
    lib = gdstk.read_gds(str(path))
    cells = {c.name: c for c in lib.cells}
    plate_cell = cells["PLATE"]
    die = next(c for c in lib.cells if c.name.startswith("DIE_"))
    refs = [r for r in plate_cell.references if r.cell.name == die.name]
    assert refs and all(r.repetition.columns >= 1 for r in refs)
    origins = np.concatenate([np.asarray(r.repetition.get_offsets()) + r.origin for r in refs])
    assert len(origins) == rep["dies"]
    # every placed die's footprint (die cell bbox, element included) lies in the usable circle,
    # no two overlap, and the count is the most this lattice can hold
    (x0, y0), (x1, y1) = die.bounding_box()
    lo, hi = origins + (x0, y0), origins + (x1, y1)
    corners = np.stack([lo, hi, np.c_[lo[:, 0], hi[:, 1]], np.c_[hi[:, 0], lo[:, 1]]])
    assert np.hypot(corners[..., 0], corners[..., 1]).max() <= USABLE_R_UM + 1e-6
    for a, b in combinations(range(len(origins)), 2):
        assert (hi[a] <= lo[b]).any() or (hi[b] <= lo[a]).any(), f"dies {a} and {b} overlap"
    pitch_x, pitch_y = rep["die_pitch_um"]
    assert pitch_x >= x1 - x0 and pitch_y >= y1 - y0
    assert rep["dies"] == _lattice_count(x1 - x0, y1 - y0, pitch_x, pitch_y)


def test_plate_has_global_marks_on_every_mask(plate):
    path, rep = plate
    lib = gdstk.read_gds(str(path))
    plate_cell = next(c for c in lib.cells if c.name == "PLATE")
    for side in (-1, 1):
        near = [p for p in plate_cell.polygons
                if np.abs(np.asarray(p.bounding_box()).mean(axis=0) - (side * 47_000, 0)).max() < 1_000]
        assert {p.layer for p in near} == set(LAYERS)  # the first mask's crosses, the others' frames
        pts = np.concatenate([p.points for p in near])
        r = np.hypot(pts[:, 0], pts[:, 1])
        assert r.min() > USABLE_R_UM and r.max() < WAFER_R_UM  # on the wafer, clear of every die


def test_klayout_opens_the_plate(plate):
    db = pytest.importorskip("klayout.db")
    path, rep = plate
    ly = db.Layout()
    ly.read(str(path))
    top = ly.cell("PLATE")
    placed = sum(inst.na * inst.nb for inst in top.each_inst() if inst.cell.name.startswith("DIE_"))
    assert placed == rep["dies"]
    assert all(inst.is_regular_array() for inst in top.each_inst() if inst.cell.name.startswith("DIE_"))
    # one die's element, flattened by KLayout: the first mask's open area is the design's
    elem = ly.cell("ELEMENT_lens")
    area = db.Region(elem.begin_shapes_rec(ly.layer(1, 0))).area()
    yy, xx = np.mgrid[:300, :300] - 150
    levels = (xx ** 2 + yy ** 2) // 400 % 16
    p = int(round(PITCH * 1e9))
    assert area == int((levels & 1).sum()) * p * p
