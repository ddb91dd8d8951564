"""GDSII/OASIS export of the binary etch masks, with read-back verification.

Plate coordinates are micrometres (library unit 1e-6 m, precision 1e-9 m), y up, the
element centred on the die centre (0, 0). Pixel ``(r, c)`` of the design (row 0 at the
top) spans ``x in [x0 + c p, x0 + (c+1) p]`` and ``y in [y0 - (r+1) p, y0 - r p]``: rows
run toward decreasing y. With ``mirrored=True`` every x is negated (contact printing, the
mask is used face down), so columns run toward decreasing x.

Tone: ``"dark"`` (dark field, the default) draws on each mask layer the area its etch opens
(bit set: clear on the photomask, resist exposed, Cr and glass etched); ``"clear"`` (clear
field) draws the complement inside the element grid (the chrome that protects unetched
pixels).

Every export is read back with gdstk and each mask layer is rasterized on the pixel grid by
:func:`rasterize_layer` (a scanline fill of the polygons read from the file, written apart
from :mod:`masks.polygons`); the recomposed levels must equal the design's, else
:class:`DoeError` and no file.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from pathlib import Path

import gdstk
import numpy as np

from doedesign.errors import DoeError
from doedesign.fileio import atomic_path
from doedesign.progress import Progress

from .decompose import masks_to_levels
from .polygons import mask_polygons

log = logging.getLogger(__name__)

UNIT_M = 1e-6
PRECISION_M = 1e-9
MAX_VERTICES = 199
TONES = ("dark", "clear")
DEFAULT_LAYERS = (1, 2, 3, 4)
APERTURE_LAYER = 10
DIE_LAYER = 11
TEXT_LAYER = 20
ELEMENT_CELL = "ELEMENT"


@dataclass(frozen=True)
class PixelGrid:
    """Where the design pixels sit on the plate.

    Attributes
    ----------
    shape : (rows, cols)
    pitch_dbu : int
        Pixel pitch in database units (nm).
    mirrored : bool
        x -> -x applied (contact printing).
    """

    shape: tuple
    pitch_dbu: int
    mirrored: bool = False

    @classmethod
    def centred(cls, shape, pitch_m, mirrored=False):
        """Grid of ``shape`` pixels of ``pitch_m`` centred on (0, 0)."""
        pitch_dbu = pitch_m / PRECISION_M
        if not (np.isfinite(pitch_dbu) and pitch_dbu >= 1):
            raise DoeError(f"pixel pitch {pitch_m} m is not a positive length of at least 1 nm")
        if abs(pitch_dbu - round(pitch_dbu)) > 1e-6 * pitch_dbu:
            raise DoeError(f"pixel pitch {pitch_m * 1e9:.4f} nm is not a whole number of the 1 nm "
                           "GDS database unit; pixel edges would be rounded")
        return cls(tuple(int(s) for s in shape), int(round(pitch_dbu)), bool(mirrored))

    @property
    def origin_dbu(self):
        """(x, y) of the top-left corner of pixel (0, 0) before mirroring, in nm."""
        rows, cols = self.shape
        return -(cols * self.pitch_dbu) // 2, (rows * self.pitch_dbu) // 2

    @property
    def pitch_um(self):
        return self.pitch_dbu * PRECISION_M / UNIT_M

    def to_um(self, colrow):
        """Pixel-corner indices ``(col, row)`` -> plate coordinates (um), float array."""
        colrow = np.asarray(colrow)
        x0, y0 = self.origin_dbu
        x = x0 + colrow[..., 0] * self.pitch_dbu
        y = y0 - colrow[..., 1] * self.pitch_dbu
        if self.mirrored:
            x = -x
        return np.stack([x, y], axis=-1) * (PRECISION_M / UNIT_M)

    def to_index(self, xy_um):
        """Plate coordinates (um) -> fractional pixel-corner indices ``(col, row)``."""
        xy = np.asarray(xy_um, dtype=np.float64) * (UNIT_M / PRECISION_M)
        x0, y0 = self.origin_dbu
        x = -xy[..., 0] if self.mirrored else xy[..., 0]
        return np.stack([(x - x0) / self.pitch_dbu, (y0 - xy[..., 1]) / self.pitch_dbu], axis=-1)

    def bbox_um(self):
        """((xmin, ymin), (xmax, ymax)) of the element in um."""
        corners = self.to_um(np.array([[0, 0], [self.shape[1], self.shape[0]]]))
        return tuple(corners.min(axis=0)), tuple(corners.max(axis=0))

    def report(self):
        """The ``pixel_grid`` entry of ``report.json``."""
        x0, y0 = self.origin_dbu
        x0 = -x0 if self.mirrored else x0
        return {"origin_um": [x0 * 1e-3, y0 * 1e-3], "pitch_um": self.pitch_um,
                "shape": list(self.shape), "rows": "toward decreasing y",
                "columns": "toward decreasing x" if self.mirrored else "toward increasing x",
                "mirrored": self.mirrored,
                "origin_is": "outer corner of pixel (0, 0) at the start of row 0 and column 0"}


def drawn_masks(masks, tone="dark"):
    """What each layer draws: the open (etched) pixels for dark field, the rest for clear field."""
    if tone not in TONES:
        raise DoeError(f"tone must be one of {', '.join(TONES)}, got {tone!r}")
    masks = np.asarray(masks, dtype=bool)
    return masks if tone == "dark" else ~masks


def element_cell(masks, grid, layers=DEFAULT_LAYERS, datatype=0, tone="dark",
                 name=ELEMENT_CELL, progress=None):
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
    layers = _check_layers(layers, drawn.shape[0])
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


def read_library(path):
    """Read a GDSII (``.gds``) or OASIS (``.oas``) file with gdstk; DoeError if unreadable."""
    path = Path(path)
    try:
        if path.suffix.lower().startswith(".oas"):
            return gdstk.read_oas(str(path))
        return gdstk.read_gds(str(path))
    except (OSError, RuntimeError) as exc:
        raise DoeError(f"{path}: cannot read as GDSII/OASIS: {exc}") from None


def rasterize_layer(polygons, grid):
    """Scanline fill of polygons on the pixel grid (pixel-exact Manhattan input only).

    Parameters
    ----------
    polygons : list of ndarray (k, 2)
        Vertices in plate coordinates (um), as read from a file.
    grid : PixelGrid

    Returns
    -------
    coverage : ndarray of int32, shape grid.shape
        How many polygons cover each pixel (1 inside, 0 outside; 2+ means overlap).
    problems : list of str
        Off-grid vertices, non-Manhattan edges, vertices outside the grid, too many vertices.
    """
    rows, cols = grid.shape
    problems = []
    coverage = np.zeros((rows + 1, cols + 1), np.int64)
    if not polygons:
        return coverage[:rows, :cols].astype(np.int32), problems
    counts = np.array([len(p) for p in polygons])
    if counts.max() > MAX_VERTICES:
        problems.append(f"{int((counts > MAX_VERTICES).sum())} polygons exceed {MAX_VERTICES} vertices")
    idx = grid.to_index(np.concatenate(polygons))
    rounded = np.rint(idx)
    if np.abs(idx - rounded).max() > 1e-6:
        problems.append(f"{int((np.abs(idx - rounded) > 1e-6).any(axis=1).sum())} vertices off the pixel grid")
    pts = rounded.astype(np.int64)
    if pts.min() < 0 or pts[:, 0].max() > cols or pts[:, 1].max() > rows:
        problems.append("vertices outside the element's pixel grid")
        pts[:, 0] = np.clip(pts[:, 0], 0, cols)
        pts[:, 1] = np.clip(pts[:, 1], 0, rows)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    nxt = np.arange(len(pts)) + 1
    nxt[np.cumsum(counts) - 1] = starts  # each polygon closes on its first vertex
    x, y = pts[:, 0], pts[:, 1]
    xn, yn = x[nxt], y[nxt]
    diagonal = (x != xn) & (y != yn)
    if diagonal.any():
        problems.append(f"{int(diagonal.sum())} edges are not axis-parallel")
    # Orientation from the shoelace area: a polygon counts +1 inside whichever way it winds.
    area2 = np.add.reduceat(x * yn - xn * y, starts)
    orient = -np.sign(area2).repeat(counts)
    vertical = (x == xn) & (y != yn)
    w = (np.sign(yn - y) * orient)[vertical]
    xc, lo, hi = x[vertical], np.minimum(y, yn)[vertical], np.maximum(y, yn)[vertical]
    size = (rows + 1) * (cols + 1)
    diff = (np.bincount(lo * (cols + 1) + xc, w, minlength=size)
            - np.bincount(hi * (cols + 1) + xc, w, minlength=size))
    coverage = np.cumsum(np.cumsum(diff.reshape(rows + 1, cols + 1), axis=0), axis=1)
    return np.rint(coverage[:rows, :cols]).astype(np.int32), problems


def verify_file(path, masks, grid, layers=DEFAULT_LAYERS, datatype=0, tone="dark",
                cell_name=ELEMENT_CELL):
    """Read an exported file back, rasterize every mask layer, recompose and compare levels.

    Returns
    -------
    dict
        ``mismatched_pixels``, ``passed``, per-layer ``layers`` (mismatches, overlaps) and
        ``problems`` (empty when passed). Geometry of the other (non-element) cells on the
        mask layers, all placed in die coordinates, must not reach the element's area.
    """
    masks = np.asarray(masks, dtype=bool)
    layers = _check_layers(layers, masks.shape[0])
    lib = read_library(path)
    cells = {c.name: c for c in lib.cells}
    if cell_name not in cells:
        return {"passed": False, "mismatched_pixels": int(masks[0].size),
                "problems": [f"{path}: no cell {cell_name!r}"], "layers": []}
    cell = cells[cell_name]
    problems, per_layer, recovered = [], [], []
    for j, layer in enumerate(layers):
        polys = [p.points for p in cell.polygons if p.layer == layer and p.datatype == datatype]
        coverage, probs = rasterize_layer(polys, grid)
        problems += [f"layer {layer}: {p}" for p in probs]
        overlaps = int((coverage > 1).sum())
        if overlaps or (coverage < 0).any():
            problems.append(f"layer {layer}: {overlaps} pixels covered by more than one polygon")
        drawn = coverage > 0
        opened = drawn if tone == "dark" else ~drawn
        recovered.append(opened)
        per_layer.append({"layer": layer, "mismatched_pixels": int((opened != masks[j]).sum()),
                          "overlapping_pixels": overlaps})
    mismatch = int((masks_to_levels(np.array(recovered)) != masks_to_levels(masks)).sum())
    (gx0, gy0), (gx1, gy1) = grid.bbox_um()
    for other in lib.cells:
        if other.name.startswith(ELEMENT_CELL):  # other dies' elements live in their own frame
            continue
        for poly in other.polygons:
            if poly.layer in layers:
                (px0, py0), (px1, py1) = poly.bounding_box()
                if px0 < gx1 - 1e-4 and px1 > gx0 + 1e-4 and py0 < gy1 - 1e-4 and py1 > gy0 + 1e-4:
                    problems.append(f"cell {other.name}: layer {poly.layer} geometry overlaps the element")
                    break
    return {"passed": mismatch == 0 and not problems, "mismatched_pixels": mismatch,
            "layers": per_layer, "problems": problems}


def write_verified(lib, path, masks, grid, layers=DEFAULT_LAYERS, datatype=0, tone="dark",
                   cell_name=ELEMENT_CELL):
    """Write ``lib`` to ``path`` (.gds, or .oas for OASIS), verify, then rename into place.

    Raises
    ------
    DoeError
        When the read-back levels differ from the design; no file is left behind.
    """
    path = Path(path)
    oasis = path.suffix.lower() == ".oas"
    with atomic_path(path, suffix=".oas" if oasis else ".gds") as tmp:
        if oasis:
            lib.write_oas(str(tmp))
        else:
            lib.write_gds(str(tmp), max_points=MAX_VERTICES)
        result = verify_file(tmp, masks, grid, layers, datatype, tone, cell_name)
        if not result["passed"]:
            raise DoeError(f"{path}: verification failed, file not written: "
                           f"{result['mismatched_pixels']} mismatched pixels; "
                           + "; ".join(result["problems"][:5]))
    result["file_size_bytes"] = path.stat().st_size
    return result


def export_masks(path, masks, pitch_m, *, layers=DEFAULT_LAYERS, datatype=0, tone="dark",
                 mirrored=False, depths_m=None, etch_order=None, name="design",
                 clear_aperture_m=None, die_size_m=10e-3, oasis=False, marks=True):
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
    from . import layout
    from .decompose import DEFAULT_DEPTHS_M, check_etch_order

    t0 = time.perf_counter()
    masks = np.asarray(masks)
    if masks.dtype != bool or masks.ndim != 3:
        raise DoeError(f"masks must be a boolean array (n_masks, rows, cols), got {masks.dtype} {masks.shape}")
    n_masks = masks.shape[0]
    layers = _check_layers(layers, n_masks)
    depths_m = tuple(DEFAULT_DEPTHS_M[:n_masks] if depths_m is None else depths_m)
    if len(depths_m) != n_masks:
        raise DoeError(f"need {n_masks} etch depths, got {len(depths_m)}")
    etch_order = check_etch_order(range(n_masks) if etch_order is None else etch_order, n_masks)
    grid = PixelGrid.centred(masks.shape[1:], pitch_m, mirrored)
    settings = layout.DieSettings(name=name, layers=layers, datatype=datatype, tone=tone,
                                  mirrored=mirrored, depths_m=depths_m, etch_order=etch_order,
                                  die_size_m=die_size_m, clear_aperture_m=clear_aperture_m,
                                  marks=marks)
    lib = gdstk.Library(name=_gds_name(name), unit=UNIT_M, precision=PRECISION_M)
    with Progress(n_masks + 2, desc="doe masks") as bar:
        elem, stats = element_cell(masks, grid, layers, datatype, tone, progress=bar)
        lib.add(elem)
        top = layout.die_cells(lib, elem, grid, settings)
        lib.add(top)
        bar.update(1, "writing and verifying")
        outputs = [Path(path)] + ([Path(path).with_suffix(".oas")] if oasis else [])
        verification = None
        for out in outputs:
            result = write_verified(lib, out, masks, grid, layers, datatype, tone)
            verification = verification or result
            log.info("%s: %d bytes, verified", out, result["file_size_bytes"])
        bar.update(1, "verified")
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


def _check_layers(layers, n_masks):
    layers = tuple(int(v) for v in layers)
    if len(layers) != n_masks:
        raise DoeError(f"need one GDS layer per mask: {n_masks} masks, got layers {list(layers)}")
    if len(set(layers)) != len(layers) or min(layers) < 0 or max(layers) > 255:
        raise DoeError(f"mask layers must be distinct numbers 0..255, got {list(layers)}")
    if set(layers) & {APERTURE_LAYER, DIE_LAYER, TEXT_LAYER}:
        raise DoeError(f"mask layers {list(layers)} collide with the aperture/die/text layers "
                       f"{APERTURE_LAYER}, {DIE_LAYER}, {TEXT_LAYER}")
    return layers


def _gds_name(name):
    clean = "".join(ch if ch.isalnum() or ch in "_-" else "_" for ch in str(name))
    return clean[:32] or "design"
