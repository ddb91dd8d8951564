"""Pixel-exact Manhattan polygons from a binary mask, fully vectorized.

Every row of the mask is cut into runs of set pixels; a run is joined to the run below
when each is the other's only overlapping neighbour. Such a chain of runs is a simple
staircase polygon (left edge down, right edge up), so the outlines are merged along the
columns and the rows, never cut diagonally, never overlap (runs are disjoint), and every
vertex lies on a pixel corner. Chains are cut so that no polygon has more than
``max_vertices`` vertices (199 is the GDSII limit most tools accept).

Coordinates here are integer pixel-corner indices ``(col, row)``: pixel ``(r, c)`` spans
columns ``c .. c+1`` and rows ``r .. r+1`` (row 0 at the top). :mod:`masks.gds` maps them
onto the plate.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from doedesign.errors import DoeError


@dataclass
class PolygonSet:
    """Polygons of one mask layer as one flat vertex array.

    Attributes
    ----------
    vertices : ndarray of int64, shape (n_vertices, 2)
        ``(col, row)`` pixel-corner indices, polygon after polygon.
    offsets : ndarray of int64, shape (n_polygons + 1,)
        Polygon ``i`` is ``vertices[offsets[i]:offsets[i + 1]]``.
    """

    vertices: np.ndarray
    offsets: np.ndarray

    @property
    def n_polygons(self):
        return len(self.offsets) - 1

    @property
    def n_vertices(self):
        return len(self.vertices)

    @property
    def max_vertices(self):
        return int(np.diff(self.offsets).max()) if self.n_polygons else 0

    def split(self):
        """List of ``(k, 2)`` vertex arrays, one per polygon."""
        off = self.offsets.tolist()
        return [self.vertices[a:b] for a, b in zip(off[:-1], off[1:])]


def mask_polygons(mask, max_vertices=199):
    """Merged Manhattan polygons covering exactly the True pixels of ``mask``.

    Parameters
    ----------
    mask : ndarray of bool, shape (rows, cols)
    max_vertices : int
        Largest vertex count of one polygon (at least 8).

    Returns
    -------
    PolygonSet
        Counter-clockwise polygons in (col, row-down) index space.
    """
    mask = np.asarray(mask)
    if mask.ndim != 2 or mask.dtype != bool:
        raise DoeError(f"mask must be a 2-D boolean array, got {mask.dtype} shape {mask.shape}")
    if max_vertices < 8:
        raise DoeError(f"max_vertices must be at least 8, got {max_vertices}")
    rows, cols = mask.shape
    edges = np.diff(mask.view(np.int8), axis=1, prepend=0, append=0)
    r, c0 = np.nonzero(edges == 1)
    c1 = np.nonzero(edges == -1)[1]
    n = r.size
    if n == 0:
        return PolygonSet(np.zeros((0, 2), np.int64), np.zeros(1, np.int64))
    r = r.astype(np.int64)
    c0 = c0.astype(np.int64)
    c1 = c1.astype(np.int64)
    width = cols + 1
    starts = r * width + c0  # row-major keys: runs are sorted by them
    ends = r * width + c1

    below, n_below = _overlaps(starts, ends, r, c0, c1, r + 1, width, n)
    above, n_above = _overlaps(starts, ends, r, c0, c1, r - 1, width, n)
    linked = (n_below == 1)
    linked[linked] = n_above[below[linked]] == 1
    src = np.nonzero(linked)[0]
    graph = coo_matrix((np.ones(src.size, np.int8), (src, below[src])), shape=(n, n))
    head = connected_components(graph, directed=False)[1].astype(np.int64)
    order = np.argsort(head * (rows + 1) + r)
    r, c0, c1, head = r[order], c0[order], c1[order], head[order]
    has_pred = np.ones(n, bool)
    has_pred[0] = False
    has_pred[1:] = head[1:] == head[:-1]

    # Vertices a transition adds: 2 where the left edge steps, 2 where the right edge steps.
    prev = np.maximum(np.arange(n) - 1, 0)
    step_l = has_pred & (c0 != c0[prev])
    step_r = has_pred & (c1 != c1[prev])
    contrib = 2 * step_l.astype(np.int64) + 2 * step_r
    cum = np.cumsum(contrib)
    chain_start = np.maximum.accumulate(np.where(has_pred, 0, np.arange(n)))
    cum_local = cum - cum[chain_start]
    segment = cum_local // (max_vertices - 4)
    first = ~has_pred
    first[1:] |= segment[1:] != segment[:-1]
    poly = np.cumsum(first) - 1
    last = np.ones(n, bool)
    last[:-1] = first[1:]

    nxt = np.minimum(np.arange(n) + 1, n - 1)
    # Corners per run: left-top, left-bottom (left edge, walked down), right-bottom,
    # right-top (right edge, walked up); a corner exists where the polygon starts or ends
    # or where that edge steps sideways.
    left_emit = np.stack([first | step_l, last | (c0 != c0[nxt])], axis=1)
    right_emit = np.stack([last | (c1 != c1[nxt]), first | step_r], axis=1)
    left_xy = np.stack([np.stack([c0, r], 1), np.stack([c0, r + 1], 1)], axis=1)
    right_xy = np.stack([np.stack([c1, r + 1], 1), np.stack([c1, r], 1)], axis=1)
    n_poly = int(poly[-1]) + 1
    n_left = np.bincount(poly, left_emit.sum(axis=1), minlength=n_poly).astype(np.int64)
    n_right = np.bincount(poly, right_emit.sum(axis=1), minlength=n_poly).astype(np.int64)
    offsets = np.zeros(n_poly + 1, np.int64)
    np.cumsum(n_left + n_right, out=offsets[1:])
    vertices = np.empty((offsets[-1], 2), np.int64)
    # Left edge: runs in chain order; right edge: the same runs reversed (reverse the
    # whole list, which keeps each polygon's runs together, now last to first).
    sel = left_emit.ravel()
    vpoly = np.repeat(poly, 2)[sel]
    rank = np.arange(vpoly.size) - np.concatenate([[0], np.cumsum(n_left)[:-1]])[vpoly]
    vertices[offsets[vpoly] + rank] = left_xy.reshape(-1, 2)[sel]
    sel = right_emit[::-1].ravel()
    vpoly = np.repeat(poly[::-1], 2)[sel]
    start = np.zeros(n_poly, np.int64)
    start[::-1] = np.concatenate([[0], np.cumsum(n_right[::-1])[:-1]])
    rank = np.arange(vpoly.size) - start[vpoly]
    vertices[offsets[vpoly] + n_left[vpoly] + rank] = right_xy[::-1].reshape(-1, 2)[sel]
    return PolygonSet(vertices, offsets)


def _overlaps(starts, ends, r, c0, c1, row, width, n):
    """First overlapping run in ``row`` (per run) and how many runs there overlap it."""
    lo = np.searchsorted(ends, row * width + c0, side="right")
    hi = np.searchsorted(starts, row * width + c1, side="left") - 1
    lo_c = np.minimum(lo, n - 1)
    hi_c = np.clip(hi, 0, n - 1)
    ok = (lo < n) & (hi >= 0) & (r[lo_c] == row) & (r[hi_c] == row) & (hi >= lo)
    count = np.where(ok, hi - lo + 1, 0)
    return lo_c, count
