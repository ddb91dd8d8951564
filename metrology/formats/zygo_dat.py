"""MetroPro ``.dat`` binary files (header formats 1, 2 and 3).

Layout (MetroPro Reference Guide OMP-0347): a header whose first bytes are a magic
number naming its format and size, then ``ac_n_buckets`` intensity frames (uint16
big-endian, ``ac_height x ac_width`` each), then the phase array (int32 big-endian,
``cn_height x cn_width``, row-major, row 0 at the top of the camera image). The
fields used here are all big-endian; fields from byte 502 on are little-endian but
none of them is needed to recover heights.

Height in metres = counts * S * O * wavelength / R with R = 4096, 32768 or 131072
for phase_res 0, 1, 2, negated when the phase-sign field is set. Counts at or above
2147483640 are invalid.

The returned array keeps camera order (row 0 at the top of the camera image).
"""

from __future__ import annotations

import datetime as _dt
import logging
import struct
from pathlib import Path

import numpy as np

from metrology.formats.measurement import Measurement, MeasurementFileError
from metrology.formats.plausibility import pixel_size

__all__ = ["FIELDS", "INVALID_INTENSITY", "INVALID_PHASE", "MAGIC", "MAGIC_BY_FORMAT", "PHASE_RES_COUNTS",
           "counts_to_height", "height_step_m", "height_to_counts", "read_dat", "read_header", "unix_to_iso"]

log = logging.getLogger(__name__)

# magic -> (header_format, header_size)
MAGIC = {
    0x881B036F: (1, 834),
    0x881B0370: (2, 834),
    0x881B0371: (3, 4096),
}
MAGIC_BY_FORMAT = {fmt: (magic, size) for magic, (fmt, size) in MAGIC.items()}

# phase_res code -> R, the counts per wave of the phase array
PHASE_RES_COUNTS = {0: 4096, 1: 32768, 2: 131072}
INVALID_PHASE = 2147483640
INVALID_INTENSITY = 65412

# Header fields read and written by this package: name -> (byte offset, struct code).
# All big-endian (the little-endian part starts at byte 502 and is not needed).
FIELDS = {
    "magic": (0, "I"),
    "header_format": (4, "H"),
    "header_size": (6, "I"),
    "ac_org_x": (48, "h"),
    "ac_org_y": (50, "h"),
    "ac_width": (52, "H"),
    "ac_height": (54, "H"),
    "ac_n_buckets": (56, "H"),
    "ac_n_bytes": (60, "I"),
    "cn_org_x": (64, "h"),
    "cn_org_y": (66, "h"),
    "cn_width": (68, "H"),
    "cn_height": (70, "H"),
    "cn_n_bytes": (72, "I"),
    "time_stamp": (76, "i"),
    "comment": (80, "82s"),
    "intf_scale_factor": (164, "f"),
    "wavelength_in": (168, "f"),
    "num_aperture": (172, "f"),
    "obliquity_factor": (176, "f"),
    "magnification": (180, "f"),
    "lateral_res": (184, "f"),
    "phase_res": (218, "h"),
    "phase_sign": (232, "h"),
    "obj_name": (246, "12s"),
    "part_name": (258, "40s"),
}


def height_step_m(intf_scale_factor: float, obliquity_factor: float, wavelength_m: float, phase_res: int,
                  path: str | Path = "<data>") -> float:
    """Height of one phase count, S * O * wavelength / R, in metres.

    Raises
    ------
    MeasurementFileError
        Unknown ``phase_res`` code or a non-positive scale, obliquity or wavelength.
    """
    if phase_res not in PHASE_RES_COUNTS:
        raise MeasurementFileError(f"{path}: phase_res is {phase_res}; expected 0, 1 or 2")
    for name, value in (("interferometric scale factor", intf_scale_factor),
                        ("obliquity factor", obliquity_factor), ("wavelength", wavelength_m)):
        if not (np.isfinite(value) and value > 0):
            raise MeasurementFileError(f"{path}: {name} is {value}; cannot convert phase to height")
    return float(intf_scale_factor) * float(obliquity_factor) * float(wavelength_m) / PHASE_RES_COUNTS[phase_res]


def counts_to_height(counts: np.ndarray, step_m: float, sign_flip: bool) -> np.ndarray:
    """Phase counts (int array) to heights in metres; invalid counts become NaN."""
    height = counts.astype(np.float64) * (-step_m if sign_flip else step_m)
    height[counts >= INVALID_PHASE] = np.nan
    return height


def height_to_counts(height_m: np.ndarray, step_m: float, sign_flip: bool, path: str | Path = "<data>") -> np.ndarray:
    """Heights in metres to int32 phase counts (the inverse of :func:`counts_to_height`).

    NaN becomes the invalid marker; heights beyond the count range raise.
    """
    height_m = np.asarray(height_m, dtype=np.float64)
    valid = np.isfinite(height_m)
    counts = np.zeros(height_m.shape, dtype=np.float64)
    counts[valid] = np.rint(height_m[valid] / (-step_m if sign_flip else step_m))
    if valid.any() and np.abs(counts[valid]).max() >= INVALID_PHASE:
        raise MeasurementFileError(f"{path}: heights up to {np.nanmax(np.abs(height_m)):.3g} m exceed the "
                                   f"phase count range at {step_m:.3g} m per count")
    counts[~valid] = INVALID_PHASE
    return counts.astype(np.int32)


def unix_to_iso(seconds: float) -> str | None:
    """Unix seconds to an ISO 8601 UTC string (None for 0, i.e. not recorded)."""
    if not seconds:
        return None
    try:
        return _dt.datetime.fromtimestamp(int(seconds), _dt.timezone.utc).isoformat()
    except (OverflowError, OSError, ValueError):
        log.warning("time stamp %s is out of range; not recorded", seconds)
        return None


def _text(raw):
    return raw.split(b"\0", 1)[0].decode("latin-1").strip()


def read_header(path: str | Path, raw: bytes) -> dict:
    """Decode and check the header of a ``.dat`` file.

    Parameters
    ----------
    path : Path
        For messages.
    raw : bytes
        At least the first 4096 bytes of the file (fewer if the file is shorter).

    Returns
    -------
    dict
        Field name to value (strings decoded).
    """
    if len(raw) < 4:
        raise MeasurementFileError(f"{path}: truncated .dat file ({len(raw)} bytes, no header)")
    magic = struct.unpack(">I", raw[:4])[0]
    if magic not in MAGIC:
        raise MeasurementFileError(f"{path}: not a MetroPro .dat file (magic 0x{magic:08X}; "
                                   "expected 0x881B036F, 0x881B0370 or 0x881B0371)")
    fmt, size = MAGIC[magic]
    if len(raw) < size:
        raise MeasurementFileError(f"{path}: truncated .dat file: header format {fmt} needs {size} "
                                   f"header bytes, file has {len(raw)}")
    header = {}
    for name, (offset, code) in FIELDS.items():
        value = struct.unpack_from(">" + code, raw, offset)[0]
        header[name] = _text(value) if isinstance(value, bytes) else value
    if header["header_format"] != fmt or header["header_size"] != size:
        raise MeasurementFileError(
            f"{path}: header mismatch: magic says format {fmt} with {size} header bytes, header "
            f"fields say format {header['header_format']} with {header['header_size']}")
    aw, ah, nb = header["ac_width"], header["ac_height"], header["ac_n_buckets"]
    if header["ac_n_bytes"] != 2 * aw * ah * nb:
        raise MeasurementFileError(f"{path}: ac_n_bytes {header['ac_n_bytes']} != 2 x {aw} x {ah} x {nb} "
                                   "(intensity width, height, buckets)")
    cw, ch = header["cn_width"], header["cn_height"]
    if header["cn_n_bytes"] != 4 * cw * ch:
        raise MeasurementFileError(f"{path}: cn_n_bytes {header['cn_n_bytes']} != 4 x {cw} x {ch} "
                                   "(phase width, height)")
    return header


def read_dat(path: str | Path, pixel_size_m: float | None = None) -> Measurement:
    """Read a MetroPro ``.dat`` file.

    Parameters
    ----------
    path : str or Path
    pixel_size_m : float, optional
        Lateral sampling to use when the header's ``lateral_res`` is 0 (uncalibrated);
        overrides the header when given.

    Returns
    -------
    Measurement
        Heights in metres, camera order (row 0 at the top of the camera image),
        NaN where the phase is invalid.

    Raises
    ------
    MeasurementFileError
        Truncated file, wrong magic, header format/size mismatch, file size not equal to
        header_size + 2 nb aw ah + 4 cw ch, no phase data, unknown phase_res.
    """
    path = Path(path)
    try:
        with open(path, "rb") as f:
            raw = f.read(4096)
        file_size = path.stat().st_size
    except OSError as exc:
        raise MeasurementFileError(f"{path}: cannot read ({exc.strerror or exc})") from None
    h = read_header(path, raw)
    n_intensity = h["ac_width"] * h["ac_height"] * h["ac_n_buckets"]
    cw, ch = h["cn_width"], h["cn_height"]
    expected = h["header_size"] + 2 * n_intensity + 4 * cw * ch
    if file_size != expected:
        what = "truncated" if file_size < expected else "too long"
        raise MeasurementFileError(
            f"{path}: {what}: expected {expected} bytes (header {h['header_size']} + intensity "
            f"2x{h['ac_n_buckets']}x{h['ac_width']}x{h['ac_height']} + phase 4x{cw}x{ch}), found {file_size}")
    if cw * ch == 0:
        raise MeasurementFileError(f"{path}: the file holds no phase (height) data")
    step = height_step_m(h["intf_scale_factor"], h["obliquity_factor"], h["wavelength_in"],
                         h["phase_res"], path)
    # Skip the intensity frames without reading them: only the phase carries height.
    counts = np.fromfile(path, dtype=">i4", count=cw * ch,
                         offset=h["header_size"] + 2 * n_intensity).reshape(ch, cw)
    height = counts_to_height(counts, step, h["phase_sign"] != 0)
    pixel = pixel_size(path, pixel_size_m, h["lateral_res"], "lateral_res_m",
                       f"lateral_res is {h['lateral_res']} (not calibrated)")
    metadata = {
        "source_file": str(path),
        "format": "metropro_dat",
        "header_format": h["header_format"],
        "wavelength_m": float(h["wavelength_in"]),
        "intf_scale_factor": float(h["intf_scale_factor"]),
        "obliquity_factor": float(h["obliquity_factor"]),
        "phase_res": h["phase_res"],
        "phase_counts_per_wave": PHASE_RES_COUNTS[h["phase_res"]],
        "height_step_m": step,
        "sign_flip": h["phase_sign"] != 0,
        "numerical_aperture": float(h["num_aperture"]),
        "magnification": float(h["magnification"]),
        "lateral_res_m": float(h["lateral_res"]),
        "objective": h["obj_name"],
        "timestamp": unix_to_iso(h["time_stamp"]),
        "comment": h["comment"],
        "part_name": h["part_name"],
        "phase_origin": (h["cn_org_x"], h["cn_org_y"]),
        "intensity_origin": (h["ac_org_x"], h["ac_org_y"]),
        "intensity_shape": (h["ac_height"], h["ac_width"]),
        "intensity_frames": h["ac_n_buckets"],
    }
    log.info("%s: MetroPro format %d, %dx%d phase, step %.3g m", path, h["header_format"], ch, cw, step)
    return Measurement(height, pixel, metadata)
