"""Etch depths, overlay and linewidth bias fitted in the camera's frame (``doe compare``).

The same measurement model as ``doe diagnose --frame camera``
(:class:`metrology.matching.instrument.InstrumentModel`): the model surface is rendered into
the profilometer's own pixels (objective blur and pixel-area integration in one kernel, the
placement of the camera field on the design, levelling projected out) and compared there; the
measured heights are never resampled or smoothed.

The surface is ``-sum_j D_j S_j`` with ``S_j`` mask j's printed opening (the process model's
coverage, :func:`masks.process.simulate_surface`) as the camera reports it. It is linear in
the depths ``D_j``; a mask's overlay moves its own map's sampling points (translation commutes
with the blur and the pixel integral); the linewidth bias and the blur enter through
derivative maps ``dS_j/db_j`` and ``dS_j/dsigma``, rebuilt about the current values on each
outer pass (two or three passes converge: the maps are exact at the point of expansion). The
placement (shift, rotation, per-axis scale) is fitted with them as a nuisance and reported
with its uncertainties. Pixels whose residual is a robust outlier (spikes) are excluded after
the first pass.

Conventions as in :mod:`metrology.matching.compare`: overlay (dx, dy) with x toward
increasing design column and y up; bias positive = openings wider.
"""

from __future__ import annotations

import threading
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from scipy import optimize

from doedesign.errors import DoeError
from metrology.matching.instrument import PLACEMENT_PARAMS, InstrumentModel, Placement
from metrology.matching.level import Leveller, robust_valid
from metrology.matching.transfer import LateralTransfer
from metrology.matching.window import busiest_camera_window

__all__ = ["InstrumentFit", "fit_in_camera_frame"]

# Steps of the derivative maps: linewidth bias (m) and blur sigma (m).
BIAS_STEP_M = 0.02e-6
SIGMA_STEP_M = 0.02e-6
# Solver units: heights in 100 nm, bias and blur in um, shifts in design pixels.
_H, _UM = 1e-7, 1e-6


@dataclass
class InstrumentFit:
    """Result of :func:`fit_in_camera_frame` (SI units).

    Attributes
    ----------
    depths_m, depths_err_m : ndarray (n_masks,)
    overlay_m, overlay_err_m : ndarray (n_masks, 2)
        (dx, dy) of each mask relative to mask 0 (row 0 is zero).
    bias_m, bias_err_m : ndarray (n_masks,)
    blur_sigma_m, blur_sigma_err_m : float
        Objective blur (Gaussian sigma) besides the pixel integral.
    transfer : LateralTransfer
        The whole lateral transfer the fit rendered through (its fill factor held, the blur the
        fitted one; or a calibrated or chosen one, held).
    batwing : (float, float) or None
        The batwing (amplitude, sigma_m) held beside the transfer, if any.
    placement : Placement
        Refined camera pixel -> design pixel map of the whole field (mask 0 on the design).
    placement_report : dict
        Refinement, uncertainties (camera pixels, degrees) and the final matrix and offset.
    residual_m : ndarray
        Measured minus model after levelling on the window (NaN where excluded).
    window_camera_px : list of int
        ``[row0, row1, col0, col1]`` of the fitted window (half-open).
    rms_residual_m : float
    n_pixels, excluded_pixels : int
    """

    depths_m: np.ndarray
    depths_err_m: np.ndarray
    overlay_m: np.ndarray
    overlay_err_m: np.ndarray
    bias_m: np.ndarray
    bias_err_m: np.ndarray
    blur_sigma_m: float
    blur_sigma_err_m: float
    placement: Placement
    placement_report: dict
    residual_m: np.ndarray
    window_camera_px: list
    rms_residual_m: float
    n_pixels: int
    excluded_pixels: int
    transfer: LateralTransfer = field(default_factory=LateralTransfer)
    batwing: tuple[float, float] | None = None

    @property
    def rss_m2(self) -> float:
        """Sum of squared residuals over the pixels fitted (m^2)."""
        return float(np.nansum(self.residual_m ** 2))


class _MaskMaps:
    """Each mask's camera map and its derivatives in bias and blur, about ``(bias, sigma)``;
    the pixel fill factor ``fill`` held. With a ``transfer`` held (and a ``batwing`` beside it)
    the blur's column is zero."""

    def __init__(self, model, levels, pitch_m, bias_m, sigma_m, fill=1.0, transfer=None, batwing=None):
        self.bias_m = np.asarray(bias_m, float).copy()
        self.sigma_m = float(sigma_m) if transfer is None else transfer.sigma_m
        cov = self._coverage(model, levels, pitch_m, self.bias_m)
        d_bias = (self._coverage(model, levels, pitch_m, self.bias_m + BIAS_STEP_M)
                  - self._coverage(model, levels, pitch_m, self.bias_m - BIAS_STEP_M)) / (2 * BIAS_STEP_M / _UM)
        if transfer is not None:
            self.transfer = transfer
            self.maps = [(_mapped(model, c, transfer, batwing), _mapped(model, db, transfer, batwing),
                          np.zeros(c.shape)) for c, db in zip(cov, d_bias)]
        else:
            self.transfer = LateralTransfer(sigma_m=self.sigma_m, fill_factor=fill)

            def at(sigma):
                return LateralTransfer(sigma_m=sigma, fill_factor=fill)

            hs = min(SIGMA_STEP_M, 0.5 * self.sigma_m)
            self.maps = [(model.camera_map(c, self.transfer), model.camera_map(db, self.transfer),
                          (model.camera_map(c, at(self.sigma_m + hs)) - model.camera_map(c, at(self.sigma_m - hs)))
                          / (2 * hs / _UM)) for c, db in zip(cov, d_bias)]
        self._samples = {}
        self._lock = threading.Lock()

    def sampled(self, model, j, placement):
        """Mask ``j``'s three maps sampled under ``placement``; kept for the next calls, since a
        Jacobian column of a depth, bias, blur or another mask's shift leaves them unchanged."""
        key = (j, placement.matrix.tobytes(), placement.offset.tobytes())
        with self._lock:
            out = self._samples.pop(key, None)
        if out is None:  # sampled outside the lock: a Jacobian's columns run in threads
            out = tuple(model.sample(m, placement) for m in self.maps[j])
        with self._lock:
            self._samples[key] = out
            while len(self._samples) > 8 * len(self.maps):
                self._samples.pop(next(iter(self._samples)))
        return out

    @staticmethod
    def _coverage(model, levels, pitch_m, bias_m):
        """Printed openings (n_masks, fine rows, fine cols) on the model's window, 0 off the design."""
        from masks.process import ProcessParams, simulate_surface

        params = ProcessParams.ideal(len(bias_m)).copy(linewidth_bias=np.asarray(bias_m, float))
        s = simulate_surface(levels, pitch_m, params, step_m=model.step_m, region=model.region)
        printed = s.masks_printed
        if model.moments:
            from masks.moments import moment_corrected

            printed = np.stack([moment_corrected(p) for p in printed])
        u = model.upsample
        r0, r1, c0, c1 = model.window
        out = np.zeros((len(bias_m), (r1 - r0) * u, (c1 - c0) * u))
        a, b = (model.region[0] - r0) * u, (model.region[2] - c0) * u
        out[:, a:a + printed.shape[1], b:b + printed.shape[2]] = printed
        return out


def _mapped(model, fine, transfer, batwing):
    """Camera map of ``fine`` through ``transfer``, with a ``batwing`` (amplitude, sigma_m)
    beside its objective (mapped without the objective's transfer and added, as the diagnosis's
    camera model does: :meth:`metrology.diagnosis.camera.CameraHeightProblem.render`)."""
    coeffs = model.camera_map(fine, transfer)
    if batwing is None:
        return coeffs
    from dataclasses import replace

    from metrology.diagnosis.effects import get_effect

    edge = get_effect("batwing").apply(fine, np.asarray(batwing, float), model.step_m) - fine
    return coeffs + model.camera_map(edge, replace(transfer, na=0.0))


def fit_in_camera_frame(height_m: np.ndarray, levels: np.ndarray, placement: Placement, pitch_m: float,
                        depths0_m: Sequence[float], overlay0_m: np.ndarray | None = None,
                        bias0_m: Sequence[float] | None = None, blur0_m: float = 0.4e-6, window_px: int = 128,
                        passes: int = 2, transfer: LateralTransfer | None = None, fill: float = 1.0,
                        batwing: Sequence[float] | None = None) -> InstrumentFit:
    """Fit depths, overlay, bias, blur and placement to a camera height map in its own frame.

    Parameters
    ----------
    height_m : ndarray
        Camera heights (m, z up), NaN = invalid, row 0 at the top of the camera image; as
        read (any tilt is projected out).
    levels : ndarray of int
        Design levels (16 for four masks).
    placement : Placement
        Starting placement, camera pixel -> design pixel, with mask 0 on the design.
    pitch_m : float
    depths0_m : sequence of float
        Starting etch depths, one per mask.
    overlay0_m : ndarray (n_masks, 2), optional
        Starting overlay relative to mask 0.
    bias0_m : sequence of float, optional
        Starting linewidth bias.
    blur0_m : float
        Starting objective blur.
    window_px : int
        Camera pixels per side of the window fitted (the one richest in every mask's edges).
    passes : int
        Outer passes (derivative maps rebuilt about the current bias and blur).
    transfer : LateralTransfer, optional
        A calibrated or chosen lateral transfer (``doe calibrate instrument``, or
        :func:`metrology.matching.instrument_family.fit_instrument_family`), held fixed; default:
        a Gaussian blur (fitted, bounded at 0) with the pixel fill factor ``fill``.
    fill : float
        Pixel fill factor held while the blur is fitted (1: whole pixels, 0: point samples).
    batwing : (float, float), optional
        A batwing (amplitude, sigma_m) held beside ``transfer``.

    Returns
    -------
    InstrumentFit
    """
    from metrology.diagnosis.parallel import parallel_map

    meas = np.asarray(height_m, float)
    levels = np.asarray(levels)
    n = len(depths0_m)
    r0, c0 = busiest_camera_window(levels, placement, meas.shape, window_px)
    size = min(window_px, *meas.shape)
    crop = meas[r0:r0 + size, c0:c0 + size]
    start = Placement(placement.matrix, placement.offset + placement.matrix @ np.array([r0, c0], float))
    model = InstrumentModel(levels, pitch_m, crop.shape, start)
    finite = np.isfinite(crop)
    if finite.sum() < 200:
        raise DoeError("instrument-frame fit: fewer than 200 valid camera pixels in the window")
    overlay0 = np.zeros((n, 2)) if overlay0_m is None else np.asarray(overlay0_m, float)
    if transfer is not None:
        blur0_m = transfer.sigma_m
    # Parameters: depths (100 nm), shifts of masks 1.. (design px, row/col), bias (um), blur (um), placement.
    x = np.concatenate([np.asarray(depths0_m, float) / _H,
                        np.column_stack([-overlay0[1:, 1], overlay0[1:, 0]]).ravel() / pitch_m,
                        (np.zeros(n) if bias0_m is None else np.asarray(bias0_m, float)) / _UM,
                        [blur0_m / _UM], np.zeros(len(PLACEMENT_PARAMS))])
    i_shift, i_bias, i_blur, i_place = n, 3 * n - 2, 4 * n - 2, 4 * n - 1
    keep = finite
    if passes < 1:
        raise DoeError(f"instrument-frame fit: passes must be at least 1, got {passes}")
    res = maps = leveller = None

    # The finite-difference Jacobian's columns in threads (the same evaluations in any order:
    # the same fit); its serial columns were a fifth of a CSI file's serial time.
    def columns(f, xs):
        return list(parallel_map(f, xs))

    for k in range(passes):
        maps = _MaskMaps(model, levels, pitch_m, x[i_bias:i_blur] * _UM, max(x[i_blur], 0.02) * _UM, fill, transfer,
                         None if batwing is None else tuple(float(v) for v in batwing))
        leveller = Leveller(crop.shape, keep)

        def render(p, maps=maps):
            place = start.refined(p[i_place:], crop.shape)
            shifts = np.vstack([[0.0, 0.0], p[i_shift:i_bias].reshape(n - 1, 2)])
            db = p[i_bias:i_blur] - maps.bias_m / _UM
            ds = p[i_blur] - maps.sigma_m / _UM
            total = np.zeros(crop.shape)
            for j in range(n):
                # Overlay alone (no rotation): the mask's map sampled where the moved mask shows.
                v0, v_b, v_s = maps.sampled(model, j, place.in_frame_of(shifts[j], 0.0, (0.0, 0.0)))
                total -= p[j] * (v0 + db[j] * v_b + ds * v_s)
            return total * _H

        def fun(p, render=render, leveller=leveller, keep=keep):
            return leveller(crop[keep] - render(p)[keep]) / _H

        res = optimize.least_squares(fun, x, method="lm", x_scale="jac", xtol=1e-10, ftol=1e-10, max_nfev=400,
                                     workers=columns)
        if transfer is None and res.x[i_blur] < 0:
            # A blur has no negative width: where the free fit crosses zero (a transfer the
            # family cannot hold, such as an objective's cut-off, drove it to -1.5 um on a
            # coherence-scanning file), the fit is bounded there.
            lo = np.full(x.size, -np.inf)
            lo[i_blur] = 0.0
            res = optimize.least_squares(fun, np.maximum(x, lo), method="trf", bounds=(lo, np.inf), x_scale="jac",
                                         xtol=1e-10, ftol=1e-10, max_nfev=400, workers=columns)
        x = res.x
        if k == 0:
            resid = np.full(crop.shape, np.nan)
            resid[keep] = res.fun * _H
            keep = robust_valid(resid, finite)
    assert res is not None and maps is not None  # passes >= 1
    resid_map = np.full(crop.shape, np.nan)
    resid_map[keep] = res.fun * _H
    dof = max(res.fun.size - x.size, 1)
    try:
        cov = np.linalg.pinv(res.jac.T @ res.jac) * np.sum(res.fun ** 2) / dof
        err = np.sqrt(np.clip(np.diag(cov), 0, None))
    except np.linalg.LinAlgError:
        err = np.full(x.size, np.nan)
    fitted = maps.transfer if transfer is not None else LateralTransfer(sigma_m=x[i_blur] * _UM, fill_factor=fill)
    out = _result(x, err, n, pitch_m, start, placement, crop.shape, (r0, c0), resid_map, keep, finite)
    out.transfer = fitted
    out.batwing = None if batwing is None or transfer is None else (float(batwing[0]), float(batwing[1]))
    return out


def _result(x, err, n, pitch_m, start, placement, shape, corner, resid_map, keep, finite):
    """Unpack solver units into an :class:`InstrumentFit`."""
    i_shift, i_bias, i_blur, i_place = n, 3 * n - 2, 4 * n - 2, 4 * n - 1

    def overlay(v):
        rc = np.vstack([[0.0, 0.0], v[i_shift:i_bias].reshape(n - 1, 2)]) * pitch_m
        return np.column_stack([rc[:, 1], -rc[:, 0]])

    window_place = start.refined(x[i_place:], shape)
    # The whole field's placement: the window's, moved back to camera pixel (0, 0).
    field = Placement(window_place.matrix, window_place.offset - window_place.matrix @ np.asarray(corner, float))
    pixel_m = pitch_m * float(np.sqrt(abs(np.linalg.det(placement.matrix))))
    e = err[i_place:]
    report = {"refinement": {name: float(v) for name, v in zip(PLACEMENT_PARAMS, x[i_place:])},
              "shift_uncertainty_camera_px": [float(v * pitch_m / pixel_m) for v in e[:2]],
              "rotation_uncertainty_deg": float(np.degrees(e[2])), "scale_uncertainty": [float(v) for v in e[3:5]],
              "matrix": field.matrix.tolist(), "offset": field.offset.tolist(),
              "convention": "camera pixel centre (row, col) -> design pixel [R, C] = matrix @ [row, col] + offset"}
    ok = np.isfinite(resid_map)
    return InstrumentFit(
        depths_m=x[:n] * _H, depths_err_m=err[:n] * _H, overlay_m=overlay(x), overlay_err_m=np.abs(overlay(err)),
        bias_m=x[i_bias:i_blur] * _UM, bias_err_m=err[i_bias:i_blur] * _UM, blur_sigma_m=float(x[i_blur] * _UM),
        blur_sigma_err_m=float(err[i_blur] * _UM), placement=field, placement_report=report, residual_m=resid_map,
        window_camera_px=[int(corner[0]), int(corner[0] + shape[0]), int(corner[1]), int(corner[1] + shape[1])],
        rms_residual_m=float(np.sqrt(np.mean(resid_map[ok] ** 2))), n_pixels=int(ok.sum()),
        excluded_pixels=int(finite.sum() - keep.sum()))
