"""Spectral weights for polychromatic PSFs: colour-channel responses, LEDs and bandpasses.

Each function returns non-negative weights on a given wavelength grid (metres); use them
with :meth:`doedesign.engine.result.PSFResult.polychromatic`. The colour responses are smooth
Gaussian approximations of a typical CMOS Bayer sensor (not a measured camera curve);
pass measured curves with :func:`tabulated` when you have them.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

from .errors import DoeError

__all__ = ["RGB_BANDS_M", "bandpass", "gaussian_band", "rgb_response", "tabulated"]

# Centre and full width at half maximum (m) of the approximate R, G, B responses.
RGB_BANDS_M = {"R": (600e-9, 80e-9), "G": (535e-9, 90e-9), "B": (460e-9, 70e-9)}


def _grid(wavelengths_m):
    wl = np.atleast_1d(np.asarray(wavelengths_m, dtype=float))
    if wl.size == 0 or np.any(wl <= 0) or not np.all(np.isfinite(wl)):
        raise DoeError("wavelength grid must hold positive finite values")
    return wl


def gaussian_band(wavelengths_m: ArrayLike, centre_m: float, fwhm_m: float) -> np.ndarray:
    """Gaussian spectrum (an LED or a narrowband filter) sampled on ``wavelengths_m``."""
    wl = _grid(wavelengths_m)
    if fwhm_m <= 0:
        raise DoeError(f"band FWHM must be positive, got {fwhm_m}")
    sigma = fwhm_m / (2 * np.sqrt(2 * np.log(2)))
    return np.exp(-0.5 * ((wl - centre_m) / sigma) ** 2)


def bandpass(wavelengths_m: ArrayLike, low_m: float, high_m: float) -> np.ndarray:
    """Flat-top band between ``low_m`` and ``high_m`` (inclusive)."""
    wl = _grid(wavelengths_m)
    if high_m <= low_m:
        raise DoeError(f"bandpass needs low < high, got {low_m}, {high_m}")
    return ((wl >= low_m) & (wl <= high_m)).astype(float)


def rgb_response(wavelengths_m: ArrayLike) -> np.ndarray:
    """Approximate R, G, B channel responses, shape (3, wavelengths)."""
    return np.stack([gaussian_band(wavelengths_m, *RGB_BANDS_M[c]) for c in "RGB"])


def tabulated(wavelengths_m: ArrayLike, table_wavelengths_m: ArrayLike, values: ArrayLike) -> np.ndarray:
    """A measured curve interpolated onto ``wavelengths_m`` (zero outside the table)."""
    wl = _grid(wavelengths_m)
    tw = np.asarray(table_wavelengths_m, dtype=float)
    tv = np.asarray(values, dtype=float)
    if tw.shape != tv.shape or tw.ndim != 1 or np.any(np.diff(tw) <= 0) or np.any(tv < 0):
        raise DoeError("tabulated spectrum needs increasing wavelengths and one non-negative value each")
    return np.interp(wl, tw, tv, left=0.0, right=0.0)
