"""AFM and optical-profiler formats read through SurfaceTopography, behind the tool's reader API.

Formats: Nanosurf ``.nid``, Bruker NanoScope ``.spm`` / ``.di``, NT-MDT ``.mdt``, Sensofar
``.plu``, Digital Surf ``.sur``, Wyko ``.opd`` and Vision64 ``.opdx``, Keyence ``.vk4``,
Gwyddion ``.gwy``. ISO 25178-72 ``.x3p`` is read by :mod:`metrology.formats.x3p` (x3pio) and
stylus line scans by ``metrology.formats.profile``.

Libraries compared (licence; wheel without a compiler on CPython 3.11.7; CPU time and peak
traced Python memory reading a 2000 x 2000 float64 x3p written by x3pio, measured once on this
machine; failure on a truncated file as tests/metrology/test_surface_libs.py checks it):

- SurfaceTopography 1.27 (MIT; its dependency igor2 is LGPL-3, used unmodified): manylinux
  wheel, 0.42 s CPU, peak 3.0x the 32 MB map; truncated files raise its own errors or bare
  struct / value errors (caught here), but a ``.nid`` cut inside its data frames is read
  without error (a known gap, xfail in the tests).
- x3pio 2.0 (MIT, pure Python): 0.27 s CPU, peak 3.4x; ``X3pFormatError`` /
  ``X3pChecksumError`` on damage.
- NSFopen 2.2 (MIT; a 26 MB wheel with example data, pulls pandas) and gwyfile 0.3 (MIT, pure
  Python): install; one format each, speed and failure modes not measured; not dependencies.
- nanoscope 1.2 (Apache-2.0): does not install (Requires-Python <= 3.11.4).
- surfalize 0.19 (GPL-3): refused by licence.

SurfaceTopography (ContactEngineering, a maintained library for surface metrology) reads every
format listed here, gives each channel's grid size and physical size from the header before
any height is read, its unit and undefined points; one library for all keeps one set of
failure modes. NSFopen and gwyfile read one format each and add nothing SurfaceTopography
lacks for these files (NSFopen pulls pandas and a 26 MB wheel), so they are not dependencies.

What this module adds: the size claimed by the header is checked with
:func:`~metrology.formats.plausibility.check_claimed_pixels` (against the file's size) before
the library reads the heights; any exception of the library on a damaged or hostile file
becomes one :class:`~metrology.formats.measurement.MeasurementFileError` naming the file
(a third-party parser can raise anything on hostile bytes, hence the broad catch); heights
and sizes are converted to metres from the channel's unit; the library's (x, y) array is
transposed to the tool's row-major (rows = y) order with row 0 the first row stored; a
non-square pixel is kept (``Measurement.pixel_size_y_m``).
"""

from __future__ import annotations

import logging
import os
from pathlib import Path
from typing import Any

import numpy as np

from metrology.formats.measurement import Measurement, MeasurementFileError
from metrology.formats.plausibility import check_claimed_pixels, pixel_size

__all__ = ["LIB_EXTENSIONS", "RASTER_FORMATS", "UNITS_M", "height_channel", "open_reader", "read_surface_lib", "to_metres"]

log = logging.getLogger(__name__)

#: Extension -> SurfaceTopography's format name (passed, so one reader parses the file).
LIB_EXTENSIONS = {".nid": "ezd", ".spm": "di", ".di": "di", ".mdt": "mdt", ".plu": "plu", ".sur": "sur",
                  ".opd": "opd", ".opdx": "opdx", ".vk4": "vk", ".gwy": "gwy"}
UNITS_M = {"km": 1e3, "m": 1.0, "mm": 1e-3, "µm": 1e-6, "μm": 1e-6, "um": 1e-6, "nm": 1e-9, "Å": 1e-10,
           "pm": 1e-12}
# Scanning-probe formats: the map is a raster scan, line by line along the rows (fast axis x),
# so each line carries its own z offset and the two axes their own piezo calibration.
RASTER_FORMATS = frozenset({"ezd", "di", "mdt"})
_HEIGHT_WORDS = ("topograph", "height", "z-axis", "zsensor", "z sensor", "z-sensor", "z_axis", "default")


def to_metres(path: str | Path, unit: object, what: str) -> float:
    """Metres per ``unit`` (a SurfaceTopography unit string); refuses an unknown unit."""
    if isinstance(unit, (tuple, list)):
        unit = unit[0]
    if not isinstance(unit, str) or unit not in UNITS_M:
        raise MeasurementFileError(f"{path}: {what} unit {unit!r} is not a length (known: {', '.join(UNITS_M)})")
    return UNITS_M[unit]


def open_reader(path: str | Path, fmt: str) -> Any:
    """SurfaceTopography's reader on ``path`` (header parsed, heights not read yet)."""
    from SurfaceTopography.IO import open_topography

    try:
        return open_topography(str(path), format=fmt)
    except MemoryError:
        raise MeasurementFileError(f"{path}: cannot read as {fmt}: the header claims more memory than "
                                   f"this machine has") from None
    except Exception as exc:  # a third-party parser on hostile bytes: any exception, one line
        raise MeasurementFileError(f"{path}: cannot read as {fmt}: {_one_line(exc)}") from None


def _one_line(exc: BaseException) -> str:
    text = " ".join(str(exc).split()) or type(exc).__name__
    return text[:300]


def height_channel(path: str | Path, reader: Any, channel: int | str | None = None) -> Any:
    """The channel holding heights: ``channel`` (index or name) when given, else the first
    whose name says topography / height / Z and whose unit is a length, else the first
    channel with a length unit."""
    channels = list(reader.channels)
    if not channels:
        raise MeasurementFileError(f"{path}: the file holds no data channel")
    names = [str(c.name) for c in channels]
    if channel is not None:
        if isinstance(channel, int) and 0 <= channel < len(channels):
            return channels[channel]
        if channel in names:
            return channels[names.index(channel)]
        raise MeasurementFileError(f"{path}: no channel {channel!r} (channels: {', '.join(names)})")

    def is_length(c):
        unit = c.unit[0] if isinstance(c.unit, (tuple, list)) else c.unit
        return unit in UNITS_M and (c.height_scale_factor is not None or c.reader is not None)

    lengths = [c for c in channels if is_length(c)]
    for c in lengths:
        if any(w in str(c.name).lower() for w in _HEIGHT_WORDS):
            return c
    if lengths:
        return lengths[0]
    raise MeasurementFileError(f"{path}: no channel with heights in a length unit (channels: {', '.join(names)})")


def read_surface_lib(path: str | Path, pixel_size_m: float | None = None, format: str | None = None,
                     channel: int | str | None = None) -> Measurement:
    """Read an AFM / optical-profiler file through SurfaceTopography.

    Parameters
    ----------
    path : str or Path
    pixel_size_m : float, optional
        Column pitch overriding the file's (the row pitch scales with it).
    format : str, optional
        SurfaceTopography's format name; from the extension (:data:`LIB_EXTENSIONS`) when None.
    channel : int or str, optional
        Channel index or name; the height channel is chosen when None (see :func:`height_channel`).

    Returns
    -------
    Measurement
        Heights in metres (NaN where the file marks no data), row 0 the first row stored,
        ``pixel_size_m`` along x (columns) and ``pixel_size_y_m`` along y when it differs.
        A 1-D uniform line scan becomes a 1-row map.

    Raises
    ------
    MeasurementFileError
        Damaged, truncated or hostile file; a claimed size beyond what the file can hold.
    """
    path = Path(path)
    fmt = format or LIB_EXTENSIONS.get(path.suffix.lower())
    if fmt is None:
        raise MeasurementFileError(f"{path}: no SurfaceTopography format for extension '{path.suffix}'")
    reader = open_reader(path, fmt)
    ch = height_channel(path, reader, channel)
    grid = tuple(int(n) for n in ch.nb_grid_pts)
    # Every format here stores at least one byte per point uncompressed: a header claiming
    # more points than the file has bytes (times the 16x slack) is refused before reading.
    check_claimed_pixels(path, grid, listed=os.path.getsize(path), what=f"channel '{ch.name}'")
    if not ch.is_uniform:
        raise MeasurementFileError(f"{path}: channel '{ch.name}' is sampled non-uniformly (a line scan): "
                                   f"read it with metrology.formats.profile.read_profile or `doe inspect`")
    try:
        topo = reader.topography(channel_index=ch.index)
        heights = np.ma.filled(np.ma.asarray(topo.heights(), dtype=np.float64), np.nan)
        sizes = tuple(float(s) for s in topo.physical_sizes)
        unit = topo.unit
    except MemoryError:
        raise MeasurementFileError(f"{path}: the data of channel '{ch.name}' do not fit in memory") from None
    except MeasurementFileError:
        raise
    except Exception as exc:  # truncated data, bad scale, ...: one line naming the file
        raise MeasurementFileError(f"{path}: cannot read channel '{ch.name}' as {fmt}: {_one_line(exc)}") from None
    if heights.shape != grid:
        raise MeasurementFileError(f"{path}: channel '{ch.name}' holds {heights.shape} points, header says {grid}")
    scale = to_metres(path, unit, "height")
    lateral = to_metres(path, getattr(ch, "lateral_unit", None) or unit, "lateral")
    height = heights.T * scale if heights.ndim == 2 else heights[np.newaxis, :] * scale
    pitch_x = sizes[0] * lateral / grid[0]
    pitch_y = sizes[1] * lateral / grid[1] if len(grid) == 2 else None
    x = pixel_size(path, pixel_size_m, pitch_x, "x pixel size (physical size / points)", f"channel '{ch.name}'")
    y = None if pitch_y is None else pitch_y * (x / pitch_x)
    info = topo.info if isinstance(getattr(topo, "info", None), dict) else {}
    metadata = {"source_file": str(path), "format": path.suffix.lower().lstrip("."), "reader": "SurfaceTopography",
                "channel": str(ch.name), "channels": [str(c.name) for c in reader.channels],
                "file_height_unit": str(unit)}
    if fmt in RASTER_FORMATS:
        metadata["raster_scan"] = True
    inst = info.get("instrument")
    if isinstance(inst, dict) and inst.get("name"):
        metadata["instrument"] = str(inst["name"])
    if info.get("acquisition_time") is not None:
        metadata["timestamp"] = str(info["acquisition_time"])
    return Measurement(height, x, metadata, pixel_size_y_m=y)
