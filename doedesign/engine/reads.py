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

from .backend import Array, Backend, numpy_backend
from .lags import sinc

__all__ = ["ReadAxis", "apply_energy_operator", "read_axis", "read_pixels", "read_pixels_adjoint"]


@dataclass
class ReadAxis:
    """Node fringes of the lines read along one pupil axis, and that axis's energy operator.

    ``fringe`` (lines * nodes, n): ``exp(-2 pi i f m y)`` at each node ``y`` for pupil index ``m``;
    ``weight`` (lines, nodes): Gauss-Legendre weight times the sinc^2 envelope;
    ``symbol_fft``: FFT of the circulant embedding of the energy Toeplitz operator (or None).
    All three are arrays of the engine's backend.
    """

    fringe: Array
    weight: Array
    symbol_fft: Array | None


def read_axis(centres: np.ndarray, u: np.ndarray, w: np.ndarray, freq: float, n: int,
              lag_sum: Array | None = None, backend: Backend | None = None) -> ReadAxis:
    """:class:`ReadAxis` for pixel ``centres`` read, node offsets ``u`` and weights ``w`` in a pixel
    (host arrays), on ``backend`` (default NumPy).

    ``lag_sum``: the window-summed kernel ``s(k)`` for lags ``-(n-1)..(n-1)`` (a backend array)
    when the energy is needed.
    """
    backend = backend or numpy_backend()
    xp = backend.xp
    freq = float(freq)  # a NumPy scalar would pull the namespace's arrays back into NumPy
    y = xp.asarray((centres[:, None] + u[None, :]).ravel(), dtype=xp.float64)
    m = xp.arange(n, dtype=xp.float64)
    fringe = xp.exp(-2j * np.pi * freq * (y[:, None] * m[None, :]))
    weight = xp.reshape(sinc(freq * y, xp) ** 2, (centres.size, u.size)) * xp.asarray(w, dtype=xp.float64)[None, :]
    symbol = None
    if lag_sum is not None:
        size = sfft.next_fast_len(2 * n - 1)
        # (T t)[m] = sum_m' s(m' - m) t[m'] is a convolution with g[k] = s(-k) (circular index):
        # lags k = -(n-1)..0 of s go to 0..n-1 reversed, k = 1..n-1 to size-1 down to size-n+1.
        g = xp.zeros(size, dtype=xp.complex128)
        g[:n] = xp.flip(lag_sum[:n])
        if n > 1:
            g[size - (n - 1):] = xp.flip(lag_sum[n:])
        symbol = backend.fft(g)
    return ReadAxis(fringe, weight, symbol)


def apply_energy_operator(t: Array, ay: ReadAxis, ax: ReadAxis, backend: Backend | None = None,
                          work: dict | None = None) -> Array:
    """``Ty t Tx^T`` by FFT convolution along each axis (zero-padded, no wrap-around).

    ``work``: optional dict of reusable padded buffers (fresh large arrays cost page faults
    at every evaluation).
    """
    backend = backend or numpy_backend()
    xp = backend.xp
    a, b = t.shape
    work = {} if work is None else work
    if ay.symbol_fft is None or ax.symbol_fft is None:
        raise ValueError("apply_energy_operator: the read axes were made without lag_sum (no energy operator)")
    ly, lx = ay.symbol_fft.shape[0], ax.symbol_fft.shape[0]
    col = work.get("col")
    if col is None or col.shape != (ly, b):
        col = work["col"] = xp.zeros((ly, b), dtype=xp.complex128)
    row = work.get("row")
    if row is None or row.shape != (a, lx):
        row = work["row"] = xp.zeros((a, lx), dtype=xp.complex128)
    col[:a, ...] = t
    col[a:, ...] = 0
    v = backend.fft(col, axis=0)
    v *= ay.symbol_fft[:, None]
    v = backend.ifft(v, axis=0)
    row[:, :b] = v[:a, ...]
    row[:, b:] = 0
    v = backend.fft(row, axis=1)
    v *= ax.symbol_fft[None, :]
    v = backend.ifft(v, axis=1)
    return xp.asarray(v[:, :b], copy=True)


def _node_intensity(field, ay: ReadAxis, ax: ReadAxis, xp):
    nr, qy = ay.weight.shape
    nc, qx = ax.weight.shape
    return xp.reshape(xp.real(field) ** 2 + xp.imag(field) ** 2, (nr, qy, nc, qx))


def read_pixels(t: Array, ay: ReadAxis, ax: ReadAxis, scale: float, backend: Backend | None = None) -> tuple[Array, Array]:
    """Pixel values on every (row line, column line) pair read, and the node field for the adjoint.

    Returns
    -------
    values : array (row lines, column lines)
    field : array (row lines * nodes, column lines * nodes), ``F`` at the node grid.
    """
    xp = (backend or numpy_backend()).xp
    field = ay.fringe @ t @ ax.fringe.T
    inten = _node_intensity(field, ay, ax, xp)
    # sum over nodes q (rows) and s (columns) of w_y[r, q] I[r, q, c, s] w_x[c, s]
    per_row_node = xp.sum(inten * ax.weight[None, None, ...], axis=3)
    values = scale * xp.sum(per_row_node * ay.weight[:, :, None], axis=1)
    return values, field


def read_pixels_adjoint(dvalues: Array, field: Array, ay: ReadAxis, ax: ReadAxis, scale: float,
                        backend: Backend | None = None) -> Array:
    """``dL / dt*`` from ``dL / dvalues`` (row lines, column lines) through :func:`read_pixels`."""
    xp = (backend or numpy_backend()).xp
    nr, qy = ay.weight.shape
    nc, qx = ax.weight.shape
    node = scale * (dvalues[:, None, :, None] * ay.weight[:, :, None, None] * ax.weight[None, None, ...])
    node = xp.reshape(node, (nr * qy, nc * qx))
    return xp.conj(ay.fringe).T @ (node * field) @ xp.conj(ax.fringe)
