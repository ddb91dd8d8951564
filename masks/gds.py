"""GDSII/OASIS export of the binary etch masks of one die, with read-back verification.

The pieces live in rooms of their own: the pixel grid, units and layers in
:mod:`masks.grid` (coordinates, tone), the raw GDSII record writer in
:mod:`masks.gds_records`, the reader in :mod:`masks.gds_read`, the read-back check in
:mod:`masks.verify`, and everything on the die besides the element in :mod:`masks.layout`.
This module assembles them: :func:`export_masks` writes one verified die.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Sequence
from pathlib import Path

import gdstk
import numpy as np

from doedesign.errors import DoeError
from doedesign.progress import Progress

from . import layout
from .decompose import DEFAULT_DEPTHS_M, check_etch_order
from .gds_records import gds_name
from .grid import (APERTURE_LAYER, DEFAULT_LAYERS, DIE_LAYER, ELEMENT_CELL, MAX_VERTICES, PRECISION_M, TEXT_LAYER,
                   UNIT_M, PixelGrid, check_layers, drawn_masks)
from .polygons import mask_polygons
from .verify import write_verified

__all__ = ["element_cell", "export_masks"]

log = logging.getLogger(__name__)


def element_cell(masks: np.ndarray, grid: PixelGrid, layers: Sequence[int] = DEFAULT_LAYERS, datatype: int = 0,
                 tone: str = "dark", name: str = ELEMENT_CELL,
                 progress: Progress | None = None) -> tuple[gdstk.Cell, list[dict]]:
    """Cell holding the merged pixel polygons of every mask, one layer per mask.

    Parameters
    ----------
    masks : ndarray of bool, shape (n_masks, rows, cols)
        True where mask j's etch opens the glass.
    grid : PixelGrid
    layers : sequence of int
        GDS layer of each mask.
    datatype : int
    tone : {"dark", "clear"}
    name : str
    progress : Progress, optional
        Advanced once per mask.

    Returns
    -------
    cell : gdstk.Cell
    stats : list of dict
        Per mask: layer, datatype, polygons, vertices, max_vertices.
    """
    drawn = drawn_masks(masks, tone)
    if drawn.ndim != 3 or drawn.shape[1:] != tuple(grid.shape):
        raise DoeError(f"masks shaped {drawn.shape} do not match the pixel grid {grid.shape}")
    layers = check_layers(layers, drawn.shape[0])
    cell = gdstk.Cell(name)
    stats = []
    for j, layer in enumerate(layers):
        pset = mask_polygons(drawn[j], MAX_VERTICES)
        pts = grid.to_um(pset.vertices)
        off = pset.offsets.tolist()
        cell.add(*[gdstk.Polygon(pts[a:b], layer, datatype) for a, b in zip(off[:-1], off[1:])])
        stats.append({"layer": layer, "datatype": int(datatype), "polygons": pset.n_polygons,
                      "vertices": pset.n_vertices, "max_vertices": pset.max_vertices})
        if progress is not None:
            progress.update(1, f"mask {j + 1}: {pset.n_polygons} polygons")
    return cell, stats


def export_masks(path: str | Path, masks: np.ndarray, pitch_m: float, *, layers: Sequence[int] = DEFAULT_LAYERS,
                 datatype: int = 0, tone: str = "dark", mirrored: bool = False,
                 depths_m: Sequence[float] | None = None, etch_order: Sequence[int] | None = None,
                 name: str = "design", clear_aperture_m: float | None = None, die_size_m: float = 10e-3,
                 oasis: bool = False, marks: bool = True) -> dict:
    """Write one die (element, Cr aperture, die outline, labels, marks) and verify it.

    Parameters
    ----------
    path : str or Path
        ``.gds`` destination; with ``oasis=True`` a ``.oas`` is written beside it too.
    masks : ndarray of bool, shape (n_masks, rows, cols)
    pitch_m : float
    layers, datatype, tone, mirrored
        See the module docstring.
    depths_m : sequence of float, optional
        Etch depth of each mask, for labels and the report.
    etch_order : sequence of int, optional
        Mask etched in each process step (default 0, 1, 2, ...).
    name : str
        Design name (cell and label text).
    clear_aperture_m : float, optional
        Diameter of the clear circle; None draws no Cr-aperture layer.
    die_size_m : float
    marks : bool
        Add alignment marks, verniers and test structures outside the die.

    Returns
    -------
    dict
        Report: ``layers``, ``pixel_grid``, ``tone``, ``etch_order``, ``file_size_bytes``,
        ``seconds``, ``verification``.
    """
    t0 = time.perf_counter()
    masks = np.asarray(masks)
    if masks.dtype != bool or masks.ndim != 3:
        raise DoeError(f"masks must be a boolean array (n_masks, rows, cols), got {masks.dtype} {masks.shape}")
    n_masks = masks.shape[0]
    layers = check_layers(layers, n_masks)
    depths_m = tuple(DEFAULT_DEPTHS_M[:n_masks] if depths_m is None else depths_m)
    if len(depths_m) != n_masks:
        raise DoeError(f"need {n_masks} etch depths, got {len(depths_m)}")
    etch_order = check_etch_order(range(n_masks) if etch_order is None else etch_order, n_masks)
    grid = PixelGrid.centred(masks.shape[1:], pitch_m, mirrored)
    settings = layout.DieSettings(name=name, layers=layers, datatype=datatype, tone=tone,
                                  mirrored=mirrored, depths_m=depths_m, etch_order=etch_order,
                                  die_size_m=die_size_m, clear_aperture_m=clear_aperture_m,
                                  marks=marks)
    lib = gdstk.Library(name=gds_name(name), unit=UNIT_M, precision=PRECISION_M)
    # The element cell stays empty in the gdstk library: its polygons are streamed into the
    # GDSII file (and only built as gdstk objects when an OASIS copy is asked for).
    elem = gdstk.Cell(ELEMENT_CELL)
    lib.add(elem)
    top = layout.die_cells(lib, elem, grid, settings)
    lib.add(top)
    outputs = [Path(path)] + ([Path(path).with_suffix(".oas")] if oasis else [])
    with Progress(n_masks + 1 + int(oasis), desc="doe masks") as bar:
        verification = write_verified(lib, outputs[0], masks, grid, layers, datatype, tone,
                                      progress=bar)
        stats = verification.pop("stats")
        log.info("%s: %d bytes, verified", outputs[0], verification["file_size_bytes"])
        bar.update(1, "verified")
        if oasis:
            full, _ = element_cell(masks, grid, layers, datatype, tone)
            elem.add(*full.polygons)
            result = write_verified(lib, outputs[1], masks, grid, layers, datatype, tone)
            log.info("%s: %d bytes, verified", outputs[1], result["file_size_bytes"])
            bar.update(1, "OASIS verified")
    for j, st in enumerate(stats):
        st.update(mask=j, etch_depth_nm=depths_m[j] * 1e9, etch_step=etch_order.index(j) + 1)
    return {
        "name": name, "file": str(outputs[0]),
        "oasis_file": str(outputs[1]) if oasis else None,
        "layers": stats, "pixel_grid": grid.report(),
        "tone": {"name": tone, "drawn": "etched (open) pixels" if tone == "dark"
                 else "unetched pixels (chrome) inside the element"},
        "etch_order": list(etch_order), "unit_m": UNIT_M, "precision_m": PRECISION_M,
        "cells": {"element": ELEMENT_CELL, "top": top.name},
        "aperture_layer": APERTURE_LAYER if clear_aperture_m else None,
        "clear_aperture_m": clear_aperture_m, "die_layer": DIE_LAYER, "text_layer": TEXT_LAYER,
        "file_size_bytes": verification["file_size_bytes"],
        "seconds": time.perf_counter() - t0,
        "verification": {"mismatched_pixels": verification["mismatched_pixels"],
                         "passed": verification["passed"], "layers": verification["layers"]},
    }
