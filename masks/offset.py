"""Edge offsets of mask geometry: a mask's merged pixel polygons grown or shrunk by a distance,
and the read-back check of such geometry on a fine grid.

Offsetting (:func:`offset_polygons`): an opening grown by ``d`` covers every point within
Chebyshev distance ``d`` of it; shrunk, every point whose ``d``-square lies inside it (for
Manhattan geometry the Minkowski sum with, or erosion by, a square: every opening edge moves by
``d`` and square corners stay square). For ``|d|`` under half the pitch that region is a union
of the cells cut by the lines ``k pitch +- |d|`` (:func:`offset_cells`), so it is built
exactly as a raster of those cells traced by :mod:`masks.polygons` (merged, holes keyholed,
split to the vertex limit), whose lattice is then mapped onto those lines. Vertices sit off
the pixel grid, so the pixel-grid check of :mod:`masks.verify` no longer applies. (Offsetting
the merged pixel polygons with Clipper instead opened every keyhole cut and every split into a
slit when shrinking.)

Checking (:func:`verify_offset_layer`), written apart from the offsetting: the polygons read
back from the file are filled by a winding-number scanline at the points of a fine grid whose
lines straddle every line an offset edge may lie on (``k pitch +- d``, half a database unit to
either side) and cross every pixel's middle, and compared with the Chebyshev criterion
evaluated from the pixel mask by a summed-area table. Edges lie on whole database units, so
no sample sits on one, and an edge missing or moved by one unit flips a sample beside its
line. Every vertex must also lie on one of those lines. Both must hold exactly.

Coordinates follow :class:`masks.grid.PixelGrid` (y up on the plate, rows toward decreasing
y, x negated when mirrored).
"""

from __future__ import annotations

import math

import gdstk
import numpy as np

from doedesign.errors import DoeError

from .grid import MAX_VERTICES, PRECISION_M, PixelGrid
from .polygons import mask_polygons

__all__ = ["expected_open", "offset_cells", "offset_polygons", "sample_positions_dbu", "verify_offset_layer",
           "winding_at_samples"]


def offset_polygons(mask: np.ndarray, grid: PixelGrid, offset_m: float, layer: int, datatype: int = 0
                    ) -> list[gdstk.Polygon]:
    """The open areas of a pixel mask with every edge moved outward by ``offset_m`` (inward if negative).

    Parameters
    ----------
    mask : ndarray of bool (rows, cols)
        True where the mask opens (dark tone: what is drawn), row 0 at the top.
    grid : PixelGrid
    offset_m : float
        Edge offset (m), rounded to the 1 nm database unit; positive = openings wider. Less
        than half the pixel pitch in size.
    layer, datatype : int

    Returns
    -------
    list of gdstk.Polygon
        In plate coordinates (um), at most :data:`masks.grid.MAX_VERTICES` vertices each, holes
        joined by zero-width cuts, no two overlapping.

    Raises
    ------
    DoeError
        An offset of half the pitch or more.
    """
    mask = np.asarray(mask, bool)
    pitch = grid.pitch_dbu
    b = int(round(offset_m / PRECISION_M))
    if 2 * abs(b) >= pitch:
        raise DoeError(f"an edge offset of {offset_m * 1e6:.3f} um reaches half the {grid.pitch_um:g} um pixel")
    if b == 0:
        pset = mask_polygons(mask, MAX_VERTICES)
        pts = grid.to_um(pset.vertices)
    else:
        pset = mask_polygons(offset_cells(mask, b > 0), MAX_VERTICES)
        # refined lattice line j lies at (j // 2) pitch - |b| (j even) or + |b| (j odd)
        pts = grid.dbu_to_um(pset.vertices // 2 * pitch + np.where(pset.vertices % 2 == 1, abs(b), -abs(b)))
    off = pset.offsets.tolist()
    return [gdstk.Polygon(pts[a:c], layer=layer, datatype=datatype)  # type: ignore[arg-type]  # gdstk takes any (k, 2) array; its stub says Sequence of tuples
            for a, c in zip(off[:-1], off[1:])]


def offset_cells(mask: np.ndarray, grow: bool) -> np.ndarray:
    """The offset openings of ``mask`` as a raster of ``(2 rows + 1, 2 cols + 1)`` cells.

    For an offset ``b`` with ``0 < |b| < pitch / 2`` the lines ``k pitch +- |b|`` cut the plate
    into cells on which the offset is constant: cell ``2 k + 1`` of an axis is the middle of
    pixel ``k``, ``[k p + |b|, (k + 1) p - |b|]``; cell ``2 k`` straddles pixel line ``k``,
    ``[k p - |b|, k p + |b|]``, and the square of half-side ``|b|`` around any point inside
    it meets the pixels on both sides. A cell is open when any (grown) or every (shrunk)
    pixel its points' squares meet is open: a middle cell its own pixel, a straddling cell the
    two pixels across its line, a cell straddling a pixel corner the four pixels there;
    outside the grid is closed.

    Parameters
    ----------
    mask : ndarray of bool (rows, cols)
    grow : bool
        True for a positive offset (openings wider), False for a negative one.

    Returns
    -------
    ndarray of bool (2 rows + 1, 2 cols + 1)
        The open cells; its lattice line ``j`` lies at ``(j // 2) pitch - |b|`` (``j`` even)
        or ``(j // 2) pitch + |b|`` (``j`` odd) along either axis.
    """
    padded = np.pad(np.asarray(mask, bool), 1)
    join = np.logical_or if grow else np.logical_and
    cols = join(padded[:, :-1], padded[:, 1:])  # (rows + 2, cols + 1): across each column line
    out = np.empty((2 * mask.shape[0] + 1, 2 * mask.shape[1] + 1), bool)
    out[1::2, 1::2] = mask
    out[1::2, 0::2] = cols[1:-1]
    out[0::2, 1::2] = join(padded[:-1, 1:-1], padded[1:, 1:-1])
    out[0::2, 0::2] = join(cols[:-1], cols[1:])
    return out


def sample_positions_dbu(n_px: int, pitch_dbu: int, offset_dbu: int, margin_px: int) -> np.ndarray:
    """Sample coordinates along one axis (database units from the grid's outer corner, on half
    units), sorted: half a unit to either side of every line ``k pitch +- offset`` and one in
    the middle of every pixel, from ``margin_px`` pixels before the grid to as many after it."""
    k = np.arange(-margin_px, n_px + margin_px + 1)[:, None] * pitch_dbu
    b = abs(int(offset_dbu))
    pos = np.concatenate([(k + np.array([-b - 0.5, -b + 0.5, b - 0.5, b + 0.5])).ravel(),
                          (k[:-1] + pitch_dbu // 2 + 0.5).ravel()])
    return np.unique(pos)


def expected_open(mask: np.ndarray, pitch_dbu: int, offset_dbu: int, xs: np.ndarray, ys: np.ndarray) -> np.ndarray:
    """Whether each sample (ys[i], xs[j]) lies in the mask's openings offset by ``offset_dbu``.

    Grown (offset >= 0): some open pixel meets the square of half-side ``offset`` around the
    sample. Shrunk: every pixel that square meets is open (outside the grid is closed).
    Counted with a summed-area table of the padded mask.
    """
    mask = np.asarray(mask, bool)
    b = abs(int(offset_dbu))
    pad = b // pitch_dbu + 2 + int(max(-xs.min(), -ys.min(), xs.max() - mask.shape[1] * pitch_dbu,
                                       ys.max() - mask.shape[0] * pitch_dbu, 0) // pitch_dbu)
    padded = np.pad(mask, pad).astype(np.int64)
    sat = np.zeros((padded.shape[0] + 1, padded.shape[1] + 1), np.int64)
    sat[1:, 1:] = padded.cumsum(0).cumsum(1)
    c0 = np.floor((xs - b) / pitch_dbu).astype(np.int64) + pad
    c1 = np.floor((xs + b) / pitch_dbu).astype(np.int64) + pad + 1
    r0 = np.floor((ys - b) / pitch_dbu).astype(np.int64)[:, None] + pad
    r1 = np.floor((ys + b) / pitch_dbu).astype(np.int64)[:, None] + pad + 1
    count = sat[r1, c1] - sat[r0, c1] - sat[r1, c0] + sat[r0, c0]
    if offset_dbu >= 0:
        return count > 0
    return count == (r1 - r0) * (c1 - c0)


def winding_at_samples(points: np.ndarray, counts: np.ndarray, xs: np.ndarray, ys: np.ndarray
                       ) -> tuple[np.ndarray, list[str]]:
    """How many polygons cover each sample (ys[i], xs[j]): a scanline winding count.

    ``points`` (n, 2) are vertices in database units with x to the right and y downward (rows),
    ``counts`` the vertices of each polygon. Each polygon counts +1 inside whichever way it
    winds. Samples lie on half units, so none sits on an edge.
    """
    problems: list[str] = []
    counts = np.asarray(counts, np.int64)
    if counts.size == 0:
        return np.zeros((ys.size, xs.size), np.int16), problems
    ends = np.cumsum(counts)
    starts = ends - counts
    x, y = points[:, 0].astype(np.int64), points[:, 1].astype(np.int64)
    xn, yn = np.roll(x, -1), np.roll(y, -1)
    xn[ends - 1], yn[ends - 1] = x[starts], y[starts]
    diagonal = (x != xn) & (y != yn)
    if diagonal.any():
        problems.append(f"{int(diagonal.sum())} edges are not axis-parallel")
    area2 = np.add.reduceat(x * yn - xn * y, starts)
    vertical = np.nonzero((x == xn) & (y != yn))[0]
    poly = np.searchsorted(ends, vertical, side="right")
    w = (np.sign(yn[vertical] - y[vertical]) * -np.sign(area2)[poly]).astype(np.int16)
    ix = np.searchsorted(xs, x[vertical])
    lo = np.searchsorted(ys, np.minimum(y[vertical], yn[vertical]))
    hi = np.searchsorted(ys, np.maximum(y[vertical], yn[vertical]))
    # int16: a sample is covered by a handful of polygons at most (the geometry of one layer).
    diff = np.zeros((ys.size + 1, xs.size + 1), np.int16)
    np.add.at(diff, (lo, ix), w)
    np.add.at(diff, (hi, ix), -w)
    np.cumsum(diff, axis=0, out=diff)
    np.cumsum(diff, axis=1, out=diff)
    return diff[:ys.size, :xs.size], problems


def verify_offset_layer(points_dbu: np.ndarray, counts: np.ndarray, mask: np.ndarray, grid: PixelGrid,
                        offset_m: float) -> dict:
    """Check one layer's read-back polygons against the offset of its pixel mask.

    Parameters
    ----------
    points_dbu : ndarray of int64 (n, 2)
        Vertices as read from the file (plate database units, y up).
    counts : ndarray of int
        Vertices per polygon.
    mask : ndarray of bool (rows, cols)
        The open pixels before the offset.
    grid : PixelGrid
    offset_m : float

    Returns
    -------
    dict
        ``mismatched_samples``, ``samples``, ``overlapping_samples``,
        ``vertices_off_lines`` and ``problems``.
    """
    pitch = grid.pitch_dbu
    b = int(round(offset_m / PRECISION_M))
    if 2 * abs(b) >= pitch:
        raise DoeError(f"an edge offset of {offset_m * 1e6:.3f} um reaches half the {grid.pitch_um:g} um pixel")
    rows, cols = grid.shape
    x0, y0 = grid.origin_dbu
    pts = np.array(points_dbu, np.int64)
    if grid.mirrored:
        pts[:, 0] = -pts[:, 0]
    pts[:, 0] -= x0
    pts[:, 1] = y0 - pts[:, 1]
    on_line = np.zeros(pts.shape, bool)
    for sign in (1, -1):
        on_line |= (pts - sign * b) % pitch == 0
    off_lines = int((~on_line.all(axis=1)).sum())
    margin = math.ceil(abs(b) / pitch) + 1
    xs = sample_positions_dbu(cols, pitch, b, margin)
    ys = sample_positions_dbu(rows, pitch, b, margin)
    cover, problems = winding_at_samples(pts, counts, xs, ys)
    want = expected_open(mask, pitch, b, xs, ys)
    mismatched = int(((cover > 0) != want).sum())
    overlaps = int((cover > 1).sum())
    if overlaps or (cover < 0).any():
        problems.append(f"{overlaps} samples covered by more than one polygon")
    if off_lines:
        problems.append(f"{off_lines} vertices off the lines k pitch +- offset")
    return {"mismatched_samples": mismatched, "samples": int(cover.size),
            "overlapping_samples": overlaps, "vertices_off_lines": off_lines, "problems": problems}
