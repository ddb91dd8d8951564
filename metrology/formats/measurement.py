"""A profilometer height map with its lateral sampling and provenance.

Orientation: ``height_m[0, 0]`` is the first pixel stored in the file, i.e. row 0 is
the top row of the camera image and column 0 its left column (camera order). The
readers never flip or transpose; registration to the design finds any flip or
rotation of the part under the instrument.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from doedesign.errors import DoeError
from doedesign.fileio import json_ready
from masks.process_params import finite_float

__all__ = ["Measurement", "MeasurementFileError", "read_head"]


class MeasurementFileError(DoeError):
    """A measurement file is missing, foreign, truncated or inconsistent.

    The message names the file and the problem.
    """


def read_head(path: str | Path, n_bytes: int) -> bytes:
    """The first ``n_bytes`` of a measurement file; a clean error when it cannot be read."""
    from doedesign.fileio import check_input_file

    path = check_input_file(path, MeasurementFileError)  # a named pipe would block the open
    try:
        with open(path, "rb") as fh:
            return fh.read(n_bytes)
    except OSError as exc:
        raise MeasurementFileError(f"{path}: cannot read ({exc.strerror or exc})") from None


@dataclass
class Measurement:
    """A measured surface height map.

    Attributes
    ----------
    height_m : ndarray of float64, shape (rows, cols)
        Surface height in metres, z up; NaN marks invalid pixels (no data). Row 0 is
        the top row of the camera image, as stored in the file (camera order).
    pixel_size_m : float
        Lateral sampling (metres per pixel) on the part along the columns (x, the fast axis);
        the row pitch too when ``pixel_size_y_m`` is None (square pixels).
    metadata : dict
        Provenance; keys present when the file has them: ``source_file``, ``format``,
        ``wavelength_m``, ``magnification``, ``objective``, ``numerical_aperture``,
        ``timestamp`` (ISO 8601, UTC), ``comment``, ``part_name``, ``phase_origin``
        ``(cn_org_x, cn_org_y)`` (camera pixel of column 0 / row 0), and format details.
    pixel_size_y_m : float or None
        Row pitch (metres, along y) when it differs from ``pixel_size_m`` (an x3p file of
        0.128 x 0.315 um pixels); None for square pixels. Read as the file gives it, never
        refused; :meth:`square_pixels` resamples the rows for code that assumes one pitch.
    """

    height_m: np.ndarray
    pixel_size_m: float
    metadata: dict = field(default_factory=dict)
    pixel_size_y_m: float | None = None

    def __post_init__(self):
        self.height_m = np.asarray(self.height_m, dtype=np.float64)
        if self.height_m.ndim != 2 or self.height_m.size == 0:
            raise DoeError(f"height_m must be a non-empty 2-D array, got shape {self.height_m.shape}")
        self.pixel_size_m = finite_float(self.pixel_size_m, "pixel_size_m")
        if self.pixel_size_m <= 0:
            raise DoeError(f"pixel_size_m must be positive, got {self.pixel_size_m}")
        self.metadata = dict(self.metadata)
        if self.pixel_size_y_m is not None:
            self.pixel_size_y_m = finite_float(self.pixel_size_y_m, "pixel_size_y_m")
            if self.pixel_size_y_m <= 0:
                raise DoeError(f"pixel_size_y_m must be positive, got {self.pixel_size_y_m}")
            if abs(self.pixel_size_y_m - self.pixel_size_m) <= 1e-9 * self.pixel_size_m:
                self.pixel_size_y_m = None

    @property
    def pitches_m(self) -> tuple[float, float]:
        """(row pitch along y, column pitch along x) in metres."""
        return (self.pixel_size_y_m or self.pixel_size_m, self.pixel_size_m)

    def square_pixels(self) -> "Measurement":
        """This measurement on square pixels of the column pitch (itself when already square).

        The rows are resampled by linear interpolation along y (a pixel next to a NaN stays
        NaN). Registration, levelling and the comparison take one pixel pitch; ``doe compare``
        and ``doe diagnose`` call this after reading, and the report keeps both file pitches
        (``metadata["file_pitches_m"]``).
        """
        if self.pixel_size_y_m is None:
            return self
        from doedesign.budget import check_memory
        from scipy.ndimage import map_coordinates

        rows, cols = self.height_m.shape
        pitch_y, pitch_x = self.pitches_m
        new_rows = max(1, int(round((rows - 1) * pitch_y / pitch_x)) + 1)
        check_memory(3 * new_rows * cols * 8, "resampling the rows to square pixels")
        y = np.arange(new_rows) * (pitch_x / pitch_y)
        yy, xx = np.meshgrid(np.minimum(y, rows - 1), np.arange(cols), indexing="ij")
        height = map_coordinates(self.height_m, [yy, xx], order=1, mode="nearest", cval=np.nan)
        meta = {**self.metadata, "file_pitches_m": [pitch_y, pitch_x], "file_shape": [rows, cols]}
        return Measurement(height, pitch_x, meta)

    @property
    def shape(self) -> tuple[int, int]:
        """(rows, cols) of the height map."""
        return self.height_m.shape

    @property
    def valid(self) -> np.ndarray:
        """Boolean mask of the pixels holding data."""
        return np.isfinite(self.height_m)

    def summary(self) -> dict:
        """Plain-JSON summary for ``doe inspect``.

        Returns
        -------
        dict
            ``kind`` ("measurement"), ``shape``, ``pixel_size_m``, ``invalid_fraction``,
            ``height_min_m``, ``height_max_m``, ``height_rms_m`` (rms about the mean of
            the valid pixels; the three are None when no pixel is valid),
            ``metadata``.
        """
        valid = self.height_m[self.valid]
        hmin: float | None
        hmax: float | None
        rms: float | None
        if valid.size:
            hmin, hmax = float(valid.min()), float(valid.max())
            rms = float(np.sqrt(np.mean((valid - valid.mean()) ** 2)))
        else:
            hmin = hmax = rms = None
        return {
            "kind": "measurement",
            "shape": list(self.shape),
            "pixel_size_m": self.pixel_size_m,
            "pixel_size_y_m": self.pitches_m[0],
            "invalid_fraction": float(1.0 - valid.size / self.height_m.size),
            "height_min_m": hmin,
            "height_max_m": hmax,
            "height_rms_m": rms,
            "metadata": json_ready(self.metadata),
        }

