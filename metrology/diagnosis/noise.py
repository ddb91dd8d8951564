"""Noise floor and correlation area of a measurement, estimated from the data alone.

Pixels that scatter about a per-group constant (flat feature interiors for heights, unlit
tiles for PSFs) give the noise rms; the autocorrelation of that scatter gives the correlation
area ``A`` (pixels) and the effective sample count ``n_eff = N / A`` of the criterion.

A group may instead scatter about its own plane (``trend="plane"``): a profilometer's flat
interiors carry smooth height changes that are not noise (an etch depth varying across the field,
the instrument's own form, what levelling the whole field leaves within one feature). About its
mean alone, a 2.8 % per mm etch gradient or a CSI's form set the floor of a generated field at
1.3-3x its noise, with a correlation area of 20-50 pixels for white noise.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from doedesign.errors import DoeError

__all__ = ["MAX_LAG_PX", "NoiseEstimate", "estimate_noise"]

# Lags (pixels) over which the noise autocorrelation is summed into the correlation area.
MAX_LAG_PX = 3


@dataclass
class NoiseEstimate:
    """Noise floor and correlation of the measurement, estimated from the data.

    Attributes
    ----------
    sigma : float
        Robust rms of the noise (measurement units).
    corr_area_px : float
        Correlation area ``A = sum of the autocorrelation over lags`` (pixels, >= 1).
    n_samples : int
        Pixels the estimate used.
    """

    sigma: float
    corr_area_px: float
    n_samples: int


def estimate_noise(values: np.ndarray, groups: np.ndarray, max_lag: int = MAX_LAG_PX,
                   trend: str = "mean") -> NoiseEstimate:
    """Noise rms and correlation area from pixels scattering about a per-group constant or plane.

    Parameters
    ----------
    values : ndarray (rows, cols)
    groups : ndarray of int (rows, cols)
        Label of each pixel's flat region; 0 excludes the pixel. Within a group the true
        signal is taken as constant, so the scatter about the group mean is noise.
    max_lag : int
        Largest lag (pixels) of the autocorrelation summed into the correlation area.
    trend : {"mean", "plane"}
        What each group's signal is taken to be: a constant, or a plane in (row, col).

    Returns
    -------
    NoiseEstimate
    """
    groups = np.asarray(groups)
    valid = (groups > 0) & np.isfinite(values)
    n = int(valid.sum())
    labels = groups[valid]
    n_groups = np.unique(labels).size
    if n - n_groups < 50:
        raise DoeError(f"too few flat pixels ({n}) to estimate the noise floor; "
                       "the measurement must include feature interiors away from edges")
    if trend not in ("mean", "plane"):
        raise ValueError(f"trend must be 'mean' or 'plane', not {trend!r}")
    counts = np.bincount(labels)
    dev = np.zeros(values.shape)
    dev[valid] = _about_trend(values, valid, labels, counts, trend == "plane")
    area = _correlation_area(dev, valid, groups, max_lag)
    # Removing each group's mean (or plane: p = 3 parameters) also removes ~p A pixels' worth of
    # correlated noise variance; undo that shrinkage per group (groups smaller than 3 p A carry
    # too little and are dropped).
    p = 3 if trend == "plane" else 1
    n_g = counts[labels]
    keep = n_g > 3 * p * area
    if keep.sum() < 50:
        raise DoeError(f"too few flat pixels in features wider than the noise correlation "
                       f"({int(keep.sum())}) to estimate the noise floor")
    scaled = dev[valid][keep] * np.sqrt(n_g[keep] / (n_g[keep] - p * area))
    # MAD is robust to spikes and to a few edge pixels left in the interiors.
    var = (1.4826 * np.median(np.abs(scaled - np.median(scaled)))) ** 2
    if not var > 0:
        var = float(np.mean(scaled ** 2))
    n = int(keep.sum())
    return NoiseEstimate(sigma=float(np.sqrt(var)), corr_area_px=area, n_samples=n)


def _about_trend(values, valid, labels, counts, plane):
    """Each valid pixel's value less its group's mean, or its group's least-squares plane."""
    v = values[valid]
    n = np.maximum(counts, 1).astype(float)
    dev = v - (np.bincount(labels, weights=v) / n)[labels]
    if not plane:
        return dev
    # Coordinates about each group's centroid, so the plane's slopes decouple from its mean.
    rows, cols = np.nonzero(valid)
    r = rows - (np.bincount(labels, weights=rows) / n)[labels]
    c = cols - (np.bincount(labels, weights=cols) / n)[labels]
    srr, scc, src = (np.bincount(labels, weights=w) for w in (r * r, c * c, r * c))
    svr, svc = np.bincount(labels, weights=dev * r), np.bincount(labels, weights=dev * c)
    det = srr * scc - src ** 2
    # A group on one line (or one pixel) has no plane: its mean alone is removed.
    ok = det > 1e-9 * srr * scc
    safe = np.where(ok, det, 1.0)
    a = np.where(ok, (svr * scc - svc * src) / safe, 0.0)
    b = np.where(ok, (svc * srr - svr * src) / safe, 0.0)
    return dev - a[labels] * r - b[labels] * c


def _correlation_area(dev, valid, groups, max_lag):
    """Sum of the autocorrelation of ``dev`` over lags up to ``max_lag`` (pairs within a group)."""
    # Clip at 5 robust sigmas: a few spikes or edge pixels left in the interiors would
    # otherwise set both the clip level and the autocorrelation, and inflate the area.
    d = dev[valid]
    sigma = 1.4826 * np.median(np.abs(d - np.median(d)))
    if not sigma > 0:
        sigma = float(np.sqrt(np.mean(d ** 2)))
    ok = valid & (np.abs(dev) < 5 * sigma)
    # Re-centre each group on its kept pixels: the outliers also moved the group's mean, and
    # that offset would correlate at every lag.
    lab = groups[ok]
    centre = np.bincount(lab, weights=dev[ok]) / np.maximum(np.bincount(lab), 1)
    clip = np.zeros(dev.shape)
    clip[ok] = dev[ok] - centre[lab]
    ref = np.mean(clip[valid] ** 2)
    rows, cols = dev.shape
    area = 0.0
    for dy in range(-max_lag, max_lag + 1):
        for dx in range(-max_lag, max_lag + 1):
            a = (slice(max(0, -dy), rows - max(0, dy)), slice(max(0, -dx), cols - max(0, dx)))
            b = (slice(max(0, dy), rows + min(0, dy)), slice(max(0, dx), cols + min(0, dx)))
            same = valid[a] & valid[b] & (groups[a] == groups[b])
            if same.sum() < 20:
                continue
            area += max(np.mean(clip[a][same] * clip[b][same]) / ref, 0.0)
    return float(max(area, 1.0))
