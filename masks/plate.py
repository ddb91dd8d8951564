"""Mask plates: dies of one or several designs on a 4-inch wafer inside a 5-inch plate
frame, one layer per mask, written as one GDSII library and verified die by die.
"""

from __future__ import annotations

from dataclasses import dataclass

import gdstk
import numpy as np

from doedesign.errors import DoeError
from doedesign.fileio import atomic_path

from .grid import DEFAULT_LAYERS, MAX_VERTICES, PRECISION_M, UNIT_M, PixelGrid
from .gds import element_cell
from .gds_records import gds_name
from .layout import DieSettings, die_cells
from .verify import verify_file

__all__ = ["EDGE_EXCLUSION_M", "PLATE_LAYER", "PLATE_SIZE_M", "PlateDesign", "WAFER_DIAMETER_M", "WAFER_LAYER",
           "plate_layout", "write_plate"]

WAFER_DIAMETER_M = 100e-3
PLATE_SIZE_M = 127e-3
EDGE_EXCLUSION_M = 5e-3
PLATE_LAYER = 30
WAFER_LAYER = 31


@dataclass
class PlateDesign:
    """One die of a plate: its masks (n_masks, rows, cols), pitch and clear aperture."""

    name: str
    masks: np.ndarray
    pitch_m: float
    clear_aperture_m: float | None = None


def plate_layout(designs, *, layers=DEFAULT_LAYERS, datatype=0, tone="dark", mirrored=False,
                 depths_m=(75e-9, 150e-9, 300e-9, 600e-9), die_size_m=10e-3, die_pitch_m=16e-3,
                 wafer_diameter_m=WAFER_DIAMETER_M, plate_size_m=PLATE_SIZE_M):
    """Several dies on one 4-inch wafer inside a 5-inch plate frame, one layer per mask.

    Each mask plate is written from its own layer of the one library. Dies sit on a square
    grid of ``die_pitch_m`` centred on the wafer; each die (with its marks and test
    structures) must lie inside the wafer minus a 5 mm edge exclusion.

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
    plate = gdstk.Cell("PLATE")
    n = len(designs)
    ncol = int(np.ceil(np.sqrt(n)))
    nrow = int(np.ceil(n / ncol))
    pitch_um = die_pitch_m / UNIT_M
    usable_um = (wafer_diameter_m / 2 - EDGE_EXCLUSION_M) / UNIT_M
    dies = []
    for i, d in enumerate(designs):
        masks = np.asarray(d.masks, dtype=bool)
        row, col = divmod(i, ncol)
        centre = ((col - (ncol - 1) / 2) * pitch_um, ((nrow - 1) / 2 - row) * pitch_um)
        reach = die_size_m / 2 / UNIT_M + 4500  # marks and test structures around the die
        if np.hypot(abs(centre[0]) + reach, abs(centre[1]) + reach) > usable_um:
            raise DoeError(f"plate_layout: die {d.name!r} at {centre[0] / 1e3:.1f}, {centre[1] / 1e3:.1f} mm "
                           f"falls outside the wafer's usable {2 * usable_um / 1e3:.0f} mm circle; "
                           "use fewer designs or a smaller die pitch")
        grid = PixelGrid.centred(masks.shape[1:], d.pitch_m, mirrored)
        elem_name = gds_name(f"ELEMENT_{d.name}")
        elem, stats = element_cell(masks, grid, layers, datatype, tone, name=elem_name)
        lib.add(elem)
        settings = DieSettings(name=d.name, layers=tuple(layers), datatype=datatype, tone=tone,
                               mirrored=mirrored, depths_m=tuple(depths_m),
                               etch_order=tuple(range(len(layers))), die_size_m=die_size_m,
                               clear_aperture_m=d.clear_aperture_m, pitch_um=grid.pitch_um)
        top = die_cells(lib, elem, grid, settings)
        lib.add(top)
        placed = (-centre[0] if mirrored else centre[0], centre[1])
        plate.add(gdstk.Reference(top, placed))
        dies.append({"name": d.name, "cell": elem_name, "centre_um": placed, "grid": grid,
                     "masks": masks, "layers": stats})
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
    lib.add(plate)
    return lib, dies


def write_plate(path, lib, dies, layers=DEFAULT_LAYERS, datatype=0, tone="dark"):
    """Write a plate library and verify every die's element; DoeError and no file on mismatch."""
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
