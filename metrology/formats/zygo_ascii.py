"""Zygo ASCII exports: ``.xyz`` (XYZ Data File, Format 1) and ``.asc`` (ASCII Data File, Format 2).

Both start with a header of lines in a fixed order, ended by a line holding only
``#`` (line numbers from 1):

1. title ("Zygo XYZ Data File - Format 1" or "Zygo ASCII Data File - Format 2")
2. software type, major, minor, bug version, "software date"
3. intensity origin x, y, width, height, number of buckets, intensity range
4. phase origin x, y, width, height (camera pixels)
5. "comment"
6. "part serial number"
7. "part name"
8. source, interferometric scale factor S, wavelength (m), numerical aperture,
   obliquity factor O, magnification, camera resolution (m per pixel), time stamp
   (Unix seconds)
9. camera width, height, system type, board, serial, instrument id, "objective name"
10. acquisition settings
11. phase_res, phase averages, minimum area size, discontinuity action and filter,
    connection order, remove tilt bias, data sign, code V type
12. and later lines: further settings (not needed)

Lines 1 to 8 are required; line 11 is needed only to convert ``.asc`` phase counts.
Quoted fields are text; the rest are numbers.

``.xyz`` data: one line per pixel, "col row z", col/row in camera pixels (the phase
origin is subtracted here), z in micrometres by default (``z_unit_m``), invalid
pixels written "No Data". ``.asc`` data: intensity integers, "#", phase counts
(10 per line) converting as in ``.dat``, "#".

Arrays keep camera order: row 0 at the top of the camera image.
"""

from __future__ import annotations

import logging
import re
import warnings
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from metrology.formats.measurement import Measurement, MeasurementFileError
from metrology.formats.plausibility import check_claimed_pixels, pixel_size
from metrology.formats.zygo_dat import PHASE_RES_COUNTS, counts_to_height, height_step_m, unix_to_iso

__all__ = ["NO_DATA", "TITLE_ASC", "TITLE_XYZ", "header_lines", "parse_header", "read_asc", "read_xyz"]

log = logging.getLogger(__name__)

TITLE_XYZ = "Zygo XYZ Data File - Format 1"
TITLE_ASC = "Zygo ASCII Data File - Format 2"
NO_DATA = "No Data"
_TOKEN = re.compile(r'"[^"]*"|\S+')
_END_OF_BLOCK = re.compile(r"^[ \t]*#[ \t]*\r?$", re.MULTILINE)
_CONTENT_LINE = re.compile(r"^[ \t]*[^\s#]", re.MULTILINE)


def header_lines(title: str, *, intensity_origin: tuple[int, int] = (0, 0),
                 intensity_shape: tuple[int, int] = (0, 0), intensity_frames: int = 0,
                 phase_origin: tuple[int, int] = (0, 0), phase_shape: tuple[int, int], comment: str = "",
                 part_serial: str = "", part_name: str = "", intf_scale_factor: float = 0.5,
                 wavelength_m: float = 632.8e-9, numerical_aperture: float = 0.0, obliquity_factor: float = 1.0,
                 magnification: float = 0.0, pixel_size_m: float = 0.0, time_stamp: int = 0, objective: str = "",
                 phase_res: int = 1, sign_flip: bool = False) -> list[str]:
    """The header lines of a Zygo ASCII file, in the documented order (without the ``#``).

    Shapes are (rows, cols); origins (x, y) in camera pixels.
    """
    (ih, iw), (ph, pw) = intensity_shape, phase_shape
    return [
        title,
        '1 0 0 0 "doe-toolkit"',
        f"{intensity_origin[0]} {intensity_origin[1]} {iw} {ih} {intensity_frames} 65535",
        f"{phase_origin[0]} {phase_origin[1]} {pw} {ph}",
        _quote(comment),
        _quote(part_serial),
        _quote(part_name),
        f"0 {intf_scale_factor!r} {wavelength_m!r} {numerical_aperture!r} {obliquity_factor!r} "
        f"{magnification!r} {pixel_size_m!r} {int(time_stamp)}",
        f'{pw} {ph} 0 0 0 0 {_quote(objective)}',
        "0 0 0 0 0 0 0 0 0 0",
        f"{phase_res} 0 0 0 0 0 0 {1 if sign_flip else 0} 0",
        '0 ""',
        "0 0",
        '""',
    ]


def _quote(text):
    return '"' + str(text).replace('"', "'") + '"'


def _split_header(path, text):
    """(title, header tokens per line, text after the '#' line).

    The data part stays one string: splitting a million-pixel export into line
    objects would cost several hundred MB.
    """
    match = _END_OF_BLOCK.search(text)
    if match is None:
        raise MeasurementFileError(f"{path}: no '#' line ends the header; not a Zygo ASCII file "
                                   "(or truncated)")
    lines = text[:match.start()].splitlines()
    if not lines or not lines[0].startswith("Zygo"):
        first = lines[0][:40] if lines else "#"
        raise MeasurementFileError(f"{path}: first line is not a Zygo ASCII title: {first!r}")
    if len(lines) < 8:
        raise MeasurementFileError(f"{path}: header has {len(lines)} lines; need at least 8")
    return lines[0].strip(), [_TOKEN.findall(line) for line in lines], text[match.end():]


def _number(path, header, line, index, cast=float):
    """Field ``index`` (0-based) of header line ``line`` (1-based) as a number."""
    fields = header[line - 1]
    try:
        return cast(float(fields[index]))
    except (IndexError, ValueError, OverflowError):  # OverflowError: int(inf)
        raise MeasurementFileError(f"{path}: header line {line} field {index + 1} is not a number: "
                                   f"{' '.join(fields)!r}") from None


def _text(header, line):
    fields = header[line - 1] if len(header) >= line else []
    return " ".join(fields).strip('"') if fields else ""


def parse_header(path: str | Path, header: Sequence[str]) -> dict:
    """Header fields as a dict (origins as (x, y), shapes as (rows, cols))."""
    h = {
        "intensity_origin": (_number(path, header, 3, 0, int), _number(path, header, 3, 1, int)),
        "intensity_shape": (_number(path, header, 3, 3, int), _number(path, header, 3, 2, int)),
        "intensity_frames": _number(path, header, 3, 4, int),
        "phase_origin": (_number(path, header, 4, 0, int), _number(path, header, 4, 1, int)),
        "phase_shape": (_number(path, header, 4, 3, int), _number(path, header, 4, 2, int)),
        "comment": _text(header, 5),
        "part_serial": _text(header, 6),
        "part_name": _text(header, 7),
        "intf_scale_factor": _number(path, header, 8, 1),
        "wavelength_m": _number(path, header, 8, 2),
        "numerical_aperture": _number(path, header, 8, 3),
        "obliquity_factor": _number(path, header, 8, 4),
        "magnification": _number(path, header, 8, 5),
        "lateral_res_m": _number(path, header, 8, 6),
        "time_stamp": _number(path, header, 8, 7, int),
        "objective": header[8][-1].strip('"') if len(header) >= 9 and header[8] else "",
    }
    if len(header) >= 11 and len(header[10]) >= 8:
        h["phase_res"] = _number(path, header, 11, 0, int)
        h["sign_flip"] = _number(path, header, 11, 7, int) != 0
    return h


def _metadata(path, fmt, h):
    keys = ("wavelength_m", "intf_scale_factor", "obliquity_factor", "numerical_aperture", "magnification",
            "lateral_res_m", "objective", "comment", "part_serial", "part_name", "phase_origin",
            "intensity_origin", "intensity_shape", "intensity_frames", "phase_res", "sign_flip")
    meta = {"source_file": str(path), "format": fmt, "timestamp": unix_to_iso(h["time_stamp"])}
    meta.update({k: h[k] for k in keys if k in h})
    return meta


def _pixel(path, h, pixel_size_m):
    return pixel_size(path, pixel_size_m, h["lateral_res_m"], "lateral_res_m",
                      f"camera resolution is {h['lateral_res_m']} (not calibrated)")


def _read_text(path):
    from doedesign.fileio import check_input_file

    path = check_input_file(path, MeasurementFileError)
    try:
        return path, path.read_text(encoding="latin-1")
    except OSError as exc:
        raise MeasurementFileError(f"{path}: cannot read ({exc.strerror or exc})") from None


def _floats(path, text, what):
    """All numbers in ``text`` (whitespace separated), parsed in C without a token list."""
    if not text.strip():  # numpy parses a blank string as [-1.0]
        return np.zeros(0)
    try:
        with warnings.catch_warnings():
            # Older numpy warns instead of raising when a token is not a number.
            warnings.simplefilter("error", DeprecationWarning)
            return np.fromstring(text, dtype=np.float64, sep=" ")
    except (ValueError, DeprecationWarning):
        raise MeasurementFileError(f"{path}: unparseable {what}: a field is not a number") from None


def read_xyz(path: str | Path, pixel_size_m: float | None = None, z_unit_m: float = 1e-6) -> Measurement:
    """Read a Zygo ``.xyz`` export.

    Parameters
    ----------
    path : str or Path
    pixel_size_m : float, optional
        Lateral sampling if the header's camera resolution is 0; overrides it when given.
    z_unit_m : float
        Unit of the z column (micrometres from MetroPro; Mx lets the user choose).

    Returns
    -------
    Measurement
        Heights in metres on the phase window (origin subtracted), camera order;
        NaN for "No Data" and for pixels not listed.
    """
    path, text = _read_text(path)
    title, header, body = _split_header(path, text)
    h = parse_header(path, header)
    body = _END_OF_BLOCK.sub("", body)
    values = _floats(path, body.replace(NO_DATA, "nan"), "data line (expected 'col row z')")
    if values.size == 0:
        raise MeasurementFileError(f"{path}: no data lines after the header")
    n_lines = sum(1 for _ in _CONTENT_LINE.finditer(body))
    if values.size != 3 * n_lines:
        raise MeasurementFileError(f"{path}: data lines must hold 'col row z' (3 fields); "
                                   f"found {values.size} fields on {n_lines} lines")
    xyz = values.reshape(-1, 3)
    if not np.all(np.isfinite(xyz[:, :2])) or np.any(xyz[:, :2] != np.round(xyz[:, :2])):
        raise MeasurementFileError(f"{path}: column/row indices must be integers")
    cols = xyz[:, 0].astype(np.int64) - h["phase_origin"][0]
    rows = xyz[:, 1].astype(np.int64) - h["phase_origin"][1]
    ph, pw = h["phase_shape"]
    if ph <= 0 or pw <= 0:
        ph, pw = int(rows.max()) + 1, int(cols.max()) + 1
    if rows.min() < 0 or cols.min() < 0 or rows.max() >= ph or cols.max() >= pw:
        raise MeasurementFileError(f"{path}: pixel indices fall outside the phase window "
                                   f"(origin {h['phase_origin']}, {pw} x {ph})")
    check_claimed_pixels(path, (ph, pw), listed=len(rows), what="the phase window (header line 4)")
    flat = rows * pw + cols
    unique, first = np.unique(flat, return_index=True)
    if unique.size != flat.size:
        repeated = np.setdiff1d(np.arange(flat.size), first)[0]
        raise MeasurementFileError(f"{path}: pixel (col {cols[repeated] + h['phase_origin'][0]}, row "
                                   f"{rows[repeated] + h['phase_origin'][1]}) is listed more than once "
                                   f"({flat.size - unique.size} repeated lines; data line {repeated + 1})")
    height = np.full((ph, pw), np.nan)
    height[rows, cols] = xyz[:, 2] * z_unit_m
    meta = _metadata(path, "zygo_xyz", h)
    meta["z_unit_m"] = z_unit_m
    return Measurement(height, _pixel(path, h, pixel_size_m), meta)


def _check_counts(path, counts, width):
    """Phase counts must be integers of the int32 range (the invalid marker included)."""
    bad = ~np.isfinite(counts) | (counts != np.round(counts)) | (np.abs(counts) > 2**31 - 1)
    if bad.any():
        i = int(np.argmax(bad))
        raise MeasurementFileError(f"{path}: phase count at row {i // width}, col {i % width} is {counts[i]!r}; "
                                   f"counts are integers within the int32 range ({int(bad.sum())} bad values)")


def read_asc(path: str | Path, pixel_size_m: float | None = None, phase_res: int | None = None) -> Measurement:
    """Read a Zygo ``.asc`` export.

    Parameters
    ----------
    path : str or Path
    pixel_size_m : float, optional
        Lateral sampling if the header's camera resolution is 0; overrides it when given.
    phase_res : int, optional
        Phase resolution code (0, 1, 2) when header line 11 is missing; overrides it.

    Returns
    -------
    Measurement
        Heights in metres on the phase window, camera order, NaN where invalid.
    """
    path, text = _read_text(path)
    title, header, body = _split_header(path, text)
    h = parse_header(path, header)
    sections = _END_OF_BLOCK.split(body)[:-1]  # the part after the last '#' is not a block
    if len(sections) < 2:
        raise MeasurementFileError(f"{path}: expected intensity and phase blocks each ended by '#'; "
                                   f"found {len(sections)} (truncated?)")
    intensity = _floats(path, sections[0], "intensity block")
    counts = _floats(path, sections[1], "phase block")
    ih, iw = h["intensity_shape"]
    if intensity.size != ih * iw * h["intensity_frames"]:
        raise MeasurementFileError(f"{path}: intensity block holds {intensity.size} values; header says "
                                   f"{h['intensity_frames']} x {iw} x {ih}")
    ph, pw = h["phase_shape"]
    if counts.size != ph * pw or counts.size == 0:
        raise MeasurementFileError(f"{path}: phase block holds {counts.size} values; header says {pw} x {ph}")
    if phase_res is None:
        if "phase_res" not in h:
            raise MeasurementFileError(f"{path}: header line 11 (phase_res) is missing; pass phase_res "
                                       f"({', '.join(f'{k} -> {v}' for k, v in PHASE_RES_COUNTS.items())})")
        phase_res = h["phase_res"]
    h["phase_res"] = phase_res
    step = height_step_m(h["intf_scale_factor"], h["obliquity_factor"], h["wavelength_m"], phase_res, path)
    _check_counts(path, counts, pw)
    height = counts_to_height(counts.astype(np.int64).reshape(ph, pw), step, h.get("sign_flip", False))
    meta = _metadata(path, "zygo_asc", h)
    meta["height_step_m"] = step
    return Measurement(height, _pixel(path, h, pixel_size_m), meta)
