"""The built-in height-domain effects: what the fab's process and the profilometer do to the heights.

Process-stage effects map :class:`masks.process_params.ProcessParams` to new ones (the masks
stage's process model then draws the surface); surface-stage effects act on the model heights on
the fine grid (the instrument's blur and batwing). The per-mask effects carry the parameters of
the four-mask (16-level) process; :meth:`~metrology.diagnosis.effect_model.Effect.for_masks`
resizes them for another mask count. :mod:`metrology.diagnosis.effects` registers them.

The blur and batwing taps are written here, not taken from scipy.ndimage's Gaussian filters:
they integrate the Gaussian over each pixel (a pixel-averaged map), so they tend to the identity
as the width goes to zero, which a least-squares fit of the width needs.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import scipy.ndimage as ndi
from scipy.special import erf

from metrology.diagnosis.effect_model import Effect, Parameter

__all__ = ["BUILTIN_HEIGHT", "batwing_profile", "batwing_transfer", "gaussian_blur"]

# Peak of sigma^2 d/dx G_sigma(x) for a unit step, at x = sigma: 1 / sqrt(2 pi e). Batwing
# amplitudes are quoted as the peak overshoot as a fraction of the step height.
_DOG_PEAK = 1.0 / np.sqrt(2.0 * np.pi * np.exp(1.0))


def _gaussian_taps(sigma_m, step_m):
    """Pixel-integrated Gaussian and Gaussian-second-derivative taps (per axis).

    For pixel-averaged heights ``h_k`` the blurred value at pixel ``j`` is
    ``sum_k h_k * integral over pixel k of G(x_j - x)``: taps ``Phi((m + 1/2) s / sigma) -
    Phi((m - 1/2) s / sigma)``; likewise ``G'(m s + s/2) - G'(m s - s/2)`` for ``G''``. They tend
    to the identity as sigma -> 0 (continuous for a least-squares fit) and do not depend on
    the size of the map (an FFT filter's band edge does).
    """
    half = int(np.ceil(5.0 * sigma_m / step_m)) + 1
    edges = (np.arange(-half, half + 2) - 0.5) * step_m
    cdf = 0.5 * (1.0 + erf(edges / (np.sqrt(2.0) * sigma_m)))
    smooth = np.diff(cdf)
    dens = np.exp(-0.5 * (edges / sigma_m) ** 2) / (np.sqrt(2.0 * np.pi) * sigma_m)
    first = -edges / sigma_m ** 2 * dens  # G'(x)
    second = np.diff(first)  # integral of G'' over each pixel (1/m^2 * m)
    return smooth / smooth.sum(), second


def gaussian_blur(height_m: np.ndarray, sigma_m: float, step_m: float) -> np.ndarray:
    """Gaussian blur of standard deviation ``sigma_m`` of a pixel-averaged map (separable)."""
    h = np.asarray(height_m, dtype=float)
    if sigma_m <= 0:
        return h
    smooth, _ = _gaussian_taps(sigma_m, step_m)
    out = ndi.correlate1d(h, smooth, axis=0, mode="nearest")
    return ndi.correlate1d(out, smooth, axis=1, mode="nearest")


def batwing_profile(height_m: np.ndarray, amplitude: float, sigma_m: float, step_m: float) -> np.ndarray:
    """Edge overshoot of a white-light interferometer: ``-a sigma^2 lap(G_sigma * h) / peak``.

    Across a step of height H the added profile is a derivative of Gaussian of width
    ``sigma_m``: an overshoot of ``amplitude * H`` at the top corner and an undershoot as deep
    at the bottom corner, zero on flat areas.
    """
    h = np.asarray(height_m, dtype=float)
    if sigma_m <= 0 or amplitude == 0:
        return np.zeros_like(h)
    smooth, second = _gaussian_taps(sigma_m, step_m)
    lap = (ndi.correlate1d(ndi.correlate1d(h, second, axis=0, mode="nearest"), smooth, axis=1, mode="nearest")
           + ndi.correlate1d(ndi.correlate1d(h, smooth, axis=0, mode="nearest"), second, axis=1, mode="nearest"))
    return -amplitude * sigma_m ** 2 / _DOG_PEAK * lap


def _etch_depth(params, values):
    depths = np.asarray(params.etch_depth, dtype=float) * (1.0 + values)
    return params.copy(etch_depth=tuple(depths))


def _mask_overlay(params, values):
    overlay = np.array(params.mask_overlay, dtype=float, copy=True)
    overlay[1:, 0] += values[0::2]
    overlay[1:, 1] += values[1::2]
    return params.copy(mask_overlay=overlay)


def _linewidth_bias(params, values):
    return params.copy(linewidth_bias=np.asarray(params.linewidth_bias, dtype=float) + values)


def _proximity_blur(params, values):
    return params.copy(proximity_blur=float(values[0]))


def _proximity_print(params, values):
    # The print through the gap replaces the contact print's Gaussian stand-in (the two exclude
    # each other in ProcessParams): applied after it (order 1), it wins where both are fitted.
    return params.copy(proximity_gap=float(values[0]), resist_threshold=float(values[1]), proximity_blur=0.0)


def _sidewall_slope(params, values):
    return params.copy(sidewall_slope=float(values[0]))


def _etch_loading(params, values):
    return params.copy(etch_loading=float(values[0]))


def _mask_rotation(params, values):
    rotation = np.array(params.mask_rotation, dtype=float, copy=True)
    rotation[1:] += values
    return params.copy(mask_rotation=rotation)


def _microtrenching(params, values):
    trench = np.array(params.microtrenching, dtype=float, copy=True)
    trench[:, 0] += values[0::2]
    # The width is a fitted value, not an increment: at zero depth it is free and harmless.
    trench[:, 1] = values[1::2]
    return params.copy(microtrenching=trench)


def _etch_gradient(params, values):
    return params.copy(etch_gradient=np.asarray(params.etch_gradient, dtype=float) + values)


def _instrument_blur(height_m, values, step_m):
    return gaussian_blur(height_m, float(values[0]), step_m)


def _batwing(height_m, values, step_m):
    return height_m + batwing_profile(height_m, float(values[0]), float(values[1]), step_m)


def batwing_transfer(values: Sequence[float], step_m: float, wr: np.ndarray, wc: np.ndarray,
                     reach_px: int) -> np.ndarray | None:
    """Fourier factor of ``h + batwing_profile(h)``: the same separable taps' responses (they
    are symmetric, so real: ``sum_k t_k cos(w k)``), or None beyond ``reach_px`` cells."""
    amplitude, sigma_m = float(values[0]), float(values[1])
    if sigma_m <= 0 or amplitude == 0:
        return np.ones((1, 1), np.float32)
    smooth, second = _gaussian_taps(sigma_m, step_m)
    half = smooth.size // 2
    if half > reach_px:
        return None
    k = np.arange(-half, half + 1)

    def response(taps, w):
        return np.cos(np.outer(w, k)) @ taps

    # The factor is kept in single precision: its two outer products are formed in it too.
    c = -amplitude * sigma_m ** 2 / _DOG_PEAK
    out = np.outer((c * response(second, wr)).astype(np.float32), response(smooth, wc).astype(np.float32))
    out += np.outer((c * response(smooth, wr)).astype(np.float32), response(second, wc).astype(np.float32))
    out += np.float32(1.0)
    return out


_UM = 1e-6


def _depth_params(n):
    return [Parameter(f"depth_error_mask{j}", "1", -0.3, 0.3, 0.02, smooth=True) for j in range(n)]


def _overlay_params(n):
    return [Parameter(f"{ax}_mask{j}_m", "m", -3 * _UM, 3 * _UM, 0.2 * _UM) for j in range(1, n) for ax in ("dx", "dy")]


def _bias_params(n):
    return [Parameter(f"bias_mask{j}_m", "m", -1.5 * _UM, 1.5 * _UM, 0.1 * _UM) for j in range(n)]


def _rotation_params(n):
    return [Parameter(f"rotation_mask{j}_deg", "deg", -0.5, 0.5, 0.005) for j in range(1, n)]


def _trench_params(n):
    return [Parameter(f"{q}_mask{j}_m", "m", lo, hi, sc, null, smooth=True) for j in range(n)
            for q, lo, hi, sc, null in (("depth", 0.0, 150e-9, 5e-9, 0.0),
                                        ("width", 0.05 * _UM, 3 * _UM, 0.1 * _UM, 0.4 * _UM))]


# The registry holds the per-mask effects of the four-mask (16-level) process; a diagnosis of an
# element of another mask count resizes them (effects_for(..., n_masks)).
_N = 4
BUILTIN_HEIGHT = [
    Effect("etch_depth", "height", "process", _depth_params(_N), _etch_depth,
           "Each mask's etch went deeper or shallower than its target by a fraction: the 16 level "
           "heights stop being multiples of one step.", mask_params=_depth_params),
    Effect("mask_overlay", "height", "process",
           _overlay_params(_N), _mask_overlay,
           "A mask was printed shifted against the first one (x toward +column, y up): one-signed slivers "
           "of that mask's depth appear on opposite edges of its features.", mask_params=_overlay_params),
    Effect("linewidth_bias", "height", "process",
           _bias_params(_N), _linewidth_bias,
           "A mask's openings printed wider (positive) or narrower than drawn, from exposure dose or "
           "development: same-sign slivers on every edge of its features.", mask_params=_bias_params),
    Effect("proximity_blur", "height", "process",
           [Parameter("sigma_m", "m", 0.0, 4 * _UM, 0.5 * _UM)], _proximity_blur,
           "The contact-print gap blurs the mask's aerial image before the resist threshold: corners round "
           "and small isolated features shrink.", start=(0.8 * _UM,), rivals=("proximity_print",)),
    Effect("proximity_print", "height", "process",
           [Parameter("gap_m", "m", 0.0, 100 * _UM, 5 * _UM),
            Parameter("threshold", "1", 0.15, 0.85, 0.05, 0.5)], _proximity_print,
           "The masks printed through a gap between chrome and resist (masks.proximity: Fresnel diffraction "
           "of the lamp's lines, collimation, resist threshold): each edge moves by an amount that depends on "
           "the feature's size and the dose, small openings print smaller or vanish, edges ripple.",
           start=(30 * _UM, 0.4), order=1, rivals=("proximity_blur",)),
    Effect("sidewall_slope", "height", "process",
           [Parameter("ramp_width_m", "m", 0.0, 3 * _UM, 0.3 * _UM)], _sidewall_slope,
           "The etch leaves sloped sidewalls: steps become ramps of a finite width.", start=(1.5 * _UM,)),
    Effect("etch_loading", "height", "process",
           [Parameter("loading", "1", -0.5, 0.5, 0.02, smooth=True)], _etch_loading,
           "The etch rate depends on the local open fraction of the mask: depth follows pattern density."),
    Effect("mask_rotation", "height", "process",
           _rotation_params(_N), _mask_rotation,
           "A mask was printed rotated about the design's centre (design pixel ((rows - 1) / 2, (cols - 1) / 2), "
           "not the camera field's) against the first one: its overlay grows linearly with the distance from "
           "that centre, opposite in sign on opposite sides.", mask_params=_rotation_params),
    Effect("microtrenching", "height", "process",
           _trench_params(_N), _microtrenching,
           "Ions reflected from the sidewalls etched deeper at the foot of a mask's etched edges: a trench "
           "inside each opening along its edges, decaying over a width, in proportion to that etch.",
           mask_params=_trench_params),
    Effect("etch_gradient", "height", "process",
           [Parameter(f"{ax}_per_m", "1/m", -100.0, 100.0, 5.0, smooth=True) for ax in ("x", "y")], _etch_gradient,
           "Plasma non-uniformity made every etch deeper on one side of the field by the same relative "
           "amount per metre (x toward +column, y up; 10 /m = 1 % per mm), referred to the design's centre "
           "(depths nominal there, not at the camera field's centre)."),
    Effect("instrument_blur", "height", "surface",
           [Parameter("sigma_m", "m", 0.0, 3 * _UM, 0.2 * _UM)], _instrument_blur,
           "Measurement artefact: the profilometer's finite lateral resolution (about 0.8 um at NA 0.4) "
           "smooths every step.", kind="artefact", order=20, start=(0.4 * _UM,), linear=True),
    Effect("batwing", "height", "surface",
           [Parameter("amplitude", "1", -1.0, 1.0, 0.05, smooth=True),
            Parameter("sigma_m", "m", 0.1 * _UM, 3 * _UM, 0.2 * _UM, 0.1 * _UM, smooth=True)],
           _batwing,
           "Measurement artefact: a white-light interferometer overshoots at steps shorter than its coherence "
           "length, a signed edge spike proportional to the step height.", kind="artefact", order=10,
           start=(0.05, 0.6 * _UM), linear=True, fourier=batwing_transfer, beside_objective=True),
]
