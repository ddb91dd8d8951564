"""Losses between a simulated PSF and a :class:`~doedesign.targets.Target`, with gradients.

Every loss takes the coded PSF shaped (depths, wavelengths, rows, cols), as
:meth:`doedesign.psf.PSFEngine.value_and_grad` hands it over, and returns
``(loss, dloss_dpsf)``. Per-plane terms are averaged with the target's channel weights
(normalized to sum 1), so the numbers compare across targets with different band counts.

- ``l1``: the seed's L1 distance (supplement Eq. 2). Its kink at zero has no gradient, so
  it is smoothed as ``sum w (sqrt(r^2 + eps^2) - eps)`` with ``r = psf - target``; ``eps``
  (a fraction of the light per pixel) sets where it turns quadratic: well below the target
  values, so the optimum is the L1 optimum to within ``eps`` per pixel.
- ``energy``: ``1 - sum(psf * mask * w) / sum(target)``: the light missing from the target
  pixels (a single spot's value is one minus its diffraction efficiency).
- ``l2``: ``sum w r^2 / sum(target^2)``, relative squared error.
- ``peak``: soft maximum of each plane, ``(sum psf^p)^(1/p) / mean target value``, scaled by
  the target's ``peak_penalty``; keeps HDR streaks from collapsing into a spot.
- ``uniformity``: the squared coefficient of variation ``var(a) / mean(a)^2`` of the
  delivered-to-wanted ratios ``a_i = psf_i / target_i`` over each plane's target pixels
  (spot arrays: how unequal the spots are, whatever their absolute efficiency). Unlike
  ``l2`` it does not pull toward a chosen absolute energy, so it can be added to ``energy``
  without fixing the efficiency in advance.

:func:`reweight_target` is the gradient analogue of weighted Gerchberg-Saxton (WGS): between
optimization rounds each target pixel's loss weight is multiplied by
``(mean ratio / its ratio)^alpha``, so pixels that get too little light count more in the next
round (used by :func:`doedesign.optimize.design_doe` with ``reweight_rounds``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .errors import DoeError

__all__ = ["DEFAULT_EPS", "LossSpec", "PEAK_POWER", "TERMS", "energy_loss", "l2_loss", "make_loss",
           "peak_loss", "reweight_target", "smooth_l1", "target_metrics", "uniformity_loss"]

TERMS = ("l1", "energy", "l2", "peak", "uniformity")
DEFAULT_EPS = 1e-6
PEAK_POWER = 8


def _plane_weights(target):
    cw = target.channel_weight
    return cw / cw.sum()


def smooth_l1(psf, target, eps=DEFAULT_EPS):
    """Smoothed L1 distance ``sum w (sqrt(r^2 + eps^2) - eps)``, channel-weighted."""
    r = psf - target.intensity
    s = np.sqrt(r * r + eps * eps)
    w = target.pixel_weight * _plane_weights(target)[..., None, None]
    return float(np.sum(w * (s - eps))), w * r / s


def energy_loss(psf, target):
    """Fraction of the wanted light that misses the target pixels."""
    pw = _plane_weights(target)[..., None, None]
    mask = target.mask * target.pixel_weight
    wanted = target.energy[..., None, None]
    grad = -pw * mask / wanted
    return float(np.sum(pw[..., 0, 0]) + np.sum(grad * psf)), grad


def l2_loss(psf, target):
    """Squared error relative to the target's own squared norm."""
    r = psf - target.intensity
    norm = np.sum(target.intensity ** 2, axis=(-2, -1), keepdims=True)
    w = target.pixel_weight * _plane_weights(target)[..., None, None] / norm
    return float(np.sum(w * r * r)), 2 * w * r


def peak_loss(psf, target, power=PEAK_POWER):
    """Soft maximum ``(sum psf^p)^(1/p)`` of each plane over the target's mean value there."""
    mean_target = target.energy / target.mask.sum(axis=(-2, -1))
    x = np.maximum(psf, 0.0)
    scale = x.max(axis=(-2, -1), keepdims=True)
    scale = np.where(scale > 0, scale, 1.0)
    u = x / scale
    norm_p = np.sum(u ** power, axis=(-2, -1), keepdims=True)
    soft_max = scale * norm_p ** (1.0 / power)
    pw = _plane_weights(target) / mean_target
    value = float(np.sum(pw * soft_max[..., 0, 0]))
    grad = pw[..., None, None] * u ** (power - 1) * norm_p ** (1.0 / power - 1.0)
    return value, grad


def _delivered_ratio(psf, target):
    """``psf / target`` on the target pixels (0 elsewhere), the mask and its pixel count per plane."""
    m = target.mask
    a = np.where(m, psf / np.where(m, target.intensity, 1.0), 0.0)
    return a, m, m.sum(axis=(-2, -1), keepdims=True)


def uniformity_loss(psf, target):
    """Squared coefficient of variation of ``psf / target`` over each plane's target pixels.

    With ``a_i`` the ratios, ``mu`` their mean and ``V`` their variance over the ``M`` target
    pixels, the value is ``V / mu^2`` (channel-weighted) and ``d/da_i = 2 ((a_i - mu) - V / mu)
    / (M mu^2)``. A plane with a single target pixel contributes nothing.
    """
    a, m, count = _delivered_ratio(psf, target)
    mu = np.maximum(a.sum(axis=(-2, -1), keepdims=True) / count, 1e-30)
    dev = np.where(m, a - mu, 0.0)
    var = np.sum(dev * dev, axis=(-2, -1), keepdims=True) / count
    pw = _plane_weights(target)[..., None, None]
    value = float(np.sum(pw * var / mu ** 2))
    grad = np.where(m, pw * 2 * (dev - var / mu) / (count * mu ** 2) / np.where(m, target.intensity, 1.0), 0.0)
    return value, grad


def reweight_target(target, psf, alpha=1.0, floor=1e-3):
    """A copy of ``target`` whose pixel weights favour the target pixels that got too little light.

    The weight of each target pixel is multiplied by ``(mean(a) / a_i)^alpha`` with
    ``a_i = psf_i / target_i`` (ratios below ``floor`` times the plane's mean are raised to
    it, so a dark pixel cannot blow up the weights); the factors are scaled to mean 1 over
    each plane's target pixels, and pixels outside the target keep their weights. This is the
    weighting step of weighted Gerchberg-Saxton applied to the loss weights instead of the
    target amplitudes.

    Returns
    -------
    Target
        With ``pixel_weight`` of the full (depths, wavelengths, rows, cols) shape.
    """
    if not (np.isfinite(alpha) and alpha > 0):
        raise DoeError(f"reweighting exponent must be positive, got {alpha}")
    a, m, count = _delivered_ratio(np.asarray(psf, dtype=float), target)
    mu = a.sum(axis=(-2, -1), keepdims=True) / count
    if np.any(mu <= 0):
        raise DoeError(f"target {target.name!r}: no light on a plane's target pixels; cannot reweight")
    factor = np.where(m, (mu / np.maximum(a, floor * mu)) ** alpha, 0.0)
    factor = np.where(m, factor * count / factor.sum(axis=(-2, -1), keepdims=True), 1.0)
    pw = np.broadcast_to(target.pixel_weight, target.intensity.shape) * factor
    return target.with_weights(pixel=pw)


@dataclass
class LossSpec:
    """Weights of the loss terms (see the module docstring); zero drops a term."""

    l1: float = 1.0
    energy: float = 0.0
    l2: float = 0.0
    peak: float | None = None  # None: the target's own peak_penalty
    eps: float = DEFAULT_EPS
    uniformity: float = 0.0

    def __post_init__(self):
        for name in ("l1", "energy", "l2", "eps", "uniformity"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v >= 0):
                raise DoeError(f"loss weight {name} must be a non-negative number, got {v}")
        if self.eps <= 0:
            raise DoeError("loss eps must be positive")

    @classmethod
    def parse(cls, text):
        """From ``"l1"`` or ``"l1=1,energy=0.5,peak=0.1"`` (weights default to 1 when given bare)."""
        weights = {"l1": 0.0, "energy": 0.0, "l2": 0.0, "uniformity": 0.0}
        peak = None
        for part in str(text).split(","):
            part = part.strip()
            if not part:
                continue
            name, _, value = part.partition("=")
            name = name.strip()
            if name not in TERMS:
                raise DoeError(f"unknown loss term {name!r}; terms are {', '.join(TERMS)}")
            try:
                v = float(value) if value else 1.0
            except ValueError:
                raise DoeError(f"loss term {name!r}: {value!r} is not a number") from None
            if name == "peak":
                peak = v
            else:
                weights[name] = v
        if not any(weights.values()) and not peak:
            raise DoeError(f"loss {text!r} has no term with a positive weight")
        return cls(peak=peak, **weights)


def make_loss(target, spec=None):
    """The loss ``psf -> (value, dvalue_dpsf)`` of ``target`` under the weights ``spec``."""
    spec = spec or LossSpec()
    peak_weight = target.peak_penalty if spec.peak is None else spec.peak

    def loss(psf):
        if psf.shape != target.intensity.shape:
            raise DoeError(f"PSF of shape {psf.shape} does not match the target {target.intensity.shape}")
        total, grad = 0.0, np.zeros_like(psf)
        for weight, fn in ((spec.l1, lambda p: smooth_l1(p, target, spec.eps)),
                           (spec.energy, lambda p: energy_loss(p, target)),
                           (spec.l2, lambda p: l2_loss(p, target)),
                           (peak_weight, lambda p: peak_loss(p, target)),
                           (spec.uniformity, lambda p: uniformity_loss(p, target))):
            if weight:
                v, g = fn(psf)
                total += weight * v
                grad += weight * g
        return total, grad

    return loss


def target_metrics(psf, target):
    """Figures of a PSF against a target (all fractions of the coded view's light).

    Returns
    -------
    dict
        ``energy_on_target`` (depths x wavelengths), ``energy_in_window``, ``efficiency``
        (channel-weighted mean energy on target), ``l1`` (unsmoothed, channel-weighted),
        ``peak_over_target_mean`` (brightest pixel over the mean target pixel value).
    """
    psf = np.asarray(psf)
    on = np.sum(psf * target.mask, axis=(-2, -1))
    pw = _plane_weights(target)
    mean_target = target.energy / target.mask.sum(axis=(-2, -1))
    return {
        "energy_on_target": on.tolist(),
        "energy_in_window": psf.sum(axis=(-2, -1)).tolist(),
        "efficiency": float(np.sum(pw * on)),
        "l1": float(np.sum(pw * np.abs(psf - target.intensity).sum(axis=(-2, -1)))),
        "peak_over_target_mean": (psf.max(axis=(-2, -1)) / mean_target).tolist(),
    }
