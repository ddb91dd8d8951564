"""A raw GDSII record writer: BOUNDARY elements built with numpy and spliced into a library
that gdstk wrote, plus the small record rules (8-byte reals, structure names).

Writing: gdstk writes the library (die outline, aperture, labels, marks, references) with
an empty element cell; the element's BOUNDARY records are built with numpy from the vertex
arrays of :mod:`masks.polygons`, one mask layer at a time, and spliced into that cell
(:func:`write_element_gds`), so no Python object is made per polygon. Coordinates follow
:class:`masks.grid.PixelGrid`.
"""

from __future__ import annotations

from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from doedesign.errors import DoeError
from doedesign.fileio import make_temporary

from .grid import (DEFAULT_LAYERS, ELEMENT_CELL, GDS_VERTEX_CEILING, MAX_VERTICES, PixelGrid, check_layers,
                   drawn_masks)
from .polygons import PolygonSet, mask_polygons

if TYPE_CHECKING:
    import gdstk

    from doedesign.progress import Progress

__all__ = ["BOUNDARY", "DATATYPE", "ENDEL", "ENDLIB", "ENDSTR", "LAYER", "STRNAME", "UNITS", "WORKERS", "XY",
           "boundary_records", "gds_name", "real8", "structure_end", "write_element_gds"]

WORKERS = 2  # threads for per-layer work

# GDSII record headers (length, record type, data type), big-endian; see the GDSII stream
# format: BOUNDARY 0x0800, LAYER 0x0D02, DATATYPE 0x0E02, XY 0x1003, ENDEL 0x1100,
# STRNAME 0x0606, ENDSTR 0x0700, BGNSTR 0x0502, UNITS 0x0305, ENDLIB 0x0400.
BOUNDARY, LAYER, DATATYPE, XY, ENDEL = 0x0800, 0x0D02, 0x0E02, 0x1003, 0x1100
STRNAME, ENDSTR, UNITS, ENDLIB = 0x0606, 0x0700, 0x0305, 0x0400


def boundary_records(pset: PolygonSet, grid: PixelGrid, layer: int, datatype: int = 0,
                     max_vertices: int = MAX_VERTICES) -> bytes:
    """GDSII BOUNDARY elements for a :class:`~masks.polygons.PolygonSet`, as one big-endian byte string.

    Each polygon is written as BOUNDARY, LAYER, DATATYPE, XY (its vertices in database
    units, closed by repeating the first) and ENDEL, all built with numpy in one pass.
    Vertex ``(col, row)`` goes to ``x = x0 + col p``, ``y = y0 - row p`` (rows row-major,
    row 0 at the top, so rows run toward decreasing GDS y; x negated when mirrored).
    """
    counts = np.diff(pset.offsets)
    if counts.size == 0:
        return b""
    if counts.max() > min(max_vertices, GDS_VERTEX_CEILING):
        raise DoeError(f"layer {layer}: polygon with {int(counts.max())} vertices exceeds "
                       f"{min(max_vertices, GDS_VERTEX_CEILING)}")
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
    out[start] = (4 << 16) | BOUNDARY
    out[start + 1] = (6 << 16) | LAYER
    out[start + 2] = ((layer & 0xFFFF) << 16) | 6
    out[start + 3] = (DATATYPE << 16) | (datatype & 0xFFFF)
    out[start + 4] = ((4 + 8 * (counts + 1)) << 16) | XY
    out[start + 7 + 2 * counts] = (4 << 16) | ENDEL
    poly = np.repeat(np.arange(counts.size), counts)
    pos = start[poly] + 5 + 2 * (np.arange(len(poly)) - pset.offsets[poly])
    out[pos] = x.astype(np.int32).view(np.uint32)
    out[pos + 1] = y.astype(np.int32).view(np.uint32)
    first = pset.offsets[:-1]
    out[start + 5 + 2 * counts] = out[pos[first]]
    out[start + 6 + 2 * counts] = out[pos[first] + 1]
    return out.astype(">u4").tobytes()


def structure_end(data: bytes, name: str) -> int:
    """Byte offset of the ENDSTR record of structure ``name`` in a GDSII byte string."""
    pos, current, target = 0, None, name.encode()
    while pos + 4 <= len(data):
        length, rtype = int.from_bytes(data[pos:pos + 2], "big"), int.from_bytes(data[pos + 2:pos + 4], "big")
        if length < 4:
            break
        if rtype == STRNAME:
            current = data[pos + 4:pos + length].rstrip(b"\0")
        elif rtype == ENDSTR and current == target:
            return pos
        pos += length
    raise DoeError(f"structure {name!r} not found in the written library")


def write_element_gds(lib: gdstk.Library, path: str | Path, masks: np.ndarray, grid: PixelGrid,
                      layers: Sequence[int] = DEFAULT_LAYERS, datatype: int = 0, tone: str = "dark",
                      cell_name: str = ELEMENT_CELL, progress: Progress | None = None,
                      max_vertices: int = MAX_VERTICES) -> list[dict]:
    """Write ``lib`` (holding an empty element cell) with the element's polygons streamed in.

    gdstk writes everything else (marks, aperture, labels, references), fracturing its
    polygons to ``max_vertices``; the element's BOUNDARY records are built with numpy per
    mask layer (polygons of at most ``max_vertices`` vertices, :func:`boundary_records`)
    and spliced into its structure, so no Python object is made per polygon and one layer
    is in memory at a time.

    Returns
    -------
    list of dict
        Per mask: layer, datatype, polygons, vertices, max_vertices.
    """
    drawn = drawn_masks(masks, tone)
    layers = check_layers(layers, drawn.shape[0])
    if drawn.shape[1:] != tuple(grid.shape):
        raise DoeError(f"masks shaped {drawn.shape} do not match the pixel grid {grid.shape}")
    path = Path(path)
    # A temporary like doedesign.fileio.atomic_path's, so a killed run's skeleton is found
    # and removed by the next run like any other temporary.
    skeleton_path = make_temporary(path.parent)
    try:
        lib.write_gds(str(skeleton_path), max_points=max_vertices)
        skeleton = skeleton_path.read_bytes()
    finally:
        skeleton_path.unlink(missing_ok=True)
    cut = structure_end(skeleton, cell_name)

    def one_layer(j):
        pset = mask_polygons(drawn[j], max_vertices)
        stat = {"layer": layers[j], "datatype": int(datatype), "polygons": pset.n_polygons,
                "vertices": pset.n_vertices, "max_vertices": pset.max_vertices}
        return boundary_records(pset, grid, layers[j], datatype, max_vertices), stat

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


def real8(b: bytes) -> float:
    """GDSII 8-byte real (excess-64, base-16 exponent, 56-bit mantissa)."""
    v = int.from_bytes(b, "big")
    sign = -1.0 if v >> 63 else 1.0
    return sign * (v & ((1 << 56) - 1)) / float(1 << 56) * 16.0 ** (((v >> 56) & 0x7F) - 64)


def gds_name(name: object) -> str:
    """A GDSII structure/library name: letters, digits, ``_`` and ``-``, at most 32 characters."""
    clean = "".join(ch if ch.isalnum() or ch in "_-" else "_" for ch in str(name))
    return clean[:32] or "design"
