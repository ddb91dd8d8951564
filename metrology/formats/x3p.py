"""ISO 25178-72 ``.x3p`` read and write through x3pio.

x3pio (MIT, pure Python on NumPy and defusedxml) reads and writes the standard's container (a
zip of ``main.xml``, the binary point data and their MD5 checksums), gives the header (axes,
increments, data type, point count) before the points are inflated (:func:`x3pio.info`), and
refuses a damaged file with ``X3pFormatError`` / ``X3pChecksumError``. SurfaceTopography reads
x3p too but writes none, so x3pio serves both ways; the tests read what this module writes
back with SurfaceTopography (an independent reader).

Orientation: x3p stores a surface as (rows along y, columns along x), x the fast axis, which
is the tool's row-major order; nothing is flipped. The row and column increments are kept as
they are (an x3p from MountainsMap with 0.128 x 0.315 um pixels reads as such).
"""

from __future__ import annotations

import datetime
import logging
import zipfile
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike

from doedesign.fileio import atomic_path
from metrology.formats.measurement import Measurement, MeasurementFileError
from metrology.formats.plausibility import check_claimed_pixels, pixel_size

__all__ = ["MAX_X3P_INFLATION", "read_x3p", "write_levelled_and_residual", "write_x3p"]

log = logging.getLogger(__name__)

# Largest ratio of inflated to stored bytes accepted: real point data deflate 2-10x; a few
# hundred covers constant fields, and a zip bomb (1000x and more) is refused before inflating.
MAX_X3P_INFLATION = 500


def _check_zip(path: Path) -> None:
    try:
        with zipfile.ZipFile(path) as zf:
            members = zf.infolist()
    except (zipfile.BadZipFile, OSError, ValueError) as exc:
        raise MeasurementFileError(f"{path}: not an x3p container (a zip): {exc}") from None
    stored = max(1, path.stat().st_size)
    inflated = sum(m.file_size for m in members)
    if inflated > MAX_X3P_INFLATION * stored + 2**20:
        raise MeasurementFileError(f"{path}: the x3p members claim {inflated} bytes inflated from {stored} "
                                   f"(over {MAX_X3P_INFLATION}x): refused before inflating")


def read_x3p(path: str | Path, pixel_size_m: float | None = None) -> Measurement:
    """Read an ISO 25178-72 surface (``.x3p``) of regular grid.

    Parameters
    ----------
    path : str or Path
    pixel_size_m : float, optional
        Column pitch overriding the file's x increment (the y increment scales with it).

    Returns
    -------
    Measurement
        Heights in metres (NaN where the file marks a point not measured), the x increment as
        ``pixel_size_m`` and the y increment as ``pixel_size_y_m`` when they differ. Layer 0
        when the file holds several (the metadata says how many).

    Raises
    ------
    MeasurementFileError
        Not an x3p, a profile or point cloud, a damaged container, a bad checksum, or a
        claimed size beyond the limit.
    """
    import x3pio

    path = Path(path)
    _check_zip(path)
    try:
        info = x3pio.info(path)
        check_claimed_pixels(path, tuple(info.shape) + (max(1, int(info.layer_count)),), what="main.xml")
        if str(getattr(info.feature_type, "value", info.feature_type)) != "SUR":
            raise MeasurementFileError(f"{path}: the x3p holds a {info.feature_type} (not a surface SUR); "
                                       f"x3p profiles and point clouds are not read")
        surf = x3pio.read(path)
        layer = surf.layers[0]
        z = np.asarray(layer.z, dtype=np.float64)
        dx = float(surf.header.x.increment) if surf.header.x.increment else None
        dy = float(surf.header.y.increment) if surf.header.y.increment else None
    except MeasurementFileError:
        raise
    except MemoryError:
        raise MeasurementFileError(f"{path}: the x3p data do not fit in memory") from None
    except Exception as exc:  # x3pio's X3pError family and anything a hostile zip/XML raises
        text = " ".join(str(exc).split())[:300] or type(exc).__name__
        raise MeasurementFileError(f"{path}: cannot read as x3p: {text}") from None
    if z.ndim != 2:
        raise MeasurementFileError(f"{path}: expected a 2-D surface, got shape {z.shape}")
    x = pixel_size(path, pixel_size_m, dx, "x increment", "the x axis is not incremental")
    y = None if dy is None or dx is None else dy * (x / dx)
    meta = surf.metadata
    metadata = {"source_file": str(path), "format": "x3p", "reader": "x3pio", "layers": len(surf.layers)}
    inst = getattr(meta, "instrument", None) if meta is not None else None
    if inst is not None:
        metadata["instrument"] = " ".join(str(v) for v in (inst.manufacturer, inst.model, inst.version) if v)
    date = getattr(meta, "date", None) if meta is not None else None
    if date is not None:
        metadata["timestamp"] = date.isoformat()
    if meta is not None and getattr(meta, "comment", None):
        metadata["comment"] = str(meta.comment)
    return Measurement(z, x, metadata, pixel_size_y_m=y)


def _metadata(x3pio, comment):
    # Every Record2 field filled: SurfaceTopography's reader fails on an absent instrument or date.
    now = datetime.datetime.now(datetime.timezone.utc).replace(microsecond=0)
    return x3pio.Metadata(date=now, creator="doe-toolkit", calibration_date=now, comment=comment or None,
                          instrument=x3pio.Instrument("doe-toolkit", "levelled measurement", "not available", "1"),
                          probing_system=x3pio.ProbingSystem(type=x3pio.ProbingType.SOFTWARE,
                                                             identification="doe-toolkit"))


def write_x3p(path: str | Path, height_m: ArrayLike, pixel_size_m: float, pixel_size_y_m: float | None = None,
              comment: str = "") -> Path:
    """Write a height map as an ISO 25178-72 surface, atomically.

    Parameters
    ----------
    path : str or Path
        Destination (``.x3p``).
    height_m : array, shape (rows, cols)
        Heights in metres, NaN = not measured; row 0 is written first (y = 0).
    pixel_size_m, pixel_size_y_m : float
        Column (x) and row (y) increments in metres; square when the second is None.
    comment : str
        Stored in the file's metadata (``Record2/Comment``).

    Returns
    -------
    Path

    Notes
    -----
    The revision written is ``ISO5436 - 2000``, the one every reader takes (Gwyddion,
    MountainsMap 6, SurfaceTopography refuses x3pio's default ``ISO25178-72:2017/DAM1``); the
    heights are stored as float64 metres.
    """
    import x3pio

    height = np.asarray(height_m, dtype=np.float64)
    if height.ndim != 2:
        raise ValueError(f"height_m must be 2-D, got shape {height.shape}")
    path = Path(path)
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        x3pio.write(fh, height, x_scale=float(pixel_size_m),
                    y_scale=float(pixel_size_y_m if pixel_size_y_m is not None else pixel_size_m),
                    z_type=x3pio.DataType.FLOAT64, revision=x3pio.Revision.ISO5436_2000,
                    metadata=_metadata(x3pio, comment))
    return path


def write_levelled_and_residual(out: str | Path, levelled_m: ArrayLike, residual_m: ArrayLike, pixel_size_m: float,
                                levelled_comment: str, residual_comment: str,
                                residual_pixel_m: float | None = None) -> list[str]:
    """Write ``levelled.x3p`` and ``residual.x3p`` into ``out`` (``doe compare`` and ``doe diagnose``).

    Parameters
    ----------
    out : str or Path
        Output folder.
    levelled_m, residual_m : array (rows, cols)
        The levelled measurement and a residual (measured minus a model), row 0 first.
    pixel_size_m : float
        The levelled map's pitch (the file's, square: the maps are in the camera's frame).
    levelled_comment, residual_comment : str
        What each file holds (its ``Record2/Comment``).
    residual_pixel_m : float, optional
        The residual's pitch when it differs (default ``pixel_size_m``).

    Returns
    -------
    list of str
        The file names written.
    """
    out = Path(out)
    write_x3p(out / "levelled.x3p", levelled_m, pixel_size_m, comment=levelled_comment)
    write_x3p(out / "residual.x3p", residual_m, residual_pixel_m or pixel_size_m, comment=residual_comment)
    return ["levelled.x3p", "residual.x3p"]
