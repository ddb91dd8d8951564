"""Residual breakdown: binned statistics, the radial power spectral density, and the two views
every height problem (design frame or camera frame) shares: the structure groups the engine
tests for unexplained structure, and the breakdown the report prints."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

__all__ = ["INSTRUMENT_SHARE", "MASK_AMPLITUDES", "binned", "edge_breakdown", "instrument_signature", "radial_psd",
           "shared_profile_gain", "structure_groups"]

# Share of the edge-bound structure a profile common to every mask must hold for the residual to
# be the instrument's.
INSTRUMENT_SHARE = 0.7
# Range of each well-measured mask's amplitude of the shared profile (1 = its full share).
MASK_AMPLITUDES = (0.5, 1.5)


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


def structure_groups(levels: np.ndarray, any_edge_m: np.ndarray, edge_m: Sequence[np.ndarray] | np.ndarray,
                     keep: np.ndarray) -> list[np.ndarray]:
    """Group labels (0 = left out) in which an explained residual must average to zero.

    Level x distance to the nearest edge (edge effects), level x 4 x 4 tiles of the field
    (density and position effects), and signed distance to the edges of the two highest masks.
    """
    dist_bin = np.digitize(any_edge_m, np.array([0.25, 0.5, 1.0, 1.5, 2.5, 4.0]) * 1e-6)
    rows, cols = keep.shape
    tile = (np.arange(rows)[:, None] * 4 // rows) * 4 + (np.arange(cols)[None, :] * 4 // cols)
    signed = [np.digitize(d, np.linspace(-3e-6, 3e-6, 13)) for d in edge_m]
    maps = [levels * 8 + dist_bin, levels * 16 + tile, sum(b * 14 ** j for j, b in enumerate(signed[::-1][:2]))]
    return [np.where(keep, m + 1, 0) for m in maps]


def edge_breakdown(residual_map: np.ndarray, edge_m: Sequence[np.ndarray] | np.ndarray, levels: np.ndarray,
                   spacing_m: float) -> dict[str, dict]:
    """Residual by signed distance to each mask's edges, by level, by distance from the field
    centre and by spatial frequency (``spacing_m``: the map's pixel spacing)."""
    out = {}
    edges_d = np.linspace(-4e-6, 4e-6, 17)
    for j, d in enumerate(edge_m):
        out[f"edge_distance_mask{j}_m"] = binned(residual_map, d, edges_d)
    out["level"] = binned(residual_map, np.asarray(levels, dtype=float), np.arange(-0.5, 16.5))
    rows, cols = residual_map.shape
    yy, xx = np.mgrid[:rows, :cols]
    radius = np.hypot(yy - (rows - 1) / 2, xx - (cols - 1) / 2) * spacing_m
    out["radius_from_centre_m"] = binned(residual_map, radius, np.linspace(0, radius.max() + 1e-12, 9))
    out["spatial_frequency_per_m"] = radial_psd(residual_map, spacing_m)
    return out


# Bins of the signed distance to a mask's edge (m) of the instrument's edge profile.
_PROFILE_EDGES_M = np.linspace(-3e-6, 3e-6, 25)


def instrument_signature(residual_map: np.ndarray, edge_m: Sequence[np.ndarray] | np.ndarray,
                         depths_m: Sequence[float] | np.ndarray,
                         keep: np.ndarray, sigma: float, corr_area_px: float,
                         share: float = INSTRUMENT_SHARE,
                         amplitudes: tuple[float, float] = MASK_AMPLITUDES, every_mask: bool = True) -> dict | None:
    """Whether a residual is the instrument's: the same at every mask's edges, on both sides.

    A lateral transfer the model gets wrong leaves, at each edge, the step's height times one
    profile of the signed distance to the edge, whatever the mask; fabrication effects are
    mask-, level- or position-specific. One binned profile ``g`` shared by all masks,
    ``r = sum_j D_j g(d_j)`` (``D_j`` mask j's depth, ``d_j`` the signed distance to its edges),
    is fitted by least squares against one profile per mask. The residual is the instrument's
    when the per-mask profiles find significant structure, the shared one holds at least
    ``share`` of it, and each mask whose part of the shared prediction ``p_j = D_j g(d_j)`` is
    measured well (its amplitude ``a_j = <r, p_j> / <p_j, p_j>`` to 0.2) carries it at full
    amplitude (``0.5 <= a_j <= 1.5``), on at least two masks: a residual on one mask's edges
    (the deepest dominates any shared fit) is that mask's.

    Parameters
    ----------
    residual_map : ndarray
        Final residual (NaN where not compared), row 0 at the top.
    edge_m : sequence of ndarray
        Signed distance (m, positive inside the opening) of each pixel to each mask's edges.
    depths_m : sequence of float
        Nominal step of each mask.
    keep : ndarray of bool
    sigma, corr_area_px : float
        Noise floor and correlation area (pixels).
    share : float
    amplitudes : (float, float)
        Range of the ``a_j`` measured (default: full amplitude, 0.5 to 1.5).
    every_mask : bool
        Every mask measured well must carry the profile within ``amplitudes`` (else: at least
        two of them; a screen for whether to try the instrument's family, whose criterion then
        decides: a real instrument's edge response need not scale with every step alike).

    Returns
    -------
    dict or None
        ``explained_share`` (shared over per-mask), ``mask_amplitudes`` (``a_j``, NaN where not
        measured), ``odd_share`` (the profile's power in its part odd about the edge), the shared profile per unit step (``profile_per_m_step`` at ``distance_m``)
        and the rms it explains; or None.
    """
    eq = _edge_equations(residual_map, edge_m, depths_m, keep)
    if eq is None:
        return None
    gram, rhs, fold, nb, nm, r = eq
    n_col = nm * nb
    edges = _PROFILE_EDGES_M
    gain_mask, _ = _explained(gram, rhs)
    gain_shared, profile = _explained(fold.T @ gram @ fold, fold.T @ rhs)
    scale = sigma * np.sqrt(max(corr_area_px, 1.0))
    if gain_mask <= 0 or gain_mask / scale ** 2 < 25.0 + n_col or gain_shared < share * gain_mask:
        return None
    low, high = amplitudes
    found: list[float] = []
    for j in range(nm):
        blk = slice(j * nb, (j + 1) * nb)
        norm2 = float(profile @ gram[blk, blk] @ profile)
        found.append(float(profile @ rhs[blk]) / norm2 if norm2 > (5.0 * scale) ** 2 else np.nan)
    measured = [a for a in found if np.isfinite(a)]
    inside = sum(low <= a <= high for a in measured)
    if inside < 2 or (every_mask and inside < len(measured)):
        return None
    odd = 0.5 * (profile - profile[::-1])  # the bins are symmetric about the edge
    return {"explained_share": gain_shared / gain_mask, "mask_amplitudes": found,
            "odd_share": float(np.sum(odd ** 2) / max(np.sum(profile ** 2), 1e-300)),
            "explained_rms_m": float(np.sqrt(gain_shared / r.size)),
            "distance_m": (0.5 * (edges[1:] + edges[:-1])).tolist(), "profile_per_m_step": profile.tolist()}


def shared_profile_gain(residual_map: np.ndarray, edge_m: Sequence[np.ndarray], depths_m: Sequence[float],
                        keep: np.ndarray) -> tuple[float, float]:
    """RSS of a residual and how much of it one binned edge profile shared by every mask
    (``r = sum_j D_j g(d_j)``, see :func:`instrument_signature`) removes. What a wrong lateral
    transfer leaves at straight edges is such a profile, so this screens whether the instrument's
    family has anything left to earn; not a bound (the family's joint refit, which moves the
    placement and the named effects too, can earn more). ``(rss, 0)`` where too few pixels."""
    eq = _edge_equations(residual_map, edge_m, depths_m, keep)
    if eq is None:
        return float(np.sum(residual_map[keep & np.isfinite(residual_map)] ** 2)), 0.0
    gram, rhs, fold, _, _, r = eq
    return float(np.sum(r ** 2)), _explained(fold.T @ gram @ fold, fold.T @ rhs)[0]


def _edge_equations(residual_map, edge_m, depths_m, keep):
    """Normal equations of the per-mask edge profiles (one column per mask and distance bin,
    scaled by the mask's depth) on the residual, the fold that sums them into one shared
    profile, the bin and mask counts and the residual's values; None where too few pixels."""
    edges = _PROFILE_EDGES_M
    ok = keep & np.isfinite(residual_map)
    r = residual_map[ok]
    nb, nm = len(edges) - 1, len(edge_m)
    if nm < 2 or r.size < 10 * nb:
        return None
    # Column index (mask j, bin k) -> j nb + k of each pixel, -1 outside the bins; the models'
    # normal equations by counting (a field's 250 000 pixels x 96 columns held densely, and
    # their least squares, cost seconds).
    cols = np.full((nm, r.size), -1)
    for j, d in enumerate(edge_m):
        d = np.asarray(d)[ok]
        # Mirror bins: d and -d fall in bins nb - 1 - k and k (the profile's odd part is then exact).
        idx = np.where(d < 0, nb - np.digitize(-d, edges), np.digitize(d, edges) - 1)
        cols[j] = np.where((idx >= 0) & (idx < nb), j * nb + idx, -1)
    depth_of = np.repeat(np.asarray(depths_m, float), nb)
    n_col = nm * nb
    rhs = np.zeros(n_col)
    gram = np.zeros(n_col * n_col)
    for j in range(nm):
        inj = cols[j] >= 0
        rhs += np.bincount(cols[j][inj], weights=r[inj], minlength=n_col)
        for k in range(nm):
            both = inj & (cols[k] >= 0)
            gram += np.bincount(cols[j][both] * n_col + cols[k][both], minlength=n_col * n_col)
    gram = gram.reshape(n_col, n_col) * np.outer(depth_of, depth_of)
    rhs *= depth_of
    # The shared model's columns are the sums of the masks' columns of the same bin.
    fold = np.tile(np.eye(nb), (nm, 1))
    return gram, rhs, fold, nb, nm, r


def _explained(g, b):
    """RSS reduction and coefficients of the least squares with normal equations ``g x = b``
    (columns that no pixel reaches left out)."""
    used = np.diag(g) > 0
    coef = np.zeros(b.size)
    coef[used] = np.linalg.lstsq(g[np.ix_(used, used)], b[used], rcond=None)[0]
    return float(b @ coef), coef
