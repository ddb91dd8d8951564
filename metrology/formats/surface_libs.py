"""AFM and optical-profiler formats read through SurfaceTopography, behind the tool's reader API.

Formats: Nanosurf ``.nid``, Bruker NanoScope ``.spm`` / ``.di``, NT-MDT ``.mdt``, Sensofar
``.plu``, Digital Surf ``.sur``, Wyko ``.opd`` and Vision64 ``.opdx``, Keyence ``.vk4``,
Gwyddion ``.gwy``; Bruker Dektak stylus-profiler CSV line scans (recognised by their
``Scan Parameters`` header, ``CONTENT_FORMATS``). ISO 25178-72 ``.x3p`` is read by
:mod:`metrology.formats.x3p` (x3pio).

Libraries compared (licence; wheel without a compiler on CPython 3.11.7; CPU time and peak
traced Python memory reading a 2000 x 2000 float64 x3p written by x3pio, measured once on this
machine; failure on a truncated file as tests/metrology/test_surface_libs.py checks it):

- SurfaceTopography 1.27 (MIT; its dependency igor2 is LGPL-3, used unmodified): manylinux
  wheel, 0.42 s CPU, peak 3.0x the 32 MB map; truncated files raise its own errors or bare
  struct / value errors (caught here), but a ``.nid`` cut inside its data frames is read
  without error (it checks only the frame it reads: the whole declaration is checked here,
  :mod:`metrology.formats.declared_size`). Its XYZ reader parses the Dektak CSV header.
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
(a third-party parser can raise anything on hostile bytes, hence the broad catch); the library
reads the file through :class:`BoundedReader`, so that a length read from hostile bytes never
makes it allocate more than the file holds (CPython allocates ``n`` bytes for ``read(n)``
before reading: SurfaceTopography's OPDx reader asked for 1.85 GB on 200 kB of random bytes
behind the OPDx magic); the library's warnings (numpy overflow on a hostile header's sizes)
are logged at INFO level, not printed beside the one-line error; heights
and sizes are converted to metres from the channel's unit; the library's (x, y) array is
transposed to the tool's row-major (rows = y) order with row 0 the first row stored; a
non-square pixel is kept (``Measurement.pixel_size_y_m``); a line scan the library reads as
non-uniform (x printed rounded) becomes a 1-row map when its positions are a uniform grid
(:func:`~metrology.formats.profile.line_pitch`); the data a header declares are checked against
the file where the library checks only part of them (``DECLARED_CHECKS``).
"""

from __future__ import annotations

import io
import logging
import os
import warnings
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np

from metrology.formats.declared_size import check_dektak_length, check_nid_frames
from metrology.formats.measurement import Measurement, MeasurementFileError
from metrology.formats.plausibility import check_claimed_pixels, pixel_size
from metrology.formats.profile import line_pitch

__all__ = ["BoundedReader", "CONTENT_FORMATS", "DECLARED_CHECKS", "LIB_EXTENSIONS", "RASTER_FORMATS", "UNITS_M",
           "height_channel", "is_dektak", "library_warnings", "open_reader", "read_dektak", "read_surface_lib",
           "to_metres"]

log = logging.getLogger(__name__)

#: Extension -> SurfaceTopography's format name (passed, so one reader parses the file).
LIB_EXTENSIONS = {".nid": "ezd", ".spm": "di", ".di": "di", ".mdt": "mdt", ".plu": "plu", ".sur": "sur",
                  ".opd": "opd", ".opdx": "opdx", ".vk4": "vk", ".gwy": "gwy"}
# Formats recognised by their content (a Dektak CSV shares ``.csv`` with the Mx profile export)
# -> SurfaceTopography's format name.
CONTENT_FORMATS = {"dektak": "xyz"}
DEKTAK_MAGIC = b"Scan Parameters"
UNITS_M = {"km": 1e3, "m": 1.0, "mm": 1e-3, "µm": 1e-6, "μm": 1e-6, "um": 1e-6, "nm": 1e-9, "Å": 1e-10,
           "pm": 1e-12}
# Scanning-probe formats: the map is a raster scan, line by line along the rows (fast axis x),
# so each line carries its own z offset and the two axes their own piezo calibration.
RASTER_FORMATS = frozenset({"ezd", "di", "mdt"})
_HEIGHT_WORDS = ("topograph", "height", "z-axis", "zsensor", "z sensor", "z-sensor", "z_axis", "default")


def is_dektak(head: bytes) -> bool:
    """True when a file's first bytes are a Dektak CSV header (a UTF-8 byte-order mark allowed)."""
    return head.removeprefix(b"\xef\xbb\xbf").startswith(DEKTAK_MAGIC)


# SurfaceTopography format -> the check of the file's declared data run before the heights
# are read (the library checks only the part it reads).
DECLARED_CHECKS = {"ezd": check_nid_frames}


def to_metres(path: str | Path, unit: object, what: str) -> float:
    """Metres per ``unit`` (a SurfaceTopography unit string); refuses an unknown unit."""
    if isinstance(unit, (tuple, list)):
        unit = unit[0]
    if not isinstance(unit, str) or unit not in UNITS_M:
        raise MeasurementFileError(f"{path}: {what} unit {unit!r} is not a length (known: {', '.join(UNITS_M)})")
    return UNITS_M[unit]


class BoundedReader(io.BufferedReader):
    """A binary file whose ``read(n)`` asks for no more than the bytes left before its end.

    ``read(n)`` of a CPython file allocates ``n`` bytes before it reads; a parser that takes
    ``n`` from hostile bytes (a 4 GB name length) would allocate it for a 200 kB file.
    """

    def __init__(self, path: str | Path) -> None:
        super().__init__(io.FileIO(path, "rb"))
        self.end = os.fstat(self.fileno()).st_size

    def read(self, size: int | None = -1) -> bytes:
        if size is not None and size > 0:
            size = min(size, max(0, self.end - self.tell()))
        return super().read(size)


@contextmanager
def library_warnings(path: str | Path) -> Iterator[None]:
    """Warnings the library raises inside the block, logged at INFO level naming ``path``
    (``doe --verbose`` shows them) instead of printed to stderr."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        yield
    for w in caught:
        log.info("%s: %s from the reader: %s", path, w.category.__name__, w.message)


def open_reader(path: str | Path, fmt: str, label: str | None = None) -> Any:
    """SurfaceTopography's reader on ``path`` (header parsed, heights not read yet), reading
    through :class:`BoundedReader` (the library opens it anew for each read); errors name the
    format as ``label`` (``fmt`` when None)."""
    from SurfaceTopography.IO import open_topography

    try:
        with library_warnings(path):
            return open_topography(lambda: BoundedReader(path), format=fmt)
    except MemoryError:
        raise MeasurementFileError(f"{path}: cannot read as {label or fmt}: the header claims more memory than "
                                   f"this machine has") from None
    except Exception as exc:  # a third-party parser on hostile bytes: any exception, one line
        raise MeasurementFileError(f"{path}: cannot read as {label or fmt}: {_one_line(exc)}") from None


def _one_line(exc: BaseException) -> str:
    text = " ".join(str(exc).split()) or type(exc).__name__
    return "".join(c if c.isprintable() else "?" for c in text[:300])


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
                     channel: int | str | None = None, label: str | None = None) -> Measurement:
    """Read an AFM / optical-profiler file or a line scan through SurfaceTopography.

    Parameters
    ----------
    path : str or Path
    pixel_size_m : float, optional
        Column pitch overriding the file's (the row pitch scales with it).
    format : str, optional
        SurfaceTopography's format name; from the extension (:data:`LIB_EXTENSIONS`) when None.
    channel : int or str, optional
        Channel index or name; the height channel is chosen when None (see :func:`height_channel`).
    label : str, optional
        The format's name in errors (``format`` when None).

    Returns
    -------
    Measurement
        Heights in metres (NaN where the file marks no data), row 0 the first row stored,
        ``pixel_size_m`` along x (columns) and ``pixel_size_y_m`` along y when it differs.
        A 1-D line scan (uniform, or printed with rounded positions) becomes a 1-row map.

    Raises
    ------
    MeasurementFileError
        Damaged, truncated or hostile file; a claimed size beyond what the file can hold; a
        line scan whose positions are not a uniform grid.
    """
    path = Path(path)
    fmt = format or LIB_EXTENSIONS.get(path.suffix.lower())
    if fmt is None:
        raise MeasurementFileError(f"{path}: no SurfaceTopography format for extension '{path.suffix}'")
    reader = open_reader(path, fmt, label)
    ch = height_channel(path, reader, channel)
    grid = tuple(int(n) for n in ch.nb_grid_pts)
    # Every format here stores at least one byte per point uncompressed: a header claiming
    # more points than the file has bytes (times the 16x slack) is refused before reading.
    check_claimed_pixels(path, grid, listed=os.path.getsize(path), what=f"channel '{ch.name}'")
    if fmt in DECLARED_CHECKS:
        DECLARED_CHECKS[fmt](path)
    positions = None
    try:
        with library_warnings(path):
            topo = reader.topography(channel_index=ch.index)
            if ch.is_uniform:
                heights = topo.heights()
            else:
                positions, heights = topo.positions_and_heights()
                positions = np.asarray(positions, dtype=np.float64)
            heights = np.ma.filled(np.ma.asarray(heights, dtype=np.float64), np.nan)
            sizes = tuple(float(s) for s in topo.physical_sizes)
            unit = topo.unit
    except MemoryError:
        raise MeasurementFileError(f"{path}: the data of channel '{ch.name}' do not fit in memory") from None
    except MeasurementFileError:
        raise
    except Exception as exc:  # truncated data, bad scale, ...: one line naming the file
        raise MeasurementFileError(f"{path}: cannot read channel '{ch.name}' as {label or fmt}: {_one_line(exc)}") from None
    if heights.shape != grid:
        raise MeasurementFileError(f"{path}: channel '{ch.name}' holds {heights.shape} points, header says {grid}")
    scale = to_metres(path, unit, "height")
    lateral = to_metres(path, getattr(ch, "lateral_unit", None) or unit, "lateral")
    height = heights.T * scale if heights.ndim == 2 else heights[np.newaxis, :] * scale
    info = topo.info if isinstance(getattr(topo, "info", None), dict) else {}
    metadata: dict[str, Any] = {"source_file": str(path), "format": path.suffix.lower().lstrip("."), "reader": "SurfaceTopography",
                "channel": str(ch.name), "channels": [str(c.name) for c in reader.channels],
                "file_height_unit": str(unit)}
    if positions is None:
        pitch_x = sizes[0] * lateral / grid[0]
        pitch_y = sizes[1] * lateral / grid[1] if len(grid) == 2 else None
    else:
        # SurfaceTopography gives the positions as the file prints them (a Dektak's rounded).
        step = line_pitch(path, positions, f"channel '{ch.name}' x positions", rounded=True)
        pitch_x, pitch_y = step * lateral, None
        metadata["x0_m"] = float(positions[0]) * lateral
        header = info.get("raw_metadata")
        if isinstance(header, dict):
            metadata["file_header"] = {str(k): str(v)[:200] for k, v in list(header.items())[:200]}
            if fmt == CONTENT_FORMATS["dektak"]:
                check_dektak_length(path, header, grid[0], pitch_x)
    x = pixel_size(path, pixel_size_m, pitch_x, "x pixel size (physical size / points)", f"channel '{ch.name}'")
    y = None if pitch_y is None else pitch_y * (x / pitch_x)
    if fmt in RASTER_FORMATS:
        metadata["raster_scan"] = True
    inst = info.get("instrument")
    if isinstance(inst, dict) and inst.get("name"):
        metadata["instrument"] = str(inst["name"])
    tip = inst.get("parameters", {}).get("tip_radius") if isinstance(inst, dict) else None
    if isinstance(tip, dict) and isinstance(tip.get("value"), (int, float)) and tip.get("unit") in UNITS_M:
        metadata["tip_radius_m"] = float(tip["value"]) * UNITS_M[tip["unit"]]
    if info.get("acquisition_time") is not None:
        metadata["timestamp"] = str(info["acquisition_time"])
    return Measurement(height, x, metadata, pixel_size_y_m=y)


def read_dektak(path: str | Path, pixel_size_m: float | None = None) -> Measurement:
    """Read a Bruker Dektak stylus-profiler CSV line scan (SurfaceTopography's XYZ reader).

    Returns
    -------
    Measurement
        A 1-row map in file order, heights in metres; the pixel size is the sample spacing
        (the export prints x rounded, :func:`~metrology.formats.profile.line_pitch`); the header's
        key-value pairs in ``metadata["file_header"]``, the stylus tip in ``tip_radius_m``.

    Raises
    ------
    MeasurementFileError
        Not a Dektak CSV, an incomplete last line, points short of the header's ``Length``.
    """
    meas = read_surface_lib(path, pixel_size_m, format=CONTENT_FORMATS["dektak"], label="Dektak CSV")
    meas.metadata.update({"format": "dektak_csv", "instrument": "Bruker Dektak (stylus profiler)"})
    return meas
