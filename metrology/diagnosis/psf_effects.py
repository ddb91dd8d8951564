"""The built-in PSF-domain effects: what the calibration bench and the sensor add to a PSF stack.

Calibration effects (the source's bandwidth, a defocus, the dual-pixel crosstalk, a background)
and one fabrication effect seen through the optics (a common depth scale).
:mod:`metrology.diagnosis.effects` registers them.
"""

from __future__ import annotations

import numpy as np

from metrology.diagnosis.effect_model import Effect, Parameter

__all__ = ["BUILTIN_PSF", "FWHM_PER_SIGMA"]

# Gauss-Hermite nodes for averaging over a Gaussian source spectrum (exact for polynomials of
# degree 5 in wavelength, enough for a smear of a few pixels).
_GH_NODES, _GH_WEIGHTS = np.polynomial.hermite_e.hermegauss(3)
_GH_WEIGHTS = _GH_WEIGHTS / _GH_WEIGHTS.sum()
FWHM_PER_SIGMA = 2.0 * np.sqrt(2.0 * np.log(2.0))


def _depth_scale(height_m, values):
    return height_m * (1.0 + float(values[0]))


def _defocus(render, values, info):
    inv = 1.0 / info["depth_m"] + float(values[0])
    depth = np.inf if inv <= 0 else 1.0 / inv

    def shifted(height_m, wavelengths_m, depth_m):
        return render(height_m, wavelengths_m, depth)

    return shifted


def _source_bandwidth(render, values, info):
    sigma = float(values[0]) / FWHM_PER_SIGMA
    if sigma <= 0:
        return render

    def averaged(height_m, wavelengths_m, depth_m):
        wl = np.asarray(wavelengths_m, dtype=float)
        samples = (wl[None, :] + sigma * _GH_NODES[:, None]).ravel()
        stack = render(height_m, samples, depth_m)
        stack = stack.reshape(stack.shape[0], _GH_NODES.size, wl.size, *stack.shape[-2:])
        return np.tensordot(stack, _GH_WEIGHTS, axes=([1], [0]))

    return averaged


def _dual_pixel_crosstalk(stack, values, info):
    views, full, full_views = list(info["views"]), info["full"], list(info["full_views"])
    if "coded" not in views:
        return stack
    c = float(values[0])
    out = stack.copy()
    out[views.index("coded")] = ((1.0 - c) * full[full_views.index("coded")]
                                 + c * full[full_views.index("uncoded")])
    return out


def _background(stack, values, info):
    return stack + np.asarray(values, dtype=float).reshape(stack.shape[:2])[..., None, None]


BUILTIN_PSF = [
    Effect("dual_pixel_crosstalk", "psf", "sensor",
           [Parameter("fraction", "1", 0.0, 0.5, 0.02)], _dual_pixel_crosstalk,
           "The dual-pixel sensor leaks a fraction of the uncoded view's light into the coded view.",
           kind="calibration", start=(0.02,)),
    Effect("source_bandwidth", "psf", "optics",
           [Parameter("fwhm_m", "m", 0.0, 60e-9, 3e-9)], _source_bandwidth,
           "The calibration source is not monochromatic: each PSF is averaged over a band of wavelengths, "
           "smearing diffraction orders radially.", kind="calibration", start=(4e-9,)),
    Effect("defocus", "psf", "optics",
           [Parameter("inverse_distance_change_per_m", "1/m", -0.19, 5.0, 0.1)], _defocus,
           "The point source was not where the camera is focused (or the sensor moved): a change of "
           "1/distance adds a spherical phase that blurs the PSF symmetrically.", kind="calibration",
           start=(0.3,)),
    Effect("depth_scale", "psf", "height",
           [Parameter("scale_error", "1", -0.3, 0.3, 0.02)], _depth_scale,
           "All heights are off by one factor (index or depth calibration): light moves into the zero "
           "and second orders.", kind="fabrication"),
    Effect("background", "psf", "sensor",
           [Parameter("offset", "1", -1e-3, 1e-3, 1e-6)], _background,
           "A constant offset per view and wavelength (dark level, stray light), as a fraction of the "
           "channel's light per pixel.", kind="calibration", per_channel=True, order=10),
]
