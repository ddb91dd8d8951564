"""Losses between a simulated PSF and a :class:`~doedesign.targets.base.Target`, with gradients.

Every loss takes the coded PSF shaped (depths, wavelengths, rows, cols), as
:meth:`doedesign.engine.psf.PSFEngine.value_and_grad` hands it over, and returns
``(loss, dloss_dpsf)``. Per-plane terms are averaged with the target's channel weights
(normalized to sum 1), so the numbers compare across targets with different band counts.

- ``l1``: the seed's L1 distance (supplement Eq. 2). On the target pixels its kink at zero
  has no gradient, so it is smoothed there as ``sum w (sqrt(r^2 + eps^2) - eps)`` with
  ``r = psf - target``; ``eps`` (a fraction of the light per pixel) sets where it turns
  quadratic: well below the target values, so the optimum is the L1 optimum to within ``eps``
  per pixel. Off the target ``r = psf >= 0`` (a pixel-integrated intensity), so ``|r| = psf``
  exactly, which is smooth and needs no smoothing: that part is ``w`` times the light there.
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
round (used by :func:`doedesign.optimizer.optimize.design_doe` with ``reweight_rounds``).

Losses that read few pixels
---------------------------
:func:`make_loss` returns a :class:`Loss`. When its terms need only the target pixels and the
window's total energy (``energy``, ``uniformity``, and ``l1`` with one off-target pixel weight
per plane; not ``l2`` or ``peak``), ``Loss.reads`` names those pixels (:class:`PixelReads`) and
``Loss.sparse(values, energy)`` evaluates the same loss from them alone. The PSF engine then
computes only those pixels and the energy (:meth:`doedesign.engine.psf.PSFEngine.value_and_grad`), so
Bayer, spot and similar targets never build the whole window. ``reads`` is None otherwise.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from ..errors import DoeError

if TYPE_CHECKING:
    from ..targets import Target

__all__ = ["DEFAULT_EPS", "Loss", "LossSpec", "MAX_READ_LINES", "PEAK_POWER", "PixelReads", "TERMS",
           "energy_loss", "l2_loss", "make_loss", "peak_loss", "reweight_target", "smooth_l1", "target_metrics",
           "uniformity_loss"]

TERMS = ("l1", "energy", "l2", "peak", "uniformity")
DEFAULT_EPS = 1e-6
PEAK_POWER = 8


def _plane_weights(target):
    cw = target.channel_weight
    return cw / cw.sum()


def smooth_l1(psf: np.ndarray, target: Target, eps: float = DEFAULT_EPS) -> tuple[float, np.ndarray]:
    """L1 distance, channel-weighted: ``w (sqrt(r^2 + eps^2) - eps)`` on the target, ``w psf`` off it."""
    r = psf - target.intensity
    s = np.sqrt(r * r + eps * eps)
    w = target.pixel_weight * _plane_weights(target)[..., None, None]
    m = target.mask
    return float(np.sum(np.where(m, w * (s - eps), w * psf))), np.where(m, w * r / s, w)


def energy_loss(psf: np.ndarray, target: Target) -> tuple[float, np.ndarray]:
    """Fraction of the wanted light that misses the target pixels."""
    pw = _plane_weights(target)[..., None, None]
    mask = target.mask * target.pixel_weight
    wanted = target.energy[..., None, None]
    grad = -pw * mask / wanted
    return float(np.sum(pw[..., 0, 0]) + np.sum(grad * psf)), grad


def l2_loss(psf: np.ndarray, target: Target) -> tuple[float, np.ndarray]:
    """Squared error relative to the target's own squared norm."""
    r = psf - target.intensity
    norm = np.sum(target.intensity ** 2, axis=(-2, -1), keepdims=True)
    w = target.pixel_weight * _plane_weights(target)[..., None, None] / norm
    return float(np.sum(w * r * r)), 2 * w * r


def peak_loss(psf: np.ndarray, target: Target, power: float = PEAK_POWER) -> tuple[float, np.ndarray]:
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


def uniformity_loss(psf: np.ndarray, target: Target) -> tuple[float, np.ndarray]:
    """Squared coefficient of variation of ``psf / target`` over each plane's target pixels.

    With ``a_i`` the ratios, ``mu`` their mean and ``V`` their variance over the ``M`` target
    pixels, the value is ``V / mu^2`` (channel-weighted) and ``d/da_i = 2 ((a_i - mu) - V / mu)
    / (M mu^2)``. A plane with a single target pixel contributes nothing.
    """
    return _uniformity(psf, target.intensity, target.mask, _plane_weights(target), axis=(-2, -1))


def _uniformity(values, intensity, m, plane_weight, axis):
    """:func:`uniformity_loss` on ``values`` whose pixel axes are ``axis`` (full window or a pixel list)."""
    axis = tuple(np.atleast_1d(axis))
    a = np.where(m, values / np.where(m, intensity, 1.0), 0.0)
    count = m.sum(axis=axis, keepdims=True)
    mu = np.maximum(a.sum(axis=axis, keepdims=True) / count, 1e-30)
    dev = np.where(m, a - mu, 0.0)
    var = np.sum(dev * dev, axis=axis, keepdims=True) / count
    pw = plane_weight.reshape(plane_weight.shape + (1,) * len(axis))
    value = float(np.sum(pw * var / mu ** 2))
    grad = np.where(m, pw * 2 * (dev - var / mu) / (count * mu ** 2) / np.where(m, intensity, 1.0), 0.0)
    return value, grad


def reweight_target(target: Target, psf: np.ndarray, alpha: float = 1.0, floor: float = 1e-3) -> Target:
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
    def parse(cls, text: str) -> LossSpec:
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


@dataclass(frozen=True)
class PixelReads:
    """What a loss reads of the coded PSF: a few window pixels and perhaps the window's energy.

    ``rows``, ``cols``: (row, col) of each pixel read (row 0 at the top), the same for every
    depth and wavelength; ``energy``: whether the loss needs each plane's window total.
    """

    rows: np.ndarray
    cols: np.ndarray
    energy: bool


# Largest number of distinct window rows (and columns) a loss may read through the few-pixel
# path: the engine evaluates the field on every (row, column) pair of those lines.
MAX_READ_LINES = 8


class Loss:
    """The loss ``psf -> (value, dvalue_dpsf)`` of a target under a :class:`LossSpec`.

    Attributes
    ----------
    reads : PixelReads or None
        Set when the loss depends only on a few pixels and the window energy; then
        :meth:`sparse` gives the same value from those alone.
    """

    def __init__(self, target: Target, spec: LossSpec | None = None) -> None:
        self.target = target
        self.spec = spec or LossSpec()
        self.peak_weight = target.peak_penalty if self.spec.peak is None else self.spec.peak
        self.reads = self._reads()

    def __call__(self, psf):
        target, spec = self.target, self.spec
        if psf.shape != target.intensity.shape:
            raise DoeError(f"PSF of shape {psf.shape} does not match the target {target.intensity.shape}")
        total, grad = 0.0, np.zeros_like(psf)
        for weight, fn in ((spec.l1, lambda p: smooth_l1(p, target, spec.eps)),
                           (spec.energy, lambda p: energy_loss(p, target)),
                           (spec.l2, lambda p: l2_loss(p, target)),
                           (self.peak_weight, lambda p: peak_loss(p, target)),
                           (spec.uniformity, lambda p: uniformity_loss(p, target))):
            if weight:
                v, g = fn(psf)
                total += weight * v
                grad += weight * g
        return total, grad

    def _reads(self):
        spec, target = self.spec, self.target
        if spec.l2 or self.peak_weight:
            return None
        mask = target.mask
        union = mask.any(axis=(0, 1))
        rows, cols = np.nonzero(union)
        if np.unique(rows).size > MAX_READ_LINES or np.unique(cols).size > MAX_READ_LINES:
            return None
        if spec.l1:
            pw = np.broadcast_to(target.pixel_weight, mask.shape)
            off = np.where(mask, np.nan, pw).reshape(mask.shape[:2] + (-1,))
            first = np.nanmax(off, axis=-1, keepdims=True)
            if np.any(np.nanmax(np.abs(off - first), axis=-1) > 0):
                return None  # off-target weights vary within a plane: the energy alone cannot carry them
            self._off_weight = first[..., 0]
        self._mask = mask[..., rows, cols]
        self._intensity = target.intensity[..., rows, cols]
        self._weight = np.broadcast_to(target.pixel_weight, mask.shape)[..., rows, cols]
        return PixelReads(rows=rows, cols=cols, energy=bool(spec.l1))

    def sparse(self, values: np.ndarray, energy: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
        """The loss from the pixels in ``reads`` and the window energies.

        Parameters
        ----------
        values : ndarray (depths, wavelengths, pixels)
            The PSF at ``reads.rows``, ``reads.cols``.
        energy : ndarray (depths, wavelengths)
            Each plane's window total (ignored unless ``reads.energy``).

        Returns
        -------
        loss : float
        dvalues : ndarray like ``values``
        denergy : ndarray like ``energy``
        """
        spec, m = self.spec, self._mask
        pw = _plane_weights(self.target)
        total, dval, den = 0.0, np.zeros_like(values), np.zeros_like(energy)
        if spec.l1:
            r = values - self._intensity
            s = np.sqrt(r * r + spec.eps * spec.eps)
            w = self._weight * pw[..., None]
            off = self._off_weight * pw
            on_sum = np.sum(np.where(m, values, 0.0), axis=-1)
            total += spec.l1 * float(np.sum(np.where(m, w * (s - spec.eps), 0.0)) + np.sum(off * (energy - on_sum)))
            dval += spec.l1 * np.where(m, w * r / s - off[..., None], 0.0)
            den += spec.l1 * off
        if spec.energy:
            wanted = self.target.energy
            g = np.where(m, -(pw / wanted)[..., None] * self._weight, 0.0)
            total += spec.energy * float(np.sum(pw) + np.sum(g * values))
            dval += spec.energy * g
        if spec.uniformity:
            v, g = _uniformity(values, self._intensity, m, pw, axis=-1)
            total += spec.uniformity * v
            dval += spec.uniformity * g
        return total, dval, den


def make_loss(target: Target, spec: LossSpec | None = None) -> Loss:
    """The loss ``psf -> (value, dvalue_dpsf)`` of ``target`` under the weights ``spec`` (a :class:`Loss`)."""
    return Loss(target, spec)


def target_metrics(psf: np.ndarray, target: Target) -> dict:
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
