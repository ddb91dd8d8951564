"""Where the engine's arrays live: NumPy on the CPU, CuPy on a GPU, one copy of the physics.

The PSF engine and the functions of :mod:`doedesign.engine.lags` and :mod:`doedesign.engine.reads`
are written against the Python array API standard: they take an array namespace ``xp`` and call
only what the standard defines (plus the FFTs below), so the same code runs on NumPy, on CuPy,
and on ``array_api_strict``, a namespace that refuses everything outside the standard (the tests
run the engine on it, so a NumPy-only call fails on a CPU machine before it fails on a GPU).

A :class:`Backend` holds the namespace and the FFTs of its library: ``scipy.fft`` on NumPy
(faster than NumPy's own), split over short-lived threads (:mod:`.threaded_fft`);
``cupyx.scipy.fft`` on CuPy (cuFFT plans cached); the standard's ``xp.fft`` elsewhere. Written
here because no library does this choice: ``array_api_compat`` gives the namespace but not the
fastest FFT of each library. The same holds for the image filters the process model needs
(:attr:`Backend.ndimage`): ``scipy.ndimage`` on NumPy, ``cupyx.scipy.ndimage`` on CuPy, and on
``array_api_strict`` SciPy's through host copies (the standard has no filters; the copies keep
the arrays around them strict).

The device is chosen once per run (``--device cpu|gpu|auto``): ``auto`` takes the GPU when CuPy
imports and a real allocation on the device succeeds, else the CPU, with one log line saying why.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..errors import DoeError
from . import threaded_fft

__all__ = ["DEVICES", "Array", "Backend", "gpu_unavailable_reason", "numpy_backend", "select_backend", "strict_backend"]

log = logging.getLogger(__name__)

DEVICES = ("auto", "cpu", "gpu")
#: An array of a backend's namespace (NumPy, CuPy or array_api_strict).
Array = Any


@dataclass(frozen=True)
class Backend:
    """An array namespace and its FFTs.

    Attributes
    ----------
    name : str
        "numpy", "cupy" or "array_api_strict".
    xp : module
        The array namespace (array API standard).
    device : str
        "cpu" or "gpu".
    """

    name: str
    xp: Any
    device: str
    _fft: Any = None
    _ndimage: Any = None
    #: Threads of a CPU FFT (:mod:`.threaded_fft`); one elsewhere.
    fft_threads: int = 1

    @property
    def is_numpy(self) -> bool:
        return self.name == "numpy"

    def asarray(self, a: Any, dtype: Any = None) -> Array:
        """``a`` on this backend's device (a host array is copied over once)."""
        if self.name == "cupy":
            import cupy

            return cupy.asarray(a, dtype=dtype)
        if self.name == "array_api_strict" and isinstance(a, np.ndarray):
            a = a.tolist() if a.ndim == 0 else a
        return self.xp.asarray(a, dtype=dtype)

    def to_host(self, a: Array) -> np.ndarray:
        """A NumPy array of ``a`` (a device-to-host copy on the GPU)."""
        if self.name == "cupy":
            return a.get()
        return np.asarray(a)

    @property
    def ndimage(self) -> Any:
        """``scipy.ndimage``'s functions for this backend's arrays (filters, interpolation,
        label sums): arrays in, arrays of this backend out. Arguments that are arrays (weights,
        matrices, labels, indices) must be this backend's arrays too (:meth:`asarray`)."""
        return self._ndimage

    # FFTs: scipy.fft's signatures. On NumPy, :mod:`.threaded_fft` with ``workers`` threads
    # (default :attr:`fft_threads`), never scipy.fft's own thread pool (not fork-safe: see there);
    # the other libraries schedule their own work.
    def _transform(self, name: str, x: Array, workers: int | None, **shape) -> Array:
        if self.is_numpy:
            return getattr(threaded_fft, name)(x, threads=self.fft_threads if workers is None else workers, **shape)
        return getattr(self._fft, name)(x, **shape)

    def fft(self, x: Array, n: int | None = None, axis: int = -1, workers: int | None = None) -> Array:
        return self._transform("fft", x, workers, n=n, axis=axis)

    def power_fft(self, x: Array, n: int | None = None, axis: int = -1, workers: int | None = None) -> Array:
        """``|fft(x, n, axis)|^2`` as ``re^2 + im^2``, a real array."""
        if self.is_numpy:
            return threaded_fft.power_fft(x, n, axis, self.fft_threads if workers is None else workers)
        spec = self._fft.fft(x, n=n, axis=axis)
        # In place where the library gives views of the real and imaginary parts.
        power, im = self.xp.real(spec), self.xp.imag(spec)
        power *= power
        im *= im
        power += im
        return power

    def ifft(self, x: Array, n: int | None = None, axis: int = -1, workers: int | None = None) -> Array:
        return self._transform("ifft", x, workers, n=n, axis=axis)

    def fftn(self, x: Array, s: tuple | None = None, axes: tuple | None = None, workers: int | None = None) -> Array:
        return self._transform("fftn", x, workers, s=s, axes=axes)

    def ifftn(self, x: Array, s: tuple | None = None, axes: tuple | None = None, workers: int | None = None) -> Array:
        return self._transform("ifftn", x, workers, s=s, axes=axes)

    def rfftn(self, x: Array, s: tuple | None = None, axes: tuple | None = None, workers: int | None = None) -> Array:
        return self._transform("rfftn", x, workers, s=s, axes=axes)


def numpy_backend() -> Backend:
    """The CPU backend: NumPy arrays (through ``array_api_compat``'s NumPy namespace, which
    returns plain ``ndarray``) and ``scipy.fft``."""
    import array_api_compat.numpy as xnp
    import scipy.fft

    return Backend("numpy", xnp, "cpu", scipy.fft, _ndimage(), threaded_fft.cpu_threads())


def strict_backend() -> Backend:
    """``array_api_strict`` on the CPU: the standard and nothing else (for tests)."""
    import array_api_strict

    return Backend("array_api_strict", array_api_strict, "cpu", array_api_strict.fft, _HostNdimage(array_api_strict))


def _cupy_backend() -> Backend:
    import array_api_compat.cupy as xcp
    import cupyx.scipy.fft
    import cupyx.scipy.ndimage

    return Backend("cupy", xcp, "gpu", cupyx.scipy.fft, cupyx.scipy.ndimage)


def _ndimage():
    import scipy.ndimage

    return scipy.ndimage


class _HostNdimage:
    """``scipy.ndimage`` for a namespace without one (``array_api_strict``): array arguments
    are copied to NumPy, array results copied back."""

    def __init__(self, xp):
        self._xp = xp

    def __getattr__(self, name):
        func = getattr(_ndimage(), name)
        xp = self._xp

        def host(a):
            return np.from_dlpack(a) if hasattr(a, "__dlpack__") and not isinstance(a, np.ndarray) else a

        def call(*args, **kwargs):
            out = func(*(host(a) for a in args), **{k: host(v) for k, v in kwargs.items()})
            return xp.asarray(out) if isinstance(out, np.ndarray) else out

        return call


def gpu_unavailable_reason() -> str | None:
    """None when CuPy imports and a real allocation on the current device works, else why not."""
    try:
        import cupy
    except ImportError as exc:
        return f"CuPy is not installed ({exc}; pip install 'doe-toolkit[gpu]')"
    except Exception as exc:  # a broken CUDA installation raises other errors at import
        return f"CuPy does not import: {exc}"
    try:
        if cupy.cuda.runtime.getDeviceCount() < 1:
            return "CuPy finds no CUDA device"
        probe = cupy.ones(1024, dtype=cupy.float64)
        if float(probe.sum()) != 1024.0:
            return "a test computation on the GPU gave a wrong result"
    except Exception as exc:
        return f"the GPU did not take a test allocation: {exc}"
    return None


_CHOSEN: dict[str, Backend] = {}


def select_backend(device: str | Backend = "auto") -> Backend:
    """The backend for ``device``: "cpu", "gpu" (refused with a clear error if there is none) or
    "auto" (the GPU when usable, else the CPU with one log line saying why). A
    :class:`Backend` is returned as it is."""
    if isinstance(device, Backend):
        return device
    if device not in DEVICES:
        raise DoeError(f"device must be one of {', '.join(DEVICES)}, got {device!r}")
    if device in _CHOSEN:
        return _CHOSEN[device]
    if device == "cpu":
        chosen = numpy_backend()
    else:
        why = gpu_unavailable_reason()
        if why is None:
            chosen = _cupy_backend()
        elif device == "gpu":
            raise DoeError(f"--device gpu: {why}")
        else:
            log.info("computing on the CPU: %s", why)
            chosen = numpy_backend()
    _CHOSEN[device] = chosen
    return chosen

