"""Registration of a periodic design to a measured field: the lattice from its Fourier peaks.

A design whose metadata says ``surround: "repeat"`` is one unit cell of a lattice (a grating,
an array of discs or holes). Its edges do not fall on every design pixel, so the pixel-lattice
comb of :mod:`.register` finds nothing; the field's own lattice does the work instead:

1. the two fundamental peaks of the field's 2-D spectrum (Hann window, then each peak refined
   to a fraction of a bin by maximizing the windowed Fourier sum at that wave vector) give the
   two lattice vectors in measurement pixels: period and direction of each axis, measured
   separately, so unequal x and y scales (a scanning probe's piezo calibration) and a small
   shear are measured, not assumed away;
2. the linear part of the map sends those vectors onto the cell's edges (``cols`` design pixels
   along x, ``rows`` along y), in each of the 8 flips and transposes; orientations under which
   the cell is the same up to a shift (a disc, a centred square) cannot be told apart and the
   plain one is kept;
3. the field folded onto one cell (the mean height of every measurement pixel falling in each
   cell pixel, over all the periods in the field) is cross-correlated circularly with the cell:
   the best orientation and the shift within the cell, refined to a fraction of a pixel by a
   parabola through the peak.

A periodic design is ambiguous by whole periods: the field is registered modulo the lattice,
onto a tiling of the cell just large enough to hold it (plus half a cell around it), which
the comparison then treats as the design. Arrays are row-major, row 0 at the top.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
from scipy import optimize

from doedesign.budget import check_memory
from doedesign.errors import DoeError
from metrology.matching.register import MIN_MATCH_NCC, ORIENTATIONS, Registration, orient

__all__ = ["LATTICE_BAND", "Lattice", "MIN_CELL_PIXELS", "cell_depths", "edge_span", "fundamental_peaks", "fold_cell",
           "register_lattice"]

log = logging.getLogger(__name__)

#: The field's period may differ from the design's nominal one (file pixel size) by this factor
#: either way: a wrong lateral calibration of that size is still found.
LATTICE_BAND = 1.5
# Fewest whole periods along each axis for the Fourier peaks to mean something.
MIN_PERIODS = 2.0
#: Interior pixels of each level a cell needs for its own step height.
MIN_CELL_PIXELS = 20


@dataclass
class Lattice:
    """The field's lattice in measurement pixels.

    Attributes
    ----------
    vectors_px : ndarray (2, 2)
        Rows: the lattice vector along x (the design's columns) and along y (its rows), each as
        (row, col) in measurement pixels.
    period_px : ndarray (2,)
        Their lengths.
    turn_deg : float
        Counter-clockwise turn (y up) of the x vector against the measurement's columns.
    shear_deg : float
        Departure of the angle between the two vectors from 90 degrees.
    """

    vectors_px: np.ndarray
    period_px: np.ndarray
    turn_deg: float
    shear_deg: float

    def report(self, pixel_size_m: float, pixel_size_y_m: float | None = None) -> dict:
        """Periods in micrometres at the file's pixel size(s), turn and shear."""
        py = pixel_size_y_m or pixel_size_m
        length = [float(np.hypot(v[0] * py, v[1] * pixel_size_m)) * 1e6 for v in self.vectors_px]
        return {"period_px_xy": [float(p) for p in self.period_px], "period_um_xy": length,
                "turn_deg": self.turn_deg, "shear_deg": self.shear_deg,
                "method": "fundamental peaks of the field's 2-D spectrum (Hann window, refined off the bins)",
                "modulo": "a periodic design is ambiguous by whole periods: registered modulo the lattice"}


def edge_span(cell_levels: np.ndarray) -> int:
    """Design pixels in from an edge at which the match check reads each side: a third of the
    shortest run of one level across the cell (rows and columns, cyclic), at least 1. A
    lattice drawn on a grid finer than the instrument's edge is judged at the central third of
    its features (ISO 5436-1), not at pixels the edge's blur reaches."""
    cell = np.asarray(cell_levels)
    shortest = max(cell.shape)
    for lines in (cell, cell.T):
        for line in lines:
            change = np.flatnonzero(line != np.roll(line, 1))
            if change.size:
                shortest = min(shortest, int(np.min(np.diff(np.concatenate([change, [change[0] + line.size]])))))
    return max(1, shortest // 3)


def _filled(height_m):
    h = np.asarray(height_m, float)
    ok = np.isfinite(h)
    if ok.sum() < 100:
        raise DoeError("registration: fewer than 100 valid pixels")
    return np.where(ok, h - np.median(h[ok]), 0.0)


def fundamental_peaks(height_m: np.ndarray, period_px: tuple[float, float]) -> Lattice:
    """The field's two lattice vectors from its 2-D spectrum.

    Parameters
    ----------
    height_m : ndarray
        Measured heights (levelled or not: a plane only adds energy near zero frequency), NaN
        where invalid; row 0 at the top.
    period_px : (float, float)
        Nominal periods along x (columns) and y (rows), in measurement pixels; each fundamental
        is looked for within :data:`LATTICE_BAND` of its own.

    Returns
    -------
    Lattice

    Raises
    ------
    DoeError
        The field holds fewer than ``MIN_PERIODS`` periods, or no peak in the band.
    """
    h = _filled(height_m)
    rows, cols = h.shape
    px, py = (float(p) for p in period_px)
    if cols < MIN_PERIODS * px / LATTICE_BAND or rows < MIN_PERIODS * py / LATTICE_BAND:
        raise DoeError(f"registration: the field ({rows} x {cols} px) holds fewer than {MIN_PERIODS:g} periods "
                       f"of the design's lattice ({py:.1f} x {px:.1f} px)")
    window = np.hanning(rows)[:, None] * np.hanning(cols)[None, :]
    z = (h - np.sum(h * window) / window.sum()) * window
    spec = np.abs(np.fft.fft2(z))
    ky = np.fft.fftfreq(rows)[:, None]
    kx = np.fft.fftfreq(cols)[None, :]
    k = np.hypot(kx, ky)
    angle = np.arctan2(ky, kx)
    r_idx = np.arange(rows, dtype=float)[:, None]
    c_idx = np.arange(cols, dtype=float)[None, :]

    def amplitude(q):
        return -abs(np.sum(z * np.exp(-2j * np.pi * (q[0] * r_idx + q[1] * c_idx))))

    vectors = []
    for axis, period in ((0, px), (1, py)):
        # x: wave vectors within 45 deg of the columns' axis, kx > 0; y: of the rows', ky > 0.
        side = (np.abs(np.cos(angle)) >= np.abs(np.sin(angle))) & (kx > 0) if axis == 0 else \
               (np.abs(np.sin(angle)) > np.abs(np.cos(angle))) & (ky > 0)
        band = side & (k >= 1 / (LATTICE_BAND * period)) & (k <= LATTICE_BAND / period)
        if not band.any():
            raise DoeError(f"registration: no spectral peak near the lattice period of {period:.1f} px")
        i, j = np.unravel_index(np.argmax(np.where(band, spec, -1.0)), spec.shape)
        q0 = np.array([np.fft.fftfreq(rows)[i], np.fft.fftfreq(cols)[j]])
        res = optimize.minimize(amplitude, q0, method="Nelder-Mead",
                                options={"xatol": 1e-7, "fatol": 1e-12 * -amplitude(q0), "maxiter": 400})
        vectors.append(res.x)
    recip = np.array(vectors)  # rows: wave vectors (ky, kx) in cycles per px
    real = np.linalg.inv(recip).T  # rows: lattice vectors (row, col), recip @ real.T = identity
    period = np.hypot(real[:, 0], real[:, 1])
    turn = float(np.degrees(np.arctan2(-real[0, 0], real[0, 1])))  # y up: a row step up is +y
    between = np.degrees(np.arccos(np.dot(real[0], real[1]) / (period[0] * period[1])))
    log.info("lattice: periods %.3f x %.3f px, turn %.3f deg, shear %.3f deg", period[0], period[1], turn,
             between - 90)
    return Lattice(vectors_px=real, period_px=period, turn_deg=turn, shear_deg=float(between - 90.0))


def fold_cell(height_m: np.ndarray, matrix: np.ndarray, cell_shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """The field folded onto one cell: the mean height of the measurement pixels in each cell pixel.

    Measurement pixel (row, col) falls in cell pixel ``rint(matrix @ (row, col)) mod cell_shape``.

    Returns
    -------
    mean_m : ndarray (cell rows, cell cols)
        NaN where no valid pixel fell.
    count : ndarray of int
    """
    h = np.asarray(height_m, float)
    ok = np.isfinite(h)
    r, c = np.nonzero(ok)
    rr = np.rint(matrix[0, 0] * r + matrix[0, 1] * c).astype(np.int64) % cell_shape[0]
    cc = np.rint(matrix[1, 0] * r + matrix[1, 1] * c).astype(np.int64) % cell_shape[1]
    flat = rr * cell_shape[1] + cc
    n = cell_shape[0] * cell_shape[1]
    count = np.bincount(flat, minlength=n)
    total = np.bincount(flat, h[ok], minlength=n)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = np.where(count > 0, total / np.maximum(count, 1), np.nan)
    return mean.reshape(cell_shape), count.reshape(cell_shape)


def _circular_ncc(folded, cell):
    """NCC of the folded field against the cell at every circular shift; entry (i, j) compares
    folded[a, b] with cell[(a + i) % rows, (b + j) % cols]."""
    ok = np.isfinite(folded)
    f = np.where(ok, folded - np.nanmean(folded), 0.0)
    t = cell - cell.mean()
    num = np.real(np.fft.ifft2(np.conj(np.fft.fft2(f)) * np.fft.fft2(t)))
    norm = np.sqrt(np.sum(f * f) * np.sum(t * t))
    return num / norm if norm > 0 else np.zeros(cell.shape)


def _parabola(values, i):
    """Sub-sample offset of a circular peak at index i from a parabola through its neighbours."""
    a, b, c = values[(i - 1) % values.size], values[i], values[(i + 1) % values.size]
    den = a - 2 * b + c
    return float(np.clip(0.5 * (a - c) / den, -0.5, 0.5)) if den < 0 else 0.0


def _same_up_to_shift(cell, o):
    """The cell looks the same under orientation ``o`` up to a circular shift."""
    turned = orient(cell, o)
    if turned.shape != cell.shape:
        return False
    f = np.fft.fft2(cell - cell.mean())
    g = np.fft.fft2(turned - turned.mean())
    corr = np.real(np.fft.ifft2(np.conj(f) * g))
    norm = np.sum((cell - cell.mean()) ** 2)
    return bool(norm == 0 or corr.max() >= (1 - 1e-9) * norm)


def register_lattice(height_m: np.ndarray, cell_levels: np.ndarray, cell_printed_m: np.ndarray, pitch_m: float,
                     pixel_size_m: float, pixel_size_y_m: float | None = None
                     ) -> tuple[Registration, np.ndarray, np.ndarray, Lattice]:
    """Register a field to a periodic design (one cell), modulo the lattice.

    Parameters
    ----------
    height_m : ndarray
        Measured heights (m), NaN where invalid; row 0 at the top.
    cell_levels : ndarray of int
        The cell's levels (0 = unetched top).
    cell_printed_m : ndarray
        The heights the masks print from the cell (m).
    pitch_m : float
        Design pixel pitch (m).
    pixel_size_m, pixel_size_y_m : float
        The file's column and row pitches (m): the nominal lattice period in pixels.

    Returns
    -------
    registration : Registration
        Measurement pixel to the tiled design's pixel.
    levels, printed_m : ndarray
        The cell tiled to hold the field (the design the comparison uses).
    lattice : Lattice

    Raises
    ------
    DoeError
        No lattice, or the folded field does not match the cell.
    """
    cell = np.asarray(cell_printed_m, float)
    n_r, n_c = cell.shape
    py = pixel_size_y_m or pixel_size_m
    lattice = fundamental_peaks(height_m, (n_c * pitch_m / pixel_size_m, n_r * pitch_m / py))
    inverse = np.linalg.inv(lattice.vectors_px.T)  # columns of vectors_px.T: the x and y lattice vectors
    h = np.asarray(height_m, float)
    best = None
    for o in ORIENTATIONS:
        if o != ORIENTATIONS[0] and _same_up_to_shift(cell, o):
            continue
        t, fr, fc = o
        # The x lattice vector goes to the cell's x edge (or y, transposed), signs by the flips.
        dx = np.array([0.0, n_c]) if not t else np.array([n_r, 0.0])
        dy = np.array([n_r, 0.0]) if not t else np.array([0.0, n_c])
        if (fc and not t) or (fr and t):
            dx = -dx
        if (fr and not t) or (fc and t):
            dy = -dy
        matrix = np.column_stack([dx, dy]) @ inverse
        folded, _ = fold_cell(h, matrix, cell.shape)
        ncc = _circular_ncc(folded, cell)
        i, j = np.unravel_index(np.argmax(ncc), ncc.shape)
        if best is None or ncc[i, j] > best[0]:
            shift = (i + _parabola(ncc[:, j], i), j + _parabola(ncc[i, :], j))
            best = (float(ncc[i, j]), o, matrix, shift)
    assert best is not None  # at least one orientation is always tried
    score, o, matrix, shift = best
    log.info("lattice registration: orientation %s, shift in the cell (%.2f, %.2f) px, NCC %.3f", o, *shift, score)
    if not score >= MIN_MATCH_NCC:
        raise DoeError(f"registration: the field folded onto the design's cell does not match it (best normalized "
                       f"correlation {score:.2f}, need {MIN_MATCH_NCC}): the field shows another lattice")
    # Tile the cell so the field lies inside with half a cell around it.
    rows, cols = h.shape
    corner_r = np.array([0, 0, rows - 1, rows - 1], float)
    corner_c = np.array([0, cols - 1, 0, cols - 1], float)
    dr = matrix[0, 0] * corner_r + matrix[0, 1] * corner_c + shift[0]
    dc = matrix[1, 0] * corner_r + matrix[1, 1] * corner_c + shift[1]
    offset = np.array(shift, float)
    tiles = []
    for axis, (lo, hi, n) in enumerate(((dr.min(), dr.max(), n_r), (dc.min(), dc.max(), n_c))):
        move = n * np.ceil((0.5 * n - lo) / n)
        offset[axis] += move
        tiles.append(int(np.ceil((hi + move + 0.5 * n) / n)))
    check_memory(3 * tiles[0] * tiles[1] * cell.size * 8, f"tiling the design's {n_r} x {n_c} px cell over the field")
    levels = np.tile(np.asarray(cell_levels), tiles)
    printed = np.tile(cell, tiles)
    reg = Registration(matrix=matrix, offset=offset, pitch_m=float(pitch_m), design_shape=tuple(levels.shape),
                       measurement_shape=tuple(h.shape), match_ncc=score)
    return reg, levels, printed, lattice


def cell_depths(height_m: np.ndarray, labels: np.ndarray, interior: np.ndarray, registration: Registration,
                cell_shape: tuple[int, int]) -> dict:
    """The step (level 0 minus level 1, medians on feature interiors) of every lattice cell in the field.

    Their scatter is the step's repeatability across the field, which holds what a fit's
    formal error leaves out (scan-line noise, local etch variation, the instrument's drift);
    its standard error is the step's uncertainty from the field.

    Parameters
    ----------
    height_m : ndarray
        Levelled heights (m), 0 on the unetched top.
    labels : ndarray of int
        Design level at each measurement pixel (negative off the design).
    interior : ndarray of bool
        Feature interiors (:func:`metrology.matching.depths.interior_mask`).
    registration : Registration
        Onto the tiled design.
    cell_shape : (int, int)
        The cell's design pixels.

    Returns
    -------
    dict
        ``depth_nm`` (mean over cells), ``std_nm``, ``err_nm`` (std / sqrt(cells)) and ``cells``
        (those with :data:`MIN_CELL_PIXELS` interior pixels of both levels).
    """
    h = np.asarray(height_m, float)
    use = np.asarray(interior, bool) & np.isfinite(h) & ((labels == 0) | (labels == 1))
    r, c = np.nonzero(use)
    rr, cc = registration.to_design(r, c)
    tile = np.stack([np.rint(rr).astype(np.int64) // cell_shape[0], np.rint(cc).astype(np.int64) // cell_shape[1]])
    level = labels[r, c]
    values = h[r, c]
    ids, which = np.unique(tile, axis=1, return_inverse=True)
    which = which.ravel()
    order = np.argsort(which, kind="stable")
    bounds = np.searchsorted(which[order], np.arange(ids.shape[1] + 1))
    cells = []
    for k in range(ids.shape[1]):
        pick = order[bounds[k]:bounds[k + 1]]
        top, low = values[pick][level[pick] == 0], values[pick][level[pick] == 1]
        if top.size >= MIN_CELL_PIXELS and low.size >= MIN_CELL_PIXELS:
            # Medians: the tip's overshoot beside an edge and particles make a level's tail.
            cells.append(np.median(top) - np.median(low))
    depth = np.array(cells)
    if depth.size < 2:
        return {"depth_nm": float(depth.mean() * 1e9) if depth.size else None, "std_nm": None, "err_nm": None,
                "cells": int(depth.size)}
    std = float(np.std(depth, ddof=1))
    return {"depth_nm": float(depth.mean() * 1e9), "std_nm": std * 1e9, "err_nm": std / np.sqrt(depth.size) * 1e9,
            "cells": int(depth.size),
            "meaning": "median of level 0 minus median of level 1 on the feature interiors of each lattice cell "
                       "in the field; mean, scatter and standard error over the cells"}
