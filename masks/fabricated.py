"""The element a process would make, on the grid the PSF engine takes.

Shared by the tolerance analysis (:mod:`masks.tolerance`) and the PSF predicted from
measured heights (:mod:`metrology.matching.measured_psf`): the process model
(:func:`masks.process.simulate_surface`) is applied to the *whole* design on a grid of
``pitch / oversample`` (optionally finer, then area-averaged down), so a 1600 px element
costs (1600 q)^2 samples instead of the ~35000^2 of the 0.25 um process grid.

Approximation: the engine takes one height per sample, so a mask sliver narrower than a
sample is height-averaged instead of mixing the two fields; etch-depth errors are exact at
any ``oversample``, the scatter from sub-micron overlay and bias is underestimated at
``oversample = 1`` and less so at 2. With ``process_upsample > oversample`` the resist blur
and threshold act on a finer grid before the averaging.
"""

from __future__ import annotations

import numpy as np

from doedesign.engine.backend import Array, Backend
from doedesign.errors import DoeError

from . import litho
from .process import simulate_surface
from .process_params import ProcessParams

__all__ = ["DEFAULT_TARGET_FRACTION", "fabricated_height", "target_from_psf"]

# The "target" when the design carries none: the design PSF's brightest pixels that hold this
# share of its in-window light.
DEFAULT_TARGET_FRACTION = 0.9


def target_from_psf(psf: np.ndarray, fraction: float = DEFAULT_TARGET_FRACTION) -> np.ndarray:
    """Brightest pixels of each PSF (..., rows, cols) that hold ``fraction`` of its window light."""
    psf = np.asarray(psf)
    flat_psf = psf.reshape(-1, *psf.shape[-2:])
    out = np.zeros(flat_psf.shape, bool)
    for i, p in enumerate(flat_psf):
        flat = p.ravel()
        order = np.argsort(flat)[::-1]
        cum = np.cumsum(flat[order])
        n = int(np.searchsorted(cum, fraction * cum[-1])) + 1
        out[i].ravel()[order[:n]] = True
    return out.reshape(psf.shape)


def fabricated_height(levels: np.ndarray, pitch_m: float, params: ProcessParams, oversample: int = 2,
                      process_upsample: int | None = None, backend: str | Backend | None = None) -> Array:
    """Height map (m) of the whole element made with ``params``, ``oversample`` samples per pixel.

    Parameters
    ----------
    levels : ndarray of int (rows, cols)
        Design levels, row 0 at the top.
    pitch_m : float
    params : masks.process.ProcessParams
    oversample : int
        Samples per design pixel per axis of the result.
    process_upsample : int, optional
        Samples per design pixel of the process grid, a multiple of ``oversample``
        (default ``oversample``); the surface is area-averaged down to ``oversample``.
    backend : str or Backend, optional
        Where the process model runs (:mod:`doedesign.engine.backend`; default the CPU).

    Returns
    -------
    array of float64 (of ``backend``), shape (rows * oversample, cols * oversample)
        z up, 0 = unetched top, negative where etched; row 0 at the top.
    """
    q = int(oversample)
    u = q if process_upsample is None else int(process_upsample)
    if q < 1 or u < q or u % q:
        raise DoeError(f"oversample {oversample} must be >= 1 and process_upsample {process_upsample} "
                       "a multiple of it")
    levels = np.asarray(levels)
    height = simulate_surface(levels, pitch_m, params, step_m=pitch_m / u, backend=backend).height_m
    shape = (levels.shape[0] * u, levels.shape[1] * u)
    if tuple(height.shape) != shape:
        raise DoeError(f"process surface shape {tuple(height.shape)} differs from {shape}")
    f = u // q
    if f > 1:
        xp = litho.backend_of(backend).xp
        height = xp.mean(xp.reshape(height, (shape[0] // f, f, shape[1] // f, f)), axis=(1, 3))
    return height
