"""The lag transforms of the PSF engine: pupil autocorrelation and its kernels to sensor pixels.

For a piecewise-constant pupil ``t`` (step ``s``) the pixel-integrated intensity is
``sum_k C_k K_y[j, ky] K_x[i, kx]`` with ``C`` the discrete autocorrelation of ``t`` and per-axis
kernels ``K[j, k] = integral over sensor pixel j of sinc^2(f x) exp(-2 pi i k f x) dx``
(``f = s / lambda z``), by Gauss-Legendre quadrature (see :mod:`doedesign.engine.psf`). This module
holds those pieces as plain functions of arrays; :class:`doedesign.engine.psf.PSFEngine` caches them.
"""

from __future__ import annotations

import numpy as np
import scipy.fft as sfft

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


def axis_kernel(n_pix: int, axis: float, pixel_m: float, lags: np.ndarray, freq: float) -> np.ndarray:
    """``K[j, k]``: sensor pixel ``j`` integral of ``sinc^2(f x) exp(-2 pi i k f x)`` for each lag.

    Parameters as :func:`axis_nodes`; ``lags`` are the integer lags (columns of the result).
    """
    lags = np.asarray(lags)
    centres, u, w = axis_nodes(n_pix, axis, pixel_m, int(np.abs(lags).max()), freq)
    env = np.sinc(freq * (centres[:, None] + u[None, :])) ** 2 * w
    within = np.exp(-2j * np.pi * freq * np.outer(u, lags))
    return np.exp(-2j * np.pi * freq * np.outer(centres, lags)) * (env @ within)


def fft_shape(t: np.ndarray) -> tuple[int, int]:
    """FFT size holding a linear autocorrelation of ``t`` without wrap-around."""
    return tuple(sfft.next_fast_len(2 * n - 1) for n in t.shape)


def paired_lags(t: np.ndarray, workers: int = -1) -> tuple[np.ndarray, np.ndarray, int]:
    """Autocorrelation of ``t`` (times its FFT size) for kx >= 0, paired over +-ky.

    ``workers`` is the FFTs' thread count (-1: all cores; 1 when wavelengths run side by side).

    Returns ``(S, D, n_fft)``, ``S`` and ``D`` shaped (2, a, b) each as (real, imaginary) planes, with
    ``S[ky] = C[ky] + C[-ky]`` and ``D[ky] = C[ky] - C[-ky]`` for ky = 0..a-1. Because
    ``C[-ky, kx]`` meets ``conj(K_y)``, the row transform of the pair is ``Re K_y S + i Im K_y D``:
    real-by-complex products, half the work of the complex ones.
    """
    a, b = t.shape
    ly, lx = fft_shape(t)
    spec = sfft.fft(t, n=lx, axis=1, workers=workers)
    spec = sfft.fft(spec, n=ly, axis=0, workers=workers, overwrite_x=True)
    planes = spec.view(spec.real.dtype)
    np.square(planes, out=planes)
    power = planes[:, 0::2] + planes[:, 1::2]
    del spec, planes
    # C[k] = conj(R[k]) / N: the conjugate is taken below by the sign of the imaginary planes.
    r = sfft.rfft2(power, workers=workers)
    del power
    plus = r[:a, :b]
    minus = r[(-np.arange(a)) % ly, :b]
    s = np.empty((2, a, b), dtype=t.real.dtype)
    d = np.empty_like(s)
    np.add(plus.real, minus.real, out=s[0])
    np.add(plus.imag, minus.imag, out=s[1])
    np.negative(s[1], out=s[1])
    np.subtract(plus.real, minus.real, out=d[0])
    np.subtract(minus.imag, plus.imag, out=d[1])
    return s, d, ly * lx


def folded_psf(s: np.ndarray, d: np.ndarray, kernels: tuple[np.ndarray, ...]) -> np.ndarray:
    """``I = Re(Z K_x^T)`` with ``Z = Re K_y S + i Im K_y D`` (unscaled): six real matrix products.

    ``kernels`` are ``(Re K_y, Im K_y, Re K_x^T, Im K_x^T)`` with the ky = 0 column of ``K_y``
    halved (the +-ky pairing counts it twice) and the Hermitian fold (factor 2 for kx > 0) in ``K_x``.
    """
    kyr, kyi, kxr, kxi = kernels
    zr = kyr @ s[0]
    zi = kyr @ s[1]
    zr -= kyi @ d[1]
    zi += kyi @ d[0]
    psf = zr @ kxr
    psf -= zi @ kxi
    return psf


def phase_gradient(t: np.ndarray, d_half: np.ndarray) -> np.ndarray:
    """d loss / d phase of each pupil sample from d loss / d C (lags ky >= 0, all kx).

    Parameters
    ----------
    t : ndarray (a, b), complex
        Pupil samples.
    d_half : ndarray (a, 2 b - 1), complex
        d loss / d C for ky = 0..a-1 and kx = -(b-1)..b-1.
    """
    a, b = t.shape
    shape = fft_shape(t)
    # Full Hermitian lag array in circular layout: D_{-k} = conj(D_k).
    d_full = np.zeros(shape, dtype=complex)
    kx_idx = np.r_[shape[1] - (b - 1):shape[1], 0:b]
    d_full[np.arange(a)[:, None], kx_idx[None, :]] = d_half
    neg_rows = (-np.arange(1, a)) % shape[0]
    neg_cols = (-np.arange(-(b - 1), b)) % shape[1]
    d_full[neg_rows[:, None], neg_cols[None, :]] = d_half[1:].conj()
    # alpha_n = sum_k D_k conj(t_{n-k}); dL/dphi_n = -2 Im(alpha_n t_n).
    alpha = sfft.ifft2(sfft.fft2(d_full, workers=-1) * sfft.fft2(t.conj(), s=shape, workers=-1),
                       workers=-1)[:a, :b]
    return -2.0 * np.imag(alpha * t)
