"""A die whose mask openings are drawn with an edge offset (a linewidth correction), verified.

The same die as ``doe masks`` (:func:`masks.element.write_element`: element, Cr aperture, die
outline, labels, marks, test structures, the same cell names and layers), but each mask's
openings are drawn offset by its own distance (:func:`masks.offset.offset_polygons`) and the
file is read back and checked on a fine grid against the offset of the pixel masks
(:func:`masks.offset.verify_offset_layer`) before it is renamed into place. The labels say
which offset each mask carries. Dark tone only: a clear-tone layer draws chrome, whose
offset at the element's rim would open a frame around it.

:func:`offset_feasibility` says whether an offset keeps every feature printable: it must not
push an edge past its neighbour nor leave an opening or a gap narrower than the minimum
feature.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from pathlib import Path

import gdstk
import numpy as np

from doedesign.design import Design
from doedesign.errors import DoeError
from doedesign.fileio import atomic_path, write_json
from doedesign.levels import quantize_design

from . import layout
from .decompose import levels_to_masks
from .element import DIE_SIZE_M, clear_aperture_m, preview
from .gds_read import read_boundaries
from .gds_records import gds_name
from .grid import ELEMENT_CELL, MAX_VERTICES, PRECISION_M, UNIT_M, PixelGrid, check_layers, narrowest_runs_px
from .lyp import die_layer_styles, write_lyp
from .offset import offset_polygons, verify_offset_layer

__all__ = ["MIN_FEATURE_M", "narrowest_runs_px", "offset_feasibility", "write_offset_element"]

#: Narrowest opening or chrome line a contact-printed mask is trusted to resolve (m).
MIN_FEATURE_M = 1.0e-6


def offset_feasibility(mask: np.ndarray, pitch_m: float, offset_m: float,
                       min_feature_m: float = MIN_FEATURE_M) -> str | None:
    """Why offsetting ``mask``'s edges by ``offset_m`` cannot be drawn, or None when it can.

    Openings grow by ``2 offset`` and the gaps between them shrink by as much: the narrowest
    of either must stay at least ``min_feature_m`` wide (and so stay apart and non-empty); the
    offset must also stay under half the pixel pitch (:func:`masks.offset.offset_polygons`).
    """
    narrow_open, narrow_gap = narrowest_runs_px(mask)
    if narrow_open is not None and offset_m < 0:
        width = narrow_open * pitch_m + 2 * offset_m
        if width < min_feature_m:
            return (f"its {narrow_open} px openings would shrink to {width * 1e6:.2f} um, below the "
                    f"{min_feature_m * 1e6:.2f} um minimum feature" + (" (they vanish)" if width <= 0 else ""))
    if narrow_gap is not None and offset_m > 0:
        width = narrow_gap * pitch_m - 2 * offset_m
        if width < min_feature_m:
            return (f"its {narrow_gap} px gaps between openings would close to {width * 1e6:.2f} um, below the "
                    f"{min_feature_m * 1e6:.2f} um minimum feature" + (" (the edges cross)" if width <= 0 else ""))
    if 2 * abs(round(offset_m / PRECISION_M)) >= round(pitch_m / PRECISION_M):
        return f"it reaches half the {pitch_m * 1e6:g} um pixel"
    return None


def write_offset_element(design: Design, out: str | Path, offsets_m: Sequence[float], *,
                         notes: dict | None = None, source: str | None = None, mirrored: bool = False,
                         depths_m: Sequence[float] | None = None, layers: Sequence[int] | None = None,
                         datatype: int = 0, clear_aperture: float | None = None) -> dict:
    """Write ``OUT/<name>.gds`` with each mask's openings offset, ``OUT/<name>.lyp`` (KLayout layer
    names), ``OUT/masks.png`` and ``OUT/report.json``.

    Parameters
    ----------
    design : Design
    out : path
        Output folder (the caller wraps the writes in :func:`doedesign.fileio.output_run`).
    offsets_m : sequence of float
        Edge offset per mask (m, rounded to the 1 nm database unit); positive = openings drawn wider.
    notes : dict, optional
        Mask index -> text added to that mask's label line.
    source, mirrored, depths_m, layers, datatype, clear_aperture
        As for :func:`masks.element.write_element` (dark tone).

    Returns
    -------
    dict
        The report written to ``report.json``: layers (with each offset), pixel grid,
        verification (mismatched samples per layer, zero when passed).

    Raises
    ------
    DoeError
        A mask whose offset is not drawable (:func:`offset_feasibility`), or a file that does
        not verify (no file is left).
    """
    t0 = time.perf_counter()
    source = source or design.name
    levels, _ = quantize_design(design, None, source)
    masks = levels_to_masks(levels, design.n_masks)
    n = masks.shape[0]
    layers = check_layers(tuple(range(1, n + 1)) if layers is None else layers, n)
    offsets = [round(float(v) / PRECISION_M) * PRECISION_M for v in offsets_m]
    if len(offsets) != n:
        raise DoeError(f"need {n} edge offsets, one per mask, got {len(offsets)}")
    for j, d in enumerate(offsets):
        why = offset_feasibility(masks[j], design.pitch_m, d)
        if why:
            raise DoeError(f"{source}: mask {j}: an edge offset of {d * 1e6:+.3f} um cannot be drawn: {why}")
    depths = list(design.etch_depths_m()) if depths_m is None else list(depths_m)
    aperture = clear_aperture if clear_aperture is not None else clear_aperture_m(design)
    if aperture is not None and aperture >= DIE_SIZE_M:
        aperture = None
    name = design.name
    grid = PixelGrid.centred(masks.shape[1:], design.pitch_m, mirrored)
    settings = layout.DieSettings(name=name, layers=layers, datatype=datatype, tone="dark", mirrored=mirrored,
                                  depths_m=tuple(depths), etch_order=tuple(range(n)), die_size_m=DIE_SIZE_M,
                                  clear_aperture_m=aperture, extra={"mask_notes": dict(notes or {})})
    lib = gdstk.Library(name=gds_name(name), unit=UNIT_M, precision=PRECISION_M)
    elem = gdstk.Cell(ELEMENT_CELL)
    for j, layer in enumerate(layers):
        elem.add(*offset_polygons(masks[j], grid, offsets[j], layer, datatype))
    lib.add(elem)
    lib.add(layout.die_cells(lib, elem, grid, settings))
    out = Path(out)
    path = out / f"{Path(name).name or 'design'}.gds"
    with atomic_path(path) as tmp:
        lib.write_gds(str(tmp), max_points=MAX_VERTICES)
        read = read_boundaries(tmp)
        cell = read.cells[ELEMENT_CELL]
        checks = []
        for j, layer in enumerate(layers):
            sel = np.nonzero((cell["layer"] == layer) & (cell["datatype"] == datatype))[0]
            res = verify_offset_layer(read.points(ELEMENT_CELL, sel), cell["counts"][sel], masks[j], grid, offsets[j])
            checks.append({"layer": layer, "polygons": int(sel.size), **res})
            if res["mismatched_samples"] or res["problems"]:
                raise DoeError(f"{path}: mask {j} (layer {layer}) failed verification, file not written: "
                               f"{res['mismatched_samples']} mismatched samples; " + "; ".join(res["problems"][:5]))
    lyp = write_lyp(path.with_suffix(".lyp"), die_layer_styles(layers, datatype, depths,
                                                                 clear_aperture=aperture is not None))
    preview(levels, masks, out / "masks.png", f"{name} (drawn before the edge offsets)")
    report = {
        "name": name, "file": str(path), "layer_properties_file": str(lyp), "design": source,
        "layers": [{"mask": j, "layer": layer, "datatype": int(datatype), "etch_depth_nm": depths[j] * 1e9,
                    "etch_step": j + 1, "edge_offset_um": offsets[j] * 1e6, "note": (notes or {}).get(j)}
                   for j, layer in enumerate(layers)],
        "pixel_grid": grid.report(), "tone": {"name": "dark", "drawn": "etched (open) areas, edges offset"},
        "unit_m": UNIT_M, "precision_m": PRECISION_M,
        "cells": {"element": ELEMENT_CELL, "top": gds_name(f"DIE_{name}")},
        "clear_aperture_m": aperture, "file_size_bytes": path.stat().st_size,
        "seconds": time.perf_counter() - t0,
        "verification": {"passed": True, "method": "read back; winding fill at samples straddling every offset "
                                                   "edge line, against the Chebyshev offset of the pixel masks",
                         "mismatched_samples": 0, "layers": checks},
    }
    write_json(out / "report.json", report)
    return report
