"""The single-colour bound of a target: what a diffraction-limited spot puts on its pixels.

For each (depth, wavelength) plane of a target, the bound is the light that the camera's
diffraction-limited spot through the coded view (a flat DOE, in focus, so the spot of that
half aperture) puts on the plane's target pixels when it is centred on the best of them, times
the DOE pixel envelope ``sinc^2(p x / lambda z) sinc^2(p y / lambda z)`` at that pixel (the
light a DOE of pitch ``p`` can steer there). It is the reference each colour is scored
against: a phase-only element concentrating one colour into a pixel no larger than the spot
cannot beat it (for a small pixel, ``|sum A exp(i phi)| <= sum A`` with equality for a flat
phase), and a colour router that serves three colours at once gets less. For extended targets
(streaks, rings) it is the light of one spot on the target, a reference, not a limit.

Numbers for the seed camera (8.64 mm aperture, 50 mm, 5.4 um pixels, focused at infinity):
0.489 / 0.548 / 0.644 of the coded half's light in one pixel at 656 / 589 / 486 nm, and
0.743 / 0.788 / 0.830 through the full aperture (checked against the Airy pattern and a direct
half-disc integral in tests/doedesign/test_bounds.py).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike
from scipy import signal

from .camera import Camera
from .engine.backend import Backend
from .engine.psf import PSFEngine
from .targets import Target

__all__ = ["bound_report", "diffraction_limited_psf", "spot_bound"]


def diffraction_limited_psf(camera: Camera, pitch_m: float, shape: tuple[int, int], wavelengths_m: ArrayLike,
                            material: str = "fused_silica", device: str | Backend = "cpu") -> np.ndarray:
    """Coded-view PSF (wavelengths, rows, cols) of a flat DOE in focus: the diffraction-limited spot
    (computed on ``device``, :mod:`doedesign.engine.backend`)."""
    engine = PSFEngine(camera, pitch_m, shape, material, wavelengths_m, [camera.focus_distance_m], device=device)
    return engine.psf(np.zeros(tuple(shape)), views=("coded",)).psf[0, 0]


def spot_bound(camera: Camera, pitch_m: float, shape: tuple[int, int], target: Target,
               material: str = "fused_silica", spot: np.ndarray | None = None,
               device: str | Backend = "cpu") -> np.ndarray:
    """Single-colour bound per (depth, wavelength) plane of ``target`` (fractions of the coded view's light).

    Parameters
    ----------
    camera, pitch_m, shape : the camera and the DOE grid of the design.
    target : doedesign.targets.Target
    spot : ndarray (wavelengths, rows, cols), optional
        A precomputed :func:`diffraction_limited_psf` for the target's wavelengths.

    Returns
    -------
    ndarray (depths, wavelengths)
    """
    if spot is None:
        spot = diffraction_limited_psf(camera, pitch_m, shape, target.wavelengths_m, material, device)
    r0, c0 = camera.axis_pixel
    rows, cols = camera.window_shape
    dy = (np.arange(rows) - r0) * camera.pixel_pitch_m
    dx = (np.arange(cols) - c0) * camera.pixel_pitch_m
    z = camera.sensor_distance_m
    out = np.zeros(target.intensity.shape[:2])
    for w, wl in enumerate(target.wavelengths_m):
        envelope = np.outer(np.sinc(pitch_m * dy / (wl * z)) ** 2, np.sinc(pitch_m * dx / (wl * z)) ** 2)
        # Light on the mask of the spot centred on pixel j: sum_i mask[i] spot[axis + i - j].
        kernel = spot[w][::-1, ::-1]
        for d in range(target.intensity.shape[0]):
            mask = target.mask[d, w]
            pix = np.argwhere(mask)
            if len(pix) == 1:
                (i, j), = pix
                on = spot[w][r0, c0]
                out[d, w] = on * envelope[i, j]
                continue
            corr = signal.fftconvolve(mask.astype(float), kernel, mode="full")
            # Index of shift j in the full correlation: j + (spot shape - 1) - axis.
            vals = corr[pix[:, 0] + rows - 1 - r0, pix[:, 1] + cols - 1 - c0]
            out[d, w] = float(np.max(vals * envelope[pix[:, 0], pix[:, 1]]))
    return out


def bound_report(energy_on_target: ArrayLike, bound: ArrayLike) -> dict:
    """Per-plane energies beside their bound: ``{"energy", "bound", "fraction_of_bound", "weakest"}``."""
    e = np.asarray(energy_on_target, dtype=float)
    b = np.asarray(bound, dtype=float)
    frac = np.where(b > 0, e / np.where(b > 0, b, 1.0), 0.0)
    return {"energy": e.tolist(), "bound": b.tolist(), "fraction_of_bound": frac.tolist(),
            "weakest_energy": float(e.min()), "weakest_fraction_of_bound": float(frac.min())}
