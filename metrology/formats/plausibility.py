"""Physical-range rules for what a measurement file says, one place for every format.

A reader that converts a field without asking whether the value can be physical turns a
unit slip (632.8 written into a metres field) into heights of kilometres that look like
a result. Every reader's output passes :func:`check_measurement`, and readers check the
sizes a header claims with :func:`check_claimed_pixels` before allocating anything.
Errors name the file, the field, the value and the accepted range.

Each range holds every value a real instrument writes (the reason is written beside it)
with a wide margin, so real data is never refused; it refuses only what no instrument
produces, which is what a unit slip gives (a factor of 1000 or more). Edges are compared
after allowing for the rounding of the stored number (:func:`within`): Zygo headers store
float32 (MetroPro ``lateral_res``, a ``.datx`` X Converter), so a 1 mm pixel arrives as
0.0010000000474974513, and text exports print 6 to 7 significant digits.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from doedesign.fileio import MAX_INPUT_ARRAY_BYTES
from metrology.formats.measurement import Measurement, MeasurementFileError

__all__ = ["MAX_PIXELS", "RANGES", "STORED_REL", "Range", "check_claimed_pixels", "check_measurement", "check_value",
           "pixel_size", "within"]

#: Largest height map a file may make the tool allocate (float64 pixels).
MAX_PIXELS = MAX_INPUT_ARRAY_BYTES // 8


#: Relative slack at a range's edge for the rounding of the stored number: float32 keeps 24 bits
#: (off by at most 6e-8 of itself) and text exports print 6 to 7 significant digits (at most
#: 5e-7); 1e-6 holds both and is a thousand times finer than the unit slips the ranges catch.
STORED_REL = 1e-6


def _edges(lo, hi):
    return lo - abs(lo) * STORED_REL, hi + abs(hi) * STORED_REL


def within(value: float, lo: float, hi: float) -> bool:
    """True when ``value`` is finite and lies in ``[lo, hi]`` up to the rounding of a stored
    number (:data:`STORED_REL`): float32 edges pass, a value 2x beyond an edge does not."""
    lo, hi = _edges(lo, hi)
    return math.isfinite(value) and lo <= value <= hi


@dataclass(frozen=True)
class Range:
    """Inclusive physical range of one header quantity (edges compared with :func:`within`)."""

    lo: float
    hi: float
    unit: str
    meaning: str

    def holds(self, value: object) -> bool:
        return (isinstance(value, (int, float)) and not isinstance(value, bool)
                and within(float(value), self.lo, self.hi))


# Metadata keys (as every reader names them) -> the range a physical instrument can report.
# Each edge lies beyond the most extreme instrument named in its comment.
RANGES = {
    # Shortest: at-wavelength EUV interferometry of lithography optics (13.5 nm) and DUV Fizeaus
    # (193, 248, 355 nm). HeNe 632.8 nm (Verifire, GPI, DynaFi); white-light scanning
    # interferometers (NewView, Nexview, Bruker ContourX, Sensofar) report a mean of 0.5-0.6 um.
    # Longest: IR Fizeaus at 1.064, 3.39 and 10.6 um (CO2). 10 nm..20 um holds all of them; a
    # wavelength written in nm or um (632.8, 0.6328) is refused.
    "wavelength_m": Range(10e-9, 20e-6, "m", "a light wavelength in metres (EUV to far IR)"),
    # Finest: an AFM scan of a few tens of nm over 512-1024 px (Bruker Dimension, used to measure
    # DOE steps) samples at a few hundredths of a nm; optical profilers with 100x-150x objectives
    # (NewView/Nexview with zoom, Keyence VK-X, Sensofar S neox) sample at ~0.03-0.1 um.
    # Coarsest: a 300 mm Verifire/GPI aperture over ~1000 camera px gives 0.3 mm, the largest
    # Fizeau apertures (~800 mm) ~0.8 mm, stitched or binned maps of metre-class optics a few mm.
    # 10 pm..10 mm holds all of them; a size in um or nm written as metres (0.5, 100) is refused.
    "pixel_size_m": Range(1e-11, 1e-2, "m", "a lateral pixel size in metres (10 pm to 10 mm)"),
    # S = 0.5 in reflection (double pass), 1 in single-pass transmission; a user's wavefront scale
    # 1/(2(n-1)) for a plate's thickness in double pass is 0.17 for germanium (n ~ 4, IR) and
    # 1/(n-1) through low-index media in single pass reaches 3 (water). 0.05..10 holds them.
    "intf_scale_factor": Range(0.05, 10.0, "", "the interferometric scale factor (0.5 in reflection)"),
    # O = 1 at normal incidence, 1.0-1.2 for high-NA interference objectives (NA 0.55-0.8 at
    # 50x-100x), 1/cos(theta) on grazing-incidence interferometers (theta to ~87 deg: ~19). O < 1
    # does not occur; 0.5..20 holds all of them.
    "obliquity_factor": Range(0.5, 20.0, "", "the obliquity factor (1 at normal incidence)"),
    # The longest vertical scans of areal profilers (extended coherence-scanning and confocal scans,
    # motorized Z of wide-area systems) span a few cm; +-0.1 m holds them. A height written in um
    # or nm as metres (a 1.2 um DOE step as 1.2) is refused.
    "height_m": Range(-0.1, 0.1, "m", "a surface height in metres (no profilometer scans 10 cm)"),
}


def check_value(path: str | Path, field: str, value: Any, key: str | None = None) -> float:
    """``value`` as a float after checking it lies in ``RANGES[key or field]``.

    Raises
    ------
    MeasurementFileError
        Naming the file, the field, the value and the accepted range.
    """
    rule = RANGES[key or field]
    try:
        number = float(value)
    except (TypeError, ValueError, OverflowError):
        number = None
    if number is None or not rule.holds(number):
        unit = f" {rule.unit}" if rule.unit else ""
        raise MeasurementFileError(f"{path}: {field} = {value!r} is not {rule.meaning}: accepted "
                                   f"{rule.lo:g}..{rule.hi:g}{unit}")
    return number


def pixel_size(path: str | Path, given: float | None, stored: object, field: str, missing: str) -> float:
    """The lateral pixel size a reader uses: the caller's ``given`` value, else the file's.

    Parameters
    ----------
    given : float or None
        ``pixel_size_m`` passed by the caller; overrides the file.
    stored : number or None
        What the file records (``field`` names it in messages); None or 0 means none
        (an uncalibrated instrument).
    missing : str
        Says what the file lacks, for the message asking for ``pixel_size_m``.

    Raises
    ------
    MeasurementFileError
        Naming the file: no pixel size, or one that is NaN or outside ``RANGES["pixel_size_m"]``.
    """
    if given is not None:
        return check_value(path, "pixel_size_m (given)", given, "pixel_size_m")
    if stored is None or (isinstance(stored, (int, float)) and stored == 0):
        raise MeasurementFileError(f"{path}: {missing}; pass pixel_size_m")
    return check_value(path, field, stored, "pixel_size_m")


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
    if meas.pixel_size_y_m is not None:
        check_value(path, "row pixel size (m)", meas.pixel_size_y_m, "pixel_size_m")
    valid = np.isfinite(meas.height_m)
    if not valid.any():
        raise MeasurementFileError(f"{path}: no valid pixel ({meas.height_m.size} pixels, all marked no data)")
    rule = RANGES["height_m"]
    values = meas.height_m[valid]
    lo, hi = float(values.min()), float(values.max())
    edge_lo, edge_hi = _edges(rule.lo, rule.hi)
    if lo < edge_lo or hi > edge_hi:
        bad = np.argwhere(valid & ((meas.height_m < edge_lo) | (meas.height_m > edge_hi)))[0]
        raise MeasurementFileError(
            f"{path}: heights reach {lo:.3g}..{hi:.3g} m (first at row {bad[0]}, col {bad[1]}: "
            f"{meas.height_m[tuple(bad)]:.3g} m); not {rule.meaning} (check the unit or scale factor)")
    return meas
