"""The PSF problem: a measured PSF stack against the design's PSFs through the camera.

Stacks are (views, wavelengths, rows, cols), row 0 at the top; residuals are fractions of each
channel's light per pixel.
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING, Any

import numpy as np
import scipy.ndimage as ndi

from doedesign.errors import DoeError
from doedesign.levels import printed_height_m
from metrology.diagnosis.breakdown import binned, radial_psd
from metrology.diagnosis.effects import effects_for
from metrology.diagnosis.engine import DEFAULT_THRESHOLD, Problem, run_diagnosis
from metrology.diagnosis.parallel import WORKERS, one_thread
from metrology.diagnosis.noise import estimate_noise
from metrology.matching.window import window_sums

if TYPE_CHECKING:
    from doedesign.camera import Camera
    from doedesign.engine.psf import PSFEngine
    from metrology.diagnosis.budget import Deadline
    from doedesign.design import Design
    from doedesign.materials import Material
    from metrology.diagnosis.effects import Effect
    from metrology.diagnosis.engine import Diagnosis
    from metrology.diagnosis.noise import NoiseEstimate

log = logging.getLogger(__name__)

# Windows larger than twice this square (pixels per side) screen candidates on a crop of it.
SCREEN_WINDOW_PX = 128
# Rendered channels kept for reuse (a full-size channel, both views, is 4 MB).
RESULT_CACHE_BYTES = 512 * 2 ** 20
# Fraction of the noise floor that the single-precision error of the ideal model (measured
# against the double-precision one) may reach for the whole window's model to be rendered in
# single precision, at about twice the speed.
SINGLE_PRECISION_NOISE_FRACTION = 0.01

__all__ = ["PsfProblem", "PsfRenderer", "diagnose_psf", "psf_forward"]

# render(height_m, wavelengths_m, depth_m) -> (views, wavelengths, rows, cols) stack.
RenderFn = Callable[[np.ndarray, Sequence[float] | np.ndarray, float], np.ndarray]


class PsfRenderer:
    """Ideal PSFs of a design for any wavelengths and source distance, engines and results cached.

    ``render(height_m, wavelengths_m, depth_m)`` returns (views, wavelengths, rows, cols) for
    the views ``("coded", "uncoded")``. Rendered channels (one wavelength, both views) are kept
    up to ``RESULT_CACHE_BYTES`` and only the wavelengths not yet rendered for that height and
    distance are computed: a wavelength-averaged model reuses the channels at the nominal
    wavelengths. ``cache_size`` engines are kept (each holds its kernels); they share the
    uncoded view's lags, which do not depend on the wavelength in focus.

    Parameters
    ----------
    precision : {"double", "single"}
        Arithmetic of the transforms (:class:`doedesign.engine.psf.PSFEngine`); "single" for screening.
    device : {"cpu", "gpu", "auto"}
        Where the engines compute (:mod:`doedesign.engine.backend`).
    """

    def __init__(self, camera: Camera, pitch_m: float, shape: tuple[int, int],
                 material: str | Material = "fused_silica", doe_oversample: int = 1, cache_size: int = 4,
                 precision: str = "double", device: str = "cpu") -> None:
        self.camera, self.pitch_m, self.shape = camera, float(pitch_m), tuple(shape)
        self.material, self.q, self.precision, self.device = material, int(doe_oversample), precision, device
        self._engines: dict[tuple[Any, ...], PSFEngine] = {}
        self._channels: dict[tuple[Any, ...], np.ndarray] = {}
        self._lags: dict[Any, Any] = {}
        self.cache_size = cache_size
        self.calls = 0
        self._last_height = None

    def _engine(self, wavelengths, depth_m):
        from doedesign.engine.psf import PSFEngine

        key = (wavelengths, depth_m)
        if key not in self._engines:
            if len(self._engines) >= self.cache_size:
                self._engines.pop(next(iter(self._engines)))
            self._engines[key] = PSFEngine(self.camera, self.pitch_m, self.shape, self.material, wavelengths,
                                           (depth_m,), self.q, precision=self.precision, lag_cache=self._lags,
                                           device=self.device)
        return self._engines[key]

    def __call__(self, height_m, wavelengths_m, depth_m):
        from doedesign.engine.psf import VIEWS

        wls = tuple(float(w) for w in np.round(np.asarray(wavelengths_m, dtype=float), 15))
        depth = float(depth_m)
        # Hashing a full-size map costs about as much as a small render: the last array's key is
        # kept with the array (held, so its id is not reused); heights are never changed in place.
        if self._last_height is None or self._last_height[0] is not height_m:
            self._last_height = (height_m, hash(np.asarray(height_m).tobytes()))
        hkey = self._last_height[1]
        found = {w: self._channels.get((hkey, w, depth)) for w in wls}
        missing = tuple(w for w in found if found[w] is None)
        if missing:
            self.calls += 1
            # Wavelengths side by side, one BLAS thread each: the lag transform's products are
            # mid-sized (a crop has 128 rows) and BLAS threads spin while they wait; measured on the
            # full-size case at a load of 11-12 on 2 cores, two BLAS threads took 2-2.5x the CPU
            # time of one for each screening fit.
            with one_thread():
                fresh = self._engine(missing, depth).psf(height_m, views=VIEWS, threads=WORKERS).psf[:, 0]
            for i, w in enumerate(missing):
                found[w] = np.ascontiguousarray(fresh[:, i])
            size = fresh[:, 0].nbytes
            while self._channels and (len(self._channels) + len(missing)) * size > RESULT_CACHE_BYTES:
                self._channels.pop(next(iter(self._channels)))
            self._channels.update({(hkey, w, depth): found[w] for w in missing})
        return np.stack([found[w] for w in wls], axis=1)


def psf_forward(model: dict[str, np.ndarray], effects: dict[str, Effect], render: RenderFn, height_m: np.ndarray,
                wavelengths_m: Sequence[float] | np.ndarray, depth_m: float, views: Sequence[str]) -> np.ndarray:
    """Model PSF stack of the measured ``views`` with the effects of ``model`` applied.

    Each (view, wavelength) channel is normalized to unit sum over the window, as the measured
    stack is (its units are arbitrary).

    Parameters
    ----------
    model : dict
        Effect name -> values.
    effects : dict
        Effect name -> Effect (per-channel effects already expanded).
    render : callable
        ``render(height_m, wavelengths_m, depth_m) -> (2 views, wavelengths, rows, cols)``.
    views : sequence of str
        Measured views, a subset of ``("coded", "uncoded")``.
    """
    from doedesign.engine.psf import VIEWS

    chosen = sorted((effects[n] for n in model), key=lambda e: (("height", "optics", "sensor").index(e.stage), e.order))
    h = np.asarray(height_m, dtype=float)
    info: dict[str, Any] = {"depth_m": float(depth_m)}
    for e in chosen:
        if e.stage == "height":
            h = e.apply(h, e.check(model[e.name]))
    for e in chosen:
        if e.stage == "optics":
            render = e.apply(render, e.check(model[e.name]), info)
    full = render(h, wavelengths_m, depth_m)
    stack = full[[VIEWS.index(v) for v in views]]
    info.update(views=tuple(views), full=full, full_views=VIEWS)
    for e in chosen:
        if e.stage == "sensor":
            stack = e.apply(stack, e.check(model[e.name]), info)
    return stack / stack.sum(axis=(-2, -1), keepdims=True)


def _mosaic(stack):
    """Channels of a (views, wavelengths, rows, cols) stack one under another, separated by a
    row of NaN, as one 2-D map (row 0 at the top)."""
    v, w, rows, cols = stack.shape
    out = np.full((v * w, rows + 1, cols), np.nan)
    out[:, :rows] = stack.reshape(v * w, rows, cols)
    return out.reshape(v * w * (rows + 1), cols)[:-1]


class PsfProblem(Problem):
    """A measured PSF stack against the design's PSFs through the camera.

    Parameters
    ----------
    design_height_m : ndarray (rows, cols)
    pitch_m : float
    camera : Camera
    measured : ndarray (views, wavelengths, rows, cols)
        Any units; each channel is normalized to unit sum.
    views : sequence of str
    wavelengths_m : sequence of float
    depth_m : float
        Point-source distance (default in :func:`diagnose_psf`: the camera's focus).
    effects : list of Effect
    """

    units = "fraction of the channel's light per pixel"
    # Every PSF effect is smooth in its parameters: forward-difference Jacobians.
    kinks = False

    def __init__(self, design_height_m: np.ndarray, pitch_m: float, camera: Camera, measured: np.ndarray,
                 views: Sequence[str], wavelengths_m: Sequence[float] | np.ndarray, depth_m: float,
                 effects: Sequence[Effect], material: str | Material = "fused_silica", doe_oversample: int = 1,
                 renderer: RenderFn | None = None,
                 screen_window_px: int | None = SCREEN_WINDOW_PX, noise: NoiseEstimate | None = None,
                 device: str = "cpu") -> None:
        meas = np.asarray(measured, dtype=float)
        self.views = tuple(views)
        self.wavelengths_m = np.asarray(wavelengths_m, dtype=float)
        if meas.shape[:2] != (len(self.views), self.wavelengths_m.size) or meas.shape[2:] != tuple(camera.window_shape):
            raise DoeError(f"measured PSF stack of shape {meas.shape} does not match {len(self.views)} view(s), "
                           f"{self.wavelengths_m.size} wavelength(s) and the camera window {camera.window_shape}")
        sums = np.nansum(meas, axis=(-2, -1), keepdims=True)
        if np.any(sums <= 0):
            raise DoeError("a channel of the measured PSF stack holds no light (sum <= 0)")
        self.measured = meas / sums
        self.height_m = np.asarray(design_height_m, dtype=float)
        self.pitch_m, self.material, self.doe_oversample = float(pitch_m), material, doe_oversample
        self.depth_m = float(depth_m)
        self.camera = camera
        self.device = device
        self.render = renderer or PsfRenderer(camera, pitch_m, self.height_m.shape, material, doe_oversample,
                                              device=device)
        self.channels = [f"{v}_{wl * 1e9:.0f}nm" for v in self.views for wl in self.wavelengths_m]
        self._effect_list = list(effects)
        self.effects = {e.name: e.for_channels(self.channels) for e in self._effect_list}
        self.axis_pixel = camera.axis_pixel
        self.valid = np.isfinite(self.measured)
        self.screening = None
        if noise is not None:  # a screening crop shares the noise of the whole window
            self.noise = noise
            return
        # Where no light of either view falls in the ideal model, the measurement is noise
        # (plus a smooth background): the noise floor comes from those pixels in 8 x 8 tiles.
        full = self.render(self.height_m, self.wavelengths_m, self.depth_m)
        light = full / full.sum(axis=(-2, -1), keepdims=True)
        lit = (light > 1e-3 * light.max(axis=(-2, -1), keepdims=True)).any(axis=0)
        lit = ndi.binary_dilation(lit, structure=np.ones((1, 7, 7), dtype=bool))
        rows, cols = camera.window_shape
        tiles = (np.arange(rows)[:, None] // 8) * ((cols + 7) // 8) + np.arange(cols)[None, :] // 8 + 1
        n_tiles = int(tiles.max())
        groups = np.zeros(self.measured.shape, dtype=int)
        for vi in range(len(self.views)):
            for wi in range(self.wavelengths_m.size):
                ci = vi * self.wavelengths_m.size + wi
                groups[vi, wi] = np.where(~lit[wi] & self.valid[vi, wi], tiles + ci * n_tiles, 0)
        self.noise = estimate_noise(_mosaic(self.measured), np.nan_to_num(_mosaic(groups)).astype(int))
        self.single_precision_error = None
        if renderer is None:
            self._prefer_single(light)
        if screen_window_px and rows * cols > 2 * screen_window_px ** 2:
            self.screening = self._crop(light.sum(axis=(0, 1)), screen_window_px)

    def _prefer_single(self, light):
        """Render the model in single precision if the ideal model's largest error in it (light
        per pixel, against the double-precision ``light``) is below a hundredth of the noise floor.
        The single-precision renderer keeps the ideal channels it rendered for the comparison."""
        single = PsfRenderer(self.camera, self.pitch_m, self.height_m.shape, self.material, self.doe_oversample,
                             precision="single", device=self.device)
        ideal = single(self.height_m, self.wavelengths_m, self.depth_m)
        self.single_precision_error = float(np.abs(ideal / ideal.sum(axis=(-2, -1), keepdims=True) - light).max())
        if self.single_precision_error < SINGLE_PRECISION_NOISE_FRACTION * self.noise.sigma:
            self.render = single
        log.info("model in %s precision: single-precision error %.2g, noise floor %.3g", self.render.precision,
                 self.single_precision_error, self.noise.sigma)

    def _crop(self, light, size_px):
        """The same problem on the ``size_px`` square of the window holding the most ideal light:
        candidates are screened there, where each model evaluation costs a fraction."""
        h, w = min(size_px, light.shape[0]), min(size_px, light.shape[1])
        sums = window_sums(light, h, w)
        r0, c0 = (int(v) for v in np.unravel_index(np.argmax(sums), sums.shape))
        camera = dataclasses.replace(self.camera, window_shape=(h, w),
                                     axis_pixel=(self.axis_pixel[0] - r0, self.axis_pixel[1] - c0))
        log.info("candidates screened on the %d x %d window at (%d, %d)", h, w, r0, c0)
        # Single precision there: a few 1e-7 of the peak, far below any measured noise.
        render = PsfRenderer(camera, self.pitch_m, self.height_m.shape, self.material, self.doe_oversample,
                             precision="single", device=self.device)
        return PsfProblem(self.height_m, self.pitch_m, camera, self.measured[..., r0:r0 + h, c0:c0 + w], self.views,
                          self.wavelengths_m, self.depth_m, self._effect_list, self.material, self.doe_oversample,
                          renderer=render, noise=self.noise, device=self.device)

    def stack(self, model: dict[str, np.ndarray]) -> np.ndarray:
        return psf_forward(model, self.effects, self.render, self.height_m, self.wavelengths_m, self.depth_m,
                           self.views)

    def _residual_stack(self, model):
        # The measured channel sums carry noise and light outside the window: a free scale per
        # channel (least squares, closed form) is profiled out, like the piston for heights.
        p = np.where(self.valid, self.stack(model), 0.0)
        m = np.where(self.valid, self.measured, 0.0)
        scale = (m * p).sum(axis=(-2, -1), keepdims=True) / (p * p).sum(axis=(-2, -1), keepdims=True)
        return np.where(self.valid, m - scale * p, np.nan)

    def residual(self, model: dict[str, np.ndarray]) -> np.ndarray:
        return self._residual_stack(model)[self.valid]

    def residual_map(self, model: dict[str, np.ndarray]) -> np.ndarray:
        return _mosaic(self._residual_stack(model))

    def _radius(self):
        rows, cols = self.measured.shape[-2:]
        yy, xx = np.mgrid[:rows, :cols]
        return np.hypot(yy - self.axis_pixel[0], xx - self.axis_pixel[1])

    def structure_groups(self) -> list[np.ndarray]:
        """Radial rings about the axis per channel, and 8 x 8 pixel tiles per channel."""
        rows, cols = self.measured.shape[-2:]
        ring = np.minimum(self._radius() // 3, 40).astype(int)
        tiles = (np.arange(rows)[:, None] // 8) * ((cols + 7) // 8) + np.arange(cols)[None, :] // 8
        nch = len(self.channels)
        out = []
        for m in (ring, tiles):
            stack = np.broadcast_to(m, self.measured.shape).reshape(nch, rows, cols)
            labelled = stack + (np.arange(nch)[:, None, None] * (int(m.max()) + 1)) + 1
            out.append(np.nan_to_num(_mosaic(labelled.reshape(self.measured.shape))).astype(int))
        return out

    def breakdown(self, residual_map: np.ndarray) -> dict[str, dict]:
        """Residual by radius from the axis (pixels), by channel, and by spatial frequency."""
        nch = len(self.channels)
        rows, cols = self.measured.shape[-2:]
        r = np.full((nch, rows + 1, cols), np.nan)
        r.reshape(-1, cols)[:residual_map.shape[0]] = residual_map
        r = r[:, :rows]
        radius = np.broadcast_to(self._radius(), r.shape)
        out: dict[str, dict] = {"radius_from_axis_px": binned(r, radius, np.linspace(0, radius.max() + 1e-9, 13)),
               "channel_rms": {c: float(np.sqrt(np.nanmean(r[i] ** 2))) for i, c in enumerate(self.channels)},
               "channel_mean": {c: float(np.nanmean(r[i])) for i, c in enumerate(self.channels)}}
        out["spatial_frequency_per_px"] = radial_psd(np.nanmean(r, axis=0), 1.0)
        return out


def diagnose_psf(design: Design, camera: Camera, measured_stack: np.ndarray,
                 wavelengths_m: Sequence[float] | np.ndarray, views: Sequence[str] = ("coded",),
                 depth_m: float | None = None, candidates: Sequence[str] | None = None,
                 threshold: float = DEFAULT_THRESHOLD, max_steps: int = 5, doe_oversample: int = 1,
                 device: str = "cpu", limit: Deadline | None = None) -> Diagnosis:
    """Find, name and fit the effects that explain a measured PSF stack.

    Parameters
    ----------
    design : Design
        The element (its height map, pitch and material).
    camera : Camera
        Geometry of the measurement (window, axis pixel, DOE side).
    measured_stack : ndarray (views, wavelengths, rows, cols) or (wavelengths, rows, cols)
        Measured PSFs in any units, row 0 at the top, the axis at ``camera.axis_pixel``;
        a 3-D stack is one view (``views[0]``).
    wavelengths_m : sequence of float
    views : sequence of str
        Which views the stack holds, from ``("coded", "uncoded")``.
    depth_m : float, optional
        Point-source distance; default where the camera is focused.
    candidates : list of str, optional
        Effects to try (default every registered PSF-domain effect).
    device : {"cpu", "gpu", "auto"}
        Where the model's PSFs are rendered (:mod:`doedesign.engine.backend`).
    limit : Deadline, optional
        A limit the user asked for (:func:`~metrology.diagnosis.engine.run_diagnosis`; default none).

    Returns
    -------
    Diagnosis
    """
    stack = np.asarray(measured_stack, dtype=float)
    if stack.ndim == 3:
        stack = stack[None]
    if stack.ndim != 4:
        raise DoeError(f"measured PSF stack must be (views, wavelengths, rows, cols), got shape {stack.shape}")
    if len(views) != stack.shape[0] or any(v not in ("coded", "uncoded") for v in views):
        raise DoeError(f"views {tuple(views)} do not match a stack of {stack.shape[0]} view(s)")
    depth = camera.focus_distance_m if depth_m is None else float(depth_m)
    # The element the masks print from the design (a heights-only design as doe masks levels it).
    problem = PsfProblem(printed_height_m(design), design.pitch_m, camera, stack, views, wavelengths_m, depth,
                         effects_for("psf", candidates), material=design.material, doe_oversample=doe_oversample,
                         device=device)
    return run_diagnosis(problem, threshold=threshold, max_steps=max_steps, domain="psf", limit=limit)
