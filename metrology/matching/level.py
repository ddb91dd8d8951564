"""From a raw height map to a clean, levelled surface.

A DOE surface is a set of flat terraces (levels) at different depths, so a plane fitted
through all pixels is pulled toward wherever deep levels cluster: the etched pattern
biases the tilt. Here the plane is fitted to the unetched top (level 0) only, or jointly
with one free offset per level. In the camera frame of the measurement model, a residual's
levelling (piston, tilt, curvature) is projected out (:class:`Leveller`) and its robust
outliers left out (:func:`robust_valid`).

All functions work on plain arrays: row 0 at the top, column 0 at the left, NaN for
invalid pixels. Plane coefficients are per measurement pixel, about the array centre.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
from scipy import ndimage, signal

from doedesign.errors import DoeError

__all__ = ["DEFAULT_SPIKE_THRESHOLD_M", "HIST_BIN_M", "LevelResult", "Leveller", "MIN_CLUSTER_SEPARATION_M",
           "classify_by_histogram", "fit_plane", "level_joint", "level_on_top", "levelling_basis", "levelling_plane",
           "plane_image", "remove_spikes", "robust_valid", "step_plane", "top_level_mask"]

log = logging.getLogger(__name__)

# A spike (fringe-order slip, dust, bat-wing outlier) stands above or below all of its
# neighbours; fringe-order slips are ~lambda/2 (~300 nm), well above the ~1 nm noise, and
# a real step edge always has neighbours on its own side, so it is never flagged.
DEFAULT_SPIKE_THRESHOLD_M = 40e-9
# Histogram bin for finding level clusters: well below the 75 nm step, above the noise.
HIST_BIN_M = 0.5e-9
# Closest two level clusters may be (half the 75 nm step): noise bumps on the flank of a
# cluster must not count as a cluster of their own.
MIN_CLUSTER_SEPARATION_M = 30e-9


@dataclass
class LevelResult:
    """A levelled height map.

    Attributes
    ----------
    height_m : ndarray
        Heights with the fitted plane removed, level 0 at 0 (NaN where invalid).
    plane : ndarray (3,)
        ``(offset_m, slope_x, slope_y)``: the removed plane is
        ``offset + slope_x * (col - col_c) + slope_y * (row - row_c)`` (metres per pixel),
        with ``(row_c, col_c)`` the array centre.
    reference : ndarray of bool
        The pixels the plane was fitted to.
    level_offsets_m : ndarray or None
        Joint fit only: fitted height of each level relative to level 0.
    line_offsets_m : ndarray or None
        Joint fit of a raster scan only: each scan line's (row's) offset about the plane
        (the scanner's line-to-line z jumps), removed from ``height_m`` with the plane.
    """

    height_m: np.ndarray
    plane: np.ndarray
    reference: np.ndarray
    level_offsets_m: np.ndarray | None = None
    line_offsets_m: np.ndarray | None = None

    def artefacts(self) -> dict:
        """The plane's tilt (nm per pixel along x and y) and, for a raster scan, the rms and
        peak-to-valley of the scan lines' offsets (nm) removed in levelling, for the report."""
        out: dict[str, float | int | None] = {"tilt_x_nm_per_px": float(self.plane[1] * 1e9), "tilt_y_nm_per_px": float(self.plane[2] * 1e9)}
        if self.line_offsets_m is not None:
            lines = self.line_offsets_m[np.isfinite(self.line_offsets_m)]
            out["scan_line_offsets_rms_nm"] = float(np.sqrt(np.mean(lines ** 2)) * 1e9) if lines.size else None
            out["scan_line_offsets_pv_nm"] = float(np.ptp(lines) * 1e9) if lines.size else None
            out["scan_lines"] = int(lines.size)
        return out


def remove_spikes(height_m: np.ndarray, threshold_m: float = DEFAULT_SPIKE_THRESHOLD_M,
                  passes: int = 2) -> tuple[np.ndarray, int]:
    """Mark as invalid (NaN) the pixels that stand out from all their 8 neighbours.

    Parameters
    ----------
    height_m : ndarray
        Heights (m), NaN where invalid.
    threshold_m : float
        How far above the highest (or below the lowest) neighbour a pixel must be.
    passes : int
        Alternating passes over the 8 neighbours and over the 5 x 5 outer ring.

    Returns
    -------
    height_m : ndarray
        A copy with spikes set to NaN.
    n_removed : int
    """
    h = np.array(height_m, dtype=float)
    # First the 8 neighbours, then the outer ring of the 5 x 5 block, which skips over a
    # partner spike next to the pixel (a 2-3 px blob); a line of any length still has
    # neighbours of its own height along itself in either ring, so it is kept.
    inner = np.ones((3, 3), bool)
    inner[1, 1] = False
    outer = np.ones((5, 5), bool)
    outer[1:4, 1:4] = False
    removed = 0
    for i in range(int(passes)):
        ring = inner if i % 2 == 0 else outer
        valid = np.isfinite(h)
        hi = ndimage.maximum_filter(np.where(valid, h, -np.inf), footprint=ring, mode="nearest")
        lo = ndimage.minimum_filter(np.where(valid, h, np.inf), footprint=ring, mode="nearest")
        spikes = valid & np.isfinite(hi) & np.isfinite(lo) & ((h > hi + threshold_m) | (h < lo - threshold_m))
        h[spikes] = np.nan
        removed += int(spikes.sum())
    if removed:
        log.info("removed %d spike pixels (threshold %.0f nm)", removed, threshold_m * 1e9)
    return h, removed


def _design_matrix(rows, cols, shape):
    rc, cc = (shape[0] - 1) / 2, (shape[1] - 1) / 2
    return np.column_stack([np.ones(rows.size), cols - cc, rows - rc])


def _subsample(mask, max_points):
    """Indices (rows, cols) of up to ``max_points`` True pixels, evenly strided."""
    rows, cols = np.nonzero(mask)
    if rows.size > max_points:
        sel = np.linspace(0, rows.size - 1, max_points).astype(int)
        rows, cols = rows[sel], cols[sel]
    return rows, cols


def fit_plane(height_m: np.ndarray, mask: np.ndarray, max_points: int = 400_000) -> np.ndarray:
    """Least-squares plane through the pixels in ``mask``.

    Returns
    -------
    ndarray (3,)
        ``(offset_m, slope_x, slope_y)`` about the array centre (see :class:`LevelResult`).
    """
    mask = np.asarray(mask, bool) & np.isfinite(height_m)
    if mask.sum() < 3:
        raise DoeError(f"cannot fit a plane: only {int(mask.sum())} reference pixels")
    rows, cols = _subsample(mask, max_points)
    a = _design_matrix(rows, cols, height_m.shape)
    coef, *_ = np.linalg.lstsq(a, height_m[rows, cols], rcond=None)
    return coef


def step_plane(height_m: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """The tilt as the median height step between valid neighbours along each axis.

    On a stepped surface most neighbours share a terrace, so the median step is the tilt
    whatever the pattern. A least-squares plane through all pixels leans toward wherever the
    deep levels lie: on a demo field holding little level 0 it tilted 0.7 um across the field,
    so the topmost cluster mixed levels 0 and 1 and the registration read 0.48 for 1.00.
    Falls back to :func:`fit_plane` where no two valid pixels touch.

    Returns
    -------
    ndarray (3,)
        ``(offset_m, slope_x, slope_y)`` as :func:`fit_plane`.
    """
    h = np.where(np.asarray(valid, bool), height_m, np.nan)
    steps_x, steps_y = np.diff(h, axis=1), np.diff(h, axis=0)
    steps_x, steps_y = steps_x[np.isfinite(steps_x)], steps_y[np.isfinite(steps_y)]
    if steps_x.size == 0 or steps_y.size == 0:
        return fit_plane(height_m, valid)
    plane = np.array([0.0, float(np.median(steps_x)), float(np.median(steps_y))])
    plane[0] = float(np.nanmedian(h - plane_image(plane, h.shape)))
    return plane


def plane_image(plane: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """The plane ``(offset, slope_x, slope_y)`` evaluated on an array of ``shape``."""
    rc, cc = (shape[0] - 1) / 2, (shape[1] - 1) / 2
    r = np.arange(shape[0])[:, None] - rc
    c = np.arange(shape[1])[None, :] - cc
    return plane[0] + plane[1] * c + plane[2] * r


def _histogram_peaks(values, min_fraction=0.02):
    """Heights (m) of the histogram peaks holding a noticeable share of the pixels, and the bin."""
    lo, hi = np.percentile(values, [0.01, 99.99])
    n_bins = int(np.clip((hi - lo) / HIST_BIN_M, 16, 20000))
    counts, edges = np.histogram(values, bins=n_bins, range=(lo, hi + 1e-15))
    smooth = ndimage.gaussian_filter1d(counts.astype(float), 2.0)
    bin_m = edges[1] - edges[0]
    peaks, _ = signal.find_peaks(smooth, height=min_fraction * smooth.max(),
                                 distance=max(1, int(MIN_CLUSTER_SEPARATION_M / bin_m)))
    centres = 0.5 * (edges[:-1] + edges[1:])
    return centres[peaks], smooth[peaks], bin_m


def top_level_mask(residual_m: np.ndarray, valid: np.ndarray, window_m: float | None = None) -> np.ndarray:
    """Pixels of the topmost height cluster (the unetched level 0).

    Parameters
    ----------
    residual_m : ndarray
        Heights with most of the tilt already removed.
    valid : ndarray of bool
    window_m : float, optional
        Half-width of the accepted band around the top peak; default a third of the
        distance to the next peak below (or 20 nm when there is none).
    """
    values = residual_m[valid]
    if values.size < 10:
        raise DoeError("too few valid pixels to find the unetched level")
    peaks, _, _ = _histogram_peaks(values)
    if peaks.size == 0:
        raise DoeError("no height clusters found: is this a stepped surface?")
    top = peaks[-1]
    if window_m is None:
        window_m = (top - peaks[-2]) / 3 if peaks.size > 1 else 20e-9
    return valid & (np.abs(residual_m - top) <= window_m)


def level_on_top(height_m: np.ndarray, valid: np.ndarray | None = None, iterations: int = 4) -> LevelResult:
    """Level on a plane fitted to the unetched (level-0) pixels, found from the histogram.

    Starts from the tilt of :func:`step_plane` (the median step between neighbours, which the
    pattern does not bias), then refits on the topmost cluster until it settles.

    Returns
    -------
    LevelResult
    """
    h = np.asarray(height_m, dtype=float)
    valid = np.isfinite(h) if valid is None else (np.asarray(valid, bool) & np.isfinite(h))
    plane = step_plane(h, valid)
    ref = valid
    for _ in range(int(iterations)):
        residual = h - plane_image(plane, h.shape)
        ref = top_level_mask(residual, valid)
        plane = fit_plane(h, ref)
    out = np.where(valid, h - plane_image(plane, h.shape), np.nan)
    return LevelResult(out, plane, ref)


def level_joint(height_m: np.ndarray, labels: np.ndarray, valid: np.ndarray | None = None,
                max_points: int = 400_000, line_offsets: bool = False) -> LevelResult:
    """Fit one plane jointly with one height offset per level; level 0 ends at 0.

    Pixels further than 5 robust sigmas from the first fit are dropped and the fit repeated.

    Parameters
    ----------
    height_m : ndarray
    labels : ndarray of int
        Level of each pixel (0 = top); negative values are left out (edges, unknown).
    valid : ndarray of bool, optional
    max_points : int
        Pixels the fit uses at most (evenly strided); all of them with ``line_offsets``.
    line_offsets : bool
        A raster scan (AFM, stylus): one free offset per scan line (row) as well, the
        scanner's line-to-line z jumps. Solved exactly by taking each row's mean out of the
        data and the other columns (the row offsets' normal equations are diagonal), so the
        cost does not grow with the number of lines; each row needs a labelled pixel, on any
        level. The row offsets' straight-line trend is the plane's y tilt, the rest is
        ``line_offsets_m``.

    Returns
    -------
    LevelResult
        ``level_offsets_m[k]`` is the fitted height of level k relative to level 0
        (NaN for levels without pixels).
    """
    if line_offsets:
        return _level_joint_lines(height_m, labels, valid)
    h, labels, use, present = _joint_inputs(height_m, labels, valid)
    rows, cols = _subsample(use, max_points)
    lab = labels[rows, cols]
    index = np.searchsorted(present, lab)
    a = np.zeros((rows.size, 2 + present.size))
    base = _design_matrix(rows, cols, h.shape)
    a[:, :2] = base[:, 1:]
    a[np.arange(rows.size), 2 + index] = 1.0
    z = h[rows, cols]
    coef, *_ = np.linalg.lstsq(a, z, rcond=None)
    # Refit without outliers (edge slivers, bat-wings inside the reference areas).
    resid = z - a @ coef
    mad = 1.4826 * np.median(np.abs(resid - np.median(resid)))
    keep = np.abs(resid) <= 5 * mad if mad > 0 else np.ones(resid.size, bool)
    if keep.sum() > a.shape[1] and not keep.all():
        coef, *_ = np.linalg.lstsq(a[keep], z[keep], rcond=None)
    offsets = np.full(int(labels.max()) + 1, np.nan)
    offsets[present] = coef[2:]
    plane = np.array([offsets[0], coef[0], coef[1]])
    out = h - plane_image(plane, h.shape)
    if valid is not None:
        out = np.where(valid, out, np.nan)
    return LevelResult(out, plane, use, offsets - offsets[0])


def _joint_inputs(height_m, labels, valid):
    """Heights, labels, the pixels a joint levelling uses and the levels present among them;
    refused without a level-0 (unetched) surface to level on."""
    h = np.asarray(height_m, dtype=float)
    labels = np.asarray(labels)
    if labels.shape != h.shape:
        raise DoeError(f"labels shape {labels.shape} differs from the height map {h.shape}")
    use = (labels >= 0) & np.isfinite(h)
    if valid is not None:
        use &= np.asarray(valid, bool)
    present = np.unique(labels[use])
    if 0 not in present:
        raise DoeError("the measured field holds no unetched (level-0) surface to level on and measure depths from; "
                       "measure a field that includes some unetched surface")
    return h, labels, use, present


def _row_mean(rows, values, counts):
    """Mean of ``values`` over each row index (0 where a row has none)."""
    return np.bincount(rows, values, minlength=counts.size) / np.maximum(counts, 1)


def _level_joint_lines(height_m, labels, valid):
    """:func:`level_joint` with one offset per row (see there)."""
    h, labels, use, present = _joint_inputs(height_m, labels, valid)
    n_rows, n_cols = h.shape
    cc = (n_cols - 1) / 2
    keep = use.copy()
    for _ in range(2):
        rows, cols = np.nonzero(keep)
        # Columns: x slope, then levels other than 0 (level 0's height is in the row offsets).
        x = np.zeros((rows.size, present.size))
        x[:, 0] = cols - cc
        index = np.searchsorted(present, labels[rows, cols])
        on = index > 0
        x[np.flatnonzero(on), index[on]] = 1.0
        z = h[rows, cols]
        counts = np.bincount(rows, minlength=n_rows).astype(float)
        xm = np.stack([_row_mean(rows, x[:, j], counts) for j in range(x.shape[1])], axis=1)
        zm = _row_mean(rows, z, counts)
        coef, *_ = np.linalg.lstsq(x - xm[rows], z - zm[rows], rcond=None)
        offsets_row = zm - xm @ coef
        resid = z - x @ coef - offsets_row[rows]
        mad = 1.4826 * np.median(np.abs(resid - np.median(resid)))
        outliers = np.abs(resid) > 5 * mad if mad > 0 else np.zeros(resid.size, bool)
        if not outliers.any():
            break
        keep[rows[outliers], cols[outliers]] = False
    have = counts > 0
    if not have.any():
        raise DoeError("no labelled pixels to level on")
    r_all = np.arange(n_rows, dtype=float)
    # Rows without a labelled pixel take their neighbours' offsets (linear between them).
    offsets_row = np.interp(r_all, r_all[have], offsets_row[have])
    rc = (n_rows - 1) / 2
    slope_y, offset = np.polyfit(r_all[have] - rc, offsets_row[have], 1)
    lines = offsets_row - (offset + slope_y * (r_all - rc))
    levels = np.full(int(labels.max()) + 1, np.nan)
    levels[present] = np.concatenate([[0.0], coef[1:]])
    plane = np.array([offset, coef[0], slope_y])
    out = h - plane_image(plane, h.shape) - np.where(np.isfinite(lines), lines, 0.0)[:, None]
    if valid is not None:
        out = np.where(valid, out, np.nan)
    return LevelResult(out, plane, keep, levels, line_offsets_m=lines)


def classify_by_histogram(height_m: np.ndarray, valid: np.ndarray | None = None,
                          n_levels: int = 16) -> tuple[np.ndarray, np.ndarray]:
    """Level labels from the height histogram: each pixel to its nearest cluster peak.

    For levelled data before registration. Peaks are taken from the top down (level 0
    = highest); pixels of a surface with fewer visible clusters than ``n_levels`` get
    the labels of the clusters present.

    Returns
    -------
    labels : ndarray of int
        -1 where invalid.
    peaks_m : ndarray
        Cluster heights, top first.
    """
    h = np.asarray(height_m, dtype=float)
    valid = np.isfinite(h) if valid is None else (np.asarray(valid, bool) & np.isfinite(h))
    peaks, weight, _ = _histogram_peaks(h[valid], min_fraction=0.005)
    if peaks.size > n_levels:
        keep = np.sort(np.argsort(weight)[-n_levels:])
        peaks = peaks[keep]
    peaks = peaks[::-1]
    # Boundaries midway between the (descending) peaks.
    bounds = 0.5 * (peaks[:-1] + peaks[1:])
    labels = np.full(h.shape, -1, dtype=np.int16)
    labels[valid] = np.searchsorted(-bounds, -h[valid])
    return labels, peaks


def levelling_basis(shape: tuple[int, int], curvature: bool = False) -> np.ndarray:
    """Columns of the levelling fit on a camera field: piston, tilt (col, row), curvature.

    Coordinates are centred and scaled to +-1 so the columns are well conditioned.
    """
    r, c = np.mgrid[:shape[0], :shape[1]].astype(float)
    r = (r - (shape[0] - 1) / 2) / max(shape[0] / 2, 1)
    c = (c - (shape[1] - 1) / 2) / max(shape[1] / 2, 1)
    cols = [np.ones(shape), c, r] + ([r * r + c * c] if curvature else [])
    return np.stack([x.ravel() for x in cols], axis=1)


def levelling_plane(residual: np.ndarray, keep: np.ndarray, curvature: bool = False) -> np.ndarray:
    """The levelling (:func:`levelling_basis`) fitted to a residual map on its ``keep`` pixels
    (NaN read as 0), evaluated everywhere."""
    basis = levelling_basis(residual.shape, curvature)
    k = np.asarray(keep, bool).ravel()
    coef, *_ = np.linalg.lstsq(basis[k], np.where(np.isfinite(residual), residual, 0).ravel()[k], rcond=None)
    return (basis @ coef).reshape(residual.shape)


class Leveller:
    """Projects piston, tilt (and optionally curvature) out of residuals on valid pixels."""

    def __init__(self, shape: tuple[int, int], valid: np.ndarray, curvature: bool = False) -> None:
        self.valid = np.asarray(valid, bool)
        basis = levelling_basis(shape, curvature)[self.valid.ravel()]
        self.q, _ = np.linalg.qr(basis)

    def coefficients(self, residual: np.ndarray) -> np.ndarray:
        """Projection coefficients (on the orthonormal basis) of a 1-D residual on valid pixels."""
        return self.q.T @ residual

    def __call__(self, residual: np.ndarray) -> np.ndarray:
        """The residual (1-D, valid pixels) with the levelling terms removed."""
        return residual - self.q @ (self.q.T @ residual)


def robust_valid(residual_map: np.ndarray, valid: np.ndarray, k: float = 6.0) -> np.ndarray:
    """Valid pixels whose residual lies within ``k`` robust sigmas (1.4826 MAD) of the median:
    spikes and fringe-order errors are excluded, never smoothed."""
    vals = residual_map[valid]
    med = np.median(vals)
    mad = 1.4826 * np.median(np.abs(vals - med))
    keep = valid.copy()
    keep[valid] = np.abs(vals - med) <= k * max(mad, 1e-15)
    return keep
