"""Level heights on feature interiors and etch depths from them (the first stages of
``doe compare``).

- Level heights on feature interiors only (ISO 5436-1: the central third of a feature).
- Etch depth per mask by weighted least squares ``mu_k = c - sum_j B_kj D_j`` over the 16
  level means, with chi-square telling whether the etches add up.

Arrays are row-major, row 0 at the top (camera order).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage, stats

from doedesign.errors import DoeError

__all__ = ["DepthFit", "LEVEL_REPEATABILITY_M", "LevelStats", "MAX_EDGE_BAND_PITCH", "binary_code_matrix",
           "depths_from_levels", "feature_distances", "fit_etch_depths", "interior_mask", "level_heights"]

#: Repeatability floor (m) added in quadrature to each level mean's standard error in the
#: chi-square: a white-light profiler does not repeat a terrace height better than this.
LEVEL_REPEATABILITY_M = 0.3e-9
# Features wider than 3 design pixels keep all but a band this many design pixels wide at
# their edges (instead of only the central third), far beyond edge blur and overlay.
MAX_EDGE_BAND_PITCH = 1.0


def binary_code_matrix(n_levels: int = 16) -> np.ndarray:
    """``B[k, j]`` = bit j of level k (mask j open at level k)."""
    n_masks = int(np.log2(n_levels))
    return ((np.arange(n_levels)[:, None] >> np.arange(n_masks)[None, :]) & 1).astype(float)


def interior_mask(labels: np.ndarray, pitch_px: float) -> np.ndarray:
    """Pixels in the central third of their feature (ISO 5436-1), edges excluded.

    Parameters
    ----------
    labels : ndarray of int
        Design level at each measurement pixel; negative = outside the design.
    pitch_px : float
        DOE pitch in measurement pixels (caps the excluded band on wide features).

    Returns
    -------
    ndarray of bool
    """
    dist, dmax = feature_distances(labels)
    cap = MAX_EDGE_BAND_PITCH * pitch_px
    # No feature is narrower than one DOE pixel, whose central third starts pitch/3 in:
    # thinner pieces are features cut by the field border.
    need = np.clip(2.0 / 3.0 * dmax, pitch_px / 3.0, cap)
    return (dist >= need) & (np.asarray(labels) >= 0)


def feature_distances(labels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each pixel's distance to the nearest boundary between features, and its feature's largest.

    A feature is a connected region of one level (4-connected). ISO 5436-1's central third of a
    feature of width ``w`` is where the distance is at least ``w / 3``, i.e. ``2 / 3`` of the
    feature's largest distance ``w / 2``.

    Parameters
    ----------
    labels : ndarray of int
        Level at each pixel; negative = outside the design (no feature).

    Returns
    -------
    dist, feature_max : ndarray of float
        Distance (px) from the boundary line (a pixel beside a boundary reads 0.5) and the largest
        distance in the pixel's feature (0 outside the design).
    """
    labels = np.asarray(labels)
    edge = np.zeros(labels.shape, bool)
    diff_r = labels[1:] != labels[:-1]
    diff_c = labels[:, 1:] != labels[:, :-1]
    edge[1:] |= diff_r
    edge[:-1] |= diff_r
    edge[:, 1:] |= diff_c
    edge[:, :-1] |= diff_c
    dist = ndimage.distance_transform_edt(~edge) + 0.5
    # One id per connected feature (all levels), then each feature's largest distance.
    feature = np.zeros(labels.shape, np.int64)
    n_total = 0
    for k in np.unique(labels[labels >= 0]):
        comp, n = ndimage.label(labels == k)
        feature[comp > 0] = comp[comp > 0] + n_total
        n_total += n
    dmax = np.zeros(n_total + 1)
    np.maximum.at(dmax, feature.ravel(), dist.ravel())
    dmax[0] = 0.0
    return dist, dmax[feature]


@dataclass
class LevelStats:
    """Height of each level on feature interiors.

    Attributes
    ----------
    mean_m, std_m, median_m : ndarray (n_levels,)
        NaN for levels without interior pixels.
    count : ndarray of int (n_levels,)
    """

    mean_m: np.ndarray
    std_m: np.ndarray
    median_m: np.ndarray
    count: np.ndarray


def level_heights(height_m: np.ndarray, labels: np.ndarray, interior: np.ndarray, n_levels: int = 16) -> LevelStats:
    """Robust mean, spread and count of each level's interior heights.

    Outliers beyond 5 robust sigmas (bat-wings, particles) are left out of the mean.
    """
    use = interior & np.isfinite(height_m) & (labels >= 0)
    mean, std, med = (np.full(n_levels, np.nan) for _ in range(3))
    count = np.zeros(n_levels, int)
    lab, val = labels[use], height_m[use]
    order = np.argsort(lab, kind="stable")
    lab, val = lab[order], val[order]
    bounds = np.searchsorted(lab, np.arange(n_levels + 1))
    for k in range(n_levels):
        v = val[bounds[k]:bounds[k + 1]]
        if v.size == 0:
            continue
        m = np.median(v)
        mad = 1.4826 * np.median(np.abs(v - m))
        keep = v[np.abs(v - m) <= 5 * max(mad, 1e-12)] if mad > 0 else v
        mean[k], std[k], med[k], count[k] = keep.mean(), keep.std(), m, keep.size
    return LevelStats(mean, std, med, count)


@dataclass
class DepthFit:
    """Etch depths from the level means.

    Attributes
    ----------
    depths_m, depths_err_m : ndarray (n_masks,)
    top_m : float
        Fitted height of level 0.
    residual_m : ndarray (n_levels,)
        Level mean minus the fitted sum (NaN where a level is missing).
    chi2, dof, p_value : float
        Chi-square of the fit with each level's standard error plus
        ``LEVEL_REPEATABILITY_M``; a tiny p-value says the etches do not add up
        (loading, slivers, an etch that depends on what was etched before).
    """

    depths_m: np.ndarray
    depths_err_m: np.ndarray
    top_m: float
    residual_m: np.ndarray
    chi2: float
    dof: int
    p_value: float


def fit_etch_depths(stats_: LevelStats) -> DepthFit:
    """Weighted least squares ``mu_k = c - sum_j B_kj D_j`` over the levels present.

    Each level mean weighs by its standard error plus ``LEVEL_REPEATABILITY_M`` in quadrature.
    """
    sigma = np.sqrt(stats_.std_m ** 2 / np.maximum(stats_.count, 1) + LEVEL_REPEATABILITY_M ** 2)
    mean = np.where(stats_.count > 0, stats_.mean_m, np.nan)
    return depths_from_levels(mean, sigma)


def depths_from_levels(mean_m: np.ndarray, sigma_m: np.ndarray) -> DepthFit:
    """Etch depth per mask from level heights: weighted least squares ``mu_k = c - sum_j B_kj D_j``.

    Parameters
    ----------
    mean_m : ndarray (n_levels,)
        Height of each level (NaN = not measured).
    sigma_m : ndarray (n_levels,)
        Standard uncertainty of each height (the weights; the chi-square is counted with them).

    Returns
    -------
    DepthFit

    Raises
    ------
    DoeError
        The levels measured are too few to separate the masks' depths.
    """
    mean_m, sigma_m = np.asarray(mean_m, float), np.asarray(sigma_m, float)
    n_levels = mean_m.size
    b = binary_code_matrix(n_levels)
    ok = np.isfinite(mean_m) & np.isfinite(sigma_m) & (sigma_m > 0)
    a = np.column_stack([np.ones(n_levels), -b])[ok]
    if np.linalg.matrix_rank(a) < a.shape[1]:
        raise DoeError(f"only levels {np.flatnonzero(ok).tolist()} are measured: too few to separate "
                       f"the {b.shape[1]} etch depths")
    sigma = sigma_m[ok]
    aw = a / sigma[:, None]
    yw = mean_m[ok] / sigma
    coef, *_ = np.linalg.lstsq(aw, yw, rcond=None)
    cov = np.linalg.inv(aw.T @ aw)
    resid = np.full(n_levels, np.nan)
    resid[ok] = mean_m[ok] - a @ coef
    chi2 = float(np.sum((resid[ok] / sigma) ** 2))
    dof = int(ok.sum() - a.shape[1])
    return DepthFit(depths_m=coef[1:], depths_err_m=np.sqrt(np.diag(cov))[1:], top_m=float(coef[0]),
                    residual_m=resid, chi2=chi2, dof=dof,
                    p_value=float(stats.chi2.sf(chi2, dof)) if dof > 0 else float("nan"))
