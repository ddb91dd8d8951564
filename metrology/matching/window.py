"""Where to look: the window with the most structure, in the design's or the camera's frame.

The profilometer field of the demo, the window a height diagnosis fits (design frame) and the
window a camera-frame comparison or diagnosis fits are all placed where the pattern has level
edges (the effects show at edges and between levels), scored by one edge count
(:func:`edge_count`). Arrays are row-major, row 0 at the top; design windows are half-open
``(row0, row1, col0, col1)`` in design pixels, camera windows their top-left camera pixel.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
import scipy.ndimage as ndi

from doedesign.errors import DoeError

if TYPE_CHECKING:
    from metrology.matching.instrument import Placement

__all__ = ["busiest_camera_window", "busiest_window", "edge_count", "window_sums"]


def busiest_window(levels: np.ndarray, size_px: int, need_flat: bool = True, inside_circle: bool = False,
                   min_level0_px: int = 0) -> tuple[int, int, int, int]:
    """The window of ``size_px`` design pixels per side with the most level edges.

    Parameters
    ----------
    levels : ndarray of int (rows, cols)
    size_px : int
        Window side (clipped to the design).
    need_flat : bool
        Score edges times flat interiors (design pixels whose 3 x 3 neighbourhood is one
        level), as the diagnosis needs both; else edges alone.
    inside_circle : bool
        Keep the whole window (its diagonal) inside the element's inscribed circle, as a
        profilometer field on a round element must be.
    min_level0_px : int
        Keep only windows holding at least this many unetched (level-0) pixels whose 3 x 3
        neighbourhood is unetched too: a profilometer field is levelled on, and its depths
        measured from, the unetched surface, so a field without it cannot be compared.

    Returns
    -------
    (row0, row1, col0, col1)
        Among equally busy windows, the one nearest the centre (e.g. a periodic design).
    """
    levels = np.asarray(levels)
    rows, cols = levels.shape
    h, w = min(int(size_px), rows), min(int(size_px), cols)
    counts = window_sums(edge_count(levels), h, w)
    if need_flat:
        flat = (ndi.maximum_filter(levels, size=3) == ndi.minimum_filter(levels, size=3)).astype(float)
        counts = counts * window_sums(flat, h, w)
    rr, cc = np.mgrid[:counts.shape[0], :counts.shape[1]]
    centre = np.hypot(rr - (rows - h) / 2, cc - (cols - w) / 2)
    score = counts - 1e-6 * centre
    if inside_circle:
        radius = min(rows, cols) / 2 - 0.75 * max(h, w)
        inside = np.hypot(rr + h // 2 - (rows - 1) / 2, cc + w // 2 - (cols - 1) / 2) <= radius
        if not inside.any():
            raise DoeError(f"a {h} x {w} pixel window does not fit inside the inscribed circle of a "
                           f"{rows} x {cols} pixel design")
        score = np.where(inside, score, -np.inf)
    if min_level0_px > 0:
        top = ndi.binary_erosion(levels == 0, structure=np.ones((3, 3), bool), border_value=0)
        enough = window_sums(top.astype(float), h, w) >= min_level0_px
        if not (enough & np.isfinite(score)).any():
            raise DoeError(f"no {h} x {w} pixel window of the design holds {min_level0_px} unetched "
                           "(level-0) pixels to level and measure depths on")
        score = np.where(enough, score, -np.inf)
    r0, c0 = (int(v) for v in np.unravel_index(np.argmax(score), score.shape))
    return (r0, r0 + h, c0, c0 + w)


def window_sums(a: np.ndarray, h: int, w: int) -> np.ndarray:
    """Sum of ``a`` over every ``h x w`` window (summed-area table), indexed by the top-left pixel."""
    sat = np.pad(a.cumsum(0).cumsum(1), ((1, 0), (1, 0)))
    return sat[h:, w:] - sat[:-h, w:] - sat[h:, :-w] + sat[:-h, :-w]


def edge_count(labels: np.ndarray) -> np.ndarray:
    """Per pixel, how many of its right and lower neighbours carry another label (0, 1 or 2)."""
    labels = np.asarray(labels)
    edges = np.zeros(labels.shape)
    edges[:, :-1] += labels[:, 1:] != labels[:, :-1]
    edges[:-1, :] += labels[1:, :] != labels[:-1, :]
    return edges


def busiest_camera_window(levels: np.ndarray, placement: Placement, shape: tuple[int, int],
                          size: int) -> tuple[int, int]:
    """The ``size`` x ``size`` camera window (row0, col0) richest in every mask's edges.

    Score: the sum over masks of ``log(1 + edges of that mask)``, so a window that misses a
    mask's edges (and could not tell anything about that mask) loses to one holding all.
    """
    from masks.decompose import levels_to_masks

    if size >= min(shape):
        return 0, 0
    r, c = placement.to_design(*np.mgrid[:shape[0], :shape[1]].astype(float))
    ri = np.clip(np.rint(r).astype(int), 0, levels.shape[0] - 1)
    ci = np.clip(np.rint(c).astype(int), 0, levels.shape[1] - 1)
    n_masks = max(int(np.ceil(np.log2(max(int(levels.max()) + 1, 2)))), 1)
    score = np.zeros(shape)
    h = size // 2
    for mask in levels_to_masks(levels, n_masks):
        m = mask[ri, ci]
        score += np.log1p(ndi.uniform_filter(edge_count(m), size, mode="constant") * size * size)
    inner = score[h:shape[0] - (size - h) + 1, h:shape[1] - (size - h) + 1]
    r0, c0 = np.unravel_index(np.argmax(inner), inner.shape)
    return int(r0), int(c0)
