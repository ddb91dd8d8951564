"""The process engineer's models fitted to tile maps by weighted least squares.

Positions are metres from the design centre, x toward increasing column, y up (toward row 0).
Overlay of a mask (relative to mask 0): ``dx = Tx + Mx x - Rx y``, ``dy = Ty + My y + Ry x``;
magnification ``(Mx + My) / 2``, rotation ``(Rx + Ry) / 2`` (counter-clockwise), orthogonality
``Rx - Ry``. Etch depth error (fraction) of a mask: ``c + gx x + gy y + k (r / R)^2`` with ``R`` the
half-width of the element: ``k`` is the centre-to-edge non-uniformity. A term is named when it
differs from zero by more than :data:`NAME_SIGMA` standard errors (errors scaled by the fit's
reduced chi-square when that exceeds one: model error between tiles counts).
"""

from __future__ import annotations

import numpy as np

__all__ = ["NAME_SIGMA", "fit_depth_model", "fit_overlay_model", "wls"]

#: Standard errors by which a model term must differ from zero to be named.
NAME_SIGMA = 5.0


def wls(a: np.ndarray, y: np.ndarray, sigma: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """Weighted least squares: coefficients, their standard errors, residuals, reduced chi-square."""
    w = 1.0 / np.asarray(sigma, float)
    coef, *_ = np.linalg.lstsq(a * w[:, None], y * w, rcond=None)
    resid = y - a @ coef
    dof = max(len(y) - a.shape[1], 1)
    chi2 = float(np.sum((resid * w) ** 2) / dof)
    cov = np.linalg.pinv((a * w[:, None]).T @ (a * w[:, None])) * max(chi2, 1.0)
    return coef, np.sqrt(np.diag(cov)), resid, chi2


def _terms(values, errors, names):
    return {n: {"value": float(v), "error": float(e), "named": bool(abs(v) > NAME_SIGMA * e)}
            for n, v, e in zip(names, values, errors)}


def fit_overlay_model(x_m: np.ndarray, y_m: np.ndarray, dx_m: np.ndarray, dy_m: np.ndarray,
                      sdx_m: np.ndarray, sdy_m: np.ndarray) -> dict:
    """Translation, magnification, rotation and orthogonality of one mask's overlay field.

    Returns
    -------
    dict
        ``terms`` (name -> value, error, named: ``translation_x_m``, ``translation_y_m``,
        ``magnification_ppm``, ``rotation_urad``, ``orthogonality_urad``, ``scale_asymmetry_ppm``),
        ``residual_dx_m``, ``residual_dy_m`` per tile, ``reduced_chi2``.
    """
    x, y = np.asarray(x_m, float), np.asarray(y_m, float)
    n = x.size
    one, zero = np.ones(n), np.zeros(n)
    # Columns: Tx, Ty, Mx, My, Rx, Ry.
    a = np.block([[np.stack([one, zero, x, zero, -y, zero], 1)], [np.stack([zero, one, zero, y, zero, x], 1)]])
    coef, err, resid, chi2 = wls(a, np.concatenate([dx_m, dy_m]), np.concatenate([sdx_m, sdy_m]))
    cov_pairs = lambda i, j: 0.5 * np.hypot(err[i], err[j])  # noqa: E731  the two halves' errors combined
    values = [coef[0], coef[1], 0.5 * (coef[2] + coef[3]) * 1e6, 0.5 * (coef[4] + coef[5]) * 1e6,
              (coef[4] - coef[5]) * 1e6, (coef[2] - coef[3]) * 1e6]
    errors = [err[0], err[1], cov_pairs(2, 3) * 1e6, cov_pairs(4, 5) * 1e6, 2 * cov_pairs(4, 5) * 1e6,
              2 * cov_pairs(2, 3) * 1e6]
    names = ["translation_x_m", "translation_y_m", "magnification_ppm", "rotation_urad", "orthogonality_urad",
             "scale_asymmetry_ppm"]
    return {"terms": _terms(values, errors, names), "residual_dx_m": resid[:n].tolist(),
            "residual_dy_m": resid[n:].tolist(), "reduced_chi2": chi2}


def fit_depth_model(x_m: np.ndarray, y_m: np.ndarray, error: np.ndarray, sigma: np.ndarray,
                    half_width_m: float) -> dict:
    """Plane plus radial term of an etch-depth error map (fractions of the nominal depth).

    Returns
    -------
    dict
        ``terms`` (``offset``, ``gradient_x_per_mm``, ``gradient_y_per_mm``, ``radial_centre_to_edge``),
        ``residual`` per tile, ``reduced_chi2``.
    """
    x, y = np.asarray(x_m, float), np.asarray(y_m, float)
    rho2 = (x ** 2 + y ** 2) / half_width_m ** 2
    a = np.stack([np.ones_like(x), x * 1e3, y * 1e3, rho2], 1)
    coef, err, resid, chi2 = wls(a, np.asarray(error, float), sigma)
    names = ["offset", "gradient_x_per_mm", "gradient_y_per_mm", "radial_centre_to_edge"]
    out = {"terms": _terms(coef, err, names), "residual": resid.tolist(), "reduced_chi2": chi2}
    # The offset is the depth error at the centre, named as any other term; it is not a spatial term.
    return out
