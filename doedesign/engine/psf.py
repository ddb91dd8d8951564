"""Split-aperture PSFs: exact pixel-integrated intensity from a pixelated DOE.

Model
-----
The DOE is piecewise constant on its pixel grid (pitch ``p``; ``p/q`` with ``doe_oversample=q``).
Behind an ideal lens the sensor field is the Fraunhofer transform of the pupil
``t = A exp(i (phi_DOE + W_defocus))``, where ``A`` is the fraction of each pupil sample inside
the view's half-aperture and ``W`` the exact spherical-wave defocus
``k [(sqrt(r^2 + d^2) - d) - (sqrt(r^2 + d0^2) - d0)]`` of a point at ``d`` seen by a lens
focused at ``d0``. For a piecewise-constant pupil the intensity at sensor position ``x`` is
exactly

    I(x) = p^4 / (lambda z)^2 * sinc^2(p x / lambda z) * sum_k C_k exp(-2 pi i k p x / (lambda z)),

with ``C`` the discrete autocorrelation of ``t`` (lags ``k``). The sensor-pixel integral of
each term separates per axis into a 1-D integral of envelope times fringe, computed by
Gauss-Legendre quadrature. So the PSF is exact at the sensor pixels with no sensor-side
oversampling, aliasing-free (the envelope carries the light into higher zones correctly),
and normalized to all the light through the view's half-aperture: ``energy_in_window`` is
what the window holds, nothing is renormalized.

Cost per view and wavelength: one FFT autocorrelation on a (2N)^2 grid and a matrix
Fourier transform from the lag grid to the window's pixel centres (Hermitian half only); those
transforms live in :mod:`doedesign.engine.lags`, the result container in :mod:`doedesign.engine.result`
(re-exported here).
"""

from __future__ import annotations

import contextlib
import itertools
import logging
import os
import threading
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike
from threadpoolctl import threadpool_limits

from ..camera import DEFAULT_SURROUND, Camera, check_surround
from ..errors import DoeError, SamplingError
from ..materials import get_material
from . import adjoint
from .backend import Array, Backend, select_backend
from .lags import axis_kernel, axis_nodes, folded_psf, paired_lags
from .result import MAX_WAVELENGTHS, VIEWS, PSFResult, parse_wavelengths_nm, read_psf_arrays

if TYPE_CHECKING:
    from ..design import Design
    from ..materials import Material
    from ..progress import Progress

__all__ = ["DEFAULT_THREADS", "DEVICE_KERNEL_CACHE_SIZE", "KERNEL_CACHE_SIZE", "MAX_DEFOCUS_STEP_RAD", "MAX_WAVELENGTHS",
           "PSFEngine", "PSFResult", "VIEWS", "WARN_DEFOCUS_STEP_RAD", "compute_psf", "parse_wavelengths_nm",
           "read_psf_arrays"]

log = logging.getLogger(__name__)

# Wavelengths computed side by side by default where the caller is the only work (``doe psf``):
# the cores, at most 4 (each thread holds one wavelength's transforms).
DEFAULT_THREADS = max(1, min(4, len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity")
                             else os.cpu_count() or 1))
# Kernel pairs kept per engine (each about 26 MB for the seed camera): enough for an
# optimization over a few wavelengths, bounded for 31-band stacks in host memory. A GPU keeps
# a whole 31-band stack's (both views, both precisions) in under 4 GB of its memory.
KERNEL_CACHE_SIZE = 8
DEVICE_KERNEL_CACHE_SIZE = 128
# Largest defocus phase step (rad) between adjacent pupil samples before the piecewise-constant
# sampling of the smooth spherical term is refused, and before it is warned about.
MAX_DEFOCUS_STEP_RAD = np.pi / 2
WARN_DEFOCUS_STEP_RAD = np.pi / 4


class PSFEngine:
    """PSFs and their height gradient for one camera, DOE grid and set of wavelengths and depths.

    Parameters
    ----------
    camera : Camera
    pitch_m : float
        DOE pixel pitch.
    shape : (int, int)
        Shape of the design's height map (centred on the axis inside the aperture grid).
    material : str or Material
    wavelengths_m : sequence of float
    depths_m : sequence of float, optional
        Point-source distances; ``inf`` is optical infinity (defocused unless the camera is
        focused at infinity). Default: the camera's focus distance (in focus).
    doe_oversample : int
        Pupil samples per DOE pixel per axis, for sampling the smooth defocus term finely;
        the DOE profile itself is piecewise constant and exact at any value.
    precision : {"double", "single"}
        Arithmetic of :meth:`psf`'s transforms. "single" (complex64) is about twice as fast for
        long wavelength stacks, at a few 1e-7 of the peak (benchmarks/bench_psf.py measures
        it); gradients are always computed in double precision.
    lag_cache : dict, optional
        Where the autocorrelation lags of the uncoded view in focus are kept. Its pupil has no
        phase, so its lags do not depend on the wavelength: engines of one camera, pitch, shape
        and ``doe_oversample`` that pass the same dict compute them once between them.
    aperture : bool array, shape ``shape``, optional
        The element's clear region (a design's ``aperture``: False where its chrome blocks the
        light). It masks the coded view's pupil samples over the design; PSFs stay fractions of
        the light through the unobstructed half-aperture, so blocked light is lost light.
    surround : {"open", "opaque", "repeat"}
        What the coded view's half-aperture holds around the design
        (:data:`doedesign.camera.SURROUNDS`): open glass (default), chrome, or the design (heights and
        ``aperture``) tiled with the central tile on the design. The uncoded view is the bare
        lens either way.
    device : {"cpu", "gpu", "auto"} or Backend
        Where the transforms run (:mod:`doedesign.engine.backend`): the same functions on NumPy
        or CuPy. Heights go in and PSFs and gradients come out as NumPy arrays either way.
    """

    def __init__(self, camera: Camera, pitch_m: float, shape: tuple[int, int],
                 material: str | Material = "fused_silica", wavelengths_m: ArrayLike = (550e-9,),
                 depths_m: ArrayLike | None = None, doe_oversample: int = 1, precision: str = "double",
                 lag_cache: dict | None = None, aperture: ArrayLike | None = None,
                 device: str | Backend = "cpu", surround: str = DEFAULT_SURROUND) -> None:
        if not (np.isfinite(pitch_m) and pitch_m > 0):
            raise DoeError(f"DOE pitch must be positive, got {pitch_m}")
        self.backend = select_backend(device)
        self.xp = self.backend.xp
        self.camera = camera
        self.pitch_m = float(pitch_m)
        self.shape: tuple[int, int] = (int(shape[0]), int(shape[1]))
        self.material = get_material(material)
        self.wavelengths_m = np.atleast_1d(np.asarray(wavelengths_m, dtype=float))
        if depths_m is None:
            depths_m = (camera.focus_distance_m,)
        self.depths_m = np.atleast_1d(np.asarray(depths_m, dtype=float))
        if self.wavelengths_m.size == 0:
            raise DoeError("no wavelengths given")
        if np.any(self.depths_m <= 0) or np.any(np.isnan(self.depths_m)):
            raise DoeError(f"point-source distances must be positive, got {self.depths_m}")
        self.material.n(self.wavelengths_m)  # raises for wavelengths outside the material's range
        if precision not in ("double", "single"):
            raise DoeError(f"precision must be 'double' or 'single', got {precision!r}")
        self.precision = precision
        self.q = int(doe_oversample)
        if self.q < 1:
            raise DoeError("doe_oversample must be a positive integer")
        self.surround = check_surround(surround)
        self.grid_shape = camera.pupil_grid_shape(self.shape, self.pitch_m)
        self.step_m = self.pitch_m / self.q
        weights = camera.view_weights(self.grid_shape, self.pitch_m, self.q)
        # Offsets of the design inside the pupil grid (design centred on the axis).
        self._offset = ((self.grid_shape[0] - self.shape[0]) // 2, (self.grid_shape[1] - self.shape[1]) // 2)
        # Light is counted against the unobstructed half-aperture, before the element's chrome.
        unobstructed = {name: float(np.sum(weights[i] ** 2)) for i, name in enumerate(VIEWS)}
        clear = weights
        if aperture is not None or self.surround != "open":
            clear = np.array(weights)
            clear[0] *= self._aperture_mask(aperture)
        # The share of the coded view's light its clear region passes (1 for a bare lens).
        self.clear_fraction = float(np.sum(clear[0] ** 2)) / unobstructed["coded"]
        self._views = {}
        for i, name in enumerate(VIEWS):
            amp = weights[i]
            rows = np.flatnonzero(amp.any(axis=1))
            cols = np.flatnonzero(amp.any(axis=0))
            if rows.size == 0:
                raise DoeError(f"the {name} view has no clear aperture")
            box = (rows[0], rows[-1] + 1, cols[0], cols[-1] + 1)
            self._views[name] = (box, clear[i, box[0]:box[1], box[2]:box[3]])
        self._energy = unobstructed
        self._opd = {float(d): self._defocus_opd(d) for d in self.depths_m}
        # The same amplitudes and defocus paths on the backend's device, copied once.
        self._amp_dev = {name: self.backend.asarray(amp) for name, (_, amp) in self._views.items()}
        self._opd_dev = {d: None if opd is None else self.backend.asarray(opd) for d, opd in self._opd.items()}
        self.sampling = self._check_sampling()
        self._uncoded_cache: dict[tuple, Array] = {}
        self._kernel_cache: dict[tuple, tuple] = {}
        self._cache_lock = threading.Lock()  # psf(threads > 1) fills the kernel cache from threads
        self._lag_cache = {} if lag_cache is None else lag_cache
        self._work: dict = {}
        # (host mask, its backend copy) of value_and_grad_free
        self._free: tuple[np.ndarray, Array] | None = None

    # -- geometry -----------------------------------------------------------------------------
    def _aperture_mask(self, aperture):
        """The element's clear region on the pupil samples, its surround by :attr:`surround`."""
        ap = np.ones(self.shape, dtype=bool) if aperture is None else np.asarray(aperture)
        if ap.shape != self.shape or ap.dtype != bool:
            raise DoeError(f"aperture must be a boolean array of the design's shape {self.shape}, "
                           f"got {ap.dtype} {ap.shape}")
        q, (oy, ox) = self.q, self._offset
        if self.surround == "repeat":
            grid = self._tiled(ap, np)
        else:
            grid = np.full(self.grid_shape, self.surround == "open")
            grid[oy:oy + self.shape[0], ox:ox + self.shape[1]] = ap
        return np.repeat(np.repeat(grid.astype(float), q, 0), q, 1)

    def _tiles(self):
        """Tile counts and the start of the grid in the tiled map (the central tile on the design)."""
        (g0, g1), (n0, n1), (oy, ox) = self.grid_shape, self.shape, self._offset
        s0, s1 = (-oy) % n0, (-ox) % n1
        return (-(-(g0 + s0) // n0), -(-(g1 + s1) // n1)), (s0, s1)

    def _tiled(self, values, xp):
        """``values`` (design shape) repeated over the pupil grid, design pixel (0, 0) at the offset."""
        (r0, r1), (s0, s1) = self._tiles()
        g0, g1 = self.grid_shape
        return xp.tile(values, (r0, r1))[s0:s0 + g0, s1:s1 + g1]

    def _sample_radius2(self):
        rows, cols = self.grid_shape[0] * self.q, self.grid_shape[1] * self.q
        y = (np.arange(rows) - (rows - 1) / 2) * self.step_m
        x = (np.arange(cols) - (cols - 1) / 2) * self.step_m
        return y[:, None] ** 2 + x[None, :] ** 2

    def _defocus_opd(self, depth_m):
        """Optical path difference (m) of a point at ``depth_m`` against the focused one."""
        r2 = self._sample_radius2()
        d0 = self.camera.focus_distance_m

        def sag(d):
            if np.isinf(d):
                return np.zeros_like(r2)
            # sqrt(r^2 + d^2) - d, written to avoid cancellation for r << d.
            return r2 / (np.sqrt(r2 + d * d) + d)

        opd = sag(depth_m) - sag(d0)
        return opd if np.any(opd) else None

    def _check_sampling(self):
        z, a = self.camera.sensor_distance_m, self.camera.pixel_pitch_m
        wl_min = float(self.wavelengths_m.min())
        report = {
            "doe_oversample": self.q,
            "pupil_step_m": self.step_m,
            "zones_in_window": float(max(self.camera.window_shape) * a * self.step_m / (wl_min * z)),
            "max_defocus_step_rad": 0.0,
        }
        for d, opd in self._opd.items():
            if opd is None:
                continue
            gy, gx = np.gradient(opd, self.step_m)
            grad = np.sqrt(gx ** 2 + gy ** 2)
            clear = self.camera.view_weights(self.grid_shape, self.pitch_m, self.q).max(axis=0) > 0
            step = float(2 * np.pi / wl_min * grad[clear].max() * self.step_m)
            report["max_defocus_step_rad"] = max(report["max_defocus_step_rad"], step)
            if step > MAX_DEFOCUS_STEP_RAD:
                need = int(np.ceil(self.q * step / WARN_DEFOCUS_STEP_RAD))
                raise SamplingError(
                    f"defocus for a source at {d:g} m changes the phase by {step:.2f} rad between pupil samples "
                    f"of {self.step_m * 1e6:.2f} um at {wl_min * 1e9:.0f} nm (limit {MAX_DEFOCUS_STEP_RAD:.2f} rad): "
                    f"this would alias; use doe_oversample >= {need}")
            if step > WARN_DEFOCUS_STEP_RAD:
                log.warning("defocus phase step %.2f rad per pupil sample (source at %g m); "
                            "consider doe_oversample=%d", step, d, self.q * 2)
        return report

    # -- pupil and transforms ------------------------------------------------------------------
    def _pupil(self, view, height_m, wavelength, depth):
        """Complex pupil samples of a view inside its bounding box (``height_m`` on the device)."""
        xp = self.xp
        (r0, r1, c0, c1), _ = self._views[view]
        amp = self._amp_dev[view]
        phase = xp.zeros(amp.shape, dtype=xp.float64)
        if view == "coded":
            q, (oy, ox), shape = self.q, self._offset, self.shape
            if self.surround == "repeat":
                height_m, (oy, ox), shape = self._tiled(height_m, xp), (0, 0), self.grid_shape
            # Design pixels covering the box (the grid around the design is unetched, height 0).
            d0, d1 = max(r0 // q - oy, 0), min(-(-r1 // q) - oy, shape[0])
            e0, e1 = max(c0 // q - ox, 0), min(-(-c1 // q) - ox, shape[1])
            part = height_m[d0:d1, e0:e1]
            if q > 1:
                part = xp.repeat(xp.repeat(part, q, axis=0), q, axis=1)
            y0, x0 = (d0 + oy) * q - r0, (e0 + ox) * q - c0
            sy = slice(max(y0, 0), min(y0 + part.shape[0], r1 - r0))
            sx = slice(max(x0, 0), min(x0 + part.shape[1], c1 - c0))
            # The phase is linear in the height: the material's phase per metre at this wavelength.
            phase[sy, sx] = self._phase_per_m(wavelength) * part[sy.start - y0:sy.stop - y0,
                                                                 sx.start - x0:sx.stop - x0]
        opd = self._opd_dev[float(depth)]
        if opd is not None:
            phase += float(2 * np.pi / wavelength) * opd[r0:r1, c0:c1]
        return amp * xp.exp(1j * xp.astype(phase, xp.complex128))

    def _phase_per_m(self, wavelength):
        return float(self.material.phase(1.0, wavelength))

    def _kernels(self, view, wavelength):
        """Kernels from autocorrelation lags to pixel-integrated intensity, per axis.

        ``K[j, k] = integral over sensor pixel j of sinc^2(p x / lambda z) exp(-2 pi i k p x / lambda z) dx``
        by Gauss-Legendre quadrature, exact for the piecewise-constant pupil. Row kernels hold
        lags ky >= 0 with the Hermitian fold (factor 2 for ky > 0).
        """
        (r0, r1, c0, c1), _ = self._views[view]
        # The kernels depend on the box's size only: views of equal width share them.
        key = (r1 - r0, c1 - c0, float(wavelength))
        found = self._kernel_cache.get(key)
        if found is not None:
            return found
        cam = self.camera
        lz = wavelength * cam.sensor_distance_m
        ky = np.arange(r1 - r0)
        kx = np.arange(-(c1 - c0 - 1), c1 - c0)
        kern_y = self._axis_kernel(cam.window_shape[0], cam.axis_pixel[0], ky, lz)
        kern_y[:, 1:] *= 2.0
        kern_x = self._axis_kernel(cam.window_shape[1], cam.axis_pixel[1], kx, lz)
        out = (kern_y, kern_x, float(self.step_m ** 2 / lz ** 2))
        self._cache_put(key, out)
        return out


    def _axis_nodes(self, n_pix, axis, max_lag, lz):
        return axis_nodes(n_pix, axis, self.camera.pixel_pitch_m, max_lag, self.step_m / lz)

    def _axis_kernel(self, n_pix, axis, lags, lz):
        return axis_kernel(n_pix, axis, self.camera.pixel_pitch_m, lags, self.step_m / lz, self.xp)

    def _forward_kernels(self, view, wavelength, dtype):
        """Real and imaginary parts of the per-axis kernels for :meth:`_view_psf`'s folded transform.

        Rows: lags ky = 0..a-1 (the ky = 0 column halved, as the +-ky pairing counts it twice);
        columns: lags kx = 0..b-1 with the Hermitian fold (factor 2 for kx > 0).
        """
        (r0, r1, c0, c1), _ = self._views[view]
        key = ("forward", r1 - r0, c1 - c0, float(wavelength), np.dtype(dtype).str)
        found = self._kernel_cache.get(key)
        if found is not None:
            return found
        cam = self.camera
        lz = wavelength * cam.sensor_distance_m
        kern_y = self._axis_kernel(cam.window_shape[0], cam.axis_pixel[0], np.arange(r1 - r0), lz)
        kern_y[:, 0] *= 0.5
        kern_x = self._axis_kernel(cam.window_shape[1], cam.axis_pixel[1], np.arange(c1 - c0), lz)
        kern_x[:, 1:] *= 2.0
        xp = self.xp
        dtype = xp.float32 if np.dtype(dtype) == np.float32 else xp.float64
        out = tuple(xp.asarray(xp.astype(part, dtype), copy=True)
                    for part in (xp.real(kern_y), xp.imag(kern_y), xp.real(kern_x).T, xp.imag(kern_x).T))
        self._cache_put(key, out)
        return out

    def _cache_put(self, key, value):
        """Keep ``value`` in the kernel cache, the oldest entry out beyond ``KERNEL_CACHE_SIZE``."""
        with self._cache_lock:
            while len(self._kernel_cache) >= (KERNEL_CACHE_SIZE if self.backend.is_numpy else DEVICE_KERNEL_CACHE_SIZE):
                self._kernel_cache.pop(next(iter(self._kernel_cache)))
            self._kernel_cache[key] = value


    def _view_psf(self, view, height_m, wavelength, depth, precision="double", fft_workers=None):
        """Pixel-integrated PSF of one view; in the folded form of :func:`~doedesign.engine.lags.paired_lags`.

        ``I = Re(Z K_x^T)`` with ``Z = Re K_y S + i Im K_y D`` (lags kx >= 0, Hermitian fold in
        ``K_x``): six real matrix products, about half the work of the complex lag transform.
        The lags of a pupil that does not depend on the wavelength (the uncoded view in focus)
        are reused across wavelengths.
        """
        dtype = np.float32 if precision == "single" else np.float64
        key = ("lags", view, float(depth), np.dtype(dtype).str)
        lags = self._lag_cache.get(key)
        if lags is None:
            t = self._pupil(view, height_m, wavelength, depth)
            energy = self._energy[view]  # a phase does not change it
            if precision == "single":
                t = self.xp.astype(t, self.xp.complex64)
            lags = paired_lags(t, self.backend, fft_workers) + (energy,)
            if view == "uncoded" and self._opd[float(depth)] is None:
                self._lag_cache[key] = lags
        s, d, n_fft, energy = lags
        kernels = self._forward_kernels(view, wavelength, dtype)
        lz = wavelength * self.camera.sensor_distance_m
        scale = float(self.step_m ** 2 / lz ** 2 / energy / n_fft)
        return self.xp.astype(folded_psf(s, d, kernels), self.xp.float64) * scale

    # -- public API ----------------------------------------------------------------------------
    def _check_height(self, height_m):
        if not self.backend.is_numpy:
            # Checked on the device after the one copy there (or where a process render left it):
            # a reduction and one scalar back, not a pass over the map on the host.
            xp = self.xp
            h = xp.astype(self.backend.asarray(height_m), xp.float64, copy=False)
            if tuple(h.shape) != self.shape:
                raise DoeError(f"height map has shape {tuple(h.shape)}, the engine was built for {self.shape}")
            bad = int(xp.sum(xp.astype(~xp.isfinite(h), xp.int64)))
            if bad:
                raise DoeError(f"height map holds {bad} NaN or infinite values")
            return h
        h = np.asarray(height_m, dtype=float)
        if h.shape != self.shape:
            raise DoeError(f"height map has shape {h.shape}, the engine was built for {self.shape}")
        if not np.all(np.isfinite(h)):
            raise DoeError(f"height map holds {np.count_nonzero(~np.isfinite(h))} NaN or infinite values")
        return h

    def psf(self, height_m: ArrayLike, views: Sequence[str] = VIEWS, progress: Progress | None = None,
            threads: int = 1) -> PSFResult:
        """PSFs of the requested views for every depth and wavelength (see :class:`~doedesign.engine.result.PSFResult`).

        ``threads`` > 1 computes that many wavelengths side by side, each with one FFT and one
        BLAS thread (the transforms release the GIL), for the same result; each thread holds one
        wavelength's transforms (about 0.3 GB for a 1600 px element in double precision). On a
        GPU the wavelengths run one after another (the device is busy with one).
        """
        out = self.psf_stack(height_m, views, progress, threads)
        return PSFResult(psf=self.backend.to_host(out), views=tuple(views), wavelengths_m=self.wavelengths_m.copy(),
                         depths_m=self.depths_m.copy(), pixel_pitch_m=self.camera.pixel_pitch_m,
                         axis_pixel=self.camera.axis_pixel, sampling=dict(self.sampling), surround=self.surround,
                         coded_clear_fraction=self.clear_fraction)

    def psf_stack(self, height_m: ArrayLike, views: Sequence[str] = VIEWS, progress: Progress | None = None,
                  threads: int = 1) -> Array:
        """The PSF stack of :meth:`psf` (views, depths, wavelengths, rows, cols) left where it was
        computed: an array of the engine's backend, for a caller that reduces it there (the
        tolerance metrics). ``height_m`` may be a host array or one of the backend's."""
        h = self._check_height(height_m)
        if not self.backend.is_numpy:
            threads = 1
        for v in views:
            if v not in VIEWS:
                raise DoeError(f"unknown view {v!r}; views are {VIEWS}")
        rows, cols = self.camera.window_shape
        # Planes are written where the engine computes and cross to the host once, at the end.
        out = self.xp.empty((len(views), self.depths_m.size, self.wavelengths_m.size, rows, cols),
                            dtype=self.xp.float64)
        tasks = [(di, wi) for di in range(self.depths_m.size) for wi in range(self.wavelengths_m.size)]

        # Wavelengths side by side take one FFT thread each; one at a time, the backend's threads.
        fft_workers = 1 if threads > 1 else None

        def channel(task):
            # Views innermost: both use the same wavelength's kernels while they are cached.
            di, wi = task
            depth, wl = self.depths_m[di], self.wavelengths_m[wi]
            for vi, view in enumerate(views):
                if view == "uncoded":
                    key = (float(depth), float(wl), self.precision)
                    if key not in self._uncoded_cache:
                        self._uncoded_cache[key] = self._view_psf(view, h, wl, depth, self.precision, fft_workers)
                    out[vi, di, wi, ...] = self._uncoded_cache[key]
                else:
                    out[vi, di, wi, ...] = self._view_psf(view, h, wl, depth, self.precision, fft_workers)
            return len(views)

        # The first channel alone: it fills the lag cache the others may share. Threads are
        # started only when asked for (a pool's threads start on its first task).
        blas = threadpool_limits(limits=1, user_api="blas") if threads > 1 else contextlib.nullcontext()
        with blas, ThreadPoolExecutor(max(1, threads)) as pool:
            mapper = pool.map if threads > 1 else map
            for n in itertools.chain([channel(tasks[0])], mapper(channel, tasks[1:])):
                if progress is not None:
                    progress.update(n)
        return out

    def value_and_grad(self, height_m: ArrayLike, loss_fn: Callable[[np.ndarray], tuple[float, ArrayLike]],
                       full_window: bool = False, host: bool = True) -> tuple[float, np.ndarray]:
        """Loss of the coded PSF and its exact (adjoint) gradient with respect to the heights.

        A loss with a ``reads`` attribute (:class:`doedesign.optimizer.losses.PixelReads`, as
        :func:`doedesign.optimizer.losses.make_loss` sets for losses of a few pixels and the window
        energy) is evaluated from those pixels alone (:mod:`doedesign.engine.reads`), unless
        ``full_window`` asks for the whole window; both give the same loss and gradient.

        Parameters
        ----------
        height_m : ndarray, shape ``self.shape``
        loss_fn : callable
            ``loss_fn(psf)`` with ``psf`` shaped (depths, wavelengths, rows, cols); returns
            ``(loss, dloss_dpsf)`` with the derivative shaped like ``psf``.
        full_window : bool
            Compute the whole window even when the loss reads only a few pixels.
        host : bool
            Return the gradient as a NumPy array (else as an array of the engine's backend).

        Returns
        -------
        loss : float
        grad : ndarray, shape ``self.shape``, d loss / d height (per metre).
        """
        return adjoint.value_and_grad(self, height_m, loss_fn, full_window, host)

    def value_and_grad_free(self, x: ArrayLike, free: np.ndarray,
                            loss_fn: Callable[[np.ndarray], tuple[float, ArrayLike]],
                            full_window: bool = False) -> tuple[float, Array]:
        """:meth:`value_and_grad` of the map that holds ``x`` on ``free`` and zero elsewhere, with
        the gradient on ``free`` only, as a vector of the engine's backend.

        For a design loop whose free heights live on the host (nlopt's): only that vector goes to
        the device and only its gradient comes back; the map is assembled, and the gradient
        gathered, where the engine computes. ``free`` is a boolean mask shaped like the map (kept
        on the device for as long as the same mask is passed); ``x`` a host or backend vector.
        """
        return adjoint.value_and_grad_free(self, x, free, loss_fn, full_window)


def compute_psf(design: Design, camera: Camera | None = None, wavelengths_m: ArrayLike = (486e-9, 589e-9, 656e-9),
                depths_m: ArrayLike | None = None, doe_oversample: int = 1, views: Sequence[str] = VIEWS,
                progress: Progress | None = None, threads: int = 1, surround: str | None = None) -> PSFResult:
    """PSFs of a :class:`~doedesign.design.Design` through ``camera`` (default: the seed camera);
    ``threads`` wavelengths side by side (:meth:`PSFEngine.psf`); ``surround`` (default: the
    design file's, else open) as :func:`doedesign.camera.resolve_surround` decides."""
    from ..camera import resolve_surround

    camera = camera or Camera()
    engine = PSFEngine(camera, design.pitch_m, design.shape, design.material, wavelengths_m, depths_m,
                       doe_oversample, aperture=design.aperture,
                       surround=resolve_surround(surround, design.metadata, design.source_path or design.name)[0])
    return engine.psf(design.height_m, views=views, progress=progress, threads=threads)
