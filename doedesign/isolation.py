"""One-pixel pillars and holes: the fabrication regularizer (``fab_weight``) and their count.

A pixel above (or below) all its in-array neighbours is hard to print and to etch. The penalty
measures how far such pixels stick out, in levels, so the optimizer can flatten them; the count
goes into the design report.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

__all__ = ["isolated_pixels", "isolation_penalty"]


def _neighbour_differences(h):
    """``h - neighbour`` for the 4 neighbours (up, down, left, right), and where they exist.

    Returns (4, rows, cols) differences and a mask that is False for neighbours outside the
    array (an edge pixel is judged on the neighbours it has).
    """
    pad = np.pad(h, 1, mode="edge")
    nb = np.stack([pad[:-2, 1:-1], pad[2:, 1:-1], pad[1:-1, :-2], pad[1:-1, 2:]])
    inside = np.ones(nb.shape, dtype=bool)
    inside[0, 0, :] = inside[1, -1, :] = inside[2, :, 0] = inside[3, :, -1] = False
    return h[None] - nb, inside


_OFFSETS = ((-1, 0), (1, 0), (0, -1), (0, 1))


def isolation_penalty(height_m: ArrayLike, step_m: float) -> tuple[float, np.ndarray]:
    """How far one-pixel pillars stick up and holes dig down, in levels, per pixel.

    A pixel higher than all its neighbours contributes ``min(h - neighbour) / step`` (the
    pillar's height above its tallest neighbour); one lower than all, ``min(neighbour - h) / step``.
    Returns the mean over pixels and its (sub)gradient.
    """
    h = np.asarray(height_m, dtype=float)
    d, inside = _neighbour_differences(h)
    d = d / step_m
    n = h.size
    kmin = np.where(inside, d, np.inf).argmin(axis=0)
    kmax = np.where(inside, d, -np.inf).argmax(axis=0)
    dmin = np.take_along_axis(d, kmin[None], 0)[0]
    dmax = np.take_along_axis(d, kmax[None], 0)[0]
    pillar, hole = dmin > 0, dmax < 0
    value = float((dmin[pillar].sum() - dmax[hole].sum()) / n)
    grad = (pillar.astype(float) - hole) / (step_m * n)
    for k, (dr, dc) in enumerate(_OFFSETS):
        # Neighbour k of pixel (i, j) is (i + dr, j + dc); never outside the array (masked above).
        c = -(pillar & (kmin == k)).astype(float) + (hole & (kmax == k))
        grad += np.roll(c, (dr, dc), axis=(0, 1)) / (step_m * n)
    return value, grad


def isolated_pixels(levels: ArrayLike) -> int:
    """Number of one-pixel pillars and holes: pixels above (or below) all their in-array neighbours."""
    d, inside = _neighbour_differences(np.asarray(levels, dtype=float))
    up = np.all(np.where(inside, d > 0, True), axis=0)
    down = np.all(np.where(inside, d < 0, True), axis=0)
    return int(np.count_nonzero(up | down))
