"""The :class:`~doedesign.targets.base.Target` container: wanted sensor intensity per depth and wavelength, and sums of targets."""

from __future__ import annotations

import logging
from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import ArrayLike

from ..camera import Camera
from ..errors import DoeError

__all__ = ["Target", "combine"]

log = logging.getLogger(__name__)


@dataclass
class Target:
    """Wanted sensor intensity per depth and wavelength.

    Attributes
    ----------
    intensity : ndarray (depths, wavelengths, rows, cols)
        Fraction of the coded view's light wanted in each window pixel; row 0 at the top.
    wavelengths_m, depths_m : ndarray
        Axes of ``intensity`` (``inf`` is optical infinity).
    pixel_weight : ndarray, broadcastable to ``intensity``
        Loss weight of each pixel (0 masks it out).
    channel_weight : ndarray (depths, wavelengths)
        Relative loss weight of each depth and wavelength.
    peak_penalty : float
        Weight of a penalty on each plane's brightest pixel (HDR streaks).
    axis_pixel : (int, int)
        Window pixel on the optical axis.
    name : str
    """

    intensity: np.ndarray
    wavelengths_m: np.ndarray
    depths_m: np.ndarray
    pixel_weight: np.ndarray | float = 1.0
    channel_weight: np.ndarray | None = None
    peak_penalty: float = 0.0
    axis_pixel: tuple = (256, 256)
    name: str = "target"
    meta: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.wavelengths_m = np.atleast_1d(np.asarray(self.wavelengths_m, dtype=float))
        self.depths_m = np.atleast_1d(np.asarray(self.depths_m, dtype=float))
        self.intensity = np.asarray(self.intensity, dtype=float)
        shape = (self.depths_m.size, self.wavelengths_m.size)
        if self.intensity.ndim != 4 or self.intensity.shape[:2] != shape:
            raise DoeError(f"target {self.name!r}: intensity must be (depths, wavelengths, rows, cols) = "
                           f"({shape[0]}, {shape[1]}, rows, cols), got shape {self.intensity.shape}")
        if not np.all(np.isfinite(self.intensity)):
            raise DoeError(f"target {self.name!r}: intensity holds NaN or infinite values")
        if np.any(self.intensity < 0):
            raise DoeError(f"target {self.name!r}: intensity is negative at {np.count_nonzero(self.intensity < 0)} "
                           "pixels; a target intensity must be >= 0")
        sums = self.intensity.sum(axis=(-2, -1))
        if np.any(sums <= 0):
            d, w = np.argwhere(sums <= 0)[0]
            raise DoeError(f"target {self.name!r}: empty at depth {self.depths_m[d]:g} m, "
                           f"wavelength {self.wavelengths_m[w] * 1e9:.1f} nm (no pixel wants light)")
        if np.any(sums > 1 + 1e-9):
            raise DoeError(f"target {self.name!r}: asks for {sums.max():.3g} of the light in the window; "
                           "the energy per depth and wavelength is at most 1")
        if np.any(self.wavelengths_m <= 0) or np.any(self.wavelengths_m > 20e-6):
            raise DoeError(f"target {self.name!r}: wavelengths must be positive and in metres, got {self.wavelengths_m}")
        if np.any(~(self.depths_m > 0)):
            raise DoeError(f"target {self.name!r}: depths must be positive metres (or inf), got {self.depths_m}")
        pw = np.asarray(self.pixel_weight, dtype=float)
        try:
            np.broadcast_to(pw, self.intensity.shape)
        except ValueError:
            raise DoeError(f"target {self.name!r}: pixel_weight of shape {pw.shape} does not fit the intensity "
                           f"{self.intensity.shape}") from None
        if not np.all(np.isfinite(pw)) or np.any(pw < 0):
            raise DoeError(f"target {self.name!r}: pixel_weight must be finite and >= 0")
        self.pixel_weight = pw
        cw = np.ones(shape) if self.channel_weight is None else np.asarray(self.channel_weight, dtype=float)
        if cw.shape != shape or np.any(cw < 0) or not np.all(np.isfinite(cw)) or cw.sum() <= 0:
            raise DoeError(f"target {self.name!r}: channel_weight must be {shape} non-negative numbers, not all zero")
        self.channel_weight = cw
        self.axis_pixel = tuple(int(v) for v in self.axis_pixel)
        self.peak_penalty = float(self.peak_penalty)

    @property
    def window_shape(self) -> tuple[int, int]:
        return self.intensity.shape[-2:]

    @property
    def mask(self) -> np.ndarray:
        """Boolean (depths, wavelengths, rows, cols): the pixels that should receive light."""
        return self.intensity > 0

    @property
    def energy(self) -> np.ndarray:
        """Energy wanted in the window per (depth, wavelength)."""
        return self.intensity.sum(axis=(-2, -1))

    def with_weights(self, wavelengths: ArrayLike | None = None, depths: ArrayLike | None = None,
                     pixel: ArrayLike | None = None, peak_penalty: float | None = None) -> Target:
        """A copy with new loss weights per wavelength, per depth, per pixel or for the peak."""
        assert self.channel_weight is not None  # __post_init__ sets it
        cw = self.channel_weight.copy()
        if wavelengths is not None:
            cw = cw * _vector(wavelengths, self.wavelengths_m.size, "wavelength weights", self.name)[None, :]
        if depths is not None:
            cw = cw * _vector(depths, self.depths_m.size, "depth weights", self.name)[:, None]
        return replace(self, channel_weight=cw,
                       pixel_weight=self.pixel_weight if pixel is None else np.asarray(pixel, dtype=float),
                       peak_penalty=self.peak_penalty if peak_penalty is None else peak_penalty,
                       meta=dict(self.meta))

    def __add__(self, other: Target) -> Target:
        return combine(self, other)

    def summary(self) -> dict:
        """Plain dictionary for reports."""
        return {"name": self.name, "wavelengths_nm": (self.wavelengths_m * 1e9).round(3).tolist(),
                "depths_m": [float(d) if np.isfinite(d) else "inf" for d in self.depths_m],
                "window_shape": list(self.window_shape), "axis_pixel": list(self.axis_pixel),
                "energy": self.energy.tolist(), "target_pixels": self.mask.sum(axis=(-2, -1)).tolist(),
                "peak_penalty": self.peak_penalty, **self.meta}


def _vector(values, n, what, name):
    v = np.atleast_1d(np.asarray(values, dtype=float))
    if v.shape != (n,) or np.any(v < 0) or not np.all(np.isfinite(v)):
        raise DoeError(f"target {name!r}: {what} must be {n} non-negative numbers, got {values!r}")
    return v


def _index_of(values, axis_values):
    """Position of each of ``values`` in the union ``axis_values`` (matched to 1e-12 relative)."""
    out = []
    for v in values:
        hit = np.flatnonzero(np.isclose(axis_values, v, rtol=1e-9, atol=0) | ((axis_values == v)))
        out.append(int(hit[0]))
    return out


def combine(*targets: Target, name: str | None = None) -> Target:
    """Sum targets over the union of their wavelengths and depths.

    Intensities add; a (depth, wavelength) plane present in several targets gets the sum of
    their channel weights and the pixel-weight maximum. All must share window and axis.
    """
    if not targets:
        raise DoeError("combine: no targets given")
    first = targets[0]
    for t in targets[1:]:
        if t.window_shape != first.window_shape or t.axis_pixel != first.axis_pixel:
            raise DoeError(f"combine: target {t.name!r} has window {t.window_shape} / axis {t.axis_pixel}, "
                           f"{first.name!r} has {first.window_shape} / {first.axis_pixel}")
    wls = _union([t.wavelengths_m for t in targets])
    deps = _union([t.depths_m for t in targets])
    shape = (deps.size, wls.size) + tuple(first.window_shape)
    intensity = np.zeros(shape)
    pixel_weight = np.zeros(shape)
    channel_weight = np.zeros(shape[:2])
    present = np.zeros(shape[:2], dtype=bool)
    for t in targets:
        di, wi = _index_of(t.depths_m, deps), _index_of(t.wavelengths_m, wls)
        sel = np.ix_(di, wi)
        intensity[sel] += t.intensity
        pixel_weight[sel] = np.maximum(pixel_weight[sel], np.broadcast_to(t.pixel_weight, t.intensity.shape))
        channel_weight[sel] += t.channel_weight
        present[sel] = True
    if not present.all():
        d, w = np.argwhere(~present)[0]
        raise DoeError(f"combine: no target defines depth {deps[d]:g} m at {wls[w] * 1e9:.1f} nm; "
                       "combined targets must share wavelengths at each depth")
    total = intensity.sum(axis=(-2, -1), keepdims=True)
    if np.any(total > 1 + 1e-9):
        log.info("combined target asks for %.3g of the light; rescaling each plane to 1", total.max())
        intensity = intensity / np.maximum(total, 1.0)
    return Target(intensity, wls, deps, pixel_weight=pixel_weight, channel_weight=channel_weight,
                  peak_penalty=max(t.peak_penalty for t in targets), axis_pixel=first.axis_pixel,
                  name=name or "+".join(t.name for t in targets))


def _union(arrays):
    out = []
    for arr in arrays:
        for v in arr:
            if not any((v == u) or np.isclose(v, u, rtol=1e-9, atol=0) for u in out):
                out.append(float(v))
    return np.array(out)


# -- helpers ----------------------------------------------------------------------------------
def _camera(camera: Camera | None) -> Camera:
    return camera if camera is not None else Camera()


def _check_pixels(rows, cols, window_shape, name):
    rows, cols = np.asarray(rows), np.asarray(cols)
    bad = (rows < 0) | (rows >= window_shape[0]) | (cols < 0) | (cols >= window_shape[1])
    if np.any(bad):
        i = int(np.flatnonzero(bad)[0])
        raise DoeError(f"target {name!r}: pixel ({int(rows.flat[i])}, {int(cols.flat[i])}) is outside the "
                       f"{window_shape[0]} x {window_shape[1]} window")


def _normalize(plane, energy, name):
    s = plane.sum()
    if s <= 0:
        raise DoeError(f"target {name!r}: no pixel of the window receives light")
    return plane * (energy / s)


def _check_energy(energy, name):
    if not (0 < energy <= 1):
        raise DoeError(f"target {name!r}: energy must be in (0, 1] (fraction of the light), got {energy}")
    return float(energy)
