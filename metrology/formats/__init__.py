"""Profilometer files: Zygo MetroPro ``.dat``, ``.datx`` (HDF5), ``.xyz``, ``.asc``, Mx
profile CSV and plain height arrays, read into a :class:`~metrology.formats.measurement.Measurement`
(heights in metres, invalid pixels NaN, row 0 at the top of the camera image), and the
writers that make test fixtures and the demo's simulated measurement.
"""

__all__: list[str] = []
