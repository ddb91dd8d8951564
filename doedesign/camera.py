"""The split-aperture camera: a thin ideal lens with a DOE over one half of its aperture.

Geometry (all in one frame, viewed along the light): the DOE array is centred on the optical
axis, row 0 at the top and column 0 at the left; the sensor window uses the same (row, col)
orientation with the axis at ``axis_pixel``. No image inversion is applied, so a phase that
increases toward higher column steers light toward higher sensor column.

What surrounds a design inside the lens aperture is one stated convention (:data:`SURROUNDS`).
A design is usually smaller than the camera's clear aperture (a 1 mm element in an 8.64 mm
lens), and the light it meets in the rest of the DOE's half-aperture changes the answer: an
all-closed ``aperture`` on a small design still passes most of the light when the rest is open.
``open`` (the default, the behaviour before the choice was named) is unetched glass with no
phase; ``opaque`` is chrome, so only the design's own clear region passes light; ``repeat``
tiles the design (its heights and its ``aperture``) across the half-aperture, the central tile
where the design sits. The convention comes from a command's ``--surround`` option, else from
the design file's metadata field ``surround``, else ``open`` (:func:`resolve_surround`); it is
written into every PSF file and shown by ``doe inspect``.
"""

from __future__ import annotations

import functools
from collections.abc import Mapping
from dataclasses import asdict, dataclass

import numpy as np

from .errors import DoeError

__all__ = ["Camera", "DEFAULT_SURROUND", "MAX_WINDOW_PX", "SIDES", "SURROUNDS", "check_surround",
           "describe_surround", "resolve_surround"]

SIDES = ("left", "right", "full")
# Largest sensor window simulated (pixels per side): 8192^2 float64 per wavelength and view is
# already 0.5 GB; a design file's camera or an option claiming more is refused.
MAX_WINDOW_PX = 8192


@dataclass(frozen=True)
class Camera:
    """Split-aperture camera; the defaults are the seed paper's configuration.

    Parameters
    ----------
    aperture_diameter_m : float or None
        Clear circular aperture at the lens (8.64 mm = 1600 DOE pixels of 5.4 um).
        ``None`` means a square pupil exactly filling the design grid (gratings, tests).
    focus_distance_m : float
        Object distance the lens is focused at (5 m; 3.5 m for the depth design).
    sensor_distance_m : float
        Lens to sensor distance (50 mm); the focal length follows from the lens equation.
    pixel_pitch_m : float
        Sensor pixel pitch (5.4 um).
    window_shape : (int, int)
        Sensor window simulated, rows x cols (512 x 512).
    axis_pixel : (int, int)
        (row, col) of the sensor pixel whose centre lies on the optical axis.
    doe_side : {"left", "right", "full"}
        Which half of the aperture carries the DOE (columns left or right of the axis) or
        the full aperture. The simulation of the seed used "left"; its measured PSFs "right".
    """

    aperture_diameter_m: float | None = 8.64e-3
    focus_distance_m: float = 5.0
    sensor_distance_m: float = 50e-3
    pixel_pitch_m: float = 5.4e-6
    window_shape: tuple = (512, 512)
    axis_pixel: tuple = (256, 256)
    doe_side: str = "left"

    def __post_init__(self) -> None:
        if self.doe_side not in SIDES:
            raise DoeError(f"camera: doe_side must be one of {SIDES}, got {self.doe_side!r}")
        for name in ("focus_distance_m", "sensor_distance_m", "pixel_pitch_m"):
            value = getattr(self, name)
            if not (np.isfinite(value) and value > 0) and not (name == "focus_distance_m" and value == np.inf):
                raise DoeError(f"camera: {name} must be positive, got {value}")
        if self.aperture_diameter_m is not None and not self.aperture_diameter_m > 0:
            raise DoeError(f"camera: aperture_diameter_m must be positive, got {self.aperture_diameter_m}")
        object.__setattr__(self, "window_shape", tuple(int(v) for v in self.window_shape))
        object.__setattr__(self, "axis_pixel", tuple(int(v) for v in self.axis_pixel))
        if len(self.window_shape) != 2 or min(self.window_shape) < 1:
            raise DoeError(f"camera: window_shape must be (rows, cols), got {self.window_shape}")
        if max(self.window_shape) > MAX_WINDOW_PX:
            raise DoeError(f"camera: window_shape {self.window_shape} is over {MAX_WINDOW_PX} pixels a side")

    @property
    def focal_length_m(self) -> float:
        """Focal length imaging ``focus_distance_m`` onto the sensor (49.50 mm by default)."""
        return 1.0 / (1.0 / self.focus_distance_m + 1.0 / self.sensor_distance_m)

    @property
    def f_number(self) -> float:
        if self.aperture_diameter_m is None:
            return float("nan")
        return self.focal_length_m / self.aperture_diameter_m

    def to_dict(self) -> dict:
        """The camera's fields as a plain dict (how a design file stores its camera)."""
        d = asdict(self)
        d["focal_length_m"] = self.focal_length_m
        # Strict JSON has no Infinity: a lens focused at infinity is written "inf".
        if np.isinf(self.focus_distance_m):
            d["focus_distance_m"] = "inf"
        return d

    @classmethod
    def from_dict(cls, d: dict) -> Camera:
        keys = {f for f in cls.__dataclass_fields__}
        d = {k: (tuple(v) if isinstance(v, list) else v) for k, v in d.items() if k in keys}
        if str(d.get("focus_distance_m")).lower() == "inf":
            d["focus_distance_m"] = np.inf
        return cls(**d)

    def pupil_grid_shape(self, design_shape: tuple[int, int], pitch_m: float) -> tuple[int, int]:
        """Shape of the pupil grid (DOE pixels) holding the aperture; the design is centred in it."""
        if self.aperture_diameter_m is None:
            return (int(design_shape[0]), int(design_shape[1]))
        n_ap = self.aperture_diameter_m / pitch_m
        n = int(round(n_ap)) if abs(n_ap - round(n_ap)) < 1e-6 else int(np.ceil(n_ap))
        if design_shape[0] > n or design_shape[1] > n:
            raise DoeError(
                f"design of {design_shape[0]} x {design_shape[1]} pixels ({design_shape[1] * pitch_m * 1e3:.3f} mm wide) "
                f"is larger than the aperture grid of {n} x {n} pixels ({self.aperture_diameter_m * 1e3:.3f} mm); "
                "crop the design to the clear aperture")
        return (n, n)

    def view_weights(self, grid_shape: tuple[int, int], pitch_m: float, oversample: int = 1) -> np.ndarray:
        """Amplitude of each pupil sample for the coded and the uncoded view.

        Returns a (2, rows*oversample, cols*oversample) array holding the fraction of each
        sample's area that is inside the clear aperture and on that view's side.
        """
        return _view_weights(tuple(grid_shape), float(pitch_m), self.aperture_diameter_m,
                             self.doe_side, int(oversample)).copy()


@functools.lru_cache(maxsize=8)
def _view_weights(grid_shape, pitch_m, diameter_m, side, oversample):
    rows, cols = grid_shape[0] * oversample, grid_shape[1] * oversample
    step = pitch_m / oversample
    # Sample centres relative to the grid centre (the optical axis); rows run downward.
    y = (np.arange(rows) - (rows - 1) / 2) * step
    x = (np.arange(cols) - (cols - 1) / 2) * step
    sub = 8  # sub-samples per axis for the area fraction of edge samples
    offs = (np.arange(sub) + 0.5) / sub - 0.5
    inside = np.zeros((rows, cols))
    left = np.zeros(cols)
    for ox in offs:
        left += (x + ox * step) < 0
    left /= sub
    if diameter_m is None:
        inside[:] = 1.0
    else:
        r2 = (diameter_m / 2) ** 2
        # Samples wholly inside or outside the circle (by their nearest and farthest corner) are
        # 1 or 0; only the band the rim crosses is sub-sampled (a few thousand of millions).
        near_y, near_x = np.maximum(np.abs(y) - step / 2, 0) ** 2, np.maximum(np.abs(x) - step / 2, 0) ** 2
        far_y, far_x = (np.abs(y) + step / 2) ** 2, (np.abs(x) + step / 2) ** 2
        inside[:] = (far_y[:, None] + far_x[None, :]) <= r2
        iy, ix = np.nonzero(((near_y[:, None] + near_x[None, :]) <= r2) & ~(inside > 0))
        sy = (y[iy, None] + offs[None, :] * step) ** 2
        sx = (x[ix, None] + offs[None, :] * step) ** 2
        inside[iy, ix] = np.count_nonzero(sy[:, :, None] + sx[:, None, :] <= r2, axis=(1, 2)) / (sub * sub)
    if side == "full":
        coded, uncoded = inside, inside
    else:
        frac = left if side == "left" else 1.0 - left
        coded, uncoded = inside * frac[None, :], inside * (1.0 - frac)[None, :]
    out = np.stack([coded, uncoded])
    out.setflags(write=False)
    return out


#: What surrounds a design inside the lens aperture (the module docstring): clear glass, chrome, or the design tiled.
SURROUNDS = ("open", "opaque", "repeat")
DEFAULT_SURROUND = "open"
_TEXT = {"open": "open glass (unetched, no phase) around the design inside the lens aperture",
         "opaque": "opaque (chrome) around the design: only its own clear region passes light",
         "repeat": "the design repeated (heights and aperture tiled) across the lens aperture"}


def check_surround(value: object, where: str = "surround") -> str:
    """``value`` if it names a convention, else a one-line :class:`~doedesign.errors.DoeError`."""
    if not isinstance(value, str) or value not in SURROUNDS:
        raise DoeError(f"{where}: {value!r} is not a surround convention; use one of {', '.join(SURROUNDS)}")
    return value


def resolve_surround(option: str | None, metadata: Mapping | None = None, source: str = "design") -> tuple[str, str]:
    """The convention and where it came from (``"option"``, ``"design file"`` or ``"default"``)."""
    if option is not None:
        return check_surround(option, "--surround"), "option"
    if metadata and "surround" in metadata:
        return check_surround(metadata["surround"], f"{source}: metadata surround"), "design file"
    return DEFAULT_SURROUND, "default"


def describe_surround(value: str) -> str:
    """One sentence for reports and ``doe inspect``."""
    return _TEXT[check_surround(value)]
