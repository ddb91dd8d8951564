"""GDSII/OASIS export of the binary etch masks of one die, with read-back verification.

The pieces live in rooms of their own: the pixel grid, units and layers in
:mod:`masks.grid` (coordinates, tone), the raw GDSII record writer in
:mod:`masks.gds_records`, the reader in :mod:`masks.gds_read`, the read-back check in
:mod:`masks.verify`, everything on the die besides the element in :mod:`masks.layout` and
the KLayout layer-properties file in :mod:`masks.lyp`. This module assembles them:
:func:`export_masks` writes one verified die as GDSII, OASIS (gdstk's writer) or both,
:func:`write_layouts` any library holding one element in those formats.

Coordinates: design arrays are row-major, row 0 at the top; pixel ``(r, c)`` spans
``x in [x0 + c p, x0 + (c+1) p]``, ``y in [y0 - (r+1) p, y0 - r p]`` (micrometres, the
element centred on the die), so rows run toward decreasing GDS y and columns toward
increasing x (decreasing when mirrored). Both formats hold the same geometry.
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
from .grid import (APERTURE_LAYER, DEFAULT_LAYERS, DIE_LAYER, ELEMENT_CELL, MAX_VERTICES, PRECISION_M, SUFFIXES,
                   TEXT_LAYER, UNIT_M, PixelGrid, check_layers, drawn_masks, vertex_limits)
from .lyp import die_layer_styles, write_lyp
from .polygons import mask_polygons
from .verify import write_verified

__all__ = ["element_cell", "export_masks", "write_layouts"]

log = logging.getLogger(__name__)


def element_cell(masks: np.ndarray, grid: PixelGrid, layers: Sequence[int] = DEFAULT_LAYERS, datatype: int = 0,
                 tone: str = "dark", name: str = ELEMENT_CELL, progress: Progress | None = None,
                 max_vertices: int | None = MAX_VERTICES) -> tuple[gdstk.Cell, list[dict]]:
    """Cell holding the merged pixel polygons of every mask, one layer per mask.

    Pixel ``(r, c)`` (row 0 at the top) is placed by ``grid`` (see the module docstring:
    rows toward decreasing y).

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
    max_vertices : int or None
        Largest vertex count of one polygon (None: no limit).

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
        pset = mask_polygons(drawn[j], max_vertices)
        pts = grid.to_um(pset.vertices)
        off = pset.offsets.tolist()
        cell.add(*[gdstk.Polygon(pts[a:b], layer, datatype)  # type: ignore[arg-type]  # gdstk takes any (k, 2) array; its stub says Sequence of tuples
                   for a, b in zip(off[:-1], off[1:])])
        stats.append({"layer": layer, "datatype": int(datatype), "polygons": pset.n_polygons,
                      "vertices": pset.n_vertices, "max_vertices": pset.max_vertices})
        if progress is not None:
            progress.update(1, f"mask {j + 1}: {pset.n_polygons} polygons")
    return cell, stats


def write_layouts(lib: gdstk.Library, element: gdstk.Cell, base: str | Path, masks: np.ndarray, grid: PixelGrid,
                  limits: dict, layers: Sequence[int] = DEFAULT_LAYERS, datatype: int = 0, tone: str = "dark",
                  progress: Progress | None = None) -> list[dict]:
    """Write ``lib`` as ``base.gds`` and/or ``base.oas``, each read back and verified.

    Parameters
    ----------
    lib : gdstk.Library
        Holds ``element`` empty (its polygons are streamed into the GDSII file and added to
        the cell only for OASIS) and everything else on the layout.
    element : gdstk.Cell
    base : path
        Destination without its suffix (any suffix is replaced).
    masks, grid, layers, datatype, tone
        The element (pixel ``(r, c)``, row 0 at the top, placed by ``grid``: rows toward
        decreasing y).
    limits : dict
        Format (``"gds"``, ``"oasis"``) -> largest vertex count of one polygon (None: no
        limit), from :func:`masks.grid.vertex_limits`; the files written, GDSII first.
    progress : Progress, optional
        Advanced per mask and per verified file.

    Returns
    -------
    list of dict
        Per file: ``format``, ``file``, ``file_size_bytes``, ``max_vertices`` (the limit),
        ``layers`` (per mask: polygons, vertices, largest polygon) and ``verification``.
    """
    base = Path(base)
    records = []
    for fmt in [f for f in ("gds", "oasis") if f in limits]:
        path = base.with_suffix(SUFFIXES[fmt])
        limit = limits[fmt]
        stats = None
        if fmt == "oasis":
            element.remove(*element.polygons)
            full, stats = element_cell(masks, grid, layers, datatype, tone, progress=progress,
                                       max_vertices=limit)
            element.add(*full.polygons)
        result = write_verified(lib, path, masks, grid, layers, datatype, tone, cell_name=element.name,
                                element_inline=fmt == "gds", progress=progress if fmt == "gds" else None,
                                max_vertices=limit)
        stats = result.pop("stats", stats)
        log.info("%s: %d bytes, verified", path, result["file_size_bytes"])
        if progress is not None:
            progress.update(1, f"{fmt} verified")
        records.append({"format": fmt, "file": str(path), "file_size_bytes": result.pop("file_size_bytes"),
                        "max_vertices": limit, "layers": stats,
                        "verification": {k: result[k] for k in ("passed", "mismatched_pixels", "layers")}})
    return records


def export_masks(path: str | Path, masks: np.ndarray, pitch_m: float, *, layers: Sequence[int] = DEFAULT_LAYERS,
                 datatype: int = 0, tone: str = "dark", mirrored: bool = False,
                 depths_m: Sequence[float] | None = None, etch_order: Sequence[int] | None = None,
                 name: str = "design", clear_aperture_m: float | None = None, die_size_m: float = 10e-3,
                 formats: Sequence[str] = ("gds",), max_vertices: int | None | str = "default",
                 marks: bool = True) -> dict:
    """Write one die (element, Cr aperture, die outline, labels, marks) and verify it.

    The element's pixel ``(r, c)`` (arrays row-major, row 0 at the top) lands at
    ``x in [x0 + c p, x0 + (c+1) p]``, ``y in [y0 - (r+1) p, y0 - r p]`` around the die
    centre: rows run toward decreasing y (see :mod:`masks.grid`). Beside the layout files a
    KLayout layer-properties file ``<path stem>.lyp`` names each mask layer with its etch depth.

    Parameters
    ----------
    path : str or Path
        Destination; its suffix becomes ``.gds`` / ``.oas`` / ``.lyp`` per file.
    masks : ndarray of bool, shape (n_masks, rows, cols)
    pitch_m : float
    layers, datatype, tone, mirrored
        See the module docstring.
    depths_m : sequence of float, optional
        Etch depth of each mask, for labels, layer names and the report.
    etch_order : sequence of int, optional
        Mask etched in each process step (default 0, 1, 2, ...).
    name : str
        Design name (cell and label text).
    clear_aperture_m : float, optional
        Diameter of the clear circle; None draws no Cr-aperture layer.
    die_size_m : float
    formats : sequence of {"gds", "oasis"}
        Layout files to write (each read back and verified).
    max_vertices : int, None or "default"
        Largest vertex count of one polygon in every file (None: no limit, OASIS only);
        "default": 199 for GDSII, no limit for OASIS (:func:`masks.grid.vertex_limits`).
    marks : bool
        Add alignment marks, verniers and test structures outside the die.

    Returns
    -------
    dict
        Report: ``files`` (per file: format, size, vertex limit, polygons, verification),
        ``file`` / ``file_size_bytes`` / ``layers`` / ``verification`` of the first one,
        ``layer_properties_file``, ``pixel_grid``, ``tone``, ``etch_order``, ``seconds``.
    """
    t0 = time.perf_counter()
    limits = vertex_limits(formats, max_vertices)
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
    with Progress(len(limits) * (n_masks + 1), desc="doe masks") as bar:
        files = write_layouts(lib, elem, path, masks, grid, limits, layers, datatype, tone, progress=bar)
    lyp = write_lyp(Path(path).with_suffix(".lyp"),
                    die_layer_styles(layers, datatype, depths_m, etch_order, bool(clear_aperture_m)))
    stats = files[0]["layers"]
    for f in files:
        for j, st in enumerate(f["layers"]):
            st.update(mask=j, etch_depth_nm=depths_m[j] * 1e9, etch_step=etch_order.index(j) + 1)
    return {
        "name": name, "file": files[0]["file"], "file_size_bytes": files[0]["file_size_bytes"],
        "files": files, "layer_properties_file": str(lyp),
        "layers": stats, "pixel_grid": grid.report(),
        "tone": {"name": tone, "drawn": "etched (open) pixels" if tone == "dark"
                 else "unetched pixels (chrome) inside the element"},
        "etch_order": list(etch_order), "unit_m": UNIT_M, "precision_m": PRECISION_M,
        "cells": {"element": ELEMENT_CELL, "top": top.name},
        "aperture_layer": APERTURE_LAYER if clear_aperture_m else None,
        "clear_aperture_m": clear_aperture_m, "die_layer": DIE_LAYER, "text_layer": TEXT_LAYER,
        "seconds": time.perf_counter() - t0,
        "verification": {"passed": all(f["verification"]["passed"] for f in files),
                         "mismatched_pixels": max(f["verification"]["mismatched_pixels"] for f in files),
                         "layers": files[0]["verification"]["layers"]},
    }
