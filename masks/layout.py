"""Everything on a die besides the element: Cr aperture, die outline, labels, alignment
marks with verniers, etch test structures and printed labels (plates of dies: :mod:`masks.plate`).

Geometry is built in die coordinates (um, y up, die centre at 0, 0) and mirrored as a whole
(x -> -x) when the masks are printed face down. Marks and test structures live in their
own cells outside the die square, so they never touch the element's pixel grid.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import gdstk
import numpy as np

from doedesign.errors import DoeError

from .grid import APERTURE_LAYER, DEFAULT_LAYERS, DIE_LAYER, TEXT_LAYER, UNIT_M, PixelGrid
from .gds_records import gds_name

__all__ = ["APERTURE_SEGMENTS", "DieSettings", "LABEL_GAP_UM", "LABEL_LINE_UM", "LABEL_SIZE_UM", "VERNIER_BARS",
           "VERNIER_PITCH_UM", "VERNIER_STEP_UM", "aperture_polygons", "die_cells", "die_labels", "mark_site",
           "marks_cell", "test_structures_cell"]

APERTURE_SEGMENTS = 720  # chord sag 0.04 um on a 4.32 mm radius
VERNIER_PITCH_UM = 10.0
VERNIER_STEP_UM = 0.25  # reading resolution: main pitch minus vernier pitch
VERNIER_BARS = 21
LABEL_SIZE_UM = 80.0  # text height: readable by eye on the wafer
LABEL_LINE_UM = 1.6 * LABEL_SIZE_UM  # baseline to baseline; the font's descenders stay inside
LABEL_GAP_UM = 150.0  # from the die's top edge to the first line's baseline


@dataclass
class DieSettings:
    """How one die is drawn (see :func:`masks.gds.export_masks`)."""

    name: str = "design"
    layers: tuple = DEFAULT_LAYERS
    datatype: int = 0
    tone: str = "dark"
    mirrored: bool = False
    depths_m: tuple = (75e-9, 150e-9, 300e-9, 600e-9)
    etch_order: tuple = (0, 1, 2, 3)
    die_size_m: float = 10e-3
    clear_aperture_m: float | None = None
    marks: bool = True
    pitch_um: float = 5.4
    extra: dict = field(default_factory=dict)


def aperture_polygons(diameter_m: float, die_size_m: float, layer: int = APERTURE_LAYER,
                      segments: int = APERTURE_SEGMENTS) -> list[gdstk.Polygon]:
    """Die square minus the clear circle, as 8 octant pieces of <= 199 vertices.

    The circle is the inscribed polygon of ``segments`` chords (vertices on the circle), so
    the clear area is at most ``r (1 - cos(pi / segments))`` smaller in radius.
    """
    r = diameter_m / 2 / UNIT_M
    h = die_size_m / 2 / UNIT_M
    if not 0 < r < h:
        raise DoeError(f"clear aperture {diameter_m * 1e3:.3f} mm must be positive and smaller "
                       f"than the {die_size_m * 1e3:.3f} mm die")
    per = segments // 8
    pieces = []
    for k in range(8):
        th = np.linspace(k * np.pi / 4, (k + 1) * np.pi / 4, per + 1)
        arc = np.stack([r * np.cos(th), r * np.sin(th)], 1)
        sq = [h / max(abs(np.cos(t)), abs(np.sin(t))) * np.array([np.cos(t), np.sin(t)]) for t in (th[-1], th[0])]
        pieces.append(gdstk.Polygon(np.vstack([arc, sq]), layer))  # type: ignore[arg-type]  # gdstk takes any (k, 2) array; its stub says Sequence of tuples
    return pieces


def _stripes(x0, x1, y0, y1, open_intervals, layer, datatype, tone):
    """Rectangles of a 1-D pattern in [x0, x1] x [y0, y1]; clear tone draws the gaps."""
    iv = sorted(open_intervals)
    if tone == "clear":
        edges = [x0] + [v for a, b in iv for v in (a, b)] + [x1]
        iv = [(a, b) for a, b in zip(edges[::2], edges[1::2]) if b > a]
    return [gdstk.rectangle((a, y0), (b, y1), layer, datatype) for a, b in iv]


def test_structures_cell(settings: DieSettings, origin_um: tuple[float, float] = (0.0, 0.0),
                         name: str = "TEST") -> gdstk.Cell:
    """Per-mask binary gratings (4 periods x 2 duty cycles) and a 16-level linear grating.

    The binary gratings of mask j exist on mask j only: a profilometer reads d_j directly
    and the diffraction efficiencies give the linewidth. The 16-level grating (period
    2**n_masks pixels) combines all masks like the element does.
    """
    cell = gdstk.Cell(name)
    pitch = settings.pitch_um
    pad = 300.0
    ox, oy = origin_um
    for j, layer in enumerate(settings.layers):
        for i, (mult, duty) in enumerate([(m, d) for m in (2, 4, 8, 16) for d in (0.5, 0.25)]):
            period = mult * pitch
            n_per = int(pad // period)
            x0 = ox + i * (pad + 50)
            y0 = oy - j * (pad + 50)
            lines = [(x0 + k * period, x0 + k * period + duty * period) for k in range(n_per)]
            cell.add(*_stripes(x0, x0 + n_per * period, y0 - pad, y0, lines, layer,
                               settings.datatype, settings.tone))
    n = len(settings.layers)
    period = 2 ** n * pitch
    n_per = int(500 // period)
    x0 = ox + 8 * (pad + 50)
    for j, layer in enumerate(settings.layers):
        cols = [c for c in range(2 ** n * n_per) if (c % 2 ** n) >> j & 1]
        runs = _runs(cols)
        cell.add(*_stripes(x0, x0 + n_per * period, oy - 500, oy,
                           [(x0 + a * pitch, x0 + b * pitch) for a, b in runs], layer,
                           settings.datatype, settings.tone))
    cell.add(gdstk.Label(f"{settings.name}: gratings periods 2,4,8,16 px duty 0.5,0.25; "
                         f"{2 ** n}-level grating period {period:g} um", (ox, oy + 30), layer=TEXT_LAYER))
    return cell


def _runs(cols):
    runs = []
    for c in cols:
        if runs and runs[-1][1] == c:
            runs[-1][1] = c + 1
        else:
            runs.append([c, c + 1])
    return runs


def mark_site(cell: gdstk.Cell, centre: tuple[float, float], first_layer: int, layer: int, datatype: int = 0) -> None:
    """Cross (first mask) in a box frame (mask ``layer``) plus X and Y verniers.

    The vernier main scale (first mask) has pitch 10 um, the one of the later mask
    10 - 0.25 um: the bar pair that lines up, counted from the centre, reads the overlay in
    0.25 um steps over +-2.5 um.
    """
    cx, cy = centre
    cell.add(gdstk.rectangle((cx - 50, cy - 5), (cx + 50, cy + 5), first_layer, datatype),
             gdstk.rectangle((cx - 5, cy - 50), (cx - 5 + 10, cy - 5), first_layer, datatype),
             gdstk.rectangle((cx - 5, cy + 5), (cx + 5, cy + 50), first_layer, datatype))
    for (a, b) in [((-80, -80), (80, -65)), ((-80, 65), (80, 80)), ((-80, -65), (-65, 65)), ((65, -65), (80, 65))]:
        cell.add(gdstk.rectangle((cx + a[0], cy + a[1]), (cx + b[0], cy + b[1]), layer, datatype))
    half = VERNIER_BARS // 2
    for k in range(-half, half + 1):
        long = 10 if k == 0 else 0
        xm = cx + k * VERNIER_PITCH_UM
        xv = cx + k * (VERNIER_PITCH_UM - VERNIER_STEP_UM)
        cell.add(gdstk.rectangle((xm - 2, cy - 160 - long), (xm + 2, cy - 120), first_layer, datatype),
                 gdstk.rectangle((xv - 2, cy - 120), (xv + 2, cy - 80 + long), layer, datatype))
        ym = cy + k * VERNIER_PITCH_UM
        yv = cy + k * (VERNIER_PITCH_UM - VERNIER_STEP_UM)
        cell.add(gdstk.rectangle((cx - 160 - long, ym - 2), (cx - 120, ym + 2), first_layer, datatype),
                 gdstk.rectangle((cx - 120, yv - 2), (cx - 80 + long, yv + 2), layer, datatype))


def marks_cell(settings: DieSettings, name: str = "MARKS") -> gdstk.Cell:
    """Alignment marks of every later mask to the first, on both sides of the die (for
    rotation), in the street outside the die square, with each mask's number as text."""
    cell = gdstk.Cell(name)
    h = settings.die_size_m / 2 / UNIT_M
    first = settings.layers[0]
    for j, layer in enumerate(settings.layers[1:], start=1):
        y = h - 400 * j
        for x in (-(h + 400), h + 400):
            mark_site(cell, (x, y), first, layer, settings.datatype)
    for j, layer in enumerate(settings.layers):
        cell.add(*gdstk.text(f"M{j + 1}", 60, (-(h + 600), -h + 200 + 150 * j), layer=layer,
                             datatype=settings.datatype))
    return cell


def die_labels(settings: DieSettings, grid: PixelGrid) -> list[gdstk.Polygon]:
    """The die's labels as polygon text that a mask writer prints, above the die square.

    One line per mask, on that mask's layer (the first mask also carries the summary line;
    ``settings.extra["mask_notes"]``, mask index -> text, ends a mask's line, e.g. the
    correction drawn into it),
    each line on its own row, so no two labels overlap on the wafer and none reaches the
    element or the die square (the element may overhang the die by up to a pixel).
    """
    lines = [(f"{settings.name}: {len(settings.layers)} masks, tone {settings.tone}, mirrored "
              f"{'yes' if settings.mirrored else 'no'}, pixel {grid.pitch_um:g} um", settings.layers[0])]
    notes = settings.extra.get("mask_notes", {})
    for j, layer in enumerate(settings.layers):
        note = f", {notes[j]}" if notes.get(j) else ""
        lines.append((f"mask {j + 1}: layer {layer}/{settings.datatype} etch {settings.depths_m[j] * 1e9:.1f} nm, "
                      f"step {settings.etch_order.index(j) + 1}{note}", layer))
    h = settings.die_size_m / 2 / UNIT_M
    bottom = max(h, grid.bbox_um()[1][1]) + LABEL_GAP_UM
    polygons = []
    for i, (text, layer) in enumerate(lines):
        # gdstk's font draws printable ASCII only; anything else would vanish silently
        text = "".join(ch if " " <= ch <= "~" else "?" for ch in text)
        polygons += gdstk.text(text, LABEL_SIZE_UM, (-h, bottom + i * LABEL_LINE_UM), layer=layer,
                               datatype=settings.datatype)
    return polygons


def die_cells(lib: gdstk.Library, element: gdstk.Cell, grid: PixelGrid, settings: DieSettings) -> gdstk.Cell:
    """Add aperture/outline/labels/marks cells for one die to ``lib``; return the top cell.

    The element cell is referenced at the die centre; all other cells are placed at the
    origin in die coordinates. Mirroring is applied to every cell but the element (whose
    polygons were built mirrored already).
    """
    suffix = "" if settings.name in ("", None) else ""
    top = gdstk.Cell(gds_name(f"DIE_{settings.name}{suffix}"))
    h = settings.die_size_m / 2 / UNIT_M
    (gx0, gy0), (gx1, gy1) = grid.bbox_um()
    if gx1 - gx0 > 2 * h + 2 * grid.pitch_um or gy1 - gy0 > 2 * h + 2 * grid.pitch_um:
        raise DoeError(f"{settings.name}: element {gx1 - gx0:.1f} x {gy1 - gy0:.1f} um does not fit "
                       f"the {2 * h:.0f} um die")
    top.add(gdstk.Reference(element))
    top.add(gdstk.rectangle((-h, -h), (h, h), DIE_LAYER))
    if settings.clear_aperture_m:
        top.add(*aperture_polygons(settings.clear_aperture_m, settings.die_size_m))
    top.add(*die_labels(settings, grid))
    extra = []
    if settings.marks:
        extra = [marks_cell(settings, gds_name(f"MARKS_{settings.name}")),
                 test_structures_cell(settings, (-h, -h - 300), gds_name(f"TEST_{settings.name}"))]
    for c in extra:
        lib.add(c)
        top.add(gdstk.Reference(c))
    if settings.mirrored:
        for c in [top] + extra:
            _mirror_own(c)
    return top


def _mirror_own(cell):
    """x -> -x for a cell's own polygons and labels (references stay at the origin)."""
    for p in cell.polygons:
        p.mirror((0, 1))
    for lab in cell.labels:
        lab.origin = (-lab.origin[0], lab.origin[1])
        lab.x_reflection = not lab.x_reflection
        lab.rotation = lab.rotation + np.pi
