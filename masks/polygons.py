"""Pixel-exact Manhattan polygons from a binary mask, fully merged and vectorized.

Each 4-connected component of set pixels becomes one polygon: its outline is traced on the
pixel-corner lattice (:func:`traced_outlines`) and its holes are joined to it by zero-width
cut lines along pixel-corner rows (keyholes: GDSII has no holes). Components whose outline
would exceed ``max_vertices`` (199 is the GDSII limit most tools accept; None, for OASIS,
sets none) are cut into stacks of row runs instead (:func:`run_chain_polygons`): the
fracturing is done here, on the pixel lattice, rather than by gdstk's ``Polygon.fracture``
afterwards, because the pieces are then whole pixel rows by construction (no slivers, every
cut on a pixel edge) and no Python object is made per polygon. Every edge is axis-parallel,
every vertex lies on a pixel corner, and no two polygons overlap.

Coordinates here are integer pixel-corner indices ``(col, row)``: pixel ``(r, c)`` spans
columns ``c .. c+1`` and rows ``r .. r+1`` (row 0 at the top). :mod:`masks.gds` maps them
onto the plate.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from doedesign.errors import DoeError

__all__ = ["PolygonSet", "mask_polygons", "run_chain_polygons", "traced_outlines"]


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
    def n_polygons(self) -> int:
        return len(self.offsets) - 1

    @property
    def n_vertices(self) -> int:
        return len(self.vertices)

    @property
    def max_vertices(self) -> int:
        return int(np.diff(self.offsets).max()) if self.n_polygons else 0

    def split(self) -> list[np.ndarray]:
        """List of ``(k, 2)`` vertex arrays, one per polygon."""
        off = self.offsets.tolist()
        return [self.vertices[a:b] for a, b in zip(off[:-1], off[1:])]


def mask_polygons(mask: np.ndarray, max_vertices: int | None = 199) -> PolygonSet:
    """Fully merged Manhattan polygons covering exactly the True pixels of ``mask``.

    Each 4-connected component whose outline (holes joined by keyhole cuts) has at most
    ``max_vertices`` vertices becomes one polygon (:func:`traced_outlines`); the others
    are cut into stacks of row runs (:func:`run_chain_polygons`), split to the limit.

    Parameters
    ----------
    mask : ndarray of bool, shape (rows, cols)
    max_vertices : int or None
        Largest vertex count of one polygon (at least 4: then every polygon is a
        rectangle); None: no limit, every component one polygon.

    Returns
    -------
    PolygonSet
        Polygons in (col, row-down) index space, each wound one way round (traced outlines
        and run stacks may wind opposite ways).
    """
    mask = np.asarray(mask)
    if mask.ndim != 2 or mask.dtype != bool:
        raise DoeError(f"mask must be a 2-D boolean array, got {mask.dtype} shape {mask.shape}")
    if max_vertices is None:
        max_vertices = np.iinfo(np.int64).max
    if max_vertices < 4:
        raise DoeError(f"max_vertices must be at least 4, got {max_vertices}")
    traced, done = traced_outlines(mask, max_vertices)
    rest = run_chain_polygons(mask & ~done, max_vertices)
    return PolygonSet(np.concatenate([traced.vertices, rest.vertices]),
                      np.concatenate([traced.offsets, rest.offsets[1:] + traced.offsets[-1]]))


# Lattice point (y, x) sees pixels a = (y-1, x-1), b = (y-1, x), c = (y, x-1), d = (y, x);
# code = a + 2 b + 4 c + 8 d. An outline edge leaves the point going E (0) when d is set
# and b not, S (1) when c and not d, W (2) when a and not c, N (3) when b and not a: the set
# pixel is always on the walker's right (rows down). Directions in that order turn right
# by +1, which at a saddle (only a and d, or only b and c) keeps diagonal pixels apart
# (4-connectivity).
_CODES = np.arange(16)
_A, _B, _C, _D = (_CODES >> 0) & 1, (_CODES >> 1) & 1, (_CODES >> 2) & 1, (_CODES >> 3) & 1
_LEAVES = np.stack([_D & (1 - _B), _C & (1 - _D), _A & (1 - _C), _B & (1 - _A)], axis=1).astype(bool)
_LEAVES[[3, 5, 10, 12]] = False  # half-set blocks: the outline runs straight through, no corner
_N_LEAVES = _LEAVES.sum(axis=1).astype(np.int8)
_FIRST_LEAF = np.argmax(_LEAVES, axis=1).astype(np.int8)
_LAST_LEAF = (3 - np.argmax(_LEAVES[:, ::-1], axis=1)).astype(np.int8)
_RIGHT_PIXEL = np.array([[0, 0], [0, -1], [-1, -1], [-1, 0]])  # (dy, dx) of the set pixel


def traced_outlines(mask: np.ndarray, max_vertices: int = 199) -> tuple[PolygonSet, np.ndarray]:
    """Traced outlines, holes keyholed in, of the 4-connected components with few corners.

    Parameters
    ----------
    mask : ndarray of bool, shape (rows, cols)
    max_vertices : int

    Returns
    -------
    polygons : PolygonSet
        One polygon per such component: its vertices in walking order (set pixels on the
        walker's right with rows pointing down, so outlines run one way, holes the other).
    done : ndarray of bool, shape (rows, cols)
        The pixels those polygons cover.
    """
    rows, cols = mask.shape
    labels, n_comp = ndimage.label(mask)
    done = np.zeros(mask.shape, bool)
    empty = PolygonSet(np.zeros((0, 2), np.int64), np.zeros(1, np.int64))
    if n_comp == 0:
        return empty, done
    m = np.pad(mask, 1).view(np.uint8)
    code = m[:-1, :-1] + 2 * m[:-1, 1:] + 4 * m[1:, :-1] + 8 * m[1:, 1:]
    corner = _N_LEAVES[code] > 0
    # Corner points numbered in row-major order; the same numbers read column-major.
    # (int32 throughout: these arrays hold millions of entries and bound the memory)
    number = np.cumsum(corner.ravel(), dtype=np.int32).reshape(corner.shape) - 1
    col_order = number.T[corner.T]
    n_pt = col_order.size
    col_pos = np.empty(n_pt, np.int32)
    col_pos[col_order] = np.arange(n_pt, dtype=np.int32)
    # entries: one per edge leaving a corner point (two at a saddle), points in row-major
    # order, directions ascending
    points = np.flatnonzero(corner).astype(np.int32)
    del corner
    pt_code = code.ravel()[points]
    per_pt = _N_LEAVES[pt_code]
    entry_start = np.zeros(n_pt, np.int32)
    np.cumsum(per_pt[:-1], out=entry_start[1:])
    i = np.repeat(np.arange(n_pt, dtype=np.int32), per_pt)  # corner point of each entry
    n = i.size
    direction = _FIRST_LEAF[pt_code][i]
    direction[entry_start[per_pt == 2] + 1] = _LAST_LEAF[pt_code[per_pt == 2]]
    pt = points[i]
    y, x = np.divmod(pt, np.int32(cols + 1))
    # Next corner along each edge: the neighbour in row-major order for E/W, in
    # column-major order for S/N (an edge always ends at the next corner on its line).
    nxt_pt = i + np.where(direction == 0, np.int32(1), np.int32(-1))
    vert = direction % 2 == 1
    nxt_pt[vert] = col_order[col_pos[i[vert]] + np.where(direction[vert] == 1, np.int32(1), np.int32(-1))]
    del i, vert, col_pos
    # At the next point take the edge that turns right of ours when there are two (saddle).
    succ = entry_start[nxt_pt]
    two = np.append(entry_start[1:], np.int32(n))[nxt_pt] - succ == 2
    del nxt_pt
    succ[two] += direction[succ[two]] != (direction[two] + 1) % 4
    # Each entry's component is that of the set pixel on its right.
    comp = labels[y + _RIGHT_PIXEL[direction, 0], x + _RIGHT_PIXEL[direction, 1]] - 1
    del pt, code, points, pt_code, per_pt
    x, y, succ, added = _join_holes(mask, number, col_order, entry_start, direction, x, y, succ, comp,
                                    n_comp)
    del number, col_order
    n_corners = np.bincount(comp, minlength=n_comp) + added
    simple_comp = n_corners <= max_vertices
    # First entry of each component: labels count up in raster order, so a component's
    # first entry is where the running maximum of the labels rises.
    rise = np.ones(n, bool)
    rise[1:] = comp[1:] > np.maximum.accumulate(comp)[:-1]
    head = np.nonzero(rise)[0]
    if head.size != n_comp or not np.array_equal(comp[head], np.arange(n_comp)):
        raise RuntimeError("component labels are not in raster order")
    keep = np.nonzero(simple_comp)[0]
    if keep.size == 0:
        return empty, done
    # Walk all kept outlines at once, longest first, so the ones still walking are a prefix.
    keep = keep[np.argsort(-n_corners[keep], kind="stable")]
    lengths = n_corners[keep]
    offsets = np.zeros(keep.size + 1, np.int64)
    np.cumsum(lengths, out=offsets[1:])
    vertices = np.empty((offsets[-1], 2), np.int64)
    cur = head[keep]
    still = np.searchsorted(-lengths, -np.arange(1, int(lengths[0]) + 1), side="right")
    for step, k in enumerate(still):
        cur = cur[:k]
        vertices[offsets[:k] + step, 0] = x[cur]
        vertices[offsets[:k] + step, 1] = y[cur]
        cur = succ[cur]
    done = simple_comp[np.maximum(labels - 1, 0)] & mask
    return PolygonSet(vertices, offsets), done


def _join_holes(mask, number, col_order, entry_start, direction, x, y, succ, comp, n_comp):
    """Join every hole's outline to its component's by a zero-width cut (keyhole).

    A hole's first corner in raster order H0 is the top-left corner of its first pixel; the
    cut runs from H0 west along that pixel-corner row, between set pixels, to the first
    outline it meets at P (a concave corner, or a point inside a north-going edge). The
    ring then reads ... P, H0, (the hole, round), H0, P, ..., with P and H0 added as
    vertices where needed. Cuts only ever join a hole to an outline further up or left, so
    each component's outlines become one ring.

    Returns
    -------
    x, y, succ : ndarray
        Extended with the added vertices; ``succ`` relinked.
    added : ndarray of int64, shape (n_comp,)
        Vertices added per component.
    """
    rows, cols = mask.shape
    n = succ.size
    bg, n_bg = ndimage.label(~mask, structure=np.ones((3, 3), bool))
    flat = bg.ravel()
    rise = np.ones(flat.size, bool)
    rise[1:] = flat[1:] > np.maximum.accumulate(flat)[:-1]
    first = np.nonzero(rise & (flat > 0))[0]  # first pixel of each background component
    border = np.zeros(n_bg + 1, bool)
    border[np.concatenate([bg[0], bg[-1], bg[:, 0], bg[:, -1]])] = True
    first = first[~border[flat[first]]]
    del bg, flat, rise
    if first.size == 0:
        return x, y, succ, np.zeros(n_comp, np.int64)
    y0, x0 = np.divmod(first, cols)
    e_h0 = entry_start[number[y0, x0]]
    # P: start of the run of columns whose pixels above and below the row line are both set
    run_start = np.where(mask[:-1] & mask[1:], np.int32(-1), np.arange(cols, dtype=np.int32))
    np.maximum.accumulate(run_start, axis=1, out=run_start)
    xp = run_start[y0 - 1, x0 - 1] + 1
    del run_start
    a = (xp > 0) & mask[y0 - 1, np.maximum(xp - 1, 0)]
    c = (xp > 0) & mask[y0, np.maximum(xp - 1, 0)]
    corner = a != c
    h = y0.size
    pred = np.empty(n, np.int64)
    pred[succ] = np.arange(n)
    last_h = pred[e_h0]
    h0c = n + np.arange(h)  # second visit of H0
    p1 = n + h + np.arange(h)  # first visit of P
    mid = np.nonzero(~corner)[0]
    p2 = np.full(h, -1, np.int64)
    p2[mid] = n + 2 * h + np.arange(mid.size)  # second visit of P inside an edge
    total = n + 2 * h + mid.size
    x = np.concatenate([x, x0, xp, xp[mid]]).astype(np.int32)
    y = np.concatenate([y, y0, y0, y0[mid]]).astype(np.int32)
    succ = np.concatenate([succ, np.zeros(total - n, succ.dtype)])
    # the north-going edge holding P: from the next corner below P on its column line
    col_key = x[entry_start[col_order]].astype(np.int64) * (rows + 1) + y[entry_start[col_order]]
    below = col_order[np.searchsorted(col_key, xp[mid].astype(np.int64) * (rows + 1) + y0[mid], side="right")]
    edge = np.append(entry_start[1:], n)[below] - 1  # N is a point's last direction
    # several cuts into one edge: spliced in the order the edge meets them (south first)
    order = np.lexsort((-y0[mid], edge))
    mid, edge = mid[order], edge[order]
    group_start = np.ones(mid.size, bool)
    group_start[1:] = edge[1:] != edge[:-1]
    group_end = np.ones(mid.size, bool)
    group_end[:-1] = group_start[1:]
    after = succ[edge]  # the last cut into an edge returns to where the edge went
    inner = np.nonzero(~group_end)[0]
    after[inner] = p1[mid[inner + 1]]
    succ[p2[mid]] = after
    succ[edge[group_start]] = p1[mid[group_start]]
    succ[h0c[mid]] = p2[mid]
    cor = np.nonzero(corner)[0]
    ep = entry_start[number[y0[cor], xp[cor]]]
    # P's incoming edge may itself hold cuts: then P is reached from the last of them
    pp = pred[ep]
    cut_edges, cut_last = edge[group_end], p2[mid[group_end]]
    k = np.minimum(np.searchsorted(cut_edges, pp), max(cut_edges.size - 1, 0))
    if cut_edges.size:
        pp = np.where(cut_edges[k] == pp, cut_last[k], pp)
    succ[pp] = p1[cor]
    succ[h0c[cor]] = ep
    succ[p1] = e_h0
    succ[last_h] = h0c
    added = np.bincount(comp[e_h0], np.where(corner, 2, 3), minlength=n_comp).astype(np.int64)
    return x, y, succ, added


def run_chain_polygons(mask: np.ndarray, max_vertices: int = 199) -> PolygonSet:
    """Stacks of overlapping row runs as polygons of at most ``max_vertices`` corners.

    Every row of the mask is cut into runs of set pixels; a run is joined to its first
    overlapping run below when that run's first overlapping run above is this one. Such a
    chain of runs is a simple staircase polygon (left edge down, right edge up) without
    holes; neighbouring chains share edges but never overlap.
    """
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
    # Link each run to its first overlapping run below when that run's first overlapping run
    # above is this one: a matching, so every chain stays a stack of overlapping runs.
    linked = n_below > 0
    linked[linked] = above[below[linked]] == np.nonzero(linked)[0]
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
    # a piece's steps add fewer than max_vertices - 4 corners to its 4 (at 4 or 5: none)
    segment = cum_local // max(max_vertices - 4, 1)
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
