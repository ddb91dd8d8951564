"""The adjoint half of :class:`~doedesign.engine.psf.PSFEngine`: a loss of the coded PSF and its exact
gradient with respect to the heights.

The forward model (:mod:`doedesign.engine.psf`) keeps the pupil and the lag kernels of each
channel; the gradient runs them backwards: d loss / d PSF through the matrix Fourier transforms to
d loss / d autocorrelation lag, then through the autocorrelation to the pupil's phase
(:func:`doedesign.engine.lags.phase_gradient`) and to the heights on the design grid. A loss of a
few pixels and the window energy takes the sparse path of :mod:`doedesign.engine.reads`. These are
functions of an engine; the engine's methods of the same names call them.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike

from ..errors import DoeError
from .backend import Array
from .lags import phase_gradient
from .reads import apply_energy_operator, read_axis, read_pixels, read_pixels_adjoint

if TYPE_CHECKING:
    from .psf import PSFEngine

__all__ = ["value_and_grad", "value_and_grad_free"]


def value_and_grad(engine: PSFEngine, height_m: ArrayLike, loss_fn: Callable[[np.ndarray], tuple[float, ArrayLike]],
                   full_window: bool = False, host: bool = True) -> tuple[float, np.ndarray]:
    """:meth:`doedesign.engine.psf.PSFEngine.value_and_grad` of ``engine`` (its docstring gives the arguments)."""
    h = engine._check_height(height_m)
    reads = getattr(loss_fn, "reads", None)
    if reads is not None and not full_window:
        value, grad = _value_and_grad_reads(engine, h, loss_fn, reads)
        return value, engine.backend.to_host(grad) if host else grad
    nd, nw = engine.depths_m.size, engine.wavelengths_m.size
    xp = engine.xp
    psf = np.empty((nd, nw) + engine.camera.window_shape)
    saved = {}
    for di, depth in enumerate(engine.depths_m):
        for wi, wl in enumerate(engine.wavelengths_m):
            psf[di, wi] = engine.backend.to_host(engine._view_psf("coded", h, wl, depth))
            t = engine._pupil("coded", h, wl, depth)
            kern_y, kern_x, const = engine._kernels("coded", wl)
            saved[di, wi] = (t, kern_y, kern_x, const / engine._energy["coded"])
    loss, dpsf = loss_fn(psf)
    dpsf = np.asarray(dpsf, dtype=float)
    if dpsf.shape != psf.shape:
        raise DoeError(f"loss gradient has shape {dpsf.shape}, expected {psf.shape}")
    (r0, r1, c0, c1), _ = engine._views["coded"]
    grad_pupil = xp.zeros((r1 - r0, c1 - c0), dtype=xp.float64)
    for (di, wi), (t, kern_y, kern_x, scale) in saved.items():
        wl = engine.wavelengths_m[wi]
        # dL/dC_k for lags with ky >= 0 (the fold factor 2 of ky > 0 splits over +-ky).
        d_half = scale * (kern_y.T @ xp.astype(engine.backend.asarray(dpsf[di, wi]), xp.complex128) @ kern_x)
        d_half[1:, ...] *= 0.5
        grad_pupil += engine._phase_per_m(wl) * phase_gradient(t, d_half, engine.backend)
    grad = _height_gradient(engine, grad_pupil)
    return float(loss), engine.backend.to_host(grad) if host else grad


def value_and_grad_free(engine: PSFEngine, x: ArrayLike, free: np.ndarray,
                        loss_fn: Callable[[np.ndarray], tuple[float, ArrayLike]],
                        full_window: bool = False) -> tuple[float, Array]:
    """:meth:`doedesign.engine.psf.PSFEngine.value_and_grad_free` of ``engine``."""
    xp = engine.xp
    if engine._free is None or engine._free[0] is not free:
        engine._free = (free, engine.backend.asarray(np.asarray(free, dtype=bool)))
    mask = engine._free[1]
    h = xp.zeros(engine.shape, dtype=xp.float64)
    h[mask] = xp.astype(engine.backend.asarray(x), xp.float64)
    value, grad = value_and_grad(engine, h, loss_fn, full_window, host=False)
    return value, grad[mask]


def _height_gradient(engine: PSFEngine, grad_pupil):
    """d loss / d height on the design grid (a backend array) from d loss / d height on the coded
    view's samples."""
    xp = engine.xp
    (r0, r1, c0, c1), _ = engine._views["coded"]
    grad = xp.zeros((engine.grid_shape[0] * engine.q, engine.grid_shape[1] * engine.q), dtype=xp.float64)
    grad[r0:r1, c0:c1] = grad_pupil
    if engine.q > 1:
        grad = xp.sum(xp.reshape(grad, (engine.grid_shape[0], engine.q, engine.grid_shape[1], engine.q)), axis=(1, 3))
    if engine.surround == "repeat":  # every tile's samples are the design's heights
        (t0, t1), (s0, s1) = engine._tiles()
        (n0, n1), (g0, g1) = engine.shape, engine.grid_shape
        tiled = xp.zeros((t0 * n0, t1 * n1), dtype=xp.float64)
        tiled[s0:s0 + g0, s1:s1 + g1] = grad
        return xp.sum(xp.reshape(tiled, (t0, n0, t1, n1)), axis=(0, 2))
    oy, ox = engine._offset
    return grad[oy:oy + engine.shape[0], ox:ox + engine.shape[1]]


def _read_axes(engine: PSFEngine, wavelength, rows, cols, energy):
    """Cached :class:`~doedesign.engine.reads.ReadAxis` pair for the coded view."""
    key = ("reads", float(wavelength), tuple(rows), tuple(cols), bool(energy))
    found = engine._kernel_cache.get(key)
    if found is not None:
        return found
    (r0, r1, c0, c1), _ = engine._views["coded"]
    cam = engine.camera
    lz = wavelength * cam.sensor_distance_m
    out = []
    for n, n_pix, axis, lines in ((r1 - r0, cam.window_shape[0], cam.axis_pixel[0], rows),
                                  (c1 - c0, cam.window_shape[1], cam.axis_pixel[1], cols)):
        centres, u, w = engine._axis_nodes(n_pix, axis, n - 1, lz)
        lag_sum = (engine.xp.sum(engine._axis_kernel(n_pix, axis, np.arange(-(n - 1), n), lz), axis=0)
                   if energy else None)
        out.append(read_axis(centres[np.asarray(lines)], u, w, engine.step_m / lz, n, lag_sum, engine.backend))
    engine._cache_put(key, tuple(out))
    return tuple(out)


def _value_and_grad_reads(engine: PSFEngine, h, loss_fn, reads):
    """:func:`value_and_grad` for a loss of a few pixels and the window energy (see :mod:`.reads`)."""
    rows, r_idx = np.unique(np.asarray(reads.rows, dtype=int), return_inverse=True)
    cols, c_idx = np.unique(np.asarray(reads.cols, dtype=int), return_inverse=True)
    nd, nw = engine.depths_m.size, engine.wavelengths_m.size
    values = np.empty((nd, nw, r_idx.size))
    energy = np.zeros((nd, nw))
    saved = {}
    for di, depth in enumerate(engine.depths_m):
        for wi, wl in enumerate(engine.wavelengths_m):
            t = engine._pupil("coded", h, wl, depth)
            ay, ax = _read_axes(engine, wl, rows, cols, reads.energy)
            scale = float(engine.step_m ** 2 / (wl * engine.camera.sensor_distance_m) ** 2 / engine._energy["coded"])
            grid, field = read_pixels(t, ay, ax, scale, engine.backend)
            values[di, wi] = engine.backend.to_host(grid)[r_idx, c_idx]
            v = apply_energy_operator(t, ay, ax, engine.backend, engine._work) if reads.energy else None
            if v is not None:
                energy[di, wi] = scale * float(engine.xp.sum(engine.xp.real(engine.xp.conj(t) * v)))
            saved[di, wi] = (t, field, v, scale)
    loss, dvalues, denergy = loss_fn.sparse(values, energy)
    xp = engine.xp
    (r0, r1, c0, c1), _ = engine._views["coded"]
    grad_pupil = xp.zeros((r1 - r0, c1 - c0), dtype=xp.float64)
    for (di, wi), (t, field, v, scale) in saved.items():
        wl = engine.wavelengths_m[wi]
        ay, ax = _read_axes(engine, wl, rows, cols, reads.energy)
        dgrid = np.zeros((rows.size, cols.size))
        np.add.at(dgrid, (r_idx, c_idx), dvalues[di, wi])
        g = read_pixels_adjoint(engine.backend.asarray(dgrid), field, ay, ax, scale, engine.backend)
        if v is not None:
            g += (float(denergy[di, wi]) * scale) * v
        grad_pupil += engine._phase_per_m(wl) * 2.0 * xp.imag(xp.conj(t) * g)
    return float(loss), _height_gradient(engine, grad_pupil)
