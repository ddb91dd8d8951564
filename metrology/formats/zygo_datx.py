"""Zygo Mx ``.datx`` files (HDF5).

The surface dataset is found through the ``/MetaData`` table of (Source, Link,
Destination) strings: Root -> Measurement -> {guid}, {guid} -> Surface -> {guid2},
{guid2} -> Path -> ``/Data/Surface/{guid2}``. Files without a usable table are
searched at ``/Data/Surface/*`` and then ``/Measurement/Surface``.

Attributes of the surface dataset (each a 1-element array) give the unit (Fringes,
NanoMeters, MicroMeters, ...; NoUnits is not a height map), the no-data value, the
wavelength, the interferometric scale factor S and obliquity factor O (a value in
fringes is ``value * S * O * wavelength`` metres) and ``X Converter``, a compound
whose numeric ``Parameters`` field holds the pixel size in metres at index 1.

Only the surface dataset and its attributes are read: some files hold small side
datasets compressed with a vendor filter h5py cannot decode. Links are looked at before
they are followed and the surface's storage is checked: an external link, external raw
storage or a virtual dataset mapped from another file would read someone else's data (or
/dev/zero) as the surface, so they are refused. The array keeps camera
order (row 0 at the top of the camera image).
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from metrology.formats.measurement import Measurement, MeasurementFileError, read_head
from metrology.formats.plausibility import check_claimed_pixels, check_value, pixel_size

if TYPE_CHECKING:
    import h5py

__all__ = ["FRINGES", "HDF5_SIGNATURE", "LENGTH_UNITS_M", "NOT_HEIGHT_UNITS", "converter_parameters",
           "find_surface", "read_datx"]

log = logging.getLogger(__name__)

# Length units of the surface data, in metres. "Fringes" is handled separately.
LENGTH_UNITS_M = {
    "Meters": 1.0,
    "MilliMeters": 1e-3,
    "MicroMeters": 1e-6,
    "NanoMeters": 1e-9,
    "Angstroms": 1e-10,
}
FRINGES = "Fringes"
NOT_HEIGHT_UNITS = ("NoUnits",)
HDF5_SIGNATURE = b"\x89HDF\r\n\x1a\n"
# A No Data value at least this large marks every value at or above it (Zygo writes the type's
# maximum); a smaller one marks only itself, so a marker below the data cannot hide valid pixels.
NO_DATA_SENTINEL_MIN = 1e30
# Soft links followed in a row before a chain is taken for a loop.
MAX_SOFT_LINKS = 16


def _decode(value):
    if isinstance(value, bytes):
        return value.decode("utf-8", "replace").strip("\0 ")
    if isinstance(value, np.ndarray) and value.dtype.kind in "SUO" and value.size == 1:
        return _decode(value.reshape(-1)[0])
    return str(value).strip("\0 ") if isinstance(value, str) else value


def _attr(attrs, name, default=None):
    """First element of a 1-element attribute (decoded when text), or ``default``."""
    if name not in attrs:
        return default
    value = np.asarray(attrs[name])
    if value.dtype.names:
        return value.reshape(-1)[0] if value.size else default
    value = value.reshape(-1)
    if value.size == 0:
        return default
    item = value[0]
    return _decode(item) if isinstance(item, (bytes, str, np.bytes_, np.str_)) else item.item()


def converter_parameters(record: np.ndarray) -> np.ndarray | None:
    """The numeric parameter array of an ``X Converter`` / ``Y Converter`` record.

    The field is taken by name (``Parameters``) when present, otherwise as the first
    field, by position, holding at least two numbers: files differ in extra fields.
    """
    names = record.dtype.names or ()
    order = (["Parameters"] if "Parameters" in names else []) + list(range(len(names)))
    for key in order:
        value = np.asarray(record[key])
        if value.dtype.kind in "fiu" and value.size >= 2:
            return value.reshape(-1).astype(np.float64)
    return None


def _numbers(value):
    """The numbers of an attribute (plain or compound) as a list; text fields are skipped."""
    value = np.asarray(value).reshape(-1)
    items = list(value[0]) if value.dtype.names and value.size else list(value)
    out = []
    for item in items:
        try:
            out.append(float(item))
        except (TypeError, ValueError):
            continue
    return out


def _resolve(f, name, path, hops=0):
    """The object at ``name`` in ``f``, None when missing, never leaving the file.

    Each path component's link is looked at before it is followed: an external link
    (another file, /dev/zero, a pipe) is refused, a soft link is resolved inside the file
    (a dangling one is missing). h5py would otherwise follow both silently.
    """
    import h5py

    node, where = f["/"], ""
    for part in [p for p in name.split("/") if p]:
        if not isinstance(node, h5py.Group):
            return None
        link = node.get(part, getlink=True)
        parent, where = where, f"{where}/{part}"
        if link is None:
            return None
        if isinstance(link, h5py.ExternalLink):
            raise MeasurementFileError(f"{path}: {where} is an external link to {link.filename}:{link.path}; "
                                       "a .datx must hold its own data")
        if isinstance(link, h5py.SoftLink):
            if hops >= MAX_SOFT_LINKS:
                raise MeasurementFileError(f"{path}: {where}: more than {MAX_SOFT_LINKS} soft links in a row (a loop?)")
            target = link.path if link.path.startswith("/") else f"{parent}/{link.path}"
            node = _resolve(f, target, path, hops + 1)
            if node is None:
                return None
        elif isinstance(link, h5py.HardLink):
            node = node[part]
        else:
            raise MeasurementFileError(f"{path}: {where} is a {type(link).__name__}, not a group or dataset")
    return node


def _check_storage(dset, path):
    """Refuse a dataset whose values live outside the file (external raw storage, virtual sources)."""
    import h5py

    plist = dset.id.get_create_plist()
    if plist.get_external_count():
        target = _decode(plist.get_external(0)[0])
        raise MeasurementFileError(f"{path}: {dset.name} keeps its values in an external file ({target}); "
                                   "a .datx must hold its own data")
    if plist.get_layout() == h5py.h5d.VIRTUAL:
        outside = sorted({_decode(plist.get_virtual_filename(i)) for i in range(plist.get_virtual_count())} - {"."})
        if outside:
            raise MeasurementFileError(f"{path}: {dset.name} is a virtual dataset mapped from {', '.join(outside)}; "
                                       "a .datx must hold its own data")
    return dset


def _metadata_table(f, path):
    """Map (source, link) -> destination from ``/MetaData``; {} when absent or odd."""
    meta = _resolve(f, "MetaData", path)
    if meta is None or not hasattr(meta, "dtype"):
        return {}
    check_claimed_pixels(path, meta.shape, what="/MetaData")
    table = _check_storage(meta, path)[()]
    names = table.dtype.names
    if not names or len(names) < 3:
        return {}
    src, link, dst = (("Source", "Link", "Destination") if {"Source", "Link", "Destination"} <= set(names)
                      else names[:3])
    return {(_decode(row[src]), _decode(row[link])): _decode(row[dst]) for row in table.reshape(-1)}


def _first_dataset(f, group, path):
    found = {k: _resolve(f, f"{group.name}/{k}", path) for k in sorted(group.keys())}
    keys = [k for k, obj in found.items() if hasattr(obj, "shape")]
    if len(keys) > 1:
        log.warning("%s holds %d surfaces; reading %s", group.name, len(keys), keys[0])
    return found[keys[0]] if keys else None


def find_surface(f: h5py.File, path: str | Path) -> tuple[h5py.Dataset, str]:
    """The surface dataset of an open ``.datx`` and how it was found.

    Returns
    -------
    (h5py.Dataset, str)
        The dataset and one of "metadata", "data_surface", "measurement_surface".
    """
    table = _metadata_table(f, path)
    measurement = table.get(("Root", "Measurement"))
    surface = table.get((measurement, "Surface")) if measurement else None
    if surface:
        target = table.get((surface, "Path"), f"/Data/Surface/{surface}")
        obj = _resolve(f, target, path)
        if hasattr(obj, "shape"):
            return _check_storage(obj, path), "metadata"
        log.warning("%s: /MetaData points to %s, which is missing; searching the usual places", path, target)
    group = _resolve(f, "Data/Surface", path)
    if group is not None and not hasattr(group, "shape"):
        dset = _first_dataset(f, group, path)
        if dset is not None:
            return _check_storage(dset, path), "data_surface"
    obj = _resolve(f, "Measurement/Surface", path)
    if obj is not None:
        dset = obj if hasattr(obj, "shape") else _first_dataset(f, obj, path)
        if dset is not None:
            return _check_storage(dset, path), "measurement_surface"
    raise MeasurementFileError(f"{path}: no surface dataset (looked through /MetaData, /Data/Surface/*, "
                               "/Measurement/Surface)")


def read_datx(path: str | Path, pixel_size_m: float | None = None) -> Measurement:
    """Read a Zygo Mx ``.datx`` height map.

    Parameters
    ----------
    path : str or Path
    pixel_size_m : float, optional
        Lateral sampling when the file's X Converter lacks it; overrides it when given.

    Returns
    -------
    Measurement
        Heights in metres, camera order, NaN where the file has no data.

    Raises
    ------
    MeasurementFileError
        Not HDF5, no surface dataset, unit NoUnits or unknown, missing attributes
        needed for the conversion, a surface that is not 2-D.
    """
    import h5py

    path = Path(path)
    signature = read_head(path, 8)
    if signature != HDF5_SIGNATURE:
        raise MeasurementFileError(f"{path}: not a .datx file (no HDF5 signature)")
    try:
        f = h5py.File(path, "r")
    except OSError as exc:
        raise MeasurementFileError(f"{path}: cannot open as HDF5 (truncated or damaged?): {exc}") from None
    with f:
        try:
            dset, found = find_surface(f, path)
            return _read_surface(path, dset, found, pixel_size_m)
        except (OSError, KeyError, ValueError, TypeError, RuntimeError) as exc:
            # h5py reports damaged chunks, undecodable filters and broken attribute types this way.
            raise MeasurementFileError(f"{path}: cannot read the surface data: {exc}") from None


def _read_surface(path, dset, found, pixel_size_m):
    attrs = dset.attrs
    unit = _attr(attrs, "Unit")
    if unit is None:
        raise MeasurementFileError(f"{path}: surface {dset.name} has no 'Unit' attribute")
    if unit in NOT_HEIGHT_UNITS:
        raise MeasurementFileError(f"{path}: surface {dset.name} has unit '{unit}': not a height map")
    if unit != FRINGES and unit not in LENGTH_UNITS_M:
        raise MeasurementFileError(f"{path}: surface {dset.name} has unknown unit '{unit}' "
                                   f"(known: {FRINGES}, {', '.join(LENGTH_UNITS_M)})")
    if len(dset.shape) != 2 or 0 in dset.shape:
        raise MeasurementFileError(f"{path}: surface {dset.name} has shape {dset.shape}; expected 2-D")
    wavelength = _attr(attrs, "Wavelength")
    scale = _attr(attrs, "Interferometric Scale Factor")
    obliquity = _attr(attrs, "Obliquity Factor", 1.0)
    check_claimed_pixels(path, dset.shape, what=f"surface {dset.name}")
    if dset.dtype.kind not in "fiu":
        raise MeasurementFileError(f"{path}: surface {dset.name} holds {dset.dtype}, not numbers")
    data = dset[()].astype(np.float64, copy=False)
    no_data = _attr(attrs, "No Data")
    if no_data is not None and not isinstance(no_data, (int, float)):
        raise MeasurementFileError(f"{path}: surface attribute 'No Data' is {no_data!r}, not a number")
    invalid = ~np.isfinite(data)
    if no_data is not None and np.isfinite(no_data):
        # The marker itself (to the stored precision), never a threshold: a marker below the data
        # must not mark valid pixels invalid.
        marked = np.isclose(data, no_data, rtol=1e-6, atol=0)
        if no_data >= NO_DATA_SENTINEL_MIN:  # a sentinel at the top of the range: anything above is no data
            marked |= data >= no_data
        invalid |= marked
        if marked.any():
            log.info("%s: %d pixels hold the No Data value %g", path, int(marked.sum()), no_data)
    if unit == FRINGES:
        # The physical ranges before the product: a nm value in the wavelength field must not overflow.
        factor = (check_value(path, "Interferometric Scale Factor", scale, "intf_scale_factor")
                  * check_value(path, "Obliquity Factor", obliquity, "obliquity_factor")
                  * check_value(path, "Wavelength", wavelength, "wavelength_m"))
    else:
        factor = LENGTH_UNITS_M[unit]
    data *= factor
    data[invalid] = np.nan
    params = converter_parameters(attrs["X Converter"][()].reshape(-1)[0]) if "X Converter" in attrs else None
    pixel = pixel_size(path, pixel_size_m, params[1] if params is not None else None, "X Converter pixel size",
                       "no lateral pixel size in the X Converter")
    metadata = {
        "source_file": str(path),
        "format": "mx_datx",
        "surface_path": dset.name,
        "surface_found_by": found,
        "unit": unit,
        "wavelength_m": None if wavelength is None else float(wavelength),
        "intf_scale_factor": None if scale is None else float(scale),
        "obliquity_factor": None if obliquity is None else float(obliquity),
        "no_data": None if no_data is None else float(no_data),
    }
    if "Coordinates" in attrs:
        metadata["coordinates"] = _numbers(attrs["Coordinates"])
    log.info("%s: datx surface %s (%s), unit %s", path, dset.name, found, unit)
    return Measurement(data, pixel, metadata)
