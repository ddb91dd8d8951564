"""Memory budget: a size that a file, a design or an option claims is checked before anything
is allocated.

Every entry point whose allocations grow with its input (a design's shape and pitch, a
camera window in its metadata, a ``--window`` option) estimates the bytes its work holds at
its peak and calls :func:`check_memory` first. The limit is a share of the memory the machine
has available now (``psutil``, a dask dependency; a cgroup's ``memory.max`` where one is set),
so a request that could only end in a MemoryError, in swapping or in the kernel's OOM killer
is refused as one line instead. ``DOE_MEMORY_LIMIT`` (bytes, or with a K, M, G or T suffix)
sets the limit explicitly (a batch job's allocation).

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
           "memory_limit_bytes", "psf_bytes"]

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


def memory_limit_bytes() -> int:
    """The most one run may plan to allocate: ``DOE_MEMORY_LIMIT``, else :data:`SHARE` of the available."""
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


def check_memory(nbytes: int, what: str) -> None:
    """Refuse ``what`` when its estimated peak ``nbytes`` exceeds :func:`memory_limit_bytes`.

    Raises
    ------
    DoeError
        One line naming ``what``, the estimate and the limit.
    """
    limit = memory_limit_bytes()
    if nbytes > limit:
        source = f"{LIMIT_ENV}" if os.environ.get(LIMIT_ENV, "").strip() else \
            f"{SHARE:.0%} of the memory available now"
        raise DoeError(f"{what} would need about {format_bytes(nbytes)} of memory, over the limit of "
                       f"{format_bytes(limit)} ({source})")


def psf_bytes(camera: Camera, pitch_m: float, shape: Sequence[int], n_wavelengths: int, n_depths: int,
              oversample: int = 1, n_views: int = 2, threads: int = 1) -> int:
    """Peak bytes of a :class:`~doedesign.engine.psf.PSFEngine` computing PSFs of this size.

    The pupil grid (the camera's aperture in DOE pixels, ``oversample`` samples each) holds
    the view weights, the defocus phase and, per thread, one view's pupil and its padded
    autocorrelation (about 140 bytes per pupil sample in double precision); the result holds
    ``n_views x n_depths x n_wavelengths`` windows of float64 (the uncoded ones cached once
    more); the per-axis kernels hold a window side times the lags per wavelength.
    """
    rows, cols = (int(v) for v in camera.pupil_grid_shape(tuple(int(v) for v in shape), pitch_m))
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
