"""Terrace fit of a levelled field: each level's height from its flat interiors, step by step.

An independent check of the level heights that ``doe compare`` fits in the camera's frame
(:mod:`.instrument_fit`). It follows the terrace fit of Gwyddion (Level > Fit Terraces): find
the steps in the data, keep the flat terraces between them a stated margin away from every step
("step broadening"), and fit all terraces at once with a common polynomial background and one
height per level. The edges, their blur and the instrument's transfer play no part: only the
flat interiors do.

The rules, each stated in the report:

- A pixel is on a step where the design changes level, where it is invalid or on the field's
  border, or where the
  data's own height differs from a 4-neighbour's by more than :data:`STEP_FRACTION` of a level
  step or :data:`STEP_NOISE` standard deviations of the difference between flat neighbours
  (the median of those of one design level, robust to the few that straddle a moved edge).
- A terrace pixel lies at least ``margin_px`` from every step pixel, except on a feature too
  narrow to keep anything at that margin (a line): there ISO 5436-1's central third of the
  line is kept (distance at least ``w / 3`` from its edges, ``w`` its width, never less than
  one design pixel; a thinner piece is a feature cut by the field's border), and never a
  step pixel itself.
- Terraces are the connected flat regions of one design level (the registration names a
  terrace's level; the data shape it). The fit: ``z = sum_k h_k [level = k] + P(x, y)``,
  ``P`` a polynomial of ``degree`` without constant term, least squares over all terrace
  pixels. A terrace more than half a step from the median of its level's terraces (a pit, a particle, a
  misregistered feature) belongs to no level: it is left out and the fit made again.
- A level's standard uncertainty is the standard error of its terraces' mean heights about
  the fitted one (area-weighted; the scatter between terraces holds the correlated noise and
  the level's own non-uniformity that the pixel scatter misses), never smaller than the
  pixel scatter's standard error, with a systematic term in quadrature: the terrace height's
  reproducibility floor :data:`~metrology.matching.depths.LEVEL_REPEATABILITY_M` (the level-mean
  depth fit's). A step's is the two levels' in quadrature.

The camera-frame fit's level heights are ``-sum_j B_kj D_j`` of its etch depths ``D_j``
(:func:`metrology.matching.depths.binary_code_matrix`); :func:`check_against` sets the two
side by side, step by step and mask by mask, and warns on each that differ by more than
twice their combined standard uncertainty (k = 2).

Arrays are row-major, row 0 at the top (camera order).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np
from scipy import ndimage

from doedesign.errors import DoeError
from metrology.matching.depths import (LEVEL_REPEATABILITY_M, DepthFit, binary_code_matrix, depths_from_levels,
                                       feature_distances)

__all__ = ["COVERAGE_FACTOR", "STEP_FRACTION", "STEP_NOISE", "TerraceFit", "check_against",
           "fit_terraces", "flat_interiors"]

log = logging.getLogger(__name__)

#: A pixel differing from a 4-neighbour by more than this fraction of one level step is on a step,
STEP_FRACTION = 0.1
#: ... or by more than this many standard deviations of a flat pair's difference (noise, roughness).
STEP_NOISE = 5.0
# Coverage factor of the agreement test between the terrace and the camera-frame fits.
COVERAGE_FACTOR = 2.0
# Fewest pixels of a terrace that count as one.
MIN_TERRACE_PX = 4


def flat_interiors(height_m: np.ndarray, labels: np.ndarray, margin_px: float, step_m: float,
                   pitch_px: float) -> np.ndarray:
    """Pixels on flat terraces: ``margin_px`` from every design or measured step (the central
    third of a line too narrow for that margin).

    Parameters
    ----------
    height_m : ndarray (rows, cols)
        Levelled heights (NaN = invalid).
    labels : ndarray of int (rows, cols)
        Design level at each pixel (negative = outside the design).
    margin_px : float
        Distance from a step (pixels) a terrace pixel keeps.
    step_m : float
        One level step (sets the height difference that counts as a step).
    pitch_px : float
        The design's pitch in pixels: no feature is narrower, so a thinner piece is one cut by
        the field's border, not a line.

    Returns
    -------
    ndarray of bool
    """
    h = np.asarray(height_m, float)
    labels = np.asarray(labels)
    valid = np.isfinite(h) & (labels >= 0)
    if not valid.any():
        return valid
    # Invalid pixels and the field's border count as steps: a gap or the border hides what
    # lies beyond (a border pixel may straddle a step just outside the field).
    step = ~np.isfinite(h)
    step[[0, -1], :] = True
    step[:, [0, -1]] = True
    # Height differences between 4-neighbours of one design level: the noise, robustly (most
    # such pairs are flat), and where the data step (any pair steeper than the threshold).
    pairs = []
    for axis in (0, 1):
        d = np.abs(np.diff(h, axis=axis))
        same = np.diff(labels, axis=axis) == 0
        pairs.append((axis, d, same))
    flat_d = np.concatenate([d[same & np.isfinite(d)] for _, d, same in pairs])
    sigma_d = float(np.median(flat_d)) / 0.6745 if flat_d.size else 0.0
    threshold = max(STEP_FRACTION * abs(step_m), STEP_NOISE * sigma_d)
    for axis, d, _ in pairs:
        steep = d > threshold
        lo = [slice(None), slice(None)]
        hi = [slice(None), slice(None)]
        lo[axis], hi[axis] = slice(None, -1), slice(1, None)
        step[tuple(lo)] |= steep
        step[tuple(hi)] |= steep
    # Distances from the boundary line, as for the design's (a steep pixel reads 0.5).
    dist_step = ndimage.distance_transform_edt(~step) + 0.5 if step.any() else np.full(h.shape, np.inf)
    dist_design, dmax = feature_distances(labels)
    need = np.minimum(float(margin_px), np.maximum(2.0 / 3.0 * dmax, pitch_px / 3.0))
    # A step pixel itself (0.5 from the boundary line) is never on a terrace.
    need = np.maximum(need, 1.0)
    return valid & (dist_design >= need) & (dist_step >= need)


@dataclass
class TerraceFit:
    """Level heights from flat terraces.

    Attributes
    ----------
    heights_m, heights_err_m : ndarray (n_levels,)
        Each level's height in the levelled field's frame and its standard uncertainty (NaN
        where the level has no terrace).
    steps_m, steps_err_m : ndarray (n_levels - 1,)
        Step ``k`` is ``h_k - h_(k+1)`` (level ``k + 1`` is one step deeper: positive).
    depths : DepthFit
        Etch depth per mask from the heights (:func:`~metrology.matching.depths.depths_from_levels`).
    terraces, pixels : ndarray of int (n_levels,)
        Terraces and terrace pixels of each level.
    margin_px : float
    degree : int
        Degree of the common polynomial background.
    background_m_per_px : ndarray
        The background's coefficients (x, y, then higher powers; x along columns, y along rows
        downward, in pixels from the field's centre).
    rms_residual_m : float
        Rms of the terrace pixels about the fit.
    mask : ndarray of bool
        The terrace pixels.
    """

    heights_m: np.ndarray
    heights_err_m: np.ndarray
    steps_m: np.ndarray
    steps_err_m: np.ndarray
    depths: DepthFit | None
    terraces: np.ndarray
    pixels: np.ndarray
    margin_px: float
    degree: int
    background_m_per_px: np.ndarray
    rms_residual_m: float
    mask: np.ndarray = field(repr=False)


def _powers(degree):
    return [(i, j) for d in range(1, degree + 1) for i in range(d, -1, -1) for j in [d - i]]


def _solve(h, mask, labels, terrace, n_levels, degree):
    """Least squares of one height per level and a common polynomial on the masked pixels."""
    rows, cols = np.nonzero(mask)
    z = h[mask]
    lev = labels[mask].astype(np.int64)
    tid = terrace[mask]
    # Background columns in pixels from the field's centre (well conditioned).
    y = rows - (h.shape[0] - 1) / 2.0
    x = cols - (h.shape[1] - 1) / 2.0
    poly = np.stack([x ** i * y ** j for i, j in _powers(degree)]) if degree > 0 else np.zeros((0, z.size))
    present = np.bincount(lev, minlength=n_levels) > 0
    idx = np.cumsum(present) - 1
    n_off, n_poly = int(present.sum()), poly.shape[0]
    # Normal equations, assembled without an (pixels x unknowns) design matrix.
    ata = np.zeros((n_off + n_poly, n_off + n_poly))
    atb = np.zeros(n_off + n_poly)
    col = idx[lev]
    ata[:n_off, :n_off] = np.diag(np.bincount(col, minlength=n_off).astype(float))
    atb[:n_off] = np.bincount(col, weights=z, minlength=n_off)
    for p in range(n_poly):
        ata[:n_off, n_off + p] = ata[n_off + p, :n_off] = np.bincount(col, weights=poly[p], minlength=n_off)
        atb[n_off + p] = poly[p] @ z
        for q in range(p, n_poly):
            ata[n_off + p, n_off + q] = ata[n_off + q, n_off + p] = poly[p] @ poly[q]
    coef = np.linalg.lstsq(ata, atb, rcond=None)[0]
    offsets = coef[:n_off]
    resid = z - offsets[col] - (coef[n_off:] @ poly if n_poly else 0.0)
    return present, idx, coef, n_off, resid, lev, tid


def fit_terraces(height_m: np.ndarray, labels: np.ndarray, n_levels: int, margin_px: float, step_m: float,
                 pitch_px: float, degree: int = 1) -> TerraceFit:
    """Fit every level's height on its flat terraces with a common polynomial background.

    Parameters
    ----------
    height_m, labels : ndarray (rows, cols)
        Levelled heights and design levels, as for :func:`flat_interiors`.
    n_levels : int
    margin_px : float
        Distance from a step a terrace pixel keeps (see :func:`flat_interiors`).
    step_m : float
        One level step (nominal; sets what height difference counts as a step).
    pitch_px : float
        The design's pitch in pixels (see :func:`flat_interiors`).
    degree : int
        Degree of the background polynomial (0: none).

    Returns
    -------
    TerraceFit

    Raises
    ------
    DoeError
        No level has a terrace.
    """
    h = np.asarray(height_m, float)
    labels = np.asarray(labels)
    mask = flat_interiors(h, labels, margin_px, step_m, pitch_px)
    # Terraces: connected flat pixels of one level.
    terrace = np.zeros(h.shape, np.int64)
    n_terr = 0
    for k in range(n_levels):
        comp, n = ndimage.label(mask & (labels == k))
        terrace[comp > 0] = comp[comp > 0] + n_terr
        n_terr += n
    sizes = np.bincount(terrace.ravel(), minlength=n_terr + 1)
    keep = (sizes >= MIN_TERRACE_PX) & (np.arange(n_terr + 1) > 0)
    mask &= keep[terrace]
    if not mask.any():
        raise DoeError(f"no flat terrace {margin_px:.3g} px from every step: the field is all edges")
    present, idx, coef, n_off, resid, lev, tid = _solve(h, mask, labels, terrace, n_levels, degree)
    # A terrace more than half a step from its level's height belongs to no level of the design
    # (a pit, a particle, a misregistered feature): it is left out and the fit made again.
    # Judged against the median of its level's terraces, which one stray terrace cannot move.
    t_ids, t_inv = np.unique(tid, return_inverse=True)
    t_mean = np.bincount(t_inv, weights=resid) / np.bincount(t_inv)
    t_level = np.zeros(t_ids.size, np.int64)
    t_level[t_inv] = lev
    centre = np.zeros(n_levels)
    for k in np.unique(t_level):
        centre[k] = np.median(t_mean[t_level == k])
    stray = t_ids[np.abs(t_mean - centre[t_level]) > 0.5 * abs(step_m)]
    if stray.size:
        log.info("terrace fit: %d terraces off their level by over half a step left out", stray.size)
        mask &= ~np.isin(terrace, stray)
        if not mask.any():
            raise DoeError("no terrace lies within half a step of its design level")
        present, idx, coef, n_off, resid, lev, tid = _solve(h, mask, labels, terrace, n_levels, degree)
    offsets = coef[:n_off]
    rms = float(np.sqrt(np.mean(resid ** 2)))
    heights, errs = np.full(n_levels, np.nan), np.full(n_levels, np.nan)
    terraces, pixels = np.zeros(n_levels, int), np.zeros(n_levels, int)
    # Each terrace's mean residual: its height about its level's fitted one.
    t_ids, t_inv = np.unique(tid, return_inverse=True)
    t_n = np.bincount(t_inv).astype(float)
    t_mean = np.bincount(t_inv, weights=resid) / t_n
    t_sq = np.bincount(t_inv, weights=resid ** 2)
    t_level = np.zeros(t_ids.size, np.int64)
    t_level[t_inv] = lev
    for k in np.flatnonzero(present).tolist():
        sel = t_level == k
        w = t_n[sel]
        n_pix = w.sum()
        # Pixel scatter about the level's fit, and the area-weighted scatter of its terraces.
        pix_var = t_sq[sel].sum() / n_pix
        se_pixels = np.sqrt(pix_var / n_pix)
        m = sel.sum()
        se_terraces = (np.sqrt(m / (m - 1) * np.sum((w * t_mean[sel]) ** 2)) / n_pix) if m > 1 else 0.0
        heights[k] = offsets[idx[k]]
        errs[k] = np.hypot(max(se_pixels, se_terraces), LEVEL_REPEATABILITY_M)
        terraces[k], pixels[k] = m, int(n_pix)
    steps = heights[:-1] - heights[1:]
    steps_err = np.hypot(errs[:-1], errs[1:])
    try:
        depths = depths_from_levels(heights, errs)
    except DoeError as exc:
        log.info("terrace fit: no depth per mask (%s)", exc)
        depths = None
    return TerraceFit(heights_m=heights, heights_err_m=errs, steps_m=steps, steps_err_m=steps_err, depths=depths,
                      terraces=terraces, pixels=pixels, margin_px=float(margin_px), degree=int(degree),
                      background_m_per_px=coef[n_off:], rms_residual_m=rms, mask=mask)


def _verdict(name, a, ua, b, ub):
    diff = a - b
    limit = COVERAGE_FACTOR * float(np.hypot(ua, ub))
    if not (np.isfinite(diff) and np.isfinite(limit)):
        return {"name": name, "agree": None, "difference_nm": None, "limit_nm": None}, None
    ok = bool(abs(diff) <= limit)
    warning = None if ok else (f"{name}: terrace fit {a * 1e9:.2f} +- {ua * 1e9:.2f} nm, camera-frame fit "
                               f"{b * 1e9:.2f} +- {ub * 1e9:.2f} nm, differ by {diff * 1e9:.2f} nm "
                               f"(over k = {COVERAGE_FACTOR:g}: {limit * 1e9:.2f} nm)")
    return {"name": name, "agree": ok, "difference_nm": diff * 1e9, "limit_nm": limit * 1e9}, warning


def check_against(fit: TerraceFit, depths_m: np.ndarray, depths_err_m: np.ndarray) -> dict:
    """The terrace fit beside another fit's etch depths, step by step and mask by mask.

    Parameters
    ----------
    fit : TerraceFit
    depths_m, depths_err_m : ndarray (n_masks,)
        The other fit's etch depths and their standard uncertainties (taken as independent).

    Returns
    -------
    dict
        ``steps`` and ``masks`` (each: both values, uncertainties, difference, the k = 2 limit,
        ``agree``), ``warnings`` (one line per disagreement, naming the step or mask) and
        ``agree`` (True when every compared step and mask agrees).
    """
    nm = 1e9
    d, u = np.asarray(depths_m, float), np.asarray(depths_err_m, float)
    n_levels = fit.heights_m.size
    b = binary_code_matrix(n_levels)
    if b.shape[1] != d.size:
        raise DoeError(f"{d.size} etch depths for {n_levels} levels: the fits are of different elements")
    # Step k -> k+1 of the other fit: sum_j (B_(k+1)j - B_kj) D_j.
    db = b[1:] - b[:-1]
    other = db @ d
    other_err = np.sqrt(db ** 2 @ u ** 2)
    steps, warnings = [], []
    for k in range(n_levels - 1):
        v, w = _verdict(f"step level {k} -> {k + 1}", fit.steps_m[k], fit.steps_err_m[k], other[k], other_err[k])
        steps.append({**v, "terrace_nm": fit.steps_m[k] * nm, "terrace_err_nm": fit.steps_err_m[k] * nm,
                      "camera_frame_nm": other[k] * nm, "camera_frame_err_nm": other_err[k] * nm})
        if w:
            warnings.append(w)
    masks = []
    if fit.depths is not None:
        for j in range(d.size):
            v, w = _verdict(f"mask {j} etch depth", fit.depths.depths_m[j], fit.depths.depths_err_m[j], d[j], u[j])
            masks.append({**v, "terrace_nm": fit.depths.depths_m[j] * nm,
                          "terrace_err_nm": fit.depths.depths_err_m[j] * nm,
                          "camera_frame_nm": d[j] * nm, "camera_frame_err_nm": u[j] * nm})
            if w:
                warnings.append(w)
    compared = [s["agree"] for s in steps + masks if s["agree"] is not None]
    return {"steps": steps, "masks": masks, "warnings": warnings,
            "agree": bool(compared) and all(compared)}
