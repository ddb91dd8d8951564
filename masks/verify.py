"""Read-back verification: every export is read back and each mask layer is rasterized on
the pixel grid (GDSII by :func:`masks.gds_read.read_gds_boundaries`, OASIS by gdstk, then
:func:`masks.grid.rasterize_points`); the recomposed levels must equal the design's, else
:class:`~doedesign.errors.DoeError` and no file.
"""

from __future__ import annotations

from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from doedesign.errors import DoeError
from doedesign.fileio import atomic_path

from .decompose import masks_to_levels
from .gds_read import read_boundaries
from .gds_records import WORKERS, write_element_gds
from .grid import (DEFAULT_LAYERS, ELEMENT_CELL, MAX_VERTICES, PRECISION_M, UNIT_M, PixelGrid, check_layers,
                   rasterize_points)

if TYPE_CHECKING:
    import gdstk

    from doedesign.progress import Progress

__all__ = ["verify_file", "write_verified"]


def verify_file(path: str | Path, masks: np.ndarray, grid: PixelGrid, layers: Sequence[int] = DEFAULT_LAYERS,
                datatype: int = 0, tone: str = "dark", cell_name: str = ELEMENT_CELL,
                max_vertices: int | None = MAX_VERTICES) -> dict:
    """Read an exported file back, rasterize every mask layer, recompose and compare levels.

    GDSII files are read by :func:`~masks.gds_read.read_gds_boundaries` (numpy, written apart from the
    writer), OASIS files by gdstk. The file's coordinates map back to pixels by
    :class:`masks.grid.PixelGrid`: rows row-major, row 0 at the top, rows toward decreasing y.

    Returns
    -------
    dict
        ``mismatched_pixels``, ``passed``, per-layer ``layers`` (mismatches, overlaps) and
        ``problems`` (empty when passed). Geometry of the other (non-element) cells on the
        mask layers, all placed in die coordinates, must not reach the element's area, and
        no polygon of any cell may have more than ``max_vertices`` vertices (None: no limit).
    """
    masks = np.asarray(masks, dtype=bool)
    layers = check_layers(layers, masks.shape[0])
    read = read_boundaries(path)
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
        coverage, probs = rasterize_points(pts, cell["counts"][sel], grid, max_vertices=None)
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
    if max_vertices is not None:
        for name, c in cells.items():
            over = int((c["counts"] > max_vertices).sum())
            if over:
                problems.append(f"cell {name}: {over} polygons exceed {max_vertices} vertices "
                                f"(largest {int(c['counts'].max())})")
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


def write_verified(lib: gdstk.Library, path: str | Path, masks: np.ndarray, grid: PixelGrid,
                   layers: Sequence[int] = DEFAULT_LAYERS, datatype: int = 0, tone: str = "dark",
                   cell_name: str = ELEMENT_CELL, element_inline: bool = True,
                   progress: Progress | None = None, max_vertices: int | None = MAX_VERTICES) -> dict:
    """Write ``lib`` to ``path`` (.gds, or .oas for OASIS), verify, then rename into place.

    With ``element_inline`` (GDSII only) the element cell in ``lib`` is empty and its
    polygons are streamed in by :func:`~masks.gds_records.write_element_gds` (``progress`` advanced per mask);
    otherwise ``lib`` holds them. No polygon written has more than ``max_vertices``
    vertices (None: no limit, OASIS only): gdstk fractures the other cells' larger ones
    (for OASIS in ``lib`` itself, before writing), the element's come within the limit.

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
    if max_vertices is None and not oasis:
        raise DoeError(f"{path}: a GDSII file needs a vertex limit")
    with atomic_path(path) as tmp:
        if oasis:
            if max_vertices is not None:
                _fracture_cells(lib, max_vertices)
            lib.write_oas(str(tmp))
        elif element_inline:
            assert max_vertices is not None  # a GDSII file without a limit was refused above
            stats = write_element_gds(lib, tmp, masks, grid, layers, datatype, tone, cell_name,
                                      progress, max_vertices)
        else:
            assert max_vertices is not None  # a GDSII file without a limit was refused above
            lib.write_gds(str(tmp), max_points=max_vertices)
        result = verify_file(tmp, masks, grid, layers, datatype, tone, cell_name, max_vertices)
        if not result["passed"]:
            raise DoeError(f"{path}: verification failed, file not written: "
                           f"{result['mismatched_pixels']} mismatched pixels; "
                           + "; ".join(result["problems"][:5]))
    result["file_size_bytes"] = path.stat().st_size
    if stats is not None:
        result["stats"] = stats
    return result


def _fracture_cells(lib: gdstk.Library, max_vertices: int) -> None:
    """Replace every polygon of ``lib`` with more than ``max_vertices`` vertices by gdstk's
    fractured pieces (what ``write_gds(max_points=...)`` does for GDSII on the way out)."""
    import gdstk

    for cell in lib.cells:
        if not isinstance(cell, gdstk.Cell):  # a raw cell's polygons are not ours to fracture
            continue
        big = [p for p in cell.polygons if p.size > max_vertices]
        if big:
            cell.remove(*big)
            cell.add(*[q for p in big for q in p.fracture(max_points=max_vertices, precision=PRECISION_M / UNIT_M)])
