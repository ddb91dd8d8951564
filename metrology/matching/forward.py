"""The process model on the measurement's pixels, and registration helpers for it.

Coordinates: measurement arrays are row-major, row 0 at the top (camera order); design
pixel (i, j) is centred at design coordinates (i, j). Overlay is x toward increasing
design column, y up, as in :mod:`masks.process`.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

import numpy as np
from scipy import ndimage

from masks.process import ProcessParams, simulate_surface
from metrology.matching.register import design_on_measurement

if TYPE_CHECKING:
    from metrology.matching.register import Registration

__all__ = ["crop_registration", "design_height_on_measurement", "error_map", "fitted_process",
           "process_on_measurement", "shift_registration"]


def process_on_measurement(levels: np.ndarray, pitch_m: float, params: ProcessParams, registration: Registration,
                           blur_m: float = 0.0, step_m: float = 0.25e-6, rows: slice | None = None,
                           block_px: int = 48, pixel_subsamples: int = 1, fill_factor: float = 1.0,
                           na: float = 0.0, wavelength_m: float = 0.57e-6) -> np.ndarray:
    """The process model's surface as the profilometer would report it.

    :func:`masks.process.simulate_surface` on the design region under the field (in blocks
    of design rows, so a large field never needs one huge fine grid), blurred by a
    Gaussian of ``blur_m`` (the objective) and, with ``na``, the objective's incoherent
    circular-pupil transfer (:func:`metrology.matching.transfer.na_mtf`, by FFT on the fine
    block), then averaged over each measurement pixel's footprint through ``registration`` at
    ``pixel_subsamples`` x ``pixel_subsamples`` points over a centred square of side
    ``sqrt(fill_factor)`` pixels (bilinear on the fine grid; 1 point = sampled at the pixel
    centre). Outside the design the wafer is unetched (0).

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
    pixel_subsamples : int
        Points per axis averaged over each camera pixel (a camera pixel integrates).
    fill_factor : float
        Area fraction of each pixel integrated (a centred square of side ``sqrt(fill_factor)``).
    na, wavelength_m : float
        The objective's numerical aperture (0 = no optical cut-off) and mean wavelength.

    Returns
    -------
    ndarray, shape (n_rows, measurement cols)
    """
    shape = registration.measurement_shape
    row_idx = np.arange(shape[0])[rows if rows is not None else slice(None)].astype(float)
    col_idx = np.arange(shape[1]).astype(float)
    rr, cc = registration.to_design(row_idx[:, None], col_idx[None, :])
    out = np.zeros(rr.shape)
    nr, nc = levels.shape
    on = (rr > -0.5) & (rr < nr - 0.5) & (cc > -0.5) & (cc < nc - 0.5)
    if not on.any():
        return out
    n_sub = max(int(pixel_subsamples), 1)
    side = float(np.sqrt(min(max(fill_factor, 0.0), 1.0)))
    sub = ((np.arange(n_sub) + 0.5) / n_sub - 0.5) * side
    # Design-pixel reach of a footprint corner from its centre.
    reach = 0.5 * side * float(np.abs(np.asarray(registration.matrix)).sum(axis=1).max()) if n_sub > 1 else 0.0
    # The objective's point spread (an Airy pattern) reaches a few rings: 4 lambda / NA keeps all
    # but a fraction of a percent of it.
    optical_px = 4 * wavelength_m / na / pitch_m if na > 0 else 0.0
    r_lo, r_hi = int(np.floor(rr[on].min() + 0.5)), int(np.floor(rr[on].max() + 0.5)) + 1
    c_lo = max(int(np.floor(cc[on].min() + 0.5 - reach - optical_px)) - 1, 0)
    c_hi = min(int(np.floor(cc[on].max() + 0.5 + reach + optical_px)) + 2, nc)
    margin = 1 + int(np.ceil(4 * blur_m / pitch_m + reach + optical_px))
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
        if na > 0:
            fine = _objective(fine, surf.step_m, na, wavelength_m, int(np.ceil(optical_px * u)))
        r_sel, c_sel = np.nonzero(sel)
        total = np.zeros(r_sel.size)
        for a in sub:
            for b in sub:
                pr, pc = registration.to_design(row_idx[r_sel] + a, col_idx[c_sel] + b)
                fr = (pr - s0 + 0.5) * u - 0.5
                fc = (pc - c_lo + 0.5) * u - 0.5
                total += ndimage.map_coordinates(fine, [fr, fc], order=1, mode="nearest")
        out[sel] = total / n_sub ** 2
    return out


def _objective(fine, step_m, na, wavelength_m, pad):
    """``fine`` seen through the objective's incoherent circular-pupil transfer (edge-padded by
    ``pad`` fine cells so that nothing wraps into the block)."""
    from metrology.matching.transfer import na_mtf

    grid = np.pad(fine, pad, mode="edge")
    nu = np.hypot(np.fft.fftfreq(grid.shape[0], step_m)[:, None], np.fft.rfftfreq(grid.shape[1], step_m)[None, :])
    seen = np.fft.irfft2(np.fft.rfft2(grid) * na_mtf(nu, na, wavelength_m), s=grid.shape)
    return seen[pad:pad + fine.shape[0], pad:pad + fine.shape[1]]


def fitted_process(edge_fit: Any, depths_m: Sequence[float] | None = None, n_masks: int = 4) -> ProcessParams:
    """:class:`~masks.process_params.ProcessParams` holding the fitted depths, overlay and bias (no blur: the
    fitted edge blur is the instrument's and is applied on the measurement side)."""
    overlay = np.zeros((n_masks, 3))
    overlay[:, :2] = edge_fit.overlay_m
    depths = edge_fit.depths_m if depths_m is None else np.asarray(depths_m, float)
    return ProcessParams(etch_depth=np.array(depths, float), mask_overlay=overlay,
                         linewidth_bias=np.array(edge_fit.bias_m, float))


def shift_registration(registration: Registration, shift_m: Sequence[float], pitch_m: float) -> Registration:
    """Registration moved so that the design frame follows mask 0 (``shift_m`` = its (dx, dy)).

    The edge fit reports overlay relative to mask 0; the process model puts mask 0 where
    the design is, so the model is sampled through a registration shifted by mask 0's shift.
    """
    from dataclasses import replace

    d_rc = np.array([-shift_m[1], shift_m[0]]) / pitch_m
    return replace(registration, offset=registration.offset - d_rc)


def error_map(height_m: np.ndarray, reference_m: np.ndarray | float) -> tuple[np.ndarray, float]:
    """``height - reference`` with NaN where either is invalid, and its rms (m)."""
    err = np.asarray(height_m, float) - np.asarray(reference_m, float)
    ok = np.isfinite(err)
    rms = float(np.sqrt(np.mean(err[ok] ** 2))) if ok.any() else float("nan")
    return err, rms


def design_height_on_measurement(design_height_m: np.ndarray, registration: Registration) -> np.ndarray:
    """Design heights at each measurement pixel (nearest design pixel; NaN off the design)."""
    return design_on_measurement(np.asarray(design_height_m, float), registration, fill=np.nan)


def crop_registration(registration: Registration, row0: int, col0: int, shape: tuple[int, int]) -> Registration:
    """The registration of the sub-array ``[row0:row0 + shape[0], col0:col0 + shape[1]]``."""
    from dataclasses import replace

    offset = registration.offset + registration.matrix @ np.array([row0, col0], float)
    return replace(registration, offset=offset, measurement_shape=(int(shape[0]), int(shape[1])))
