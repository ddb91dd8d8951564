"""Physical-range rules for what a measurement file says, one place for every format.

A reader that converts a field without asking whether the value can be physical turns a
unit slip (632.8 written into a metres field) into heights of kilometres that look like
a result. Every reader's output passes :func:`check_measurement`, and readers check the
sizes a header claims with :func:`check_claimed_pixels` before allocating anything.
Errors name the file, the field, the value and the accepted range.

The ranges are wide on purpose: they hold every optical profilometer and every sane
unit, and refuse only values no instrument can produce.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from doedesign.fileio import MAX_INPUT_ARRAY_BYTES
from metrology.formats.measurement import Measurement, MeasurementFileError

__all__ = ["MAX_PIXELS", "RANGES", "Range", "check_claimed_pixels", "check_measurement", "check_value"]

# Largest height map a file may make the tool allocate (float64 pixels).
MAX_PIXELS = MAX_INPUT_ARRAY_BYTES // 8


@dataclass(frozen=True)
class Range:
    """Inclusive physical range of one header quantity."""

    lo: float
    hi: float
    unit: str
    meaning: str

    def holds(self, value: object) -> bool:
        return isinstance(value, (int, float)) and math.isfinite(value) and self.lo <= value <= self.hi


# Metadata keys (as every reader names them) -> the range a physical instrument can report.
RANGES = {
    "wavelength_m": Range(100e-9, 20e-6, "m", "a light wavelength in metres (UV to far IR)"),
    "pixel_size_m": Range(1e-9, 1e-3, "m", "a lateral pixel size in metres (1 nm to 1 mm)"),
    "intf_scale_factor": Range(0.05, 4.0, "", "the interferometric scale factor (0.5 in reflection)"),
    "obliquity_factor": Range(0.5, 5.0, "", "the obliquity factor (1 at normal incidence)"),
    "height_m": Range(-0.05, 0.05, "m", "a surface height in metres (no profilometer scans 50 mm)"),
}


def check_value(path: str | Path, field: str, value: object, key: str | None = None) -> float:
    """``value`` as a float after checking it lies in ``RANGES[key or field]``.

    Raises
    ------
    MeasurementFileError
        Naming the file, the field, the value and the accepted range.
    """
    rule = RANGES[key or field]
    try:
        number = float(value)
    except (TypeError, ValueError):
        number = None
    if number is None or not rule.holds(number):
        unit = f" {rule.unit}" if rule.unit else ""
        raise MeasurementFileError(f"{path}: {field} = {value!r} is not {rule.meaning}: accepted "
                                   f"{rule.lo:g}..{rule.hi:g}{unit}")
    return number


def check_claimed_pixels(path: str | Path, shape: Sequence[int], listed: int | None = None,
                         what: str = "the header") -> int:
    """Refuse a claimed array size beyond :data:`MAX_PIXELS` or far beyond the file's content.

    Parameters
    ----------
    shape : tuple of int
        The size the file claims, checked before anything of that size is allocated.
    listed : int, optional
        Pixels the file really holds (data lines, values); the claim may exceed it at most
        16-fold (sparse exports) unless the whole claim is small.
    """
    try:
        dims = [int(v) for v in shape]
    except (TypeError, ValueError, OverflowError):
        raise MeasurementFileError(f"{path}: {what} gives an unusable size {shape!r}") from None
    if any(d < 0 for d in dims):
        raise MeasurementFileError(f"{path}: {what} gives a negative size {tuple(dims)}")
    claimed = math.prod(dims)
    if claimed > MAX_PIXELS:
        raise MeasurementFileError(f"{path}: {what} claims {' x '.join(map(str, dims))} = {claimed:.3g} pixels, "
                                   f"over the {MAX_PIXELS:.3g}-pixel limit")
    if listed is not None and claimed > max(16 * listed, 1_000_000):
        raise MeasurementFileError(f"{path}: {what} claims {' x '.join(map(str, dims))} = {claimed} pixels but "
                                   f"the file holds only {listed}")
    return claimed


def check_measurement(path: str | Path, meas: Measurement, pixel_overridden: bool = False) -> Measurement:
    """Check a reader's :class:`~metrology.formats.measurement.Measurement` before anyone uses it.

    Header quantities in the metadata (wavelength, scale and obliquity factors) and the
    pixel size must be physical, at least one pixel must be valid and every valid height
    must lie in the height range.

    Returns
    -------
    Measurement
        ``meas`` unchanged.
    """
    meta = meas.metadata
    for key in ("wavelength_m", "intf_scale_factor", "obliquity_factor"):
        if meta.get(key) is not None:
            check_value(path, key, meta[key])
    if not pixel_overridden and meta.get("lateral_res_m"):
        check_value(path, "lateral_res_m", meta["lateral_res_m"], "pixel_size_m")
    check_value(path, "pixel size (m)", meas.pixel_size_m, "pixel_size_m")
    valid = np.isfinite(meas.height_m)
    if not valid.any():
        raise MeasurementFileError(f"{path}: no valid pixel ({meas.height_m.size} pixels, all marked no data)")
    rule = RANGES["height_m"]
    values = meas.height_m[valid]
    lo, hi = float(values.min()), float(values.max())
    if lo < rule.lo or hi > rule.hi:
        bad = np.argwhere(valid & ((meas.height_m < rule.lo) | (meas.height_m > rule.hi)))[0]
        raise MeasurementFileError(
            f"{path}: heights reach {lo:.3g}..{hi:.3g} m (first at row {bad[0]}, col {bad[1]}: "
            f"{meas.height_m[tuple(bad)]:.3g} m); not {rule.meaning} (check the unit or scale factor)")
    return meas
