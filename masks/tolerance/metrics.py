"""Figures of merit of one sample's coded PSF, chosen by the design's target kind.

Every metric is a plain float; ``DIRECTIONS`` says whether higher or lower is better. The
PSF is the coded view's, shaped (depths, wavelengths, rows, cols), each plane the fraction
of the light through the coded half-aperture per sensor pixel (row 0 at the top).

- bayer: light on the red, green and blue target pixels (``on_target_R/G/B``), their mean
  and minimum;
- hyperspectral: ``first_order_efficiency`` (light on the order spots) and
  ``zero_order_leak`` (light in the 3 x 3 pixels on the axis);
- spots: ``efficiency``, ``spot_uniformity`` = 1 - (max - min) / (max + min) of the spot
  energies, and ``zero_order_leak`` when no spot sits on the axis;
- hdr-streak: ``streak_energy`` (light on the streak) and ``peak_fraction`` (brightest
  pixel over the window light);
- depth: ``ring_radius_px`` per depth (light-weighted mean radius) and
  ``ring_radius_error_px`` (largest distance from the target's);
- anything else: ``efficiency`` on the pixels holding 90 % of the nominal PSF's light.

User metrics come from a Python script: every top-level function named ``metric_<name>``
is called as ``f(psf, info)`` (``info``: ``wavelengths_m``, ``depths_m``, ``axis_pixel``)
and must return a number; set ``f.direction = "lower"`` when lower is better.

The built-in metrics reduce the PSF where it was computed (NumPy, or CuPy on a GPU: the same
array API code) to a few numbers per plane, which cross to the host as one small vector per
sample; the last statistics over planes are taken there. A user script gets a NumPy copy.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field

import numpy as np
from scipy import ndimage as ndi

from doedesign import targets
from doedesign.camera import Camera
from doedesign.design import Design
from doedesign.engine.backend import Array, Backend, select_backend
from doedesign.errors import DoeError

from ..fabricated import target_from_psf

__all__ = ["DIRECTIONS", "MetricSet", "PRIMARY", "design_target", "design_target_mask", "design_wavelengths_depths",
           "metric_set", "metric_unit", "ring_radii_px", "user_metric_functions"]

log = logging.getLogger(__name__)

DIRECTIONS = {"peak_fraction": "lower", "zero_order_leak": "lower", "ring_radius_error_px": "lower"}
PRIMARY = {"bayer": "on_target_mean", "hyperspectral": "first_order_efficiency", "spots": "efficiency",
           "hdr-streak": "streak_energy", "depth": "ring_radius_error_px"}
BAYER_CHANNELS = ("R", "G", "B")
# Built-in metrics that are not a fraction of the light through the coded half-aperture.
_OTHER_UNITS = {"peak_fraction": "fraction of window light", "spot_uniformity": "ratio"}
_FRACTION_METRICS = {"first_order_efficiency", "streak_energy", "efficiency", "zero_order_leak"}


def metric_unit(name: str) -> str:
    """The unit of a metric, for report columns: built-in metrics are fractions of the light
    through the coded half-aperture unless named ``_px``; a user script's metrics carry its own."""
    if "_px" in name:
        return "px"
    if name in _OTHER_UNITS:
        return _OTHER_UNITS[name]
    if name.startswith("on_target_") or name in _FRACTION_METRICS:
        return "fraction of light"
    return "script's unit"


@dataclass
class MetricSet:
    """What to measure on a coded PSF; built once from the nominal PSF, shipped to workers."""

    kind: str
    wavelengths_m: np.ndarray
    depths_m: np.ndarray
    axis_pixel: tuple
    target_mask: np.ndarray
    bayer_cells: list = field(default_factory=list)
    spot_labels: np.ndarray | None = None
    target_radii_px: np.ndarray | None = None
    script_source: str | None = None
    script_name: str = "metrics script"
    note: str | None = None

    @property
    def primary(self) -> str:
        return PRIMARY.get(self.kind, "efficiency")

    def __getstate__(self):
        state = dict(self.__dict__)
        state.pop("_device", None)  # device copies stay with the process that made them
        return state

    def _on(self, be: Backend, name: str, make) -> Array:
        """A constant array (target mask, spot labels) on ``be``, copied there once."""
        cache = self.__dict__.setdefault("_device", {})
        key = (be.name, name)
        if key not in cache:
            cache[key] = be.asarray(make())
        return cache[key]

    def __call__(self, psf: Array, backend: str | Backend | None = None) -> dict:
        """The metrics of a coded PSF (depths, wavelengths, rows, cols): a host array, or one of
        ``backend`` (default the CPU), on which the reductions run."""
        be = select_backend("cpu" if backend is None else backend)
        xp = be.xp
        psf = xp.astype(be.asarray(psf), xp.float64, copy=False)
        r0, c0 = self.axis_pixel
        # Per-plane reductions where the PSF is; they come back as one vector.
        parts = {}
        if self.kind == "bayer":
            for w, (name, cells) in enumerate(zip(BAYER_CHANNELS, self.bayer_cells)):
                parts[name] = sum(psf[0, w, r0 + dr, c0 + dc] for dr, dc in cells)
        else:
            target = self._on(be, "target", lambda: np.asarray(self.target_mask, dtype=np.float64))
            parts["on"] = xp.sum(psf * target, axis=(-2, -1))
        if self.kind == "hdr-streak":
            window = xp.sum(psf, axis=(-2, -1))
            parts["peak"] = xp.max(psf, axis=(-2, -1)) / xp.maximum(window, 1e-300)
        leak = self.kind in ("hyperspectral", "spots") and not self._axis_in_target()
        if leak:
            parts["leak"] = xp.sum(psf[..., r0 - 1:r0 + 2, c0 - 1:c0 + 2], axis=(-2, -1))
        if self.kind == "spots" and self.spot_labels is not None:
            n = int(self.spot_labels.max())
            labels = self._on(be, "labels", lambda: self.spot_labels)
            index = self._on(be, "index", lambda: np.arange(1, n + 1))
            parts["spots"] = be.ndimage.sum(xp.sum(psf, axis=(0, 1)), labels, index)
        if self.kind == "depth":
            parts["radii"] = ring_radii_px(psf, self.axis_pixel, be)
        names = list(parts)
        flat = be.to_host(xp.concat([xp.reshape(xp.asarray(parts[k]), (-1,)) for k in names]))
        sizes = np.cumsum([0] + [int(np.prod(tuple(parts[k].shape))) for k in names])
        host = {k: flat[sizes[i]:sizes[i + 1]] for i, k in enumerate(names)}

        out = {}
        if self.kind == "bayer":
            vals = [host[name][0] for name in BAYER_CHANNELS]
            for name, v in zip(BAYER_CHANNELS, vals):
                out[f"on_target_{name}"] = float(v)
            out["on_target_mean"] = float(np.mean(vals))
            out["on_target_min"] = float(np.min(vals))
        elif self.kind == "hyperspectral":
            out["first_order_efficiency"] = float(host["on"].mean())
        elif self.kind == "hdr-streak":
            out["streak_energy"] = float(host["on"].mean())
            out["peak_fraction"] = float(np.mean(host["peak"]))
        else:
            out["efficiency"] = float(host["on"].mean())
        if leak:
            out["zero_order_leak"] = float(host["leak"].mean())
        if "spots" in host:
            hi, lo = float(np.max(host["spots"])), float(np.min(host["spots"]))
            out["spot_uniformity"] = 1.0 - (hi - lo) / (hi + lo) if hi + lo > 0 else 0.0
        if self.kind == "depth":
            radii = host["radii"]
            for d, r in zip(self.depths_m, radii):
                out[f"ring_radius_px[{d:g} m]"] = float(r)
            out["ring_radius_error_px"] = float(np.max(np.abs(radii - self.target_radii_px)))
        if self.script_source:
            out.update(self._user_metrics(be.to_host(psf)))
        return out

    def _axis_in_target(self):
        r0, c0 = self.axis_pixel
        return bool(self.target_mask[..., r0 - 1:r0 + 2, c0 - 1:c0 + 2].any())

    def _user_metrics(self, psf):
        if not self.script_source:
            return {}
        info = {"wavelengths_m": self.wavelengths_m, "depths_m": self.depths_m, "axis_pixel": self.axis_pixel}
        out = {}
        for name, fn in user_metric_functions(self.script_source, self.script_name).items():
            try:
                value = float(fn(psf, info))
            except Exception as exc:  # a user function may fail in any way; name it
                raise DoeError(f"{self.script_name}: metric_{name} failed: {type(exc).__name__}: {exc}") from None
            if not math.isfinite(value):
                raise DoeError(f"{self.script_name}: metric_{name} returned {value}, not a finite number")
            out[name] = value
        return out

    def directions(self) -> dict:
        """metric -> "higher" or "lower" (is better), user metrics included."""
        out = dict(DIRECTIONS)
        if self.script_source:
            for name, fn in user_metric_functions(self.script_source, self.script_name).items():
                out[name] = getattr(fn, "direction", "higher")
        return out


_SCRIPTS: dict[tuple[str, str], dict] = {}


def _target_meta(design: Design) -> dict:
    """The design's target entry (``metadata["target"]``), {} when it has none."""
    meta = design.metadata.get("target")
    return meta if isinstance(meta, dict) else {}


def user_metric_functions(source: str, name: str = "metrics script") -> dict:
    """``{name: function}`` of the ``metric_*`` functions of a script (compiled once per process)."""
    key = (name, source)
    if key not in _SCRIPTS:
        namespace = {"__name__": "doe_user_metrics"}
        try:
            exec(compile(source, name, "exec"), namespace)
        except Exception as exc:  # user code: report any error as a one-line DoeError
            raise DoeError(f"{name}: cannot run the metrics script: {type(exc).__name__}: {exc}") from None
        funcs = {k[len("metric_"):]: v for k, v in namespace.items() if k.startswith("metric_") and callable(v)}
        if not funcs:
            raise DoeError(f"{name}: defines no function named metric_<name>(psf, info)")
        _SCRIPTS[key] = funcs
    return _SCRIPTS[key]


def ring_radii_px(psf: Array, axis_pixel: tuple, backend: str | Backend | None = None) -> Array:
    """Light-weighted mean distance (px) from the axis per depth, averaged over wavelengths
    (on ``backend``'s arrays, default the CPU's)."""
    be = select_backend("cpu" if backend is None else backend)
    xp = be.xp
    rows, cols = psf.shape[-2:]
    rr, cc = np.mgrid[:rows, :cols]
    radius = be.asarray(np.hypot(rr - axis_pixel[0], cc - axis_pixel[1]))
    total = xp.sum(psf, axis=(-2, -1))
    mean_r = xp.sum(psf * radius, axis=(-2, -1)) / xp.maximum(total, 1e-300)
    return xp.mean(mean_r, axis=1)


def metric_set(design: Design, camera: Camera, nominal_psf: np.ndarray, wavelengths_m: np.ndarray,
               depths_m: np.ndarray, script: str | None = None) -> MetricSet:
    """The metrics for this design's target kind (from its metadata), set up on its nominal PSF."""
    meta = _target_meta(design)
    kind = str(meta.get("kind", "image"))
    source = None
    if script is not None:
        from pathlib import Path

        path = Path(script)
        if not path.is_file():
            raise DoeError(f"{script}: no such metrics script")
        source = path.read_text()
        user_metric_functions(source, str(script))
    if kind == "bayer" and np.size(wavelengths_m) != len(BAYER_CHANNELS):
        raise DoeError(f"a bayer design is scored at {len(BAYER_CHANNELS)} wavelengths (R, G, B), got "
                       f"{np.size(wavelengths_m)} (the design's target or --wavelengths)")
    target_mask = _target_mask(kind, meta, camera, wavelengths_m, depths_m, nominal_psf, design)
    note = None
    if kind not in targets.KINDS:
        # Warned, not refused: the generic figure still measures how much light stays where the
        # ideal element puts it, and a design from another tool or a newer version may name a
        # kind this one does not know; but a user must see that the kind's own metric is missing.
        note = (f"target kind {kind[:60]!r} is unknown to this tool (known: {', '.join(targets.KINDS)}); scored by "
                "the generic 'efficiency': light on the pixels that hold 90 % of the ideal element's PSF")
        log.warning("%s", note)
    ms = MetricSet(kind=kind, wavelengths_m=np.asarray(wavelengths_m, float), depths_m=np.asarray(depths_m, float),
                   axis_pixel=tuple(camera.axis_pixel), target_mask=target_mask, script_source=source,
                   script_name=str(script) if script else "metrics script", note=note)
    if kind == "bayer":
        ms.bayer_cells = [[(0, 0)], [(1, 0), (0, 1)] if meta.get("rggb") else [(1, 0)], [(1, 1)]]
    if kind == "spots":
        ms.spot_labels = ndi.label(target_mask.any(axis=(0, 1)))[0]
    if kind == "depth":
        ms.target_radii_px = ring_radii_px(target_mask.astype(float), camera.axis_pixel)
    return ms


def design_wavelengths_depths(design: Design, camera: Camera) -> tuple[np.ndarray, np.ndarray]:
    """Wavelengths and depths of the design's target (metadata), else 550 nm at the focus.

    The depths are metres, ``inf`` for optical infinity (stored as the string ``"inf"``).
    """
    meta = _target_meta(design)
    wls = np.asarray(meta.get("wavelengths_nm") or [550.0], float) * 1e-9
    depths = [math.inf if str(d).lower() == "inf" else float(d) for d in meta.get("depths_m") or []]
    return wls, np.asarray(depths or [camera.focus_distance_m], float)


def design_target(design: Design, camera: Camera, wavelengths_m: np.ndarray,
                  depths_m: np.ndarray) -> targets.Target | None:
    """The built-in target a design was made for, rebuilt from its metadata for ``camera``.

    The design file stores its target as ``metadata["target"]`` (:meth:`doedesign.targets.base.Target.summary`:
    kind and options); the same built-in target is rebuilt at ``wavelengths_m`` (and, but for
    Bayer, ``depths_m``).

    Returns
    -------
    doedesign.targets.Target or None
        None when the design names no built-in target or it cannot be rebuilt on this window.
    """
    meta = _target_meta(design)
    kind = str(meta.get("kind", "image"))
    if kind not in PRIMARY:
        return None
    options = {"wavelengths_m": np.asarray(wavelengths_m, float)}
    if kind != "bayer":
        options["depths_m"] = np.asarray(depths_m, float)
    for key in ("rggb", "arms", "arm_width_px", "arm_length_px", "period_m", "orders", "spot_px",
                "positions_px", "radii_px", "ring_width_px"):
        if key in meta:
            options[key] = meta[key]
    try:
        return targets.build(kind, camera=camera, **options)
    except DoeError as exc:
        log.info("target %r not rebuilt from the metadata (%s)", kind, exc)
        return None


def design_target_mask(design: Design, camera: Camera, wavelengths_m: np.ndarray,
                       depths_m: np.ndarray) -> np.ndarray | None:
    """The pixels of the target a design was made for (:func:`design_target`).

    This is the one target every figure of merit of the design is taken on (design report,
    tolerance, comparison).

    Returns
    -------
    ndarray of bool (depths, wavelengths, rows, cols) or None
        None when the design names no built-in target or it cannot be rebuilt on this window.
    """
    t = design_target(design, camera, wavelengths_m, depths_m)
    if t is None:
        return None
    shape = (np.size(depths_m), np.size(wavelengths_m), *camera.window_shape)
    if t.intensity.shape[1:] != shape[1:]:
        return None
    return np.broadcast_to(t.mask, shape)


def _target_mask(kind, meta, camera, wavelengths_m, depths_m, nominal_psf, design):
    """The design's own target pixels; else the nominal PSF's brightest."""
    mask = design_target_mask(design, camera, wavelengths_m, depths_m)
    if mask is not None and mask.shape == np.shape(nominal_psf):
        return mask
    log.info("design %r carries no target that fits its PSF; using the nominal PSF's brightest pixels", kind)
    return target_from_psf(nominal_psf)
