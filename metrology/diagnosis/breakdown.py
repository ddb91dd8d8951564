"""Residual breakdown helpers: binned statistics and the radial power spectral density."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

__all__ = ["binned", "radial_psd"]


def binned(values: np.ndarray, key: np.ndarray, edges: np.ndarray | Sequence[float]) -> dict[str, list]:
    """Mean, rms and count of ``values`` in bins of ``key`` (NaN values ignored)."""
    ok = np.isfinite(values) & np.isfinite(key)
    idx = np.digitize(key[ok], edges) - 1
    inside = (idx >= 0) & (idx < len(edges) - 1)
    v, idx = values[ok][inside], idx[inside]
    nb = len(edges) - 1
    count = np.bincount(idx, minlength=nb)
    mean = np.bincount(idx, weights=v, minlength=nb) / np.maximum(count, 1)
    ms = np.bincount(idx, weights=v ** 2, minlength=nb) / np.maximum(count, 1)
    return {"edges": np.asarray(edges, dtype=float).tolist(), "mean": mean.tolist(),
            "rms": np.sqrt(ms).tolist(), "count": count.tolist()}


def radial_psd(residual_map: np.ndarray, step_m: float) -> dict[str, list]:
    """Radially averaged power spectral density of a residual map (NaN set to 0).

    Returns a binned dict keyed by spatial frequency (cycles/m); ``mean`` holds the PSD
    (units^2 m^2), normalized so that its integral over the plane is the mean square.
    """
    r = np.nan_to_num(np.asarray(residual_map, dtype=float))
    rows, cols = r.shape
    spec = np.abs(np.fft.fft2(r)) ** 2 * step_m ** 2 / (rows * cols)
    fy = np.fft.fftfreq(rows, d=step_m)[:, None]
    fx = np.fft.fftfreq(cols, d=step_m)[None, :]
    f = np.hypot(fy, fx)
    edges = np.linspace(0, 0.5 / step_m, 16)
    out = binned(spec.ravel(), f.ravel(), edges)
    out.pop("rms")
    return out
