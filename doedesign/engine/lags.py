"""The lag transforms of the PSF engine: pupil autocorrelation and its kernels to sensor pixels.

For a piecewise-constant pupil ``t`` (step ``s``) the pixel-integrated intensity is
``sum_k C_k K_y[j, ky] K_x[i, kx]`` with ``C`` the discrete autocorrelation of ``t`` and per-axis
kernels ``K[j, k] = integral over sensor pixel j of sinc^2(f x) exp(-2 pi i k f x) dx``
(``f = s / lambda z``), by Gauss-Legendre quadrature (see :mod:`doedesign.engine.psf`). This module
holds those pieces as plain functions of arrays; :class:`doedesign.engine.psf.PSFEngine` caches them.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import scipy.fft as sfft

from .backend import Array, Backend

__all__ = ["axis_kernel", "axis_nodes", "fft_shape", "folded_psf", "paired_lags", "phase_gradient"]


def axis_nodes(n_pix: int, axis: float, pixel_m: float, max_lag: int,
               freq: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Sensor pixel centres along one axis and the Gauss-Legendre rule within a pixel.

    Nodes enough for the fastest fringe across one pixel (phase span up to
    ``2 pi |k| f a`` for lag ``k``); the one rule of both the full window and the pixel reads.

    Parameters
    ----------
    n_pix : int
        Sensor pixels along the axis.
    axis : float
        Pixel index of the optical axis.
    pixel_m : float
        Sensor pixel pitch.
    max_lag : int
        Largest lag the kernel carries.
    freq : float
        Fringe frequency per lag, ``step / (lambda z)`` (cycles per metre on the sensor).

    Returns
    -------
    centres, nodes, weights : ndarray
        Pixel centres (m), node offsets within a pixel (m) and their weights (m).
    """
    centres = (np.arange(n_pix) - axis) * pixel_m
    span = 2 * np.pi * max_lag * freq * pixel_m
    nodes, weights = np.polynomial.legendre.leggauss(int(np.ceil(span / 2)) + 8)
    return centres, nodes * pixel_m / 2, weights * pixel_m / 2


def sinc(x: Array, xp: Any = np) -> Array:
    """Normalized ``sin(pi x) / (pi x)`` (1 at 0) in namespace ``xp`` (the standard has no sinc)."""
    px = np.pi * x
    zero = px == 0
    return xp.where(zero, 1.0, xp.sin(px) / xp.where(zero, 1.0, px))


def axis_kernel(n_pix: int, axis: float, pixel_m: float, lags: np.ndarray, freq: float, xp: Any = np) -> Array:
    """``K[j, k]``: sensor pixel ``j`` integral of ``sinc^2(f x) exp(-2 pi i k f x)`` for each lag.

    Parameters as :func:`axis_nodes`; ``lags`` are the integer lags (columns of the result), a
    host array; the kernel is built in namespace ``xp`` (:mod:`doedesign.engine.backend`).
    """
    lags = np.asarray(lags)
    freq = float(freq)  # a NumPy scalar would pull the namespace's arrays back into NumPy
    centres, u, w = axis_nodes(n_pix, axis, pixel_m, int(np.abs(lags).max()), freq)
    centres, u, w, k = (xp.asarray(v, dtype=xp.float64) for v in (centres, u, w, lags))
    env = sinc(freq * (centres[:, None] + u[None, :]), xp) ** 2 * w
    within = xp.exp(-2j * np.pi * freq * (u[:, None] * k[None, :]))
    return xp.exp(-2j * np.pi * freq * (centres[:, None] * k[None, :])) * (env @ within)


def fft_shape(t: Array) -> tuple[int, int]:
    """FFT size holding a linear autocorrelation of ``t`` without wrap-around."""
    return tuple(sfft.next_fast_len(2 * n - 1) for n in t.shape)


def _flipped_rows(r, a: int, ly: int, xp):
    """Rows ``(-k) mod ly`` of ``r`` for k = 0..a-1: row 0, then ly-1 down to ly-a+1 (a gather
    written as slices: the standard indexes with integer arrays only on one axis)."""
    if a == 1:
        return r[0:1, ...]
    return xp.concat([r[0:1, ...], xp.flip(r[ly - a + 1:ly, ...], axis=0)], axis=0)


def paired_lags(t: Array, backend: Backend, workers: int | None = None) -> tuple[Array, Array, int]:
    """Autocorrelation of ``t`` (times its FFT size) for kx >= 0, paired over +-ky.

    ``backend`` is the :class:`~doedesign.engine.backend.Backend` that holds ``t``; ``workers``
    the FFTs' thread count on the CPU (default the backend's :attr:`~doedesign.engine.backend.Backend.fft_threads`).

    Returns ``(S, D, n_fft)``, ``S`` and ``D`` shaped (2, a, b) each as (real, imaginary) planes, with
    ``S[ky] = C[ky] + C[-ky]`` and ``D[ky] = C[ky] - C[-ky]`` for ky = 0..a-1. Because
    ``C[-ky, kx]`` meets ``conj(K_y)``, the row transform of the pair is ``Re K_y S + i Im K_y D``:
    real-by-complex products, half the work of the complex ones.
    """
    xp = backend.xp
    a, b = t.shape
    ly, lx = fft_shape(t)
    spec = backend.fft(t, n=lx, axis=1, workers=workers)
    power = backend.power_fft(spec, n=ly, axis=0, workers=workers)
    del spec
    # C[k] = conj(R[k]) / N: the conjugate is taken below by the sign of the imaginary planes.
    r = backend.rfftn(power, axes=(0, 1), workers=workers)
    del power
    plus = r[:a, :b]
    minus = _flipped_rows(r, a, ly, xp)[:, :b]
    pr, pi, mr, mi = xp.real(plus), xp.imag(plus), xp.real(minus), xp.imag(minus)
    s = xp.stack([pr + mr, -(pi + mi)])
    d = xp.stack([pr - mr, mi - pi])
    return s, d, ly * lx


def folded_psf(s: Array, d: Array, kernels: tuple[Array, ...]) -> Array:
    """``I = Re(Z K_x^T)`` with ``Z = Re K_y S + i Im K_y D`` (unscaled): six real matrix products.

    ``kernels`` are ``(Re K_y, Im K_y, Re K_x^T, Im K_x^T)`` with the ky = 0 column of ``K_y``
    halved (the +-ky pairing counts it twice) and the Hermitian fold (factor 2 for kx > 0) in ``K_x``.
    """
    kyr, kyi, kxr, kxi = kernels
    zr = kyr @ s[0, ...]
    zi = kyr @ s[1, ...]
    zr -= kyi @ d[1, ...]
    zi += kyi @ d[0, ...]
    psf = zr @ kxr
    psf -= zi @ kxi
    return psf


def phase_gradient(t: Array, d_half: Array, backend: Backend) -> Array:
    """d loss / d phase of each pupil sample from d loss / d C (lags ky >= 0, all kx).

    Parameters
    ----------
    t : array (a, b), complex
        Pupil samples.
    d_half : array (a, 2 b - 1), complex
        d loss / d C for ky = 0..a-1 and kx = -(b-1)..b-1.
    backend : Backend
        Where ``t`` and ``d_half`` live.
    """
    xp = backend.xp
    a, b = t.shape
    ly, lx = fft_shape(t)
    # Full Hermitian lag array in circular layout: D_{-k} = conj(D_k). Columns kx >= 0 sit at
    # 0..b-1, kx < 0 at lx-(b-1)..lx-1; row -ky at ly-ky.
    d_full = xp.zeros((ly, lx), dtype=xp.complex128)
    d_full[:a, :b] = d_half[:, b - 1:]
    d_full[:a, lx - (b - 1):] = d_half[:, :b - 1]
    if a > 1:
        # conj(D[ky, kx]) lands at (-ky, -kx): the kx axis reversed, rows 1..a-1 reversed.
        neg = xp.flip(xp.conj(d_half[1:, ...]), axis=(0, 1))
        d_full[ly - (a - 1):, :b] = neg[:, b - 1:]
        d_full[ly - (a - 1):, lx - (b - 1):] = neg[:, :b - 1]
    # alpha_n = sum_k D_k conj(t_{n-k}); dL/dphi_n = -2 Im(alpha_n t_n).
    spectrum = backend.fftn(d_full, axes=(0, 1)) * backend.fftn(xp.conj(t), s=(ly, lx), axes=(0, 1))
    alpha = backend.ifftn(spectrum, axes=(0, 1))[:a, :b]
    return -2.0 * xp.imag(alpha * t)
