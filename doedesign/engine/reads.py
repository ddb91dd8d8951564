"""A few sensor pixels and the window's total energy of a split-aperture PSF, without the window.

Used by :meth:`doedesign.engine.psf.PSFEngine.value_and_grad` for losses that declare the pixels they
read (:class:`doedesign.optimizer.losses.PixelReads`). Same model and same quadrature as the engine's
full window (see :mod:`doedesign.engine.psf`), organized for a handful of pixels:

- A pixel's value. ``sum_k C_k exp(-2 pi i k f x) = |F(x)|^2`` with
  ``F(x) = sum_m t_m exp(-2 pi i m f x)`` (``f = step / lambda z``), so the Gauss-Legendre
  quadrature of envelope times fringe over the pixel is the same quadrature of envelope times
  ``|F|^2`` at the same nodes. ``F`` at the nodes of the rows and columns read is a small
  matrix product ``Wy t Wx^T`` (a few dozen node rows by the pupil), not an FFT.
- The window energy. Summed over the window's pixels the kernels collapse to one lag profile
  per axis, ``s(k) = sum_j K[j, k]``, so ``E = scale * t^H (Ty (x) Tx) t`` with Toeplitz
  ``Ty[m, m'] = sy(m' - m)`` (Hermitian, the envelope being real). ``Ty t Tx^T`` is two 1-D
  FFT convolutions along the pupil's axes, and it is also ``dE / dt*`` up to ``scale``.

The adjoint of both gives ``dL / dt*``; the phase gradient is ``2 Im(conj(t) dL / dt*)``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.fft as sfft

__all__ = ["ReadAxis", "apply_energy_operator", "read_axis", "read_pixels", "read_pixels_adjoint"]


@dataclass
class ReadAxis:
    """Node fringes of the lines read along one pupil axis, and that axis's energy operator.

    ``fringe`` (lines * nodes, n): ``exp(-2 pi i f m y)`` at each node ``y`` for pupil index ``m``;
    ``weight`` (lines, nodes): Gauss-Legendre weight times the sinc^2 envelope;
    ``symbol_fft``: FFT of the circulant embedding of the energy Toeplitz operator (or None).
    """

    fringe: np.ndarray
    weight: np.ndarray
    symbol_fft: np.ndarray | None


def read_axis(centres: np.ndarray, u: np.ndarray, w: np.ndarray, freq: float, n: int,
              lag_sum: np.ndarray | None = None) -> ReadAxis:
    """:class:`ReadAxis` for pixel ``centres`` read, node offsets ``u`` and weights ``w`` in a pixel.

    ``lag_sum``: the window-summed kernel ``s(k)`` for lags ``-(n-1)..(n-1)`` when the energy is needed.
    """
    y = centres[:, None] + u[None, :]
    fringe = np.exp(-2j * np.pi * freq * np.outer(y.ravel(), np.arange(n)))
    weight = np.sinc(freq * y) ** 2 * w[None, :]
    symbol = None
    if lag_sum is not None:
        size = sfft.next_fast_len(2 * n - 1)
        g = np.zeros(size, dtype=complex)
        k = np.arange(-(n - 1), n)
        # (T t)[m] = sum_m' s(m' - m) t[m'] is a convolution with g[k] = s(-k).
        g[(-k) % size] = lag_sum
        symbol = sfft.fft(g)
    return ReadAxis(fringe, weight, symbol)


def apply_energy_operator(t: np.ndarray, ay: ReadAxis, ax: ReadAxis, work: dict | None = None) -> np.ndarray:
    """``Ty t Tx^T`` by FFT convolution along each axis (zero-padded, no wrap-around).

    ``work``: optional dict of reusable padded buffers (fresh large arrays cost page faults
    at every evaluation); the transforms run in place in them.
    """
    a, b = t.shape
    work = {} if work is None else work
    ly, lx = ay.symbol_fft.size, ax.symbol_fft.size
    col = work.get("col")
    if col is None or col.shape != (ly, b):
        col = work["col"] = np.zeros((ly, b), dtype=complex)
    row = work.get("row")
    if row is None or row.shape != (a, lx):
        row = work["row"] = np.zeros((a, lx), dtype=complex)
    col[:a] = t
    col[a:] = 0
    v = sfft.fft(col, axis=0, workers=-1, overwrite_x=True)
    v *= ay.symbol_fft[:, None]
    v = sfft.ifft(v, axis=0, workers=-1, overwrite_x=True)
    row[:, :b] = v[:a]
    row[:, b:] = 0
    v = sfft.fft(row, axis=1, workers=-1, overwrite_x=True)
    v *= ax.symbol_fft[None, :]
    v = sfft.ifft(v, axis=1, workers=-1, overwrite_x=True)
    return v[:, :b].copy()


def read_pixels(t: np.ndarray, ay: ReadAxis, ax: ReadAxis, scale: float) -> tuple[np.ndarray, np.ndarray]:
    """Pixel values on every (row line, column line) pair read, and the node field for the adjoint.

    Returns
    -------
    values : ndarray (row lines, column lines)
    field : ndarray (row lines * nodes, column lines * nodes), ``F`` at the node grid.
    """
    field = ay.fringe @ t @ ax.fringe.T
    nr, qy = ay.weight.shape
    nc, qx = ax.weight.shape
    inten = (field.real ** 2 + field.imag ** 2).reshape(nr, qy, nc, qx)
    values = scale * np.einsum("rq,rqcs,cs->rc", ay.weight, inten, ax.weight)
    return values, field


def read_pixels_adjoint(dvalues: np.ndarray, field: np.ndarray, ay: ReadAxis, ax: ReadAxis,
                        scale: float) -> np.ndarray:
    """``dL / dt*`` from ``dL / dvalues`` (row lines, column lines) through :func:`read_pixels`."""
    nr, qy = ay.weight.shape
    nc, qx = ax.weight.shape
    node = scale * np.einsum("rc,rq,cs->rqcs", dvalues, ay.weight, ax.weight).reshape(nr * qy, nc * qx)
    return ay.fringe.conj().T @ (node * field) @ ax.fringe.conj()
