"""CPU FFTs split across threads that end with the call.

Written by hand because scipy.fft's own threads (``workers``) are not safe here: they come from
a pool that lives as long as the process and shuts down and restarts around every fork
(pthread_atfork), and a fork soon after a restart can wait in fork() for ever (pocketfft's
prefork handler joining an idle pool thread that lost its wake-up: a CSI diagnosis once in 30
when its workers were forked, a CI test worker after PSF tests). Other code forks in the
same process as a design or a PSF prediction: subprocesses, Dask's local workers, a benchmark's
process pool.

The engine's transforms are batches of 1-D transforms along one axis of a 2-D or 3-D array, so
they split into slices of another axis that share nothing. Each slice is transformed by
scipy.fft with one worker, in a thread of a pool that is shut down before the call returns:
no thread outlives the call, so a later fork finds none. pocketfft releases the GIL, so the
slices run side by side. An n-dimensional transform is its 1-D transforms axis by axis (the
same factorization pocketfft applies), so results agree with scipy.fft's to rounding.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import scipy.fft as sfft

__all__ = ["BLOCK_LINES", "MIN_SPLIT_ELEMENTS", "cpu_threads", "fft", "fftn", "ifft", "ifftn", "power_fft", "rfftn"]

#: Below this many elements a transform runs in the calling thread: starting threads would cost
#: more than the share of the work they take.
MIN_SPLIT_ELEMENTS = 1 << 18
#: Lines of one block: a thread transforms a block, copies it into place, takes its next.
BLOCK_LINES = 128


def cpu_threads() -> int:
    """Threads the process may use: the CPUs it may run on, no more than ``OMP_NUM_THREADS``
    where that is set (the limit BLAS honours too)."""
    n = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    limit = os.environ.get("OMP_NUM_THREADS", "").strip()
    if limit.isdigit() and int(limit) > 0:
        n = min(n, int(limit))
    return max(1, n)


def _power(z: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
    """``|z|^2`` as ``re^2 + im^2`` (into ``out``)."""
    out = np.square(z.real, out=out)
    out += np.square(z.imag)
    return out


def _along(kind: str, x: np.ndarray, n: int | None, axis: int, threads: int, in_place: bool = False,
           power: bool = False) -> np.ndarray:
    """``scipy.fft.<kind>(x, n, axis)`` with the lines split over ``threads`` threads; with
    ``in_place`` (a complex transform that keeps the length) the result overwrites ``x``, which
    saves a fresh array: its pages cost as much as a pass of the transform. With ``power``, the
    transform's ``|.|^2`` (taken block by block while the block is in the cache)."""
    x = np.asarray(x)
    axis = axis % x.ndim
    others = [a for a in range(x.ndim) if a != axis]
    transform = getattr(sfft, kind)
    if threads <= 1 or x.size < MIN_SPLIT_ELEMENTS or not others:
        out = transform(x, n=n, axis=axis, workers=1)
        return _power(out) if power else out
    split = max(others, key=lambda a: x.shape[a])
    k = min(threads, x.shape[split])
    length = x.shape[axis] if n is None else n
    shape = list(x.shape)
    shape[axis] = length // 2 + 1 if kind == "rfft" else length
    # scipy.fft's result type: single stays single, everything else becomes double.
    dtype = np.result_type(x.dtype, np.complex64)
    in_place = (in_place and not power and kind != "rfft" and length == x.shape[axis] and x.dtype == dtype
                and x.flags.writeable)
    out = x if in_place else np.empty(shape, dtype=np.empty(0, dtype).real.dtype if power else dtype)
    # Blocks of lines, dealt out in turn: SciPy transforms a block (vectorized across its lines)
    # and the result, still in the cache, is copied into place. (NumPy's FFT could write in place
    # through ``out``, but is as fast in double precision and half as fast in single.)
    starts = range(0, x.shape[split], BLOCK_LINES)

    def part(i):
        for start in starts[i::k]:
            index = [slice(None)] * x.ndim
            index[split] = slice(start, start + BLOCK_LINES)
            index = tuple(index)
            if power:
                _power(transform(x[index], n=n, axis=axis, workers=1), out[index])
            else:
                out[index] = transform(x[index], n=n, axis=axis, workers=1)

    with ThreadPoolExecutor(k) as pool:
        list(pool.map(part, range(k)))
    return out


def _axes(x: np.ndarray, s: Sequence[int] | None, axes: Sequence[int] | None) -> list[tuple[int, int | None]]:
    """(axis, length) pairs of an n-dimensional transform, scipy.fft's defaults."""
    if axes is None:
        axes = range(-len(s), 0) if s is not None else range(x.ndim)
    axes = [a % x.ndim for a in axes]
    lengths = [None] * len(axes) if s is None else list(s)
    return list(zip(axes, lengths))


def fft(x: np.ndarray, n: int | None = None, axis: int = -1, threads: int = 1) -> np.ndarray:
    """``scipy.fft.fft`` along ``axis``, split across ``threads`` short-lived threads."""
    return _along("fft", x, n, axis, threads)


def power_fft(x: np.ndarray, n: int | None = None, axis: int = -1, threads: int = 1) -> np.ndarray:
    """``|fft(x, n, axis)|^2``, real: the complex transform is never held whole."""
    return _along("fft", x, n, axis, threads, power=True)


def ifft(x: np.ndarray, n: int | None = None, axis: int = -1, threads: int = 1) -> np.ndarray:
    """``scipy.fft.ifft`` along ``axis``, split across ``threads`` short-lived threads."""
    return _along("ifft", x, n, axis, threads)


def fftn(x: np.ndarray, s: Sequence[int] | None = None, axes: Sequence[int] | None = None,
         threads: int = 1) -> np.ndarray:
    """``scipy.fft.fftn`` over ``axes``, axis by axis, split across ``threads`` short-lived threads."""
    for i, (axis, n) in enumerate(reversed(_axes(np.asarray(x), s, axes))):
        x = _along("fft", x, n, axis, threads, in_place=i > 0)
    return x


def ifftn(x: np.ndarray, s: Sequence[int] | None = None, axes: Sequence[int] | None = None,
          threads: int = 1) -> np.ndarray:
    """``scipy.fft.ifftn`` over ``axes``, axis by axis, split across ``threads`` short-lived threads."""
    for i, (axis, n) in enumerate(reversed(_axes(np.asarray(x), s, axes))):
        x = _along("ifft", x, n, axis, threads, in_place=i > 0)
    return x


def rfftn(x: np.ndarray, s: Sequence[int] | None = None, axes: Sequence[int] | None = None,
          threads: int = 1) -> np.ndarray:
    """The real transform on the last of ``axes`` (halving it), complex ones on the others."""
    pairs = _axes(np.asarray(x), s, axes)
    x = _along("rfft", x, pairs[-1][1], pairs[-1][0], threads)
    for axis, n in reversed(pairs[:-1]):
        x = _along("fft", x, n, axis, threads, in_place=True)
    return x
