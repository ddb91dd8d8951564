"""Mask plates: dies on a 4-inch wafer inside a 5-inch plate frame, one layer per mask,
written as one GDSII library and verified die by die: one die each of several designs
(:func:`~masks.plate.plate_layout`), or a full wafer of one design placed by array references
(:func:`~masks.plate.wafer_plate`), with global alignment marks.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import gdstk
import numpy as np

from doedesign.errors import DoeError
from doedesign.fileio import atomic_path

from .grid import DEFAULT_LAYERS, MAX_VERTICES, PRECISION_M, UNIT_M, PixelGrid, vertex_limits
from .gds import element_cell, write_layouts
from .gds_records import gds_name
from .layout import DieSettings, die_cells, mark_site
from .lyp import LayerStyle, die_layer_styles, write_lyp
from .verify import verify_file

__all__ = ["EDGE_EXCLUSION_M", "GLOBAL_MARK_STEP_UM", "GLOBAL_MARK_X_M", "PLATE_LAYER", "PLATE_SIZE_M", "PlateDesign",
           "STREET_M", "WAFER_DIAMETER_M", "WAFER_LAYER", "die_sites", "export_plate", "global_mark_sites_um",
           "plate_layout", "wafer_plate", "write_plate"]

WAFER_DIAMETER_M = 100e-3
PLATE_SIZE_M = 127e-3
EDGE_EXCLUSION_M = 5e-3
PLATE_LAYER = 30
WAFER_LAYER = 31
#: Global alignment marks at x = +-47 mm: on the 100 mm wafer, outside the 90 mm circle the
#: dies may use (5 mm edge exclusion), so no die ever covers them.
GLOBAL_MARK_X_M = 47e-3
GLOBAL_MARK_STEP_UM = 400.0  # between the mark sites of successive masks, in y
STREET_M = 0.5e-3  # between neighbouring die footprints on a full wafer


@dataclass
class PlateDesign:
    """One die of a plate: its masks (n_masks, rows, cols), pitch and clear aperture."""

    name: str
    masks: np.ndarray
    pitch_m: float
    clear_aperture_m: float | None = None


def _die(lib, design, layers, datatype, tone, mirrored, depths_m, die_size_m, inline=False, etch_order=None):
    """Add one design's element and die cells to ``lib``; return the die's top cell and record.

    With ``inline`` the element cell stays empty: :func:`write_plate` streams its polygons
    into the file (:func:`masks.gds_records.write_element_gds`).
    """
    masks = np.asarray(design.masks, dtype=bool)
    grid = PixelGrid.centred(masks.shape[1:], design.pitch_m, mirrored)
    elem_name = gds_name(f"ELEMENT_{design.name}")
    if inline:
        elem, stats = gdstk.Cell(elem_name), None
    else:
        elem, stats = element_cell(masks, grid, layers, datatype, tone, name=elem_name)
    lib.add(elem)
    order = tuple(range(len(layers)) if etch_order is None else etch_order)
    settings = DieSettings(name=design.name, layers=tuple(layers), datatype=datatype, tone=tone,
                           mirrored=mirrored, depths_m=tuple(depths_m), etch_order=order, die_size_m=die_size_m,
                           clear_aperture_m=design.clear_aperture_m, pitch_um=grid.pitch_um)
    top = die_cells(lib, elem, grid, settings)
    lib.add(top)
    return top, {"name": design.name, "cell": elem_name, "grid": grid, "masks": masks, "layers": stats,
                 "inline": inline}


def global_mark_sites_um(n_masks: int) -> list:
    """Centres (um) of the global mark sites: for each later mask, one at -x and one at +x."""
    x = GLOBAL_MARK_X_M / UNIT_M
    return [(side, (j - n_masks / 2) * GLOBAL_MARK_STEP_UM) for j in range(1, n_masks) for side in (-x, x)]


def _plate_cell(layers, datatype, mirrored, wafer_diameter_m, plate_size_m):
    """The PLATE cell: 5-inch plate frame, wafer outline and the global alignment marks.

    One mark site per later mask (cross of the first mask in a frame of the later one, with
    verniers, :func:`masks.layout.mark_site`) on each side at +-``GLOBAL_MARK_X_M``: on the
    wafer, in the edge ring that the dies leave free.
    """
    plate = gdstk.Cell("PLATE")
    half = plate_size_m / 2 / UNIT_M
    frame = 1000.0
    plate.add(gdstk.rectangle((-half, -half), (half, -half + frame), PLATE_LAYER),
              gdstk.rectangle((-half, half - frame), (half, half), PLATE_LAYER),
              gdstk.rectangle((-half, -half + frame), (-half + frame, half - frame), PLATE_LAYER),
              gdstk.rectangle((half - frame, -half + frame), (half, half - frame), PLATE_LAYER))
    r = wafer_diameter_m / 2 / UNIT_M
    for k in range(4):
        th = np.linspace(k * np.pi / 2, (k + 1) * np.pi / 2, 91)
        ring = np.vstack([np.stack([r * np.cos(th), r * np.sin(th)], 1),
                          np.stack([(r - 200) * np.cos(th[::-1]), (r - 200) * np.sin(th[::-1])], 1)])
        plate.add(gdstk.Polygon(ring, WAFER_LAYER))
    marks = gdstk.Cell("GLOBAL_MARKS")
    for layer, centre in zip(np.repeat(layers[1:], 2), global_mark_sites_um(len(layers))):
        mark_site(marks, centre, layers[0], int(layer), datatype)
    if mirrored:
        for p in marks.polygons:
            p.mirror((0, 1))
    plate.add(*marks.polygons)
    return plate


def plate_layout(designs: Sequence[PlateDesign], *, layers: Sequence[int] = DEFAULT_LAYERS, datatype: int = 0,
                 tone: str = "dark", mirrored: bool = False,
                 depths_m: Sequence[float] = (75e-9, 150e-9, 300e-9, 600e-9), die_size_m: float = 10e-3,
                 die_pitch_m: float = 16e-3, wafer_diameter_m: float = WAFER_DIAMETER_M,
                 plate_size_m: float = PLATE_SIZE_M) -> tuple[gdstk.Library, list[dict]]:
    """Several dies on one 4-inch wafer inside a 5-inch plate frame, one layer per mask.

    Each mask plate is written from its own layer of the one library. Dies sit on a square
    grid of ``die_pitch_m`` centred on the wafer; each die (with its marks and test
    structures) must lie inside the wafer minus a 5 mm edge exclusion. Global alignment
    marks sit outside that circle (see ``_plate_cell``).

    Returns
    -------
    lib : gdstk.Library
    dies : list of dict
        Per die: name, element cell name, centre_um, PixelGrid (for verification).
    """
    if not designs:
        raise DoeError("plate_layout: no designs given")
    names = [d.name for d in designs]
    if len(set(names)) != len(names):
        raise DoeError(f"plate_layout: design names must be distinct, got {names}")
    lib = gdstk.Library(name="PLATE", unit=UNIT_M, precision=PRECISION_M)
    plate = _plate_cell(layers, datatype, mirrored, wafer_diameter_m, plate_size_m)
    n = len(designs)
    ncol = int(np.ceil(np.sqrt(n)))
    nrow = int(np.ceil(n / ncol))
    pitch_um = die_pitch_m / UNIT_M
    usable_um = (wafer_diameter_m / 2 - EDGE_EXCLUSION_M) / UNIT_M
    dies = []
    for i, d in enumerate(designs):
        row, col = divmod(i, ncol)
        centre = ((col - (ncol - 1) / 2) * pitch_um, ((nrow - 1) / 2 - row) * pitch_um)
        reach = die_size_m / 2 / UNIT_M + 4500  # marks and test structures around the die
        if np.hypot(abs(centre[0]) + reach, abs(centre[1]) + reach) > usable_um:
            raise DoeError(f"plate_layout: die {d.name!r} at {centre[0] / 1e3:.1f}, {centre[1] / 1e3:.1f} mm "
                           f"falls outside the wafer's usable {2 * usable_um / 1e3:.0f} mm circle; "
                           "use fewer designs or a smaller die pitch")
        top, die = _die(lib, d, layers, datatype, tone, mirrored, depths_m, die_size_m)
        placed = (-centre[0] if mirrored else centre[0], centre[1])
        plate.add(gdstk.Reference(top, placed))
        dies.append({**die, "centre_um": placed})
    lib.add(plate)
    return lib, dies


def die_sites(bbox_um: Sequence[Sequence[float]], usable_radius_um: float,
              street_um: float = STREET_M / UNIT_M) -> tuple[tuple[float, float], list[tuple]]:
    """Die origins (um) on a square lattice whose whole footprint lies inside the usable circle.

    Parameters
    ----------
    bbox_um : ((xmin, ymin), (xmax, ymax))
        Footprint of one die (element, marks, labels, test structures) around its origin.
    usable_radius_um : float
    street_um : float
        Gap between neighbouring footprints.

    Returns
    -------
    pitch_um : (float, float)
        Lattice pitch in x and y (footprint plus street, whole micrometres).
    rows : list of (y, x_first, count)
        Each lattice row with dies: its y, the first die's x and the number of dies, ready
        to be one array reference each.
    """
    (x0, y0), (x1, y1) = np.asarray(bbox_um, float)
    px, py = np.ceil(x1 - x0 + street_um), np.ceil(y1 - y0 + street_um)
    best: list[tuple[float, float, int]] | None = None
    # four lattice phases (footprint centred on or between the lattice lines): keep the fullest
    for fx in (0.0, 0.5):
        for fy in (0.0, 0.5):
            n_x = int(usable_radius_um // px) + 2
            n_y = int(usable_radius_um // py) + 2
            rows = []
            for k in range(-n_y, n_y + 1):
                # footprint centre at the lattice point; origin = centre - footprint middle
                cy = (k + fy) * py
                xs = [(i + fx) * px for i in range(-n_x, n_x + 1)]
                inside = [cx for cx in xs
                          if max(np.hypot(cx + sx * (x1 - x0) / 2, cy + sy * (y1 - y0) / 2)
                                 for sx in (-1, 1) for sy in (-1, 1)) <= usable_radius_um]
                if inside:
                    rows.append((cy - (y0 + y1) / 2, inside[0] - (x0 + x1) / 2, len(inside)))
            if best is None or sum(r[2] for r in rows) > sum(r[2] for r in best):
                best = rows
    assert best is not None  # the first lattice phase always sets it
    return (float(px), float(py)), best


def wafer_plate(design: PlateDesign, *, layers: Sequence[int] = DEFAULT_LAYERS, datatype: int = 0,
                tone: str = "dark", mirrored: bool = False,
                depths_m: Sequence[float] = (75e-9, 150e-9, 300e-9, 600e-9),
                etch_order: Sequence[int] | None = None, die_size_m: float = 10e-3,
                wafer_diameter_m: float = WAFER_DIAMETER_M,
                plate_size_m: float = PLATE_SIZE_M) -> tuple[gdstk.Library, list[dict]]:
    """A full wafer of one design: its die repeated over the usable circle by array references.

    The element and die cells exist once; each lattice row of :func:`die_sites` is one
    array reference (GDSII AREF) of the die cell, so nothing is flattened and the file stays
    the size of one die plus the references.

    Returns
    -------
    lib : gdstk.Library
    dies : list of one dict
        The die (see :func:`plate_layout`) with ``count``, ``pitch_um`` and ``rows``.
    """
    lib = gdstk.Library(name="PLATE", unit=UNIT_M, precision=PRECISION_M)
    plate = _plate_cell(layers, datatype, mirrored, wafer_diameter_m, plate_size_m)
    top, die = _die(lib, design, layers, datatype, tone, mirrored, depths_m, die_size_m, inline=True,
                     etch_order=etch_order)
    (bx0, by0), (bx1, by1) = top.bounding_box()
    (gx0, gy0), (gx1, gy1) = die["grid"].bbox_um()  # the element cell is still empty
    footprint = ((min(bx0, gx0), min(by0, gy0)), (max(bx1, gx1), max(by1, gy1)))
    usable_um = (wafer_diameter_m / 2 - EDGE_EXCLUSION_M) / UNIT_M
    pitch, rows = die_sites(footprint, usable_um)
    if not rows:
        raise DoeError(f"wafer_plate: the {(footprint[1][0] - footprint[0][0]) / 1e3:.1f} mm die footprint "
                       f"does not fit the wafer's usable {2 * usable_um / 1e3:.0f} mm circle")
    for y, x, count in rows:
        plate.add(gdstk.Reference(top, (x, y), columns=count, rows=1, spacing=(pitch[0], pitch[1])))
    lib.add(plate)
    return lib, [{**die, "count": sum(r[2] for r in rows), "pitch_um": list(pitch),
                  "rows": [list(r) for r in rows], "footprint_um": [list(c) for c in footprint]}]


def write_plate(path: str | Path, lib: gdstk.Library, dies: list[dict], layers: Sequence[int] = DEFAULT_LAYERS,
                datatype: int = 0, tone: str = "dark") -> dict:
    """Write a plate library (:func:`plate_layout`) as GDSII and verify every die's element;
    DoeError and no file on mismatch. A full wafer of one design (:func:`wafer_plate`, its
    element streamed in) is written by :func:`export_plate`.
    """
    if any(d.get("inline") for d in dies):
        raise DoeError("write_plate: a plate whose element is streamed in is written by export_plate")
    with atomic_path(path) as tmp:
        lib.write_gds(str(tmp), max_points=MAX_VERTICES)
        results = {}
        for d in dies:
            res = verify_file(tmp, d["masks"], d["grid"], layers, datatype, tone, cell_name=d["cell"])
            if not res["passed"]:
                raise DoeError(f"{path}: die {d['name']} failed verification: "
                               f"{res['mismatched_pixels']} mismatched pixels; " + "; ".join(res["problems"][:5]))
            results[d["name"]] = {"mismatched_pixels": res["mismatched_pixels"], "passed": True}
    return results


def export_plate(path: str | Path, design: PlateDesign, *, formats: Sequence[str] = ("gds",),
                 max_vertices: int | None | str = "default", **options: Any) -> dict:
    """Write a verified full-wafer plate of one design (:func:`wafer_plate`) to ``path``.

    ``formats`` and ``max_vertices`` as in :func:`masks.gds.export_masks` (``path``'s suffix
    becomes ``.gds`` / ``.oas``, and a KLayout ``.lyp`` is written beside them); ``options``
    go to :func:`wafer_plate`. Returns the ``plate`` entry of the report: the files and
    their sizes (``file`` and ``file_size_bytes``: the first), the die count and lattice, the
    global mark positions and the seconds.
    """
    t0 = time.perf_counter()
    limits = vertex_limits(formats, max_vertices)
    lib, dies = wafer_plate(design, **options)
    die = dies[0]
    layers = options.get("layers", DEFAULT_LAYERS)
    datatype = options.get("datatype", 0)
    element = next(c for c in lib.cells if isinstance(c, gdstk.Cell) and c.name == die["cell"])
    files = write_layouts(lib, element, path, die["masks"], die["grid"], limits, layers, datatype,
                          options.get("tone", "dark"))
    depths = options.get("depths_m", (75e-9, 150e-9, 300e-9, 600e-9))
    extra = [LayerStyle(PLATE_LAYER, 0, f"5-inch plate frame (L{PLATE_LAYER}/0)", "#606060", "I1", 2),
             LayerStyle(WAFER_LAYER, 0, f"4-inch wafer outline (L{WAFER_LAYER}/0)", "#a06030", "I0")]
    lyp = write_lyp(Path(path).with_suffix(".lyp"),
                    die_layer_styles(layers, datatype, depths, options.get("etch_order"),
                                     bool(design.clear_aperture_m), extra))
    return {"file": files[0]["file"], "file_size_bytes": files[0]["file_size_bytes"],
            "files": [{k: f[k] for k in ("format", "file", "file_size_bytes", "max_vertices")} for f in files],
            "layer_properties_file": str(lyp), "dies": die["count"],
            "die_pitch_um": die["pitch_um"], "die_footprint_um": die["footprint_um"],
            "array_references": len(die["rows"]),
            "usable_diameter_m": round(options.get("wafer_diameter_m", WAFER_DIAMETER_M) - 2 * EDGE_EXCLUSION_M, 9),
            "global_marks_um": [list(c) for c in global_mark_sites_um(len(die["masks"]))],
            "seconds": time.perf_counter() - t0,
            "verification": {"passed": all(f["verification"]["passed"] for f in files),
                             "mismatched_pixels": max(f["verification"]["mismatched_pixels"] for f in files)}}
