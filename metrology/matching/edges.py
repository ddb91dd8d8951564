"""The point-sampled edge model of ``doe compare``: per-mask shift, linewidth bias and depth
and one Gaussian edge blur fitted near the edges. Fast and robust from the registration; its
values start the instrument-frame fit (:mod:`metrology.matching.instrument_fit`), which
reports them.

Coordinates: measurement arrays are row-major, row 0 at the top (camera order); design
pixel (i, j) is centred at design coordinates (i, j). Overlay is x toward increasing
design column, y up (toward decreasing design row), as in :mod:`masks.process`.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from scipy import optimize, special

from doedesign.errors import DoeError
from masks.decompose import levels_to_masks

if TYPE_CHECKING:
    from metrology.matching.register import Registration

__all__ = ["EdgeFit", "MAX_FIT_POINTS", "WIDTH_10_90_PER_SIGMA", "fit_edges"]

# 10 %-90 % width of a Gaussian-blurred step, in sigmas.
WIDTH_10_90_PER_SIGMA = 2 * special.erfinv(0.8) * np.sqrt(2)
# Pixels used by the edge-model fit (strided over the field): enough for ~10 nm overlay.
MAX_FIT_POINTS = 90_000


def _box_blur(t, sigma):
    """A unit-wide box centred at 0 blurred by a Gaussian of ``sigma``, at ``t``."""
    s = np.sqrt(2.0) * sigma
    return 0.5 * (special.erf((t + 0.5) / s) - special.erf((t - 0.5) / s))


def _box_blur_slope(t, sigma):
    """Derivative of :func:`_box_blur` with respect to ``t``."""
    norm = 1.0 / (np.sqrt(2 * np.pi) * sigma)
    return norm * (np.exp(-0.5 * ((t + 0.5) / sigma) ** 2) - np.exp(-0.5 * ((t - 0.5) / sigma) ** 2))


def _blurred_mask(mask_padded, pad, r, c, sigma):
    """Gaussian-blurred binary pixel mask and its gradient at design coordinates (r, c).

    Exact for square pixels: each pixel's blurred box is a product of erf differences.
    """
    reach = int(np.floor(1.0 + 4.0 * sigma))
    i0 = np.rint(r).astype(int)
    j0 = np.rint(c).astype(int)
    ey = [(_box_blur(r - (i0 + d), sigma), _box_blur_slope(r - (i0 + d), sigma)) for d in range(-reach, reach + 1)]
    ex = [(_box_blur(c - (j0 + d), sigma), _box_blur_slope(c - (j0 + d), sigma)) for d in range(-reach, reach + 1)]
    val = np.zeros(r.shape)
    d_r = np.zeros(r.shape)
    d_c = np.zeros(r.shape)
    for a, (fy, sy) in zip(range(-reach, reach + 1), ey):
        rows = np.clip(i0 + a + pad, 0, mask_padded.shape[0] - 1)
        for b, (fx, sx) in zip(range(-reach, reach + 1), ex):
            cols = np.clip(j0 + b + pad, 0, mask_padded.shape[1] - 1)
            m = mask_padded[rows, cols]
            val += m * fy * fx
            d_r += m * sy * fx
            d_c += m * fy * sx
    return val, d_r, d_c


@dataclass
class EdgeFit:
    """Result of :func:`fit_edges` (design-pixel units inside, SI in the attributes).

    Attributes
    ----------
    depths_m : ndarray (n_masks,)
    shift_m : ndarray (n_masks, 2)
        (dx, dy) of each mask's pattern in the registered frame (x right, y up).
    overlay_m : ndarray (n_masks, 2)
        ``shift_m`` relative to mask 0 (row 0 is zero).
    bias_m : ndarray (n_masks,)
        Growth of every opening edge (m), positive = openings wider (as
        ``ProcessParams.linewidth_bias``).
    sigma_m : float
        Gaussian edge blur (instrument, pixel integration, sidewall and process blur).
    transition_width_m : float
        10 %-90 % width of a step edge, ``2.563 sigma``.
    stderr : dict
        Standard errors of the above (same keys and shapes).
    rms_residual_m : float
    n_points : int
    """

    depths_m: np.ndarray
    shift_m: np.ndarray
    overlay_m: np.ndarray
    bias_m: np.ndarray
    sigma_m: float
    transition_width_m: float
    stderr: dict
    rms_residual_m: float
    n_points: int


def fit_edges(height_m: np.ndarray, levels: np.ndarray, registration: Registration, pitch_m: float,
              depths0_m: Sequence[float] | np.ndarray, n_masks: int = 4, max_points: int = MAX_FIT_POINTS,
              sigma0_m: float = 0.6e-6) -> EdgeFit:
    """Fit per-mask shift, linewidth bias and depth, and one edge blur, to the measured surface.

    Model at a measurement pixel mapped to design coordinates x:
    ``z(x) = c + t . x - sum_j D_j [m_j(x - s_j) + b_j |grad m_j(x - s_j)|]``, with ``m_j``
    mask j's binary pattern blurred by a Gaussian of ``sigma`` (exact for square pixels),
    ``s_j`` its shift and ``b_j`` the outward displacement of its edges (first order).
    Gauss-Newton with the analytic Jacobian (``scipy.optimize.least_squares``) on up to
    ``max_points`` pixels strided over the field.

    Parameters
    ----------
    height_m : ndarray
        Levelled measurement (NaN invalid), measurement grid.
    levels : ndarray of int
        Design levels.
    registration : Registration
    pitch_m : float
    depths0_m : sequence of float
        Starting etch depths (e.g. from :func:`~metrology.matching.depths.fit_etch_depths`).

    Returns
    -------
    EdgeFit
    """
    h = np.asarray(height_m, float)
    valid = np.isfinite(h)
    stride = max(1, int(np.ceil(np.sqrt(valid.sum() / max_points))))
    sub = np.zeros_like(valid)
    sub[::stride, ::stride] = True
    rows, cols = np.nonzero(valid & sub)
    r, c = registration.to_design(rows, cols)
    inside = (r > -0.5) & (r < levels.shape[0] - 0.5) & (c > -0.5) & (c < levels.shape[1] - 0.5)
    r, c, z = r[inside], c[inside], h[rows[inside], cols[inside]]
    if z.size < 200:
        raise DoeError("edge fit: fewer than 200 measured pixels fall on the design")
    pad = 8
    masks = np.pad(levels_to_masks(levels, n_masks), ((0, 0), (pad, pad), (pad, pad))).astype(float)
    rc, cc = r - r.mean(), c - c.mean()
    n = n_masks

    def unpack(p):
        return p[0], p[1:1 + n], p[1 + n:1 + 3 * n].reshape(n, 2), p[1 + 3 * n:1 + 4 * n], p[1 + 4 * n], \
            p[2 + 4 * n:4 + 4 * n]

    def model(p, jac=False):
        top, depth, shift, bias, log_sigma, tilt = unpack(p)
        sigma = np.exp(log_sigma)
        zz = top + tilt[0] * rc + tilt[1] * cc
        cols_j = []
        for j in range(n):
            val, dr, dc = _blurred_mask(masks[j], pad, r - shift[j, 0], c - shift[j, 1], sigma)
            grad = np.sqrt(dr * dr + dc * dc)
            zz = zz - depth[j] * (val + bias[j] * grad)
            if jac:
                cols_j.append((-(val + bias[j] * grad), depth[j] * dr, depth[j] * dc, -depth[j] * grad))
        if not jac:
            return zz
        jm = np.empty((z.size, p.size))
        jm[:, 0] = 1.0
        for j, (dd, dsr, dsc, db) in enumerate(cols_j):
            jm[:, 1 + j] = dd
            jm[:, 1 + n + 2 * j] = dsr
            jm[:, 2 + n + 2 * j] = dsc
            jm[:, 1 + 3 * n + j] = db
        eps = 1e-3
        q = p.copy()
        q[1 + 4 * n] += eps
        jm[:, 1 + 4 * n] = (model(q) - zz) / eps
        jm[:, 2 + 4 * n] = rc
        jm[:, 3 + 4 * n] = cc
        return zz, jm

    cache = {}

    def fun(p):
        zz, jm = model(p, jac=True)
        cache["jac"] = jm
        return zz - z

    def jac(p):
        return cache["jac"]

    # Heights are scaled to ~1 in the solver (depths in units of 100 nm).
    p0 = np.concatenate([[0.0], np.asarray(depths0_m, float) / 1e-7, np.zeros(2 * n), np.zeros(n),
                         [np.log(sigma0_m / pitch_m)], [0.0, 0.0]])
    z = z / 1e-7
    res = optimize.least_squares(fun, p0, jac=jac, method="lm", xtol=1e-10, ftol=1e-12, max_nfev=60)
    top, depth, shift, bias, log_sigma, _ = unpack(res.x)
    resid = res.fun
    dof = max(z.size - res.x.size, 1)
    try:
        cov = np.linalg.inv(res.jac.T @ res.jac) * np.sum(resid ** 2) / dof
        err = np.sqrt(np.abs(np.diag(cov)))
    except np.linalg.LinAlgError:
        err = np.full(res.x.size, np.nan)
    _, d_err, s_err, b_err, ls_err, _ = unpack(err)
    sigma = float(np.exp(log_sigma))
    # Design (row, col) shifts to (x right, y up) in metres.
    shift_m = np.column_stack([shift[:, 1], -shift[:, 0]]) * pitch_m
    shift_err = np.column_stack([s_err[:, 1], s_err[:, 0]]) * pitch_m
    overlay_err = np.sqrt(shift_err ** 2 + shift_err[0] ** 2)
    overlay_err[0] = 0.0
    width = WIDTH_10_90_PER_SIGMA * sigma * pitch_m
    return EdgeFit(
        depths_m=depth * 1e-7, shift_m=shift_m, overlay_m=shift_m - shift_m[0], bias_m=bias * pitch_m,
        sigma_m=sigma * pitch_m, transition_width_m=width,
        stderr={"depths_m": d_err * 1e-7, "shift_m": shift_err, "overlay_m": overlay_err,
                "bias_m": b_err * pitch_m, "transition_width_m": width * ls_err},
        rms_residual_m=float(np.sqrt(np.mean(resid ** 2)) * 1e-7), n_points=int(z.size))
