"""Read any supported profilometer file into a :class:`~metrology.formats.measurement.Measurement`.

Formats: MetroPro ``.dat``, Mx ``.datx``, Zygo ASCII ``.xyz`` and ``.asc``, Mx profile
``.csv``, ``.npy`` / ``.npz`` height maps in metres, TIFF images, ISO 25178-72 ``.x3p``
(:mod:`metrology.formats.x3p`) and the AFM / optical-profiler formats of
:mod:`metrology.formats.surface_libs` (``.nid``, ``.spm``, ``.di``, ``.mdt``, ``.plu``,
``.sur``, ``.opd``, ``.opdx``, ``.vk4``, ``.gwy``) and Bruker Dektak CSV line scans. The
format is taken from the file's magic bytes when it has one (a Dektak CSV from its
``Scan Parameters`` header, so that it is not read as an Mx profile CSV), else from the
extension.

Every reader keeps the file's pixel order: row 0 is the first row stored, which for
Zygo files is the top of the camera image. Nothing is flipped or transposed.
"""

from __future__ import annotations

import csv
import io
import math
import logging
import re
import struct
import zipfile
from pathlib import Path
from typing import Any

import numpy as np

from doedesign.fileio import check_input_file, load_npy, parse_json, read_npz
from metrology.formats.measurement import Measurement, MeasurementFileError, read_head
from metrology.formats.plausibility import check_claimed_pixels, check_measurement, pixel_size
from metrology.formats.profile import line_pitch
from metrology.formats.surface_libs import LIB_EXTENSIONS, is_dektak, read_dektak, read_surface_lib
from metrology.formats.x3p import read_x3p
from metrology.formats.zygo_ascii import read_asc, read_xyz
from metrology.formats.zygo_dat import MAGIC, read_dat
from metrology.formats.zygo_datx import HDF5_SIGNATURE, read_datx

__all__ = ["CSV_UNITS_M", "EXTENSIONS", "FORMATS", "detect_format", "read_array", "read_measurement",
           "read_profile_csv", "read_tiff"]

log = logging.getLogger(__name__)

#: Measurement formats :func:`read_measurement` reads (by extension, without the dot).
FORMATS = ("dat", "datx", "xyz", "asc", "csv", "dektak", "npy", "npz", "tiff", "x3p") + tuple(
    sorted({e.lstrip(".") for e in LIB_EXTENSIONS}))
EXTENSIONS = {".dat": "dat", ".datx": "datx", ".xyz": "xyz", ".asc": "asc", ".csv": "csv",
              ".npy": "npy", ".npz": "npz", ".tif": "tiff", ".tiff": "tiff", ".x3p": "x3p",
              **{e: e.lstrip(".") for e in LIB_EXTENSIONS}}
# Units a CSV column header may name in brackets; micrometres when none is given.
CSV_UNITS_M = {"m": 1.0, "mm": 1e-3, "um": 1e-6, "µm": 1e-6, "μm": 1e-6, "nm": 1e-9}
_TIFF_RESOLUTION_UNIT_M = {2: 0.0254, 3: 0.01}


def detect_format(path: str | Path) -> str:
    """Format name of ``path`` from its magic bytes, else its extension.

    Raises
    ------
    MeasurementFileError
        The file is missing or neither its content nor its extension is known.
    """
    path = Path(path)
    head = read_head(path, 64)
    by_ext = EXTENSIONS.get(path.suffix.lower())
    by_magic = None
    if len(head) >= 4 and struct.unpack(">I", head[:4])[0] in MAGIC:
        by_magic = "dat"
    elif head.startswith(HDF5_SIGNATURE):
        by_magic = "datx"
    elif head.startswith(b"Zygo"):
        by_magic = "xyz" if b"XYZ" in head.split(b"\n", 1)[0].upper() else "asc"
    elif head.startswith(b"\x93NUMPY"):
        by_magic = "npy"
    elif head.startswith(b"PK"):
        by_magic = "x3p" if by_ext == "x3p" else "npz"
    elif head[:4] in (b"II*\0", b"MM\0*", b"II+\0", b"MM\0+"):
        by_magic = "tiff"
    elif is_dektak(head):
        by_magic = "dektak"
    if by_magic and by_ext and by_magic != by_ext and (by_magic, by_ext) != ("dektak", "csv"):
        log.warning("%s: content is %s although the extension says %s; reading as %s",
                    path, by_magic, by_ext, by_magic)
    fmt = by_magic or by_ext
    if fmt is None:
        raise MeasurementFileError(f"{path}: unknown measurement format (extension '{path.suffix}'; "
                                   f"known: {', '.join(sorted(EXTENSIONS))})")
    return fmt


def read_measurement(path: str | Path, format: str | None = None, pixel_size_m: float | None = None,
                     **options: Any) -> Measurement:
    """Read a profilometer file.

    Parameters
    ----------
    path : str or Path
    format : str, optional
        One of :data:`FORMATS`; detected from magic bytes / extension when None.
    pixel_size_m : float, optional
        Lateral sampling; overrides the file's value, and is required for ``.npy`` and
        for ``.npz`` / TIFF files that do not record it.
    **options
        Passed to the format reader: ``z_unit_m`` (xyz, tiff), ``phase_res`` (asc).

    Returns
    -------
    Measurement
        Heights in metres, NaN = invalid, camera order (row 0 as stored first).

    Raises
    ------
    MeasurementFileError
        Any problem with the file; the message names it.
    """
    path = check_input_file(path, MeasurementFileError)
    fmt = format or detect_format(path)
    readers = {"dat": read_dat, "datx": read_datx, "xyz": read_xyz, "asc": read_asc,
               "csv": read_profile_csv, "dektak": read_dektak, "npy": read_array, "npz": read_array, "tiff": read_tiff,
               "x3p": read_x3p, **{e.lstrip("."): read_surface_lib for e in LIB_EXTENSIONS}}
    if fmt not in readers:
        raise MeasurementFileError(f"{path}: unknown format '{fmt}' (known: {', '.join(FORMATS)})")
    try:
        meas = readers[fmt](path, pixel_size_m=pixel_size_m, **options)
    except MeasurementFileError:
        raise
    except (OSError, EOFError, ValueError, TypeError, LookupError, ArithmeticError, zipfile.BadZipFile,
            UnicodeError, struct.error, csv.Error) as exc:
        # A damaged file can fail deep inside numpy / tifffile; report it, never a traceback.
        raise MeasurementFileError(f"{path}: cannot read as {fmt}: {exc}") from None
    # One set of physical-range rules for every format (wavelength, pixel, factors, heights).
    return check_measurement(path, meas, pixel_overridden=pixel_size_m is not None)


def _need_pixel(path, pixel_size_m, stored, where, field="pixel_size_m"):
    return pixel_size(path, pixel_size_m, stored, field, f"{where} does not record the pixel size")


def read_array(path: str | Path, pixel_size_m: float | None = None) -> Measurement:
    """Read a ``.npy`` or ``.npz`` height map in metres.

    An ``.npz`` uses the key ``height_m`` (or its only array), ``pixel_size_m`` (or
    ``pitch_m``) for the sampling and an optional JSON ``metadata`` string.
    """
    path = Path(path)
    metadata = {"source_file": str(path)}
    is_zip = read_head(path, 2) == b"PK"
    if not is_zip:
        height = load_npy(path, MeasurementFileError)
        metadata["format"] = "npy"
        pixel = _need_pixel(path, pixel_size_m, None, "a .npy file")
    else:
        metadata["format"] = "npz"
        npz = read_npz(path, (), "height map", MeasurementFileError)
        names = list(npz)
        if "height_m" in names:
            height = npz["height_m"]
        elif len(names) == 1:
            height = npz[names[0]]
        else:
            raise MeasurementFileError(f"{path}: no 'height_m' array (found {', '.join(names) or 'nothing'})")
        stored = next((_scalar(path, k, npz[k]) for k in ("pixel_size_m", "pitch_m") if k in names), None)
        if "metadata" in names:
            # Provenance only: metadata that cannot be read is reported and left out.
            try:
                extra = parse_json(str(npz["metadata"]), f"{path}: 'metadata'", MeasurementFileError)
            except MeasurementFileError as exc:
                log.warning("%s; ignored", exc)
                extra = {}
            if isinstance(extra, dict):
                metadata = {**extra, **metadata}
            else:
                log.warning("%s: 'metadata' is not a JSON object; ignored", path)
        pixel = _need_pixel(path, pixel_size_m, stored, "this .npz")
    if height.ndim != 2 or height.dtype.kind not in "fiu":
        raise MeasurementFileError(f"{path}: expected a 2-D numeric height map, got {height.dtype} {height.shape}")
    return Measurement(height, pixel, metadata)


def _scalar(path, name, value):
    """A stored number (a 0-d or 1-element real array) as float; refuses text, complex, arrays."""
    value = np.asarray(value)
    if value.size != 1 or value.dtype.kind not in "fiu":
        raise MeasurementFileError(f"{path}: '{name}' must be one real number, got {value.dtype} {value.shape}")
    number = float(value.reshape(-1)[0])
    if not math.isfinite(number):
        raise MeasurementFileError(f"{path}: '{name}' is {number}")
    return number


def read_tiff(path: str | Path, pixel_size_m: float | None = None, z_unit_m: float = 1.0) -> Measurement:
    """Read the first image of a TIFF as a height map (values times ``z_unit_m`` metres).

    The pixel size comes from ``pixel_size_m`` or the XResolution / ResolutionUnit tags
    (inch or centimetre).
    """
    import tifffile

    path = Path(path)
    with tifffile.TiffFile(path) as tif:
        if len(tif.pages) == 0:
            raise MeasurementFileError(f"{path}: the TIFF holds no image")
        page = tif.pages[0]
        check_claimed_pixels(path, page.shape, what="the TIFF page")
        data = page.asarray()
        tags = page.tags
        stored = None
        unit = tags["ResolutionUnit"].value if "ResolutionUnit" in tags else None
        code = int(unit or 0) if "XResolution" in tags else 0  # 0: no unit the table knows
        if code in _TIFF_RESOLUTION_UNIT_M:
            num, den = tags["XResolution"].value
            if num > 0 and den > 0:
                stored = _TIFF_RESOLUTION_UNIT_M[code] * den / num
    if data.ndim != 2:
        raise MeasurementFileError(f"{path}: expected a single-channel 2-D image, got shape {data.shape}")
    pixel = _need_pixel(path, pixel_size_m, stored, "this TIFF", "XResolution pixel size")
    height = data.astype(np.float64) * z_unit_m
    return Measurement(height, pixel, {"source_file": str(path), "format": "tiff", "z_unit_m": z_unit_m})


def _csv_unit(path, name):
    match = re.search(r"[(\[]\s*([^)\]]+?)\s*[)\]]", name)
    if not match:
        return 1e-6
    unit = match.group(1).lower()
    if unit not in CSV_UNITS_M:
        raise MeasurementFileError(f"{path}: unknown unit '{match.group(1)}' in column '{name}'")
    return CSV_UNITS_M[unit]


def read_profile_csv(path: str | Path, pixel_size_m: float | None = None) -> Measurement:
    """Read an Mx profile CSV (columns X and Y or Slice, micrometres; blank = no data).

    Lines before the column-name row (the first row whose first cell starts with
    "X") are kept as ``key: value`` metadata. A unit in brackets in a column name
    ("X (mm)") overrides the micrometre default.

    Returns
    -------
    Measurement
        A 1-row height map in file order; the pixel size is the X step
        (:func:`~metrology.formats.profile.line_pitch`).
    """
    path = Path(path)
    text = path.read_text(encoding="utf-8-sig", errors="replace")
    rows = list(csv.reader(io.StringIO(text)))
    start = next((i for i, r in enumerate(rows) if r and r[0].strip().lower().startswith("x")), None)
    if start is None:
        raise MeasurementFileError(f"{path}: no column-name row starting with 'X' (not an Mx profile CSV)")
    names = [c.strip() for c in rows[start]]
    zcol = next((i for i, n in enumerate(names[1:], 1)
                 if n.lower().startswith(("y", "slice", "z", "height"))), None)
    if zcol is None:
        raise MeasurementFileError(f"{path}: no Y / Slice height column among {names}")
    xs, zs = [], []
    for lineno, row in enumerate(rows[start + 1:], start + 2):
        if not row or not row[0].strip():
            continue
        try:
            xs.append(float(row[0]))
            cell = row[zcol].strip() if len(row) > zcol else ""
            zs.append(float(cell) if cell else np.nan)
        except ValueError:
            raise MeasurementFileError(f"{path}: line {lineno} is not numeric: {','.join(row)!r}") from None
    x_unit = _csv_unit(path, names[0])
    step = line_pitch(path, np.asarray(xs), "X") * x_unit
    z = np.asarray(zs) * _csv_unit(path, names[zcol])
    metadata = {r[0].strip(): ",".join(r[1:]).strip() for r in rows[:start] if r and r[0].strip()}
    metadata.update({"source_file": str(path), "format": "mx_profile_csv", "x0_m": float(xs[0]) * x_unit,
                     "height_column": names[zcol]})
    return Measurement(z[np.newaxis, :], _need_pixel(path, pixel_size_m, step, "the X column", "X step"), metadata)
