"""Write height maps in the profilometer formats the readers accept.

Used by the tests (fixtures for every format and option) and by the demo (simulated
measurements a user can open in the same tools as real ones). Written from the
format facts in the readers' module docstrings; each writer is atomic and
round-trips to the format's resolution (one phase count for ``.dat`` / ``.asc``).

Arrays are written in the given order: row 0 becomes the top row of the camera
image (the first row stored). Origins are (x, y) in camera pixels.
"""

from __future__ import annotations

import struct
import uuid
from pathlib import Path
from collections.abc import Callable
from typing import Any

import numpy as np
from numpy.typing import DTypeLike

from doedesign.errors import DoeError
from doedesign.fileio import atomic_path

from metrology.formats.measurement import Measurement
from metrology.formats.zygo_ascii import NO_DATA, TITLE_ASC, TITLE_XYZ, header_lines
from metrology.formats.zygo_dat import FIELDS, MAGIC_BY_FORMAT, height_step_m, height_to_counts
from metrology.formats.zygo_datx import LENGTH_UNITS_M

__all__ = ["DATX_LAYOUTS", "DATX_NO_DATA", "HELIUM_NEON_M", "write_asc", "write_dat", "write_datx",
           "write_measurement", "write_npy", "write_npz", "write_profile_csv", "write_tiff", "write_xyz"]

DATX_LAYOUTS = ("metadata", "data_surface", "measurement_surface")
DATX_NO_DATA = np.finfo(np.float64).max
HELIUM_NEON_M = 632.8e-9


def _height(height_m):
    height = np.asarray(height_m, dtype=np.float64)
    if height.ndim != 2 or height.size == 0:
        raise DoeError(f"height_m must be a non-empty 2-D array, got shape {height.shape}")
    return height


def _intensity(intensity_frames, shape):
    """(frames, rows, cols) uint16 frames from an array or a frame count (synthetic ramps)."""
    if intensity_frames is None or np.isscalar(intensity_frames):
        n = int(intensity_frames or 0)
        ramp = (np.arange(shape[0] * shape[1]) % 4096).reshape(shape)
        return np.stack([(ramp + 1000 * k).astype(np.uint16) for k in range(n)]) if n else \
            np.zeros((0,) + tuple(shape), np.uint16)
    frames = np.asarray(intensity_frames)
    if frames.ndim == 2:
        frames = frames[np.newaxis]
    if frames.ndim != 3:
        raise DoeError(f"intensity_frames must be a count or a (frames, rows, cols) array, got {frames.shape}")
    return frames.astype(np.uint16)


def write_dat(path: str | Path, height_m: np.ndarray, pixel_size_m: float, header_format: int = 1,
              phase_res: int = 1, sign_flip: bool = False, wavelength_m: float = HELIUM_NEON_M,
              intf_scale_factor: float = 0.5, obliquity_factor: float = 1.0, intensity_frames: int = 0,
              phase_origin: tuple[int, int] = (0, 0), intensity_origin: tuple[int, int] | None = None,
              comment: str = "", part_name: str = "", objective: str = "", magnification: float = 0.0,
              numerical_aperture: float = 0.0, time_stamp: int = 0) -> Path:
    """Write a MetroPro ``.dat`` file.

    Parameters
    ----------
    path : str or Path
    height_m : array (rows, cols)
        Heights in metres, NaN = invalid; row 0 at the top of the camera image.
    pixel_size_m : float
        Lateral resolution stored in the header.
    header_format : {1, 2, 3}
    phase_res : {0, 1, 2}
        Counts per wave 4096, 32768, 131072.
    sign_flip : bool
        Store negated counts and set the phase-sign field (readers negate back).
    wavelength_m, intf_scale_factor, obliquity_factor : float
        One count is ``S * O * wavelength / R`` metres.
    intensity_frames : int or array (frames, rows, cols)
        Number of synthetic uint16 frames of the phase-window size, or the frames.
    phase_origin, intensity_origin : (x, y)
        Window origins in camera pixels (intensity defaults to the phase origin).
    comment, part_name, objective : str
        Truncated to 81, 39 and 11 characters.
    magnification, numerical_aperture : float
    time_stamp : int
        Unix seconds.

    Returns
    -------
    Path
    """
    height = _height(height_m)
    if header_format not in MAGIC_BY_FORMAT:
        raise DoeError(f"header_format must be 1, 2 or 3, got {header_format}")
    magic, size = MAGIC_BY_FORMAT[header_format]
    # The header stores float32: quantize with the values the reader will see.
    intf_scale_factor, obliquity_factor, wavelength_m = (
        float(np.float32(v)) for v in (intf_scale_factor, obliquity_factor, wavelength_m))
    step = height_step_m(intf_scale_factor, obliquity_factor, wavelength_m, phase_res, path)
    counts = height_to_counts(height, step, sign_flip, path)
    frames = _intensity(intensity_frames, height.shape)
    nb, ah, aw = frames.shape
    intensity_origin = phase_origin if intensity_origin is None else intensity_origin
    values = {
        "magic": magic, "header_format": header_format, "header_size": size,
        "ac_org_x": intensity_origin[0], "ac_org_y": intensity_origin[1],
        "ac_width": aw if nb else 0, "ac_height": ah if nb else 0, "ac_n_buckets": nb,
        "ac_n_bytes": 2 * nb * ah * aw,
        "cn_org_x": phase_origin[0], "cn_org_y": phase_origin[1],
        "cn_width": height.shape[1], "cn_height": height.shape[0], "cn_n_bytes": 4 * height.size,
        "time_stamp": int(time_stamp), "comment": comment[:81].encode("latin-1", "replace"),
        "intf_scale_factor": intf_scale_factor, "wavelength_in": wavelength_m,
        "num_aperture": numerical_aperture, "obliquity_factor": obliquity_factor,
        "magnification": magnification, "lateral_res": pixel_size_m, "phase_res": phase_res,
        "phase_sign": 1 if sign_flip else 0, "obj_name": objective[:11].encode("latin-1", "replace"),
        "part_name": part_name[:39].encode("latin-1", "replace"),
    }
    header = bytearray(size)
    for name, (offset, code) in FIELDS.items():
        struct.pack_into(">" + code, header, offset, values[name])
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            f.write(header)
            f.write(frames.astype(">u2").tobytes())
            f.write(counts.astype(">i4").tobytes())
    return Path(path)


def _converter(pixel_size_m, converter):
    """X/Y Converter record; ``converter="extra_fields"`` mimics files with more fields."""
    params = np.array([0.0, pixel_size_m, 0.0, 0.0])
    if converter == "standard":
        dtype = np.dtype([("Category", "S16"), ("BaseUnit", "S16"), ("HeightUnit", "S16"),
                          ("Parameters", "<f8", (4,))])
        return np.array([(b"LateralCat", b"Meters", b"Meters", params)], dtype=dtype)
    if converter == "extra_fields":
        dtype = np.dtype([("Version", "<i4"), ("Category", "S16"), ("BaseUnit", "S16"),
                          ("Scale", "<f8"), ("Values", "<f8", (4,)), ("Note", "S8")])
        return np.array([(2, b"LateralCat", b"Meters", 1.0, params, b"x")], dtype=dtype)
    raise DoeError(f"converter must be 'standard' or 'extra_fields', got {converter!r}")


def write_datx(path: str | Path, height_m: np.ndarray, pixel_size_m: float, unit: str = "MicroMeters",
               layout: str = "metadata", wavelength_m: float = HELIUM_NEON_M, intf_scale_factor: float = 0.5,
               obliquity_factor: float = 1.0, no_data: float = DATX_NO_DATA, converter: str = "standard",
               coordinates: tuple[int, int] = (0, 0), dtype: DTypeLike = np.float64) -> Path:
    """Write a Zygo Mx ``.datx`` (HDF5) height map.

    Parameters
    ----------
    path : str or Path
    height_m : array (rows, cols)
        Heights in metres, NaN = no data (written as ``no_data``).
    pixel_size_m : float
        Stored as ``X Converter`` / ``Y Converter`` Parameters[1].
    unit : str
        "Fringes" (value = height / (S O wavelength)), a length unit ("NanoMeters",
        "MicroMeters", ...), or "NoUnits" (values written unscaled; readers refuse it).
    layout : {"metadata", "data_surface", "measurement_surface"}
        Where the surface goes: /Data/Surface/{guid} linked from /MetaData, the same
        without /MetaData, or /Measurement/Surface.
    converter : {"standard", "extra_fields"}
        Converter record layout.
    coordinates : (x, y)
        Origin stored in the ``Coordinates`` attribute.
    dtype : numpy dtype
        Storage type of the surface.

    Returns
    -------
    Path
    """
    import h5py

    height = _height(height_m)
    if layout not in DATX_LAYOUTS:
        raise DoeError(f"layout must be one of {DATX_LAYOUTS}, got {layout!r}")
    if unit == "Fringes":
        values = height / (intf_scale_factor * obliquity_factor * wavelength_m)
    elif unit in LENGTH_UNITS_M:
        values = height / LENGTH_UNITS_M[unit]
    else:
        values = height.copy()
    values[~np.isfinite(values)] = no_data
    measurement_id = "{" + str(uuid.uuid4()).upper() + "}"
    surface_id = "{" + str(uuid.uuid4()).upper() + "}"
    with atomic_path(path) as tmp:
        with h5py.File(tmp, "w") as f:
            if layout == "measurement_surface":
                dset = f.create_dataset("Measurement/Surface", data=values.astype(dtype))
            else:
                dset = f.create_dataset(f"Data/Surface/{surface_id}", data=values.astype(dtype))
                f.create_group(f"Attributes/{measurement_id}")
            if layout == "metadata":
                text = h5py.string_dtype()
                rows = [("Root", "Measurement", measurement_id),
                        (measurement_id, "Surface", surface_id),
                        (surface_id, "Path", f"/Data/Surface/{surface_id}"),
                        (measurement_id, "Attributes", f"/Attributes/{measurement_id}")]
                table = np.array(rows, dtype=[("Source", text), ("Link", text), ("Destination", text)])
                f.create_dataset("MetaData", data=table)
            dset.attrs["Unit"] = np.array([unit.encode()])
            dset.attrs["No Data"] = np.array([no_data], dtype=dtype)
            dset.attrs["Wavelength"] = np.array([wavelength_m])
            dset.attrs["Interferometric Scale Factor"] = np.array([intf_scale_factor])
            dset.attrs["Obliquity Factor"] = np.array([obliquity_factor])
            dset.attrs["X Converter"] = _converter(pixel_size_m, converter)
            dset.attrs["Y Converter"] = _converter(pixel_size_m, converter)
            coord_type = np.dtype([("ColumnStart", "<i4"), ("RowStart", "<i4"),
                                   ("ColumnWidth", "<i4"), ("RowHeight", "<i4")])
            dset.attrs["Coordinates"] = np.array([(coordinates[0], coordinates[1], height.shape[1],
                                                   height.shape[0])], dtype=coord_type)
    return Path(path)


def _ascii_header(title, height, pixel_size_m, frames, phase_origin, options):
    nb = frames.shape[0]
    return header_lines(title, intensity_origin=phase_origin,
                        intensity_shape=frames.shape[1:] if nb else (0, 0), intensity_frames=nb,
                        phase_origin=phase_origin, phase_shape=height.shape,
                        pixel_size_m=pixel_size_m, **options)


def write_xyz(path: str | Path, height_m: np.ndarray, pixel_size_m: float, phase_origin: tuple[int, int] = (0, 0),
              z_unit_m: float = 1e-6, **header: Any) -> Path:
    """Write a Zygo ``.xyz`` export ("col row z" per pixel, z in ``z_unit_m``).

    ``header`` takes the fields of :func:`metrology.formats.zygo_ascii.header_lines`
    (wavelength_m, comment, part_name, ...). z is written with 7 decimals of its unit.
    """
    height = _height(height_m)
    lines = _ascii_header(TITLE_XYZ, height, pixel_size_m, _intensity(0, height.shape), phase_origin, header)
    rows, cols = np.indices(height.shape)
    z = height.ravel() / z_unit_m
    x0, y0 = phase_origin
    data = [f"{c + x0} {r + y0} {v:.7f}" if np.isfinite(v) else f"{c + x0} {r + y0} {NO_DATA}"
            for r, c, v in zip(rows.ravel().tolist(), cols.ravel().tolist(), z.tolist())]
    with atomic_path(path) as tmp:
        tmp.write_text("\n".join(lines + ["#"] + data + ["#"]) + "\n", encoding="latin-1")
    return Path(path)


def _ten_per_line(values):
    values = [str(v) for v in np.asarray(values).ravel().tolist()]
    return [" ".join(values[i:i + 10]) for i in range(0, len(values), 10)]


def write_asc(path: str | Path, height_m: np.ndarray, pixel_size_m: float, phase_res: int = 1,
              sign_flip: bool = False, wavelength_m: float = HELIUM_NEON_M, intf_scale_factor: float = 0.5,
              obliquity_factor: float = 1.0, intensity_frames: int = 0, phase_origin: tuple[int, int] = (0, 0),
              **header: Any) -> Path:
    """Write a Zygo ``.asc`` export (header, intensity, ``#``, phase counts 10 per line, ``#``).

    Phase counts quantize as in :func:`write_dat`; ``header`` takes further fields of
    :func:`metrology.formats.zygo_ascii.header_lines`.
    """
    height = _height(height_m)
    step = height_step_m(intf_scale_factor, obliquity_factor, wavelength_m, phase_res, path)
    counts = height_to_counts(height, step, sign_flip, path)
    frames = _intensity(intensity_frames, height.shape)
    options = dict(header, phase_res=phase_res, sign_flip=sign_flip, wavelength_m=wavelength_m,
                   intf_scale_factor=intf_scale_factor, obliquity_factor=obliquity_factor)
    lines = _ascii_header(TITLE_ASC, height, pixel_size_m, frames, phase_origin, options)
    lines += ["#"] + _ten_per_line(frames) + ["#"] + _ten_per_line(counts) + ["#"]
    with atomic_path(path) as tmp:
        tmp.write_text("\n".join(lines) + "\n", encoding="latin-1")
    return Path(path)


def write_profile_csv(path: str | Path, height_m: np.ndarray, pixel_size_m: float, x0_m: float = 0.0,
                      column: str = "Y", header: dict | None = None) -> Path:
    """Write an Mx-style profile CSV: columns X and ``column`` in micrometres, blank = no data.

    ``height_m`` is 1-D or a single row. ``header`` (dict) adds "key,value" lines
    before the column names.
    """
    z = np.asarray(height_m, dtype=np.float64)
    if z.ndim == 2 and z.shape[0] == 1:
        z = z[0]
    if z.ndim != 1 or z.size < 2:
        raise DoeError(f"a profile needs a 1-D array of at least 2 points, got shape {z.shape}")
    x_um = (x0_m + pixel_size_m * np.arange(z.size)) * 1e6
    lines = [f"{k},{v}" for k, v in (header or {}).items()] + [f"X,{column}"]
    lines += [f"{x!r},{v * 1e6!r}" if np.isfinite(v) else f"{x!r}," for x, v in zip(x_um.tolist(), z.tolist())]
    with atomic_path(path) as tmp:
        tmp.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return Path(path)


def write_npy(path: str | Path, height_m: np.ndarray) -> Path:
    """Write a bare ``.npy`` height map (metres); the reader needs ``pixel_size_m`` given."""
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        np.save(fh, _height(height_m))
    return Path(path)


def write_npz(path: str | Path, height_m: np.ndarray, pixel_size_m: float, metadata: dict | None = None) -> Path:
    """Write a ``.npz`` with ``height_m``, ``pixel_size_m`` and a JSON ``metadata`` string."""
    from doedesign.fileio import dumps_json
    from doedesign.fileio import write_npz as _write

    return _write(path, height_m=_height(height_m), pixel_size_m=np.float64(pixel_size_m),
                  metadata=np.array(dumps_json(metadata or {}, indent=None)))


def write_tiff(path: str | Path, height_m: np.ndarray, pixel_size_m: float, z_unit_m: float = 1.0) -> Path:
    """Write a float32 TIFF of ``height / z_unit_m`` with the pixel size as XResolution (per cm)."""
    import tifffile

    height = _height(height_m)
    per_cm = 0.01 / pixel_size_m
    with atomic_path(path) as tmp:
        tifffile.imwrite(tmp, (height / z_unit_m).astype(np.float32), resolution=(per_cm, per_cm),
                         resolutionunit="CENTIMETER")
    return Path(path)


def write_measurement(path: str | Path, measurement_or_array: Measurement | np.ndarray,
                      pixel_size_m: float | None = None, **options: Any) -> Path:
    """Write a :class:`~metrology.formats.measurement.Measurement` or a height array in the format named by the extension.

    Parameters
    ----------
    path : str or Path
        ``.dat``, ``.datx``, ``.xyz``, ``.asc``, ``.csv``, ``.npy``, ``.npz``, ``.tif``/``.tiff``.
    measurement_or_array : Measurement or array
    pixel_size_m : float, optional
        Required for an array; overrides the measurement's.
    **options
        Passed to the format writer.
    """
    pixel: float | None
    if isinstance(measurement_or_array, Measurement):
        height = measurement_or_array.height_m
        pixel = measurement_or_array.pixel_size_m if pixel_size_m is None else pixel_size_m
    else:
        height, pixel = measurement_or_array, pixel_size_m
    ext = Path(path).suffix.lower()
    if ext == ".npy":
        return write_npy(path, height)
    if pixel is None:
        raise DoeError(f"{path}: pixel_size_m is required to write a height array")
    writers: dict[str, Callable[..., Path]] = {".dat": write_dat, ".datx": write_datx, ".xyz": write_xyz, ".asc": write_asc,
               ".csv": write_profile_csv, ".npz": write_npz, ".tif": write_tiff, ".tiff": write_tiff}
    if ext not in writers:
        raise DoeError(f"{path}: cannot write extension '{ext}' (known: .npy, {', '.join(writers)})")
    if ext == ".npz" and isinstance(measurement_or_array, Measurement):
        options.setdefault("metadata", measurement_or_array.metadata)
    return writers[ext](path, height, pixel, **options)
