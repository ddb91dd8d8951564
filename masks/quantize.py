"""Quantization of a continuous height map onto the N etch levels of a multi-level DOE.

Sign convention (see CONTRIBUTING): z up, 0 at the unetched top surface, negative where
etched; level k is k steps deep, so its height is ``-k * step_m``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from doedesign.errors import DoeError
from doedesign.materials import get_material


def level_step_m(material, design_wavelength_m, n_levels=16):
    """Depth of one level: the 2 pi height at the design wavelength divided by ``n_levels``.

    Parameters
    ----------
    material : str or doedesign.materials.Material
        Registry name or material object.
    design_wavelength_m : float
        Wavelength (m) at which ``n_levels`` steps make exactly one 2 pi phase delay.
    n_levels : int
        Number of levels (16 for four binary masks).

    Returns
    -------
    float
        Step depth in metres (74.74 nm for fused silica at 550 nm and 16 levels).
    """
    n_levels = int(n_levels)
    if n_levels < 2:
        raise DoeError(f"n_levels must be at least 2, got {n_levels}")
    return float(get_material(material).height_2pi_m(design_wavelength_m)) / n_levels


@dataclass
class QuantizeResult:
    """Outcome of :func:`quantize`.

    Attributes
    ----------
    levels : ndarray of int16
        Level per pixel, 0 .. n_levels-1 (0 = top surface).
    height_m : ndarray of float64
        Quantized height, ``-levels * step_m`` (zero or negative).
    error_m : ndarray of float64
        Original height minus quantized height, after wrapping the original by whole
        2 pi heights (``n_levels * step_m``); within +-step/2.
    rms_error_m, max_error_m : float
        RMS and largest absolute value of ``error_m``.
    wrapped_pixels : int
        Pixels whose height lay above the top surface or below the deepest level by more
        than half a step and were moved by a whole 2 pi height (optically equivalent at
        the design wavelength only).
    step_m : float
        The level step used.
    n_levels : int
        Number of levels.
    """

    levels: np.ndarray
    height_m: np.ndarray
    error_m: np.ndarray
    rms_error_m: float
    max_error_m: float
    wrapped_pixels: int
    step_m: float
    n_levels: int

    def summary(self):
        """JSON-ready figures (nm) for reports."""
        return {"step_nm": self.step_m * 1e9, "n_levels": self.n_levels,
                "rms_error_nm": self.rms_error_m * 1e9, "max_error_nm": self.max_error_m * 1e9,
                "wrapped_pixels": self.wrapped_pixels}


def quantize(height_m, step_m, n_levels=16):
    """Round a height map to the nearest etch level, wrapping by 2 pi heights where needed.

    Level ``k = round(-h / step_m)`` (round half up in depth, never floor, so the error is
    within +-step/2). Depths that round outside ``0 .. n_levels-1`` are brought back by whole
    multiples of ``n_levels`` levels, which is one 2 pi height each: the same phase at the
    design wavelength.

    Parameters
    ----------
    height_m : array_like
        Heights in metres, design sign convention (0 top, negative etched).
    step_m : float
        Level step depth (see :func:`level_step_m`).
    n_levels : int
        Number of levels.

    Returns
    -------
    QuantizeResult

    Raises
    ------
    DoeError
        NaN or infinite heights, non-positive step or fewer than two levels.
    """
    h = np.asarray(height_m, dtype=np.float64)
    step_m = float(step_m)
    n_levels = int(n_levels)
    if not (np.isfinite(step_m) and step_m > 0):
        raise DoeError(f"quantize: level step must be a positive length in metres, got {step_m}")
    if not 2 <= n_levels <= np.iinfo(np.int16).max:
        raise DoeError(f"quantize: n_levels must be between 2 and 32767, got {n_levels}")
    bad = ~np.isfinite(h)
    if bad.any():
        raise DoeError(f"quantize: height map holds {int(bad.sum())} NaN or infinite values")
    depth_steps = -h / step_m
    # Round first, then wrap the integer: identical to wrapping the height by whole 2 pi
    # heights before rounding (n_levels is an integer), without float-modulo edge cases.
    k_raw = np.floor(depth_steps + 0.5)
    levels = np.mod(k_raw, n_levels).astype(np.int16)
    wrapped = int(np.count_nonzero((k_raw < 0) | (k_raw >= n_levels)))
    error_m = (k_raw - depth_steps) * step_m
    quantized = -levels.astype(np.float64) * step_m
    return QuantizeResult(
        levels=levels, height_m=quantized, error_m=error_m,
        rms_error_m=float(np.sqrt(np.mean(error_m ** 2))) if error_m.size else 0.0,
        max_error_m=float(np.max(np.abs(error_m))) if error_m.size else 0.0,
        wrapped_pixels=wrapped, step_m=step_m, n_levels=n_levels)
