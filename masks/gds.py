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

Writing: gdstk writes the library (die outline, aperture, labels, marks, references) with
an empty element cell; the element's BOUNDARY records are built with numpy from the vertex
arrays of :mod:`masks.polygons`, one mask layer at a time, and spliced into that cell
(:func:`write_element_gds`), so no Python object is made per polygon.

Every export is read back and each mask layer is rasterized on the pixel grid: GDSII by
:func:`read_gds_boundaries` (a vectorized record reader, sharing nothing with the writer),
OASIS by gdstk, then :func:`rasterize_points` (a scanline fill, written apart from
:mod:`masks.polygons`); the recomposed levels must equal the design's, else
:class:`DoeError` and no file.
"""

from __future__ import annotations

import logging
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import gdstk
import numpy as np

from doedesign.errors import DoeError
from doedesign.fileio import TEMP_SUFFIX, atomic_path
from doedesign.progress import Progress

from .decompose import masks_to_levels
from .polygons import mask_polygons

__all__ = ["APERTURE_LAYER", "DEFAULT_LAYERS", "DIE_LAYER", "ELEMENT_CELL", "GdsBoundaries", "MAX_VERTICES",
           "PRECISION_M", "PixelGrid", "TEXT_LAYER", "TONES", "UNIT_M", "WORKERS", "boundary_records",
           "drawn_masks", "element_cell", "export_masks", "rasterize_layer", "rasterize_points",
           "read_gds_boundaries", "read_library", "verify_file", "write_element_gds", "write_verified"]

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
WORKERS = 2  # threads for per-layer work


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


OASIS_MAGIC = b"%SEMI-OASIS\r\n"


def is_oasis(path):
    """True when the file starts with the OASIS magic (by content: temporaries have no extension)."""
    try:
        with open(path, "rb") as fh:
            return fh.read(len(OASIS_MAGIC)) == OASIS_MAGIC
    except OSError as exc:
        raise DoeError(f"{path}: cannot read ({exc.strerror or exc})") from None


def read_library(path):
    """Read a GDSII (``.gds``) or OASIS (``.oas``) file with gdstk; DoeError if unreadable."""
    path = Path(path)
    try:
        if is_oasis(path):
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
    if not polygons:
        return np.zeros(grid.shape, np.int32), []
    counts = np.array([len(p) for p in polygons])
    return rasterize_points(grid.to_index(np.concatenate(polygons)), counts, grid)


def rasterize_points(idx, counts, grid):
    """:func:`rasterize_layer` on flat arrays: ``idx`` (n, 2) (col, row) indices of the
    vertices of all polygons (float: checked to lie on the grid; integer: taken as exact),
    ``counts`` vertices per polygon."""
    rows, cols = grid.shape
    problems = []
    counts = np.asarray(counts, np.int64)
    if counts.size == 0:
        return np.zeros(grid.shape, np.int32), problems
    if counts.max() > MAX_VERTICES:
        problems.append(f"{int((counts > MAX_VERTICES).sum())} polygons exceed {MAX_VERTICES} vertices")
    if np.asarray(idx).dtype.kind in "iu":
        pts = np.array(idx, np.int64)  # exact indices (a copy: clipped below)
    else:
        rounded = np.rint(idx)
        if np.abs(idx - rounded).max() > 1e-6:
            problems.append(f"{int((np.abs(idx - rounded) > 1e-6).any(axis=1).sum())} vertices off the pixel grid")
        pts = rounded.astype(np.int64)
    if pts.min() < 0 or pts[:, 0].max() > cols or pts[:, 1].max() > rows:
        problems.append("vertices outside the element's pixel grid")
        pts[:, 0] = np.clip(pts[:, 0], 0, cols)
        pts[:, 1] = np.clip(pts[:, 1], 0, rows)
    del idx
    ends = np.cumsum(counts)
    starts = ends - counts
    x, y = pts[:, 0].astype(np.int32), pts[:, 1].astype(np.int32)
    del pts
    # each vertex's successor; each polygon closes on its first vertex
    xn, yn = np.roll(x, -1), np.roll(y, -1)
    xn[ends - 1], yn[ends - 1] = x[starts], y[starts]
    diagonal = (x != xn) & (y != yn)
    if diagonal.any():
        problems.append(f"{int(diagonal.sum())} edges are not axis-parallel")
    del diagonal
    # Orientation from the shoelace area: a polygon counts +1 inside whichever way it winds.
    area2 = np.add.reduceat(x.astype(np.int64) * yn - xn.astype(np.int64) * y, starts)
    vertical = np.nonzero((x == xn) & (y != yn))[0]
    polygon = np.searchsorted(ends, vertical, side="right")
    w = np.sign(yn[vertical] - y[vertical]) * -np.sign(area2)[polygon]
    xc = x[vertical].astype(np.int64)
    lo = np.minimum(y[vertical], yn[vertical])
    hi = np.maximum(y[vertical], yn[vertical])
    del x, y, xn, yn, vertical, polygon
    width = cols + 1
    diff = np.bincount(np.concatenate([lo * width + xc, hi * width + xc]),
                       np.concatenate([w, -w]), minlength=(rows + 1) * width)
    coverage = np.rint(diff).astype(np.int32).reshape(rows + 1, width)
    del diff
    np.cumsum(coverage, axis=0, out=coverage)
    np.cumsum(coverage, axis=1, out=coverage)
    return np.ascontiguousarray(coverage[:rows, :cols]), problems


def verify_file(path, masks, grid, layers=DEFAULT_LAYERS, datatype=0, tone="dark",
                cell_name=ELEMENT_CELL):
    """Read an exported file back, rasterize every mask layer, recompose and compare levels.

    GDSII files are read by :func:`read_gds_boundaries` (numpy, written apart from the
    writer), OASIS files by gdstk.

    Returns
    -------
    dict
        ``mismatched_pixels``, ``passed``, per-layer ``layers`` (mismatches, overlaps) and
        ``problems`` (empty when passed). Geometry of the other (non-element) cells on the
        mask layers, all placed in die coordinates, must not reach the element's area.
    """
    masks = np.asarray(masks, dtype=bool)
    layers = _check_layers(layers, masks.shape[0])
    read = _read_boundaries(path)
    cells = read.cells
    if cell_name not in cells:
        return {"passed": False, "mismatched_pixels": int(masks[0].size),
                "problems": [f"{path}: no cell {cell_name!r}"], "layers": []}
    cell = cells[cell_name]
    problems, per_layer, recovered = [], [], []
    x0, y0 = grid.origin_dbu

    def one_layer(layer):
        sel = np.nonzero((cell["layer"] == layer) & (cell["datatype"] == datatype))[0]
        pts = read.points(cell_name, sel)
        # database units -> pixel-corner indices, exactly, in integers
        if grid.mirrored:
            np.negative(pts[:, 0], out=pts[:, 0])
        pts[:, 0] -= x0
        np.subtract(y0, pts[:, 1], out=pts[:, 1])
        off = int((pts % grid.pitch_dbu != 0).any(axis=1).sum())
        pts //= grid.pitch_dbu
        coverage, probs = rasterize_points(pts, cell["counts"][sel], grid)
        del pts
        return coverage, probs + ([f"{off} vertices off the pixel grid"] if off else [])

    with ThreadPoolExecutor(WORKERS) as pool:
        rasters = list(pool.map(one_layer, layers))
    for j, (layer, (coverage, probs)) in enumerate(zip(layers, rasters)):
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
    for name, other in cells.items():
        if name.startswith(ELEMENT_CELL) or other["counts"].size == 0:
            continue  # other dies' elements live in their own frame
        starts = np.cumsum(other["counts"]) - other["counts"]
        um = read.points(name) * (PRECISION_M / UNIT_M)
        lo = np.minimum.reduceat(um, starts, axis=0)
        hi = np.maximum.reduceat(um, starts, axis=0)
        hit = (np.isin(other["layer"], layers) & (lo[:, 0] < gx1 - 1e-4) & (hi[:, 0] > gx0 + 1e-4)
               & (lo[:, 1] < gy1 - 1e-4) & (hi[:, 1] > gy0 + 1e-4))
        if hit.any():
            problems.append(f"cell {name}: layer {int(other['layer'][hit][0])} geometry overlaps the element")
    return {"passed": mismatch == 0 and not problems, "mismatched_pixels": mismatch,
            "layers": per_layer, "problems": problems}


def _read_boundaries(path):
    """:class:`GdsBoundaries` of a .gds (numpy reader) or .oas (gdstk) file."""
    path = Path(path)
    if not is_oasis(path):
        read = read_gds_boundaries(path)
        if abs(read.dbu_m - PRECISION_M) > 1e-6 * PRECISION_M:
            raise DoeError(f"{path}: database unit {read.dbu_m:g} m, expected {PRECISION_M:g} m")
        return read
    cells = {}
    for c in read_library(path).cells:
        polys = c.polygons
        pts = [p.points for p in polys]
        counts = np.array([len(q) for q in pts], np.int64)
        cells[c.name] = {
            "layer": np.array([p.layer for p in polys], np.int64),
            "datatype": np.array([p.datatype for p in polys], np.int64),
            "counts": counts, "first": np.cumsum(counts) - counts,
            "points": (np.rint(np.concatenate(pts) * (UNIT_M / PRECISION_M)).astype(np.int64)
                       if pts else np.zeros((0, 2), np.int64))}
    return GdsBoundaries(PRECISION_M, cells)


def write_verified(lib, path, masks, grid, layers=DEFAULT_LAYERS, datatype=0, tone="dark",
                   cell_name=ELEMENT_CELL, element_inline=True, progress=None):
    """Write ``lib`` to ``path`` (.gds, or .oas for OASIS), verify, then rename into place.

    With ``element_inline`` (GDSII only) the element cell in ``lib`` is empty and its
    polygons are streamed in by :func:`write_element_gds` (``progress`` advanced per mask);
    otherwise ``lib`` holds them.

    Returns
    -------
    dict
        The verification (see :func:`verify_file`) plus ``file_size_bytes`` and, when the
        element was streamed, its per-mask ``stats``.

    Raises
    ------
    DoeError
        When the read-back levels differ from the design; no file is left behind.
    """
    path = Path(path)
    oasis = path.suffix.lower() == ".oas"
    stats = None
    with atomic_path(path) as tmp:
        if oasis:
            lib.write_oas(str(tmp))
        elif element_inline:
            stats = write_element_gds(lib, tmp, masks, grid, layers, datatype, tone, cell_name,
                                      progress)
        else:
            lib.write_gds(str(tmp), max_points=MAX_VERTICES)
        result = verify_file(tmp, masks, grid, layers, datatype, tone, cell_name)
        if not result["passed"]:
            raise DoeError(f"{path}: verification failed, file not written: "
                           f"{result['mismatched_pixels']} mismatched pixels; "
                           + "; ".join(result["problems"][:5]))
    result["file_size_bytes"] = path.stat().st_size
    if stats is not None:
        result["stats"] = stats
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


# GDSII record headers (length, record type, data type), big-endian; see the GDSII stream
# format: BOUNDARY 0x0800, LAYER 0x0D02, DATATYPE 0x0E02, XY 0x1003, ENDEL 0x1100,
# STRNAME 0x0606, ENDSTR 0x0700, BGNSTR 0x0502.
_BOUNDARY, _LAYER, _DATATYPE, _XY, _ENDEL = 0x0800, 0x0D02, 0x0E02, 0x1003, 0x1100
_STRNAME, _ENDSTR = 0x0606, 0x0700


def boundary_records(pset, grid, layer, datatype=0):
    """GDSII BOUNDARY elements for a :class:`PolygonSet`, as one big-endian byte string.

    Each polygon is written as BOUNDARY, LAYER, DATATYPE, XY (its vertices in database
    units, closed by repeating the first) and ENDEL, all built with numpy in one pass.
    """
    counts = np.diff(pset.offsets)
    if counts.size == 0:
        return b""
    if counts.max() > MAX_VERTICES:
        raise DoeError(f"layer {layer}: polygon with {int(counts.max())} vertices exceeds {MAX_VERTICES}")
    x0, y0 = grid.origin_dbu
    x = x0 + pset.vertices[:, 0] * grid.pitch_dbu
    y = y0 - pset.vertices[:, 1] * grid.pitch_dbu
    if grid.mirrored:
        x = -x
    # Words of 4 bytes per polygon: 5 header words, 2 per point (k + 1 points), 1 ENDEL.
    words = 8 + 2 * counts
    start = np.zeros(counts.size, np.int64)
    np.cumsum(words[:-1], out=start[1:])
    out = np.empty(int(words.sum()), np.uint32)
    out[start] = (4 << 16) | _BOUNDARY
    out[start + 1] = (6 << 16) | _LAYER
    out[start + 2] = ((layer & 0xFFFF) << 16) | 6
    out[start + 3] = (_DATATYPE << 16) | (datatype & 0xFFFF)
    out[start + 4] = ((4 + 8 * (counts + 1)) << 16) | _XY
    out[start + 7 + 2 * counts] = (4 << 16) | _ENDEL
    poly = np.repeat(np.arange(counts.size), counts)
    pos = start[poly] + 5 + 2 * (np.arange(len(poly)) - pset.offsets[poly])
    out[pos] = x.astype(np.int32).view(np.uint32)
    out[pos + 1] = y.astype(np.int32).view(np.uint32)
    first = pset.offsets[:-1]
    out[start + 5 + 2 * counts] = out[pos[first]]
    out[start + 6 + 2 * counts] = out[pos[first] + 1]
    return out.astype(">u4").tobytes()


def _structure_end(data, name):
    """Byte offset of the ENDSTR record of structure ``name`` in a GDSII byte string."""
    pos, current, target = 0, None, name.encode()
    while pos + 4 <= len(data):
        length, rtype = int.from_bytes(data[pos:pos + 2], "big"), int.from_bytes(data[pos + 2:pos + 4], "big")
        if length < 4:
            break
        if rtype == _STRNAME:
            current = data[pos + 4:pos + length].rstrip(b"\0")
        elif rtype == _ENDSTR and current == target:
            return pos
        pos += length
    raise DoeError(f"structure {name!r} not found in the written library")


def write_element_gds(lib, path, masks, grid, layers=DEFAULT_LAYERS, datatype=0, tone="dark",
                      cell_name=ELEMENT_CELL, progress=None):
    """Write ``lib`` (holding an empty element cell) with the element's polygons streamed in.

    gdstk writes everything else (marks, aperture, labels, references); the element's
    BOUNDARY records are built with numpy per mask layer and spliced into its structure,
    so no Python object is made per polygon and one layer is in memory at a time.

    Returns
    -------
    list of dict
        Per mask: layer, datatype, polygons, vertices, max_vertices.
    """
    drawn = drawn_masks(masks, tone)
    layers = _check_layers(layers, drawn.shape[0])
    if drawn.shape[1:] != tuple(grid.shape):
        raise DoeError(f"masks shaped {drawn.shape} do not match the pixel grid {grid.shape}")
    path = Path(path)
    skeleton_path = path.with_name(path.name + ".skeleton" + TEMP_SUFFIX)
    try:
        lib.write_gds(str(skeleton_path), max_points=MAX_VERTICES)
        skeleton = skeleton_path.read_bytes()
    finally:
        skeleton_path.unlink(missing_ok=True)
    cut = _structure_end(skeleton, cell_name)
    def one_layer(j):
        pset = mask_polygons(drawn[j], MAX_VERTICES)
        stat = {"layer": layers[j], "datatype": int(datatype), "polygons": pset.n_polygons,
                "vertices": pset.n_vertices, "max_vertices": pset.max_vertices}
        return boundary_records(pset, grid, layers[j], datatype), stat

    stats = []
    # numpy releases the GIL in its array loops: two layers at a time use both cores
    with open(path, "wb") as f, ThreadPoolExecutor(WORKERS) as pool:
        f.write(skeleton[:cut])
        for j, (records, stat) in enumerate(pool.map(one_layer, range(len(layers)))):
            f.write(records)
            stats.append(stat)
            if progress is not None:
                progress.update(1, f"mask {j + 1}: {stat['polygons']} polygons")
        f.write(skeleton[cut:])
    return stats


@dataclass
class GdsBoundaries:
    """BOUNDARY elements of one GDSII file, read with numpy (see :func:`read_gds_boundaries`).

    Attributes
    ----------
    dbu_m : float
        Database unit in metres (from the UNITS record).
    cells : dict
        Structure name -> dict of arrays ``layer``, ``datatype``, ``counts`` (points per
        element, closing point dropped) and ``first`` (byte offset of each element's first
        point in the file, or its index into a ``points`` array when read by gdstk);
        :meth:`points` reads the vertices of chosen elements.
    """

    dbu_m: float
    cells: dict
    _words: tuple = ()  # big-endian int32 views of the file at byte offsets 0 and 2

    def points(self, cell, select=None):
        """Vertices (int64 (n, 2), database units) of the selected elements of ``cell``."""
        c = self.cells[cell]
        sel = np.arange(c["counts"].size) if select is None else np.asarray(select)
        counts = c["counts"][sel]
        first = c["first"][sel]
        out = np.empty((int(counts.sum()), 2), np.int64)
        ends = np.cumsum(counts)
        if "points" in c:
            out[:] = c["points"][np.repeat(first - (ends - counts), counts) + np.arange(out.shape[0])]
            return out
        # An element is a whole number of 4-byte words, so its points keep its alignment.
        aligned_pt = np.repeat(first % 4 == 0, counts)
        for aligned, words in zip((True, False), self._words):
            pick = aligned_pt == aligned
            if not pick.any():
                continue
            start = (first - (0 if aligned else 2)) // 4 - 2 * (ends - counts)
            idx = (np.repeat(start, counts) + 2 * np.arange(out.shape[0]))[pick]
            out[pick, 0] = words[idx]
            out[pick, 1] = words[idx + 1]
        return out


def _real8(b):
    """GDSII 8-byte real (excess-64, base-16 exponent, 56-bit mantissa)."""
    v = int.from_bytes(b, "big")
    sign = -1.0 if v >> 63 else 1.0
    return sign * (v & ((1 << 56) - 1)) / float(1 << 56) * 16.0 ** (((v >> 56) & 0x7F) - 64)


def read_gds_boundaries(path):
    """Every BOUNDARY of a GDSII file, grouped by structure, with a vectorized record reader.

    Candidate elements are found where a BOUNDARY header is followed by LAYER, DATATYPE, XY
    and ENDEL headers at the offsets their lengths imply; a record-by-record walk from the
    start of the file then accepts only candidates it lands on, jumping over each run of
    back-to-back candidates in one step, so bytes that merely look like a header inside
    coordinate data are never taken as one.

    Raises
    ------
    DoeError
        When the file is not a well-formed GDSII stream.
    """
    path = Path(path)
    try:
        raw = np.memmap(path, dtype=np.uint8, mode="r")
    except (OSError, ValueError) as exc:
        raise DoeError(f"{path}: cannot read as GDSII: {exc}") from None
    size = raw.size - raw.size % 2
    w = raw[:size].view(">u2")  # records start on even offsets
    # int32 views at byte offsets 0 and 2 (mod 4) for aligned reads anywhere
    v32 = tuple(raw[off:off + (size - off) // 4 * 4].view(">i4") for off in (0, 2))

    def word32(p):  # big-endian int32 at even byte offsets p
        out = np.empty(p.shape, np.int64)
        odd = (p % 4) != 0
        out[~odd] = v32[0][p[~odd] // 4]
        out[odd] = v32[1][(p[odd] - 2) // 4]
        return out

    # BOUNDARY header bytes 00 04 08 00 at either alignment
    key = np.frombuffer(b"\x00\x04\x08\x00", "<u4")[0]
    cand = np.concatenate([np.nonzero(v.view("<u4") == key)[0] * 4 + off
                           for off, v in zip((0, 2), v32)])
    cand.sort()
    cand = cand[cand + 24 <= size]
    cand = cand[(word32(cand + 4) == (6 << 16 | _LAYER)) & (w[(cand + 10) // 2] == 6)
                & (w[(cand + 12) // 2] == _DATATYPE) & (w[(cand + 18) // 2] == _XY)]
    xy_len = w[(cand + 16) // 2].astype(np.int64)
    ok = (xy_len >= 4 + 8 * 4) & ((xy_len - 4) % 8 == 0) & (cand + 20 + xy_len <= size)
    cand, xy_len = cand[ok], xy_len[ok]
    ok = word32(cand + 16 + xy_len) == (4 << 16 | _ENDEL)
    cand, xy_len = cand[ok], xy_len[ok]
    end = cand + 20 + xy_len
    # runs of candidates each starting where the previous one ends
    brk = np.ones(cand.size, bool)
    brk[1:] = end[:-1] != cand[1:]
    run = np.cumsum(brk) - 1
    run_last = np.append(np.nonzero(brk)[0][1:] - 1, cand.size - 1)
    accepted = np.zeros(cand.size, bool)
    cell_of = np.full(cand.size, -1, np.int64)
    names, dbu_m, current, pos = [], None, -1, 0
    header = bytes(raw[:min(size, 4)])
    while pos + 4 <= size:
        i = int(np.searchsorted(cand, pos))
        if i < cand.size and cand[i] == pos:
            last = run_last[run[i]]
            if current < 0:
                raise DoeError(f"{path}: BOUNDARY outside any structure at byte {pos}")
            accepted[i:last + 1] = True
            cell_of[i:last + 1] = current
            pos = int(end[last])
            continue
        length, rtype = int(w[pos // 2]), int(w[pos // 2 + 1])
        if length < 4 or pos + length > raw.size:
            raise DoeError(f"{path}: corrupt GDSII record at byte {pos}")
        if rtype == _BOUNDARY:
            raise DoeError(f"{path}: BOUNDARY at byte {pos} has records this reader does not "
                           "expect (only LAYER, DATATYPE, XY)")
        if rtype == _STRNAME:
            names.append(bytes(raw[pos + 4:pos + length]).rstrip(b"\0").decode("ascii", "replace"))
            current = len(names) - 1
        elif rtype == _ENDSTR:
            current = -1
        elif rtype == 0x0305:  # UNITS: user unit, database unit in metres
            dbu_m = _real8(bytes(raw[pos + 12:pos + 20]))
        elif rtype == 0x0400:  # ENDLIB
            break
        pos += length
    if header[2:4] != b"\x00\x02" or dbu_m is None:
        raise DoeError(f"{path}: not a GDSII stream (no HEADER/UNITS record)")
    cand, xy_len, cell_of = cand[accepted], xy_len[accepted], cell_of[accepted]
    layer = w[(cand + 8) // 2].astype(np.int16)
    datatype = w[(cand + 14) // 2].astype(np.int16)
    counts = (xy_len - 4) // 8 - 1  # the closing point repeats the first
    cells = {}
    for k, name in enumerate(names):
        sel = np.nonzero(cell_of == k)[0]
        cells[name] = {"layer": layer[sel].astype(np.int64), "datatype": datatype[sel].astype(np.int64),
                       "counts": counts[sel], "first": cand[sel] + 20}
    return GdsBoundaries(dbu_m, cells, v32)


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
