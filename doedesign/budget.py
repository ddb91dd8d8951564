"""Memory budget: a size that a file, a design or an option claims is checked before anything
is allocated.

Every entry point whose allocations grow with its input (a design's shape and pitch, a
camera window in its metadata, a ``--window`` option) estimates the bytes its work holds at
its peak and calls :func:`check_memory` first. The limit is a share of the memory the machine
has available now (``psutil``, a dask dependency; a cgroup's ``memory.max`` where one is set),
so a request that could only end in a MemoryError, in swapping or in the kernel's OOM killer
is refused as one line instead. The limits the process itself runs under count too: the
address-space and data-segment limits (``RLIMIT_AS``, ``RLIMIT_DATA``: ``ulimit -v``, a batch
queue's memory limit), less what the process has already mapped (``VmSize`` / ``VmData`` of
``/proc/self/status``), since an allocation beyond them fails however much memory the machine
has. ``DOE_MEMORY_LIMIT`` (bytes, or with a K, M, G or T suffix) sets the share limit
explicitly (a batch job's allocation); the process limits still apply under it.

The estimates are sums of the arrays each computation holds (sizes from shapes, counted
with Python integers so that absurd claims do not overflow); the PSF engine's and the mask
export's were checked against their measured peaks (``tests/cli/test_hostile_sizes.py``).
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

from .errors import DoeError

if TYPE_CHECKING:
    from .camera import Camera

__all__ = ["LIMIT_ENV", "available_bytes", "check_memory", "format_bytes", "mask_export_bytes",
           "measurement_bytes", "memory_limit_bytes", "memory_message", "process_limits", "psf_bytes"]

LIMIT_ENV = "DOE_MEMORY_LIMIT"
# Share of the available memory one run may plan to hold (the rest: Python, libraries, other work).
SHARE = 0.8
_SUFFIX = {"": 1, "K": 1024, "M": 1024 ** 2, "G": 1024 ** 3, "T": 1024 ** 4}


def format_bytes(n: float) -> str:
    """``n`` bytes as a short text (``3.2 GB``, ``63 TB``)."""
    for unit, size in (("EB", 1e18), ("PB", 1e15), ("TB", 1e12), ("GB", 1e9), ("MB", 1e6)):
        if n >= size:
            return f"{n / size:.3g} {unit}"
    return f"{n / 1e3:.3g} kB"


def _cgroup_free():
    try:
        limit = Path("/sys/fs/cgroup/memory.max").read_text().strip()
        used = int(Path("/sys/fs/cgroup/memory.current").read_text().strip())
    except (OSError, ValueError):
        return None
    return None if limit == "max" else max(int(limit) - used, 0)


def available_bytes() -> int:
    """Memory this process could still use: the system's available memory (and the cgroup's)."""
    try:
        import psutil

        free = int(psutil.virtual_memory().available)
    except ImportError:
        free = os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    cgroup = _cgroup_free()
    return free if cgroup is None else min(free, cgroup)


def _status_kb(field: str) -> int | None:
    """A ``kB`` field of ``/proc/self/status`` in bytes (None where there is none)."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith(field + ":"):
                return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        return None
    return None


def process_limits() -> list[tuple[int, str]]:
    """``(bytes still allowed, name)`` for each address-space or data limit this process runs under.

    The room left is the soft limit less what the process has mapped already (``VmSize`` for
    ``RLIMIT_AS``, ``VmData`` for ``RLIMIT_DATA``): a new array has to fit in what remains.
    """
    try:
        import resource
    except ImportError:  # not a POSIX system
        return []
    out = []
    for name, field in (("RLIMIT_AS", "VmSize"), ("RLIMIT_DATA", "VmData")):
        kind = getattr(resource, name, None)
        if kind is None:
            continue
        soft, _ = resource.getrlimit(kind)
        if soft == resource.RLIM_INFINITY or soft < 0:
            continue
        used = _status_kb(field) or 0
        out.append((max(int(soft) - used, 0), f"{name} {format_bytes(soft)}, {format_bytes(used)} of it mapped "
                                              f"already"))
    return out


def _share_limit() -> int:
    """``DOE_MEMORY_LIMIT``, else ``SHARE`` of the available memory."""
    text = os.environ.get(LIMIT_ENV, "").strip().upper().removesuffix("B")
    if text:
        number, unit = (text[:-1], text[-1]) if text[-1] in _SUFFIX else (text, "")
        try:
            value = float(number) * _SUFFIX[unit]
        except ValueError:
            raise DoeError(f"{LIMIT_ENV}={os.environ[LIMIT_ENV]!r}: give bytes, e.g. 8G") from None
        if not math.isfinite(value) or value <= 0:
            raise DoeError(f"{LIMIT_ENV}={os.environ[LIMIT_ENV]!r}: give a positive size, e.g. 8G")
        return int(value)
    return int(SHARE * available_bytes())


def _limit() -> tuple[int, str]:
    """The tightest limit and what sets it."""
    limit = _share_limit()
    source = f"{LIMIT_ENV}" if os.environ.get(LIMIT_ENV, "").strip() else f"{SHARE:.0%} of the memory available now"
    for room, name in process_limits():
        if SHARE * room < limit:
            limit, source = int(SHARE * room), f"{SHARE:.0%} of the room left under the process's {name}"
    return limit, source


def memory_limit_bytes() -> int:
    """The most one run may plan to allocate: ``DOE_MEMORY_LIMIT``, else ``SHARE`` of the
    available memory, and no more than ``SHARE`` of the room under :func:`process_limits`."""
    return _limit()[0]


def check_memory(nbytes: int, what: str) -> None:
    """Refuse ``what`` when its estimated peak ``nbytes`` exceeds the tightest limit the run is under.

    The limits: :func:`memory_limit_bytes` (``SHARE`` of the available memory, or
    ``DOE_MEMORY_LIMIT``) and the room left under each of :func:`process_limits`.

    Raises
    ------
    DoeError
        One line naming ``what``, the estimate and the limit.
    """
    limit, source = _limit()
    if nbytes > limit:
        raise DoeError(f"{what} would need about {format_bytes(nbytes)} of memory, over the limit of "
                       f"{format_bytes(limit)} ({source})")


def memory_message(exc: MemoryError) -> str:
    """One line for a :class:`MemoryError` that no estimate foresaw: the size asked, the limits."""
    shape = getattr(exc, "shape", None)
    dtype = getattr(exc, "dtype", None)
    asked = ""
    if shape is not None and dtype is not None:  # numpy's _ArrayMemoryError carries both
        try:
            asked = f" of {format_bytes(math.prod(int(v) for v in shape) * dtype.itemsize)} (an array " \
                    f"{' x '.join(str(int(v)) for v in shape)} of {dtype})"
        except (TypeError, ValueError, AttributeError):
            asked = ""
    limits = [f"{SHARE:.0%} of the memory available now is {format_bytes(SHARE * available_bytes())}"]
    limits += [f"{format_bytes(room)} left under {name}" for room, name in process_limits()]
    return f"out of memory: an allocation{asked} failed ({'; '.join(limits)}); give a smaller input or more memory"


def measurement_bytes(shape: Sequence[int]) -> int:
    """Peak bytes of comparing or diagnosing a measured field of ``shape`` (camera pixels).

    About 30 float64 maps of the field (the reading, spike removal, levelling, edge
    gradients, the read-out and the fits' residuals and models): an allowance from the
    arrays these steps hold, not a measured slope.
    """
    return 30 * 8 * int(shape[0]) * int(shape[1])


def psf_bytes(camera: Camera, pitch_m: float, shape: Sequence[int], n_wavelengths: int, n_depths: int,
              oversample: int = 1, n_views: int = 2, threads: int = 1) -> int:
    """Peak bytes of a :class:`~doedesign.engine.psf.PSFEngine` computing PSFs of this size.

    The pupil grid (the camera's aperture in DOE pixels, ``oversample`` samples each) holds
    the view weights, the defocus phase and, per thread, one view's pupil and its padded
    autocorrelation (about 140 bytes per pupil sample in double precision); the result holds
    ``n_views x n_depths x n_wavelengths`` windows of float64 (the uncoded ones cached once
    more); the per-axis kernels hold a window side times the lags per wavelength.
    """
    rows, cols = (int(v) for v in camera.pupil_grid_shape((int(shape[0]), int(shape[1])), pitch_m))
    q = int(oversample)
    samples = rows * cols * q ** 2
    win_rows, win_cols = (int(v) for v in camera.window_shape)
    fixed = 40 * samples + 8 * samples * int(n_depths)
    per_thread = 96 * samples
    result = 8 * win_rows * win_cols * n_depths * n_wavelengths * (n_views + 1)
    kernels = 32 * (win_rows * rows + win_cols * cols) * q * n_wavelengths
    return fixed + per_thread * max(1, min(int(threads), n_wavelengths * n_depths)) + result + kernels


def mask_export_bytes(shape: Sequence[int]) -> int:
    """Peak bytes of ``doe masks`` (levels, four masks, polygons, verification) for a design of ``shape``.

    About 64 bytes per design pixel: the slope of the measured peak between random 16-level
    designs of 1000 and 1600 pixels a side (4 px features, the most polygons per pixel).
    """
    return 64 * int(shape[0]) * int(shape[1])
