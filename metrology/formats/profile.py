"""Line scans: a profile's x positions to the sample spacing of the tool's uniform 1-row map.

A :class:`~metrology.formats.measurement.Measurement` is a uniform grid. Profile exports print
x rounded: a Dektak CSV prints x to 0.1 um for its 0.15625 um sampling (1500 um in 9600
points), so the steps read 0.1 or 0.2 um and SurfaceTopography reads the scan as non-uniform.
No library decides whether positions are a uniform grid printed with rounding and gives its
spacing, so :func:`line_pitch` does it here (one rule for every line-scan reader: the Mx
profile CSV and the line scans read through SurfaceTopography).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from metrology.formats.measurement import MeasurementFileError

__all__ = ["UNIFORM_REL", "line_pitch", "printed_quantum"]

# Positions may stray from the uniform grid by this fraction of a step besides any printed
# rounding (the Mx profile reader's rule before this module: each step within 1e-3 of the median).
UNIFORM_REL = 1e-3
_MAX_DECIMALS = 12


def printed_quantum(x: np.ndarray) -> float:
    """The unit of the last printed digit of positions ``x`` as the file prints them, in the
    file's unit (0.1 for "1.3, 1.4, 1.6"), or 0.0 when they carry more than
    12 decimals (printed in full precision)."""
    x = np.asarray(x, dtype=np.float64)
    for decimals in range(_MAX_DECIMALS + 1):
        scaled = x * 10.0 ** decimals
        # A decimal parsed to float64 is off by at most half an ulp (1.1e-16 of itself).
        if np.all(np.abs(scaled - np.round(scaled)) <= 1e-6 + 1e-14 * np.abs(scaled)):
            return 10.0 ** -decimals
    return 0.0


def line_pitch(path: str | Path, x: np.ndarray, what: str = "X", rounded: bool = False) -> float:
    """Sample spacing of a line scan whose positions are ``x``, in the file's unit
    (the numbers as printed, before any conversion to metres).

    The positions are a uniform grid when each lies within ``UNIFORM_REL`` of a step of
    the least-squares line through them, plus half the unit of their last printed digit
    (:func:`printed_quantum`) when ``rounded``.

    Parameters
    ----------
    path : str or Path
        Named in errors.
    x : array_like
        The positions as the file prints them.
    what : str
        Names the positions in errors.
    rounded : bool
        The format prints positions rounded to fewer digits than the spacing has (a Dektak
        CSV); an export that prints them in full (the Mx profile CSV) passes False.

    Returns
    -------
    float
        The least-squares step, in the unit of ``x``.

    Raises
    ------
    MeasurementFileError
        Fewer than two points, a position that is not finite, positions that decrease, or a
        position off the uniform grid (a non-uniform scan), naming the file.
    """
    x = np.asarray(x, dtype=np.float64).reshape(-1)
    if x.size < 2:
        raise MeasurementFileError(f"{path}: fewer than two profile points")
    if not np.all(np.isfinite(x)):
        raise MeasurementFileError(f"{path}: {what} holds a position that is not a finite number")
    index = np.arange(x.size, dtype=np.float64)
    step, x0 = np.polyfit(index, x, 1)
    if not step > 0 or np.any(np.diff(x) < 0):
        raise MeasurementFileError(f"{path}: {what} is not increasing (least-squares step {step:.4g})")
    allowed = (0.5 * printed_quantum(x) if rounded else 0.0) + UNIFORM_REL * step
    off = float(np.max(np.abs(x - (x0 + step * index))))
    if off > allowed:
        raise MeasurementFileError(f"{path}: {what} is not uniformly spaced: a position lies {off:.4g} from the "
                                   f"uniform grid of step {step:.4g} (allowed {allowed:.3g})")
    return float(step)
