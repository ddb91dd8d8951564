"""Die labels print: polygon text on the mask layers, no TEXT records there, no overlaps."""

import gdstk
import numpy as np
import pytest

from masks.decompose import levels_to_masks
from masks.gds import export_masks

PITCH = 5.4e-6
LAYERS = (1, 2, 3, 4)


def _text_layers(data):
    """Layer of every TEXT element in a GDSII byte string (a plain record walk)."""
    pos, in_text, layers = 0, False, []
    while pos + 4 <= len(data):
        length = int.from_bytes(data[pos:pos + 2], "big")
        rtype = int.from_bytes(data[pos + 2:pos + 4], "big")
        if length < 4:
            break
        if rtype == 0x0C00:  # TEXT
            in_text = True
        elif rtype == 0x0D02 and in_text:  # its LAYER
            layers.append(int.from_bytes(data[pos + 4:pos + 6], "big"))
            in_text = False
        pos += length
    return layers


def _lines(polygons):
    """Group glyph polygons into text lines: glyphs whose y ranges overlap share a line."""
    boxes = sorted((np.asarray(p.bounding_box()).ravel() for p in polygons), key=lambda b: b[1])
    lines = []
    for b in boxes:
        if lines and b[1] < lines[-1][3] and b[3] > lines[-1][1]:
            last = lines[-1]
            lines[-1] = np.array([min(last[0], b[0]), min(last[1], b[1]), max(last[2], b[2]), max(last[3], b[3])])
        else:
            lines.append(b)
    return lines


def _disjoint(a, b):
    return a[2] <= b[0] or b[2] <= a[0] or a[3] <= b[1] or b[3] <= a[1]


@pytest.mark.parametrize("mirrored", [False, True])
def test_labels_are_printed_polygons_that_do_not_overlap(tmp_path, mirrored):
    shape = (1800, 1850)  # 9.7 x 10.0 mm: the element fills the 10 mm die
    yy, xx = np.mgrid[:shape[0], :shape[1]]
    levels = ((xx // 7 + yy // 11) % 16).astype(np.int16)
    path = tmp_path / "lab.gds"
    rep = export_masks(path, levels_to_masks(levels), PITCH, mirrored=mirrored, name="lab")
    assert rep["verification"]["passed"]
    assert not set(_text_layers(path.read_bytes())) & set(LAYERS), "TEXT records on a mask layer"
    lib = gdstk.read_gds(str(path))
    die = next(c for c in lib.cells if c.name.startswith("DIE_"))
    text = [p for p in die.polygons if p.layer in LAYERS]
    assert {p.layer for p in text} == set(LAYERS)  # every mask prints its own line
    lines = _lines(text)
    assert len(lines) == len(LAYERS) + 1  # summary + one line per mask
    for i in range(len(lines)):
        for j in range(i):
            assert _disjoint(lines[i], lines[j]), f"labels {i} and {j} overlap"
    # the element's area, from the pixel grid alone: centred, rows x cols pixels
    half_w, half_h = shape[1] * PITCH / 2e-6, shape[0] * PITCH / 2e-6
    element = np.array([-half_w, -half_h, half_w, half_h])
    die_square = np.array([-5000.0, -5000.0, 5000.0, 5000.0])
    for b in lines:
        assert _disjoint(b, element) and _disjoint(b, die_square)
    assert lines[0][2] - lines[0][0] > 10 * 80  # real text (tens of glyphs), not a dot
