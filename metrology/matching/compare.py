"""Compare a registered, levelled measurement with the design and the process model.

- Level heights on feature interiors only (ISO 5436-1: the central third of a feature).
- Etch depth per mask by weighted least squares ``mu_k = c - sum_j B_kj D_j`` over the 16
  level means, with chi-square telling whether the etches add up.
- Per-mask overlay, linewidth bias and edge transition width from a fit of an edge model to
  the measured surface near the edges (see :func:`fit_edges`).
- Height error maps against the design and against the process model with the fitted
  parameters (:func:`process_on_measurement`).

Coordinates: measurement arrays are row-major, row 0 at the top (camera order); design
pixel (i, j) is centred at design coordinates (i, j). Overlay is x toward increasing
design column, y up (toward decreasing design row), as in :mod:`masks.process`.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np
from scipy import ndimage, optimize, special, stats

from doedesign.errors import DoeError
from doedesign.levels import design_levels
from masks.decompose import levels_to_masks
from masks.process import ProcessParams, simulate_surface

from metrology.matching.register import design_on_measurement

__all__ = ["Comparison", "DepthFit", "EdgeFit", "LEVEL_REPEATABILITY_M", "LevelStats", "MAX_EDGE_BAND_PITCH",
           "MAX_FIT_POINTS", "WIDTH_10_90_PER_SIGMA", "binary_code_matrix", "compare_measurement",
           "crop_registration", "design_height_on_measurement", "error_map", "fit_edges", "fit_etch_depths",
           "fitted_process", "interior_mask", "level_heights", "process_on_measurement", "shift_registration"]

log = logging.getLogger(__name__)

# Repeatability floor (m) added in quadrature to each level mean's standard error in the
# chi-square: a white-light profiler does not repeat a terrace height better than this.
LEVEL_REPEATABILITY_M = 0.3e-9
# Features wider than 3 design pixels keep all but a band this many design pixels wide at
# their edges (instead of only the central third), far beyond edge blur and overlay.
MAX_EDGE_BAND_PITCH = 1.0
# 10 %-90 % width of a Gaussian-blurred step, in sigmas.
WIDTH_10_90_PER_SIGMA = 2 * special.erfinv(0.8) * np.sqrt(2)
# Pixels used by the edge-model fit (strided over the field): enough for ~10 nm overlay.
MAX_FIT_POINTS = 90_000


def binary_code_matrix(n_levels=16):
    """``B[k, j]`` = bit j of level k (mask j open at level k)."""
    n_masks = int(np.log2(n_levels))
    return ((np.arange(n_levels)[:, None] >> np.arange(n_masks)[None, :]) & 1).astype(float)


# -- level heights and etch depths ---------------------------------------------------------
def interior_mask(labels, pitch_px):
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
    labels = np.asarray(labels)
    edge = np.zeros(labels.shape, bool)
    diff_r = labels[1:] != labels[:-1]
    diff_c = labels[:, 1:] != labels[:, :-1]
    edge[1:] |= diff_r
    edge[:-1] |= diff_r
    edge[:, 1:] |= diff_c
    edge[:, :-1] |= diff_c
    # Distance (px) from each pixel to the nearest boundary between features.
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
    cap = MAX_EDGE_BAND_PITCH * pitch_px
    # No feature is narrower than one DOE pixel, whose central third starts pitch/3 in:
    # thinner pieces are features cut by the field border.
    need = np.clip(2.0 / 3.0 * dmax, pitch_px / 3.0, cap)
    need[0] = np.inf
    inner = dist >= need[feature]
    return inner


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


def level_heights(height_m, labels, interior, n_levels=16):
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


def fit_etch_depths(stats_):
    """Weighted least squares ``mu_k = c - sum_j B_kj D_j`` over the levels present."""
    n_levels = stats_.mean_m.size
    b = binary_code_matrix(n_levels)
    ok = np.isfinite(stats_.mean_m) & (stats_.count > 0)
    a = np.column_stack([np.ones(n_levels), -b])[ok]
    if np.linalg.matrix_rank(a) < a.shape[1]:
        raise DoeError(f"only levels {np.flatnonzero(ok).tolist()} are measured: too few to separate "
                       f"the {b.shape[1]} etch depths")
    sigma = np.sqrt(stats_.std_m[ok] ** 2 / np.maximum(stats_.count[ok], 1) + LEVEL_REPEATABILITY_M ** 2)
    aw = a / sigma[:, None]
    yw = stats_.mean_m[ok] / sigma
    coef, *_ = np.linalg.lstsq(aw, yw, rcond=None)
    cov = np.linalg.inv(aw.T @ aw)
    resid = np.full(n_levels, np.nan)
    resid[ok] = stats_.mean_m[ok] - a @ coef
    chi2 = float(np.sum((resid[ok] / sigma) ** 2))
    dof = int(ok.sum() - a.shape[1])
    return DepthFit(depths_m=coef[1:], depths_err_m=np.sqrt(np.diag(cov))[1:], top_m=float(coef[0]),
                    residual_m=resid, chi2=chi2, dof=dof,
                    p_value=float(stats.chi2.sf(chi2, dof)) if dof > 0 else float("nan"))


# -- edge model: overlay, bias, transition width --------------------------------------------
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


def fit_edges(height_m, levels, registration, pitch_m, depths0_m, n_masks=4, max_points=MAX_FIT_POINTS,
              sigma0_m=0.6e-6):
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
        Starting etch depths (e.g. from :func:`fit_etch_depths`).

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


# -- forward model on the measurement grid --------------------------------------------------
def process_on_measurement(levels, pitch_m, params, registration, blur_m=0.0, step_m=0.25e-6,
                           rows=None, block_px=48):
    """The process model's surface as the profilometer would sample it.

    :func:`masks.process.simulate_surface` on the design region under the field (in blocks
    of design rows, so a large field never needs one huge fine grid), blurred by a
    Gaussian of ``blur_m`` (instrument and pixel integration), then sampled bilinearly at
    each measurement pixel centre through ``registration``. Outside the design the wafer is
    unetched (0).

    Parameters
    ----------
    levels : ndarray of int
    pitch_m : float
    params : masks.process.ProcessParams
    registration : Registration
    blur_m : float
    step_m : float
        Fine-grid step of the process simulation.
    rows : slice, optional
        Only these measurement rows (default all).
    block_px : int
        Design rows per simulated block.

    Returns
    -------
    ndarray, shape (n_rows, measurement cols)
    """
    shape = registration.measurement_shape
    row_idx = np.arange(shape[0])[rows if rows is not None else slice(None)]
    rr, cc = registration.to_design(row_idx[:, None].astype(float), np.arange(shape[1])[None, :].astype(float))
    out = np.zeros(rr.shape)
    nr, nc = levels.shape
    on = (rr > -0.5) & (rr < nr - 0.5) & (cc > -0.5) & (cc < nc - 0.5)
    if not on.any():
        return out
    r_lo, r_hi = int(np.floor(rr[on].min() + 0.5)), int(np.floor(rr[on].max() + 0.5)) + 1
    c_lo = max(int(np.floor(cc[on].min() + 0.5)) - 1, 0)
    c_hi = min(int(np.floor(cc[on].max() + 0.5)) + 2, nc)
    margin = 1 + int(np.ceil(4 * blur_m / pitch_m))
    for b0 in range(r_lo, r_hi, block_px):
        b1 = min(b0 + block_px, r_hi)
        sel = on & (rr >= b0 - 0.5) & (rr < b1 - 0.5)
        if not sel.any():
            continue
        s0, s1 = max(b0 - margin, 0), min(b1 + margin, nr)
        surf = simulate_surface(levels, pitch_m, params, step_m=step_m, region=(s0, s1, c_lo, c_hi))
        fine = surf.height_m
        u = surf.upsample
        if blur_m > 0:
            fine = ndimage.gaussian_filter(fine, blur_m / surf.step_m, mode="nearest")
        fr = (rr[sel] - s0 + 0.5) * u - 0.5
        fc = (cc[sel] - c_lo + 0.5) * u - 0.5
        out[sel] = ndimage.map_coordinates(fine, [fr, fc], order=1, mode="nearest")
    return out


def fitted_process(edge_fit, depths_m=None, n_masks=4):
    """:class:`ProcessParams` holding the fitted depths, overlay and bias (no blur: the
    fitted edge blur is the instrument's and is applied on the measurement side)."""
    overlay = np.zeros((n_masks, 3))
    overlay[:, :2] = edge_fit.overlay_m
    depths = edge_fit.depths_m if depths_m is None else np.asarray(depths_m, float)
    return ProcessParams(etch_depth=np.array(depths, float), mask_overlay=overlay,
                         linewidth_bias=np.array(edge_fit.bias_m, float))


def shift_registration(registration, shift_m, pitch_m):
    """Registration moved so that the design frame follows mask 0 (``shift_m`` = its (dx, dy)).

    The edge fit reports overlay relative to mask 0; the process model puts mask 0 where
    the design is, so the model is sampled through a registration shifted by mask 0's shift.
    """
    from dataclasses import replace

    d_rc = np.array([-shift_m[1], shift_m[0]]) / pitch_m
    return replace(registration, offset=registration.offset - d_rc)


def error_map(height_m, reference_m):
    """``height - reference`` with NaN where either is invalid, and its rms (m)."""
    err = np.asarray(height_m, float) - np.asarray(reference_m, float)
    ok = np.isfinite(err)
    rms = float(np.sqrt(np.mean(err[ok] ** 2))) if ok.any() else float("nan")
    return err, rms


def design_height_on_measurement(design_height_m, registration):
    """Design heights at each measurement pixel (nearest design pixel; NaN off the design)."""
    return design_on_measurement(np.asarray(design_height_m, float), registration, fill=np.nan)


def crop_registration(registration, row0, col0, shape):
    """The registration of the sub-array ``[row0:row0 + shape[0], col0:col0 + shape[1]]``."""
    from dataclasses import replace

    offset = registration.offset + registration.matrix @ np.array([row0, col0], float)
    return replace(registration, offset=offset, measurement_shape=tuple(shape))


@dataclass
class Comparison:
    """Everything :func:`compare_measurement` found; :meth:`report` is the JSON summary.

    Maps are on the measurement grid (row 0 at the top, camera order).
    """

    height_m: np.ndarray
    labels: np.ndarray
    interior: np.ndarray
    registration: object
    levelling: object
    stats: LevelStats
    depth_fit: DepthFit
    edge_fit: EdgeFit
    nominal_depths_m: np.ndarray
    error_design_m: np.ndarray
    error_model_m: np.ndarray
    model_window: tuple
    spikes_removed: int
    roughness_m: float
    match: dict = field(default_factory=dict)

    def fitted_params(self):
        """:class:`ProcessParams` with the level-fit depths and the edge-fit overlay and bias."""
        return fitted_process(self.edge_fit, self.depth_fit.depths_m, self.nominal_depths_m.size)

    def report(self):
        nm, um = 1e9, 1e6
        e, d, s = self.edge_fit, self.depth_fit, self.stats
        _, rms_design = error_map(self.error_design_m, 0.0)
        inner_err = np.where(self.interior, self.error_design_m, np.nan)
        _, rms_inner = error_map(inner_err, 0.0)
        _, rms_model = error_map(self.error_model_m, 0.0)
        return {
            "etch_depths_nm": d.depths_m * nm,
            "etch_depths_err_nm": d.depths_err_m * nm,
            "etch_depths_nominal_nm": self.nominal_depths_m * nm,
            "etch_depths_error_percent": (d.depths_m / self.nominal_depths_m - 1) * 100,
            "etch_depths_edge_fit_nm": e.depths_m * nm,
            "etch_sum": {"chi2": d.chi2, "dof": d.dof, "p_value": d.p_value,
                         "level_residual_nm": d.residual_m * nm, "top_nm": d.top_m * nm,
                         "note": "mu_k = top - sum_j B_kj D_j over the level means; small p: etches do not add up"},
            "level_heights_nm": s.mean_m * nm,
            "level_std_nm": s.std_m * nm,
            "level_pixel_counts": s.count,
            "overlay_um": e.overlay_m * um,
            "overlay_err_um": e.stderr["overlay_m"] * um,
            "linewidth_bias_um": e.bias_m * um,
            "linewidth_bias_err_um": e.stderr["bias_m"] * um,
            "edge_transition_width_um": e.transition_width_m * um,
            "edge_fit_rms_residual_nm": e.rms_residual_m * nm,
            "edge_fit_points": e.n_points,
            "roughness_rms_nm": self.roughness_m * nm,
            "registration": self.registration.to_dict(),
            "match": dict(self.match),
            "height_error_rms_nm": rms_design * nm,
            "height_error_interior_rms_nm": rms_inner * nm,
            "height_error_model_rms_nm": rms_model * nm,
            "model_window_rows_cols": list(self.model_window),
            "levelling": {"plane_m_per_px": self.levelling.plane[1:],
                          "method": "joint plane + one offset per level on feature interiors"},
            "spikes_removed": self.spikes_removed,
            "conventions": ("overlay (dx, dy) of each mask relative to mask 0, x toward increasing design column, "
                            "y up; linewidth bias = growth of every opening edge (+ = wider); heights z up, "
                            "0 = unetched top; level heights on the central third of features (ISO 5436-1); "
                            "roughness = pooled rms about the level means on interiors, 5-sigma outliers out (includes instrument noise)"),
        }


# A correct match puts nearly every feature interior on its design level (noise and roughness are
# a few nm, a quarter step is 19 nm); against the wrong design or field the interiors spread over
# many levels although the registration still finds a lattice (its correlation alone does not
# separate the cases: 0.6 for a small correct field, 0.62 for a wrong design).
MATCH_TOLERANCE_STEPS = 0.25
MIN_LEVEL_AGREEMENT = 0.8


def level_agreement(height_m, labels, interior, stats, step_m):
    """Fraction of valid feature-interior pixels within MATCH_TOLERANCE_STEPS of their level's mean."""
    use = interior & np.isfinite(height_m) & (labels >= 0)
    lab = labels[use]
    means = stats.mean_m[lab]
    ok = np.isfinite(means) & (np.abs(height_m[use] - means) <= MATCH_TOLERANCE_STEPS * step_m)
    return float(ok.mean()) if ok.size else 0.0


def match_quality(agreement, registration, forced=False):
    """Match quality and confidence of a comparison (the ``match`` entry of its report)."""
    return {"level_agreement": agreement, "tolerance_steps": MATCH_TOLERANCE_STEPS,
            "threshold": MIN_LEVEL_AGREEMENT, "registration_ncc": float(registration.match_ncc),
            "confidence": "high" if agreement >= MIN_LEVEL_AGREEMENT else "low", "forced": bool(forced),
            "meaning": "fraction of feature-interior pixels within tolerance_steps level steps of their "
                       "design level's mean height"}


def compare_measurement(measurement, design, n_masks=4, model_max_px=400, progress=None, force=False):
    """Level, register and compare a measurement with its design.

    Parameters
    ----------
    measurement : metrology.formats.measurement.Measurement
    design : doedesign.design.Design
    n_masks : int
    model_max_px : int
        Side of the central window (measurement pixels) on which the process model is
        simulated for the model error map; the fits use strided samples of the whole field.
    progress : doedesign.progress.Progress, optional
        Advanced once per stage (6 stages).
    force : bool
        Go on when the measurement matches the design poorly (see :func:`match_quality`).

    Returns
    -------
    Comparison

    Raises
    ------
    DoeError
        The measurement matches the design poorly (wrong design, field or orientation) and
        ``force`` is False.
    """
    from masks.decompose import binary_depths_m

    from metrology.matching.level import level_joint, level_on_top, remove_spikes
    from metrology.matching.register import register

    def step(name):
        log.info("compare: %s", name)
        if progress is not None:
            progress.update(1, status=name)

    pitch = design.pitch_m
    levels = design_levels(design, 2 ** n_masks)
    nominal = np.array(binary_depths_m(design.level_step_m(2 ** n_masks), n_masks))
    h, n_spikes = remove_spikes(measurement.height_m)
    first = level_on_top(h)
    step("levelled on level 0")
    reg = register(first.height_m, design.height_m, pitch, pixel_size_m=measurement.pixel_size_m)
    step("registered")
    labels = design_on_measurement(levels, reg)
    interior = interior_mask(labels, 1.0 / reg.decompose()["scale"])
    joint = level_joint(h, np.where(interior, labels, -1))
    height = joint.height_m
    st = level_heights(height, labels, interior, 2 ** n_masks)
    agreement = level_agreement(height, labels, interior, st, nominal[0])
    match = match_quality(agreement, reg, force)
    if match["confidence"] == "low":
        message = (f"the measurement matches the design poorly: only {agreement:.0%} of feature interiors lie "
                   f"within {MATCH_TOLERANCE_STEPS} level step of their design level (need "
                   f"{MIN_LEVEL_AGREEMENT:.0%}; registration correlation {reg.match_ncc:.2f}); check the design "
                   "file, that the field lies on the element, its orientation and the pixel size")
        if not force:
            raise DoeError(message + "; --force compares anyway")
        log.warning("%s (forced)", message)
    depth_fit = fit_etch_depths(st)
    step("level heights")
    edge = fit_edges(height, levels, reg, pitch, depth_fit.depths_m, n_masks)
    step("edge fit")
    err_design, _ = error_map(height, design_height_on_measurement(design.height_m, reg))
    rows, cols = height.shape
    wr, wc = min(rows, model_max_px), min(cols, model_max_px)
    r0, c0 = (rows - wr) // 2, (cols - wc) // 2
    params = fitted_process(edge, depth_fit.depths_m, n_masks)
    window_reg = shift_registration(crop_registration(reg, r0, c0, (wr, wc)), edge.shift_m[0], pitch)
    model = process_on_measurement(levels, pitch, params, window_reg, blur_m=edge.sigma_m, step_m=0.5e-6)
    err_model = np.full(height.shape, np.nan)
    err_model[r0:r0 + wr, c0:c0 + wc] = height[r0:r0 + wr, c0:c0 + wc] - model
    step("process model")
    have = st.count > 0
    roughness = float(np.sqrt(np.sum(st.count[have] * st.std_m[have] ** 2) / st.count[have].sum()))
    step("done")
    return Comparison(height_m=height, labels=labels, interior=interior, registration=reg, levelling=joint,
                      stats=st, depth_fit=depth_fit, edge_fit=edge, nominal_depths_m=nominal,
                      error_design_m=err_design, error_model_m=err_model, model_window=(r0, r0 + wr, c0, c0 + wc),
                      spikes_removed=n_spikes, roughness_m=roughness, match=match)
