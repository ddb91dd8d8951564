"""The instrument's lateral transfer: what a camera pixel reports of the surface around it.

A family wide enough for the profilometers in use, every member fitted, none assumed:

* **Pixel footprint** with a fill factor ``f`` in [0, 1] (an *area* fraction): each camera pixel
  reports the mean height over a centred square of side ``sqrt(f)`` camera pixels (mapped into
  the design frame by the placement: a parallelogram under rotation, scale and mirror).
  ``f = 1`` is full pixel-area integration, ``f = 0`` point sampling at the pixel centre. The
  box's transfer departs from 1 as its area at low frequency (``1 - pi^2 f a^2 nu^2 / 6`` for
  a pixel of side ``a``), so a fit is smooth in ``f`` down to point sampling.
* **Gaussian blur** of standard deviation ``sigma >= 0`` (defocus, aberrations, the camera's
  own cross-talk); ``sigma = 0`` adds nothing.
* **NA-limited objective**: the incoherent optical transfer of a circular pupil,
  ``MTF(s) = 2/pi (acos s - s sqrt(1 - s^2))`` with ``s = nu / nu_c`` and cut-off
  ``nu_c = 2 NA / lambda`` (Goodman, *Introduction to Fourier Optics*, 6.3), NA in
  [0.05, 0.95]; ``na = 0`` leaves it out (an objective whose cut-off lies beyond what the
  pixels resolve). ``lambda`` is the instrument's mean wavelength (white light: 0.57 um unless a
  calibration says otherwise); only ``NA / lambda`` is measurable.
* The batwing (a surface effect, :func:`metrology.diagnosis.height_effects.batwing_transfer`) is the
  interferometer's own edge response, of a fitted width that already is its reach in the
  measurement: its band-pass ``b`` is added to the objective's transfer, not imaged through
  it, so the whole transfer is ``pixel * blur * (MTF + b)``
  (:meth:`metrology.matching.instrument.InstrumentModel.map_of`). Imaged through the objective
  (``MTF * (1 + b)``), a CSI's edge overshoot of 0.1-0.15 of the step at 0.2-0.4 um is
  attenuated below what it reports, and the nearest member of the family leaves 0.4-3.5 nm
  at each 600 nm step (1 nm noise); beside it, the family holds it exactly. Without an
  objective both are the same.

The footprint and the blur form one spatial kernel on the fine grid (exact moments, cell
integration included: :func:`footprint_kernel`), turned into a Fourier transfer on the
camera model's FFT grid. Under an objective the kernel's continuous spectrum is used instead
(:func:`objective_spectrum`): the fine surface is uniform per cell, so its spectrum repeats
beyond the grid's Nyquist, and the discrete kernel's spectrum carries those repeats folded
into the base band, where the optical transfer, applied on the grid, would pass them (0.3 nm
rms of a 600 nm step at a 0.2 um step under NA 0.26); the objective cuts them off, so the
continuous spectrum times its transfer is the exact one, wherever the cut-off lies below the
grid's Nyquist frequency (NA < 0.71 at 0.57 um and a 0.2 um step; beyond, the image holds detail
the grid cannot carry either way). The optical transfer is isotropic, so the placement does not
enter it. Kernel written by hand: no library integrates a Gaussian over a
rotated, mirrored parallelogram and a grid cell at once.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.special import erf

from metrology.matching.array_cache import ArrayCache

__all__ = ["DEFAULT_WAVELENGTH_M", "NA_BOUNDS", "LateralTransfer", "as_transfer", "footprint_kernel",
           "footprint_spectrum", "kernel_half_width", "na_mtf", "objective_spectrum"]

# White-light interferometers: the centre of their source's band.
DEFAULT_WAVELENGTH_M = 0.57e-6
# Physical range of an objective's numerical aperture.
NA_BOUNDS = (0.05, 0.95)


@dataclass(frozen=True)
class LateralTransfer:
    """The lateral transfer's parameters (SI units; see the module docstring).

    Attributes
    ----------
    sigma_m : float
        Gaussian blur (>= 0).
    fill_factor : float
        Pixel area fraction integrated, in [0, 1] (side ``sqrt(fill_factor)`` pixels).
    na : float
        Objective numerical aperture, 0 = no optical cut-off in the model.
    wavelength_m : float
        Mean wavelength of the optical transfer.
    """

    sigma_m: float = 0.4e-6
    fill_factor: float = 1.0
    na: float = 0.0
    wavelength_m: float = DEFAULT_WAVELENGTH_M

    def __post_init__(self):
        # Physical bounds, whatever a solver's step asked for: a negative blur or fill factor
        # is their zero-width limit, an aperture beyond the physical range its nearest bound.
        object.__setattr__(self, "sigma_m", max(float(self.sigma_m), 0.0))
        object.__setattr__(self, "fill_factor", min(max(float(self.fill_factor), 0.0), 1.0))
        na = float(self.na)
        object.__setattr__(self, "na", 0.0 if na <= 0 else min(max(na, NA_BOUNDS[0]), NA_BOUNDS[1]))
        object.__setattr__(self, "wavelength_m", float(self.wavelength_m))

    @property
    def cutoff_per_m(self) -> float:
        """Optical cut-off frequency ``2 NA / lambda`` (cycles per metre); inf without one."""
        return 2.0 * self.na / self.wavelength_m if self.na > 0 else math.inf

    def optical_reach_m(self) -> float:
        """Distance beyond which the objective's point spread (Airy pattern, first zero at
        ``0.61 lambda / NA``) carries nothing the model needs: about three rings."""
        return 2.0 * self.wavelength_m / self.na if self.na > 0 else 0.0

    def to_dict(self) -> dict:
        return {"blur_sigma_m": self.sigma_m, "fill_factor": self.fill_factor, "na": self.na,
                "wavelength_m": self.wavelength_m}


def as_transfer(value: float | LateralTransfer) -> LateralTransfer:
    """A :class:`LateralTransfer`; a bare number is a Gaussian blur (m) with full pixels."""
    return value if isinstance(value, LateralTransfer) else LateralTransfer(sigma_m=float(value))


def na_mtf(nu_per_m: np.ndarray, na: float, wavelength_m: float) -> np.ndarray:
    """Incoherent transfer of a circular pupil (the "chinese hat") at frequencies ``nu``
    (cycles per metre): ``2/pi (acos s - s sqrt(1 - s^2))``, ``s = nu lambda / (2 NA)``, 0 beyond.
    The formula is evaluated inside the cut-off only (on a fit's FFT grid, a tenth of it)."""
    s = np.abs(np.asarray(nu_per_m, float)) * wavelength_m / (2.0 * na)
    out = np.zeros(s.shape)
    inside = s < 1.0
    s = s[inside]
    out[inside] = (2.0 / np.pi) * (np.arccos(s) - s * np.sqrt(1.0 - s * s))
    return out


def _footprint(matrix, pitch_m, fill_factor):
    """The pixel footprint's edge vectors (m, as columns): the placement's linear part scaled by
    the pitch and the side ``sqrt(fill_factor)`` (clipped to [0, 1])."""
    return np.asarray(matrix, float) * pitch_m * math.sqrt(min(max(fill_factor, 0.0), 1.0))


def _cell_gaussian(x_m, step_m, sigma_m):
    """Integral of a unit Gaussian of width ``sigma_m`` centred at 0 over cells centred at ``x_m``
    (a zero width is the cell's own box, approached within a thousandth of a cell)."""
    s = max(float(sigma_m), 1e-3 * step_m) * math.sqrt(2.0)
    return 0.5 * (erf((x_m + step_m / 2) / s) - erf((x_m - step_m / 2) / s))


def kernel_half_width(matrix: np.ndarray, pitch_m: float, step_m: float, sigma_m: float,
                      fill_factor: float = 1.0) -> int:
    """Half width ``k`` (fine cells, >= 1) of :func:`footprint_kernel`: the footprint's half
    extent plus four blur sigmas."""
    side = max(np.abs(np.asarray(matrix, float) * pitch_m).sum(axis=1)) * math.sqrt(max(fill_factor, 0.0))
    return max(int(math.ceil((side / 2 + 4.0 * max(sigma_m, 0.0)) / step_m)) + 1, 1)


def footprint_kernel(matrix: np.ndarray, pitch_m: float, step_m: float, sigma_m: float,
                     fill_factor: float = 1.0) -> np.ndarray:
    """Blur-and-pixel kernel on the fine grid: the mean over the pixel's footprint ``y`` of the
    integral over fine cell ``a`` of ``G_sigma(x - y)``.

    Parameters
    ----------
    matrix : ndarray (2, 2)
        Linear part of the placement (design pixels per camera pixel).
    pitch_m, step_m : float
        Design pitch and fine-grid spacing.
    sigma_m : float
        Gaussian blur (standard deviation, m; 0 = none).
    fill_factor : float
        Pixel area integrated (0 = the pixel centre alone).

    Returns
    -------
    ndarray (2 k + 1, 2 k + 1)
        Weights summing to 1, centre at index ``k``; row 0 at the top.
    """
    sigma_m = max(float(sigma_m), 0.0)
    m = _footprint(matrix, pitch_m, fill_factor)
    side = max(np.abs(m).sum(axis=1))
    q = max(8, int(math.ceil(2.0 * side / max(sigma_m, step_m))))
    sub = (np.arange(q) + 0.5) / q - 0.5
    u, v = np.meshgrid(sub, sub, indexing="ij")
    y = m @ np.stack([u.ravel(), v.ravel()])  # footprint points (row, col offsets, m)
    k = kernel_half_width(matrix, pitch_m, step_m, sigma_m, fill_factor)
    x = np.arange(-k, k + 1) * step_m
    # Each point stands for a 1/q sub-pixel: widen its Gaussian by that sub-pixel's variance so
    # the kernel's second moments are exact (the midpoint rule alone loses 1/q^2 of them).
    sub_var = np.diag(m @ m.T) / (12.0 * q * q)
    gr = _cell_gaussian(x[None, :] - y[0][:, None], step_m, math.sqrt(sigma_m ** 2 + sub_var[0]))
    gc = _cell_gaussian(x[None, :] - y[1][:, None], step_m, math.sqrt(sigma_m ** 2 + sub_var[1]))
    kernel = gr.T @ gc / y.shape[1]
    return kernel / kernel.sum()


def footprint_spectrum(matrix: np.ndarray, pitch_m: float, step_m: float, sigma_m: float,
                       fill_factor: float, nu_r: np.ndarray, nu_c: np.ndarray) -> np.ndarray:
    """Continuous Fourier transform of :func:`footprint_kernel`'s kernel: one fine cell's box,
    the pixel's footprint (a parallelogram) and the Gaussian blur, at frequencies ``nu_r``,
    ``nu_c`` (cycles per metre along rows and columns, broadcast together).

    Parameters
    ----------
    matrix, pitch_m, step_m, sigma_m, fill_factor
        As for :func:`footprint_kernel`.
    nu_r, nu_c : ndarray
        Frequencies along the row and column axes (cycles/m).

    Returns
    -------
    ndarray
        The transfer (real: the kernel is centred and symmetric), 1 at zero frequency.
    """
    nu_r, nu_c = np.asarray(nu_r, float), np.asarray(nu_c, float)
    return _pixel_factor(matrix, pitch_m, step_m, fill_factor, nu_r, nu_c) * _blur_factor(sigma_m, nu_r, nu_c)


def _pixel_factor(matrix, pitch_m, step_m, fill_factor, nu_r, nu_c):
    """:func:`footprint_spectrum`'s fine cell and pixel footprint: the footprint is ``m @ [u, v]``
    over the unit square centred at 0, a sinc per edge vector."""
    m = _footprint(matrix, pitch_m, fill_factor)
    return (np.sinc(nu_r * step_m) * np.sinc(nu_c * step_m)
            * np.sinc(nu_r * m[0, 0] + nu_c * m[1, 0]) * np.sinc(nu_r * m[0, 1] + nu_c * m[1, 1]))


def _blur_factor(sigma_m, nu_r, nu_c):
    """:func:`footprint_spectrum`'s Gaussian blur."""
    return np.exp(-2.0 * np.pi ** 2 * max(float(sigma_m), 0.0) ** 2 * (nu_r ** 2 + nu_c ** 2))


def objective_spectrum(matrix: np.ndarray, pitch_m: float, step_m: float, transfer: LateralTransfer,
                       nu_r: np.ndarray, nu_c: np.ndarray, dtype: type = np.float64,
                       weights: tuple[np.ndarray, np.ndarray] | None = None,
                       factors: ArrayCache | None = None) -> np.ndarray:
    """The whole lateral transfer under an objective on a fine grid's Fourier grid:
    :func:`footprint_spectrum` times :func:`na_mtf`, evaluated inside the cut-off only (0 beyond).

    ``nu_r`` and ``nu_c`` (1-D, cycles/m) are the grid's frequencies along rows and columns; the
    result has shape ``(nu_r.size, nu_c.size)``, in ``dtype``. Only the block of rows and columns
    within the cut-off is computed (the rest of the grid, up to its Nyquist frequency, is 0).
    ``weights``: per row and per column factors (of ``dtype``'s precision) the result is then
    multiplied by, in that order (a spline prefilter), on the block alone. ``factors``: a store of
    the three factors (pixel footprint, blur, optical transfer), each kept per the parameters it
    depends on (the grid and ``matrix`` among them; one ``pitch_m`` and ``step_m`` per store): a Jacobian column of the blur, fill factor or NA recomputes
    that factor alone. The same numbers either way.
    """
    cutoff = transfer.cutoff_per_m
    nu_r, nu_c = np.ravel(nu_r), np.ravel(nu_c)
    rows, cols = np.flatnonzero(np.abs(nu_r) < cutoff), np.flatnonzero(np.abs(nu_c) < cutoff)
    r, c = nu_r[rows][:, None], nu_c[cols][None, :]
    block = (nu_r.size, nu_c.size, rows.size, cols.size)  # the grid and, with it, the cut-off's block

    def factor(key, make):
        if factors is None:
            return make()
        value = factors.get(key)
        if value is None:
            value = make()
            factors.put(key, value)
        return value

    pixel = factor(("pixel", block, np.asarray(matrix, float).tobytes(), transfer.fill_factor),
                   lambda: _pixel_factor(matrix, pitch_m, step_m, transfer.fill_factor, r, c))
    blur = factor(("blur", block, transfer.sigma_m), lambda: _blur_factor(transfer.sigma_m, r, c))
    mtf = factor(("mtf", block, transfer.na, transfer.wavelength_m),
                 lambda: na_mtf(np.hypot(r, c), transfer.na, transfer.wavelength_m))
    inside = (pixel * blur * mtf).astype(dtype)
    if weights is not None:
        inside *= weights[0][rows][:, None]
        inside *= weights[1][cols][None, :]
    out: np.ndarray = np.zeros((nu_r.size, nu_c.size), dtype)
    out[np.ix_(rows, cols)] = inside
    return out
