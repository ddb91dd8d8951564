"""Where to look: the window of a design with the most structure.

Both the profilometer field of the demo and the window a height diagnosis fits are placed
where the pattern has level edges (the effects show at edges and between levels) and, for the
diagnosis, flat interiors too (the noise floor is measured there). Arrays are row-major, row 0
at the top; windows are half-open ``(row0, row1, col0, col1)`` in design pixels.
"""

from __future__ import annotations

import numpy as np
import scipy.ndimage as ndi

from doedesign.errors import DoeError

__all__ = ["busiest_window"]


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
    edges = np.zeros(levels.shape)
    edges[:, :-1] += levels[:, 1:] != levels[:, :-1]
    edges[:-1, :] += levels[1:, :] != levels[:-1, :]
    counts = window_sums(edges, h, w)
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


def window_sums(a, h, w):
    """Sum of ``a`` over every ``h x w`` window (summed-area table), indexed by the top-left pixel."""
    sat = np.pad(a.cumsum(0).cumsum(1), ((1, 0), (1, 0)))
    return sat[h:, w:] - sat[:-h, w:] - sat[h:, :-w] + sat[:-h, :-w]
