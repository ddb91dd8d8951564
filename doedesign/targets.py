"""Target PSFs: what the sensor window should see, per depth and wavelength.

A :class:`Target` holds the wanted intensity shaped (depths, wavelengths, rows, cols) on the
camera's sensor window (row 0 at the top, column 0 at the left, the optical axis at
``axis_pixel``). Each (depth, wavelength) plane is the fraction of the light through the coded
half-aperture wanted in each pixel, so its sum is the energy wanted in the window (at most 1).
Targets are plain objects: build them with the functions below, add them (``a + b`` or
:func:`combine`) and reweight them (:meth:`Target.with_weights`) in a script or notebook.

Built-in targets (positions are (row, col) offsets from the axis pixel unless stated):

- :func:`bayer`: the colour-sorting PSF of the seed supplement, Eq. (1): red on (0, 0),
  green on (+1, 0), blue on (+1, +1) -- pixels (256, 256), (257, 256), (257, 257) of the
  512 x 512 window -- at optical infinity; ``rggb=True`` puts half the green on (0, +1) too.
- :func:`hdr_streak`: streaks through the axis ("+" cross of 2-px arms, or one direction),
  with a peak penalty for the loss.
- :func:`hyperspectral`: diffraction orders along the axis row, positions from the grating
  equation ``sin(theta) = m lambda / period`` and ``x = z tan(theta)``.
- :func:`depth_ring`: a ring whose radius follows a schedule of depth (seed: 25 - 5 d px).
- :func:`spots`: spots with given window positions and weights.
- :func:`image`: any user image (PNG/TIFF or ``.npy``) as the intensity.

TOML schema (``doe design TARGET.toml``)
----------------------------------------
One ``[target]`` table, or several ``[[target]]`` tables whose targets are added::

    [[target]]
    kind = "bayer"                     # bayer | hdr-streak | hyperspectral | depth | spots | image
    wavelengths_nm = [656, 589, 486]   # optional, kind-specific default
    energy = 1.0                       # energy wanted in the window per wavelength and depth
    rggb = false                       # bayer only
    weight = 1.0                       # scale of this target's loss weight when combined

    [[target]]
    kind = "spots"
    positions_px = [[256, 300], [300, 256]]   # absolute (row, col) window pixels
    weights = [1.0, 2.0]
    depths_m = ["inf"]                        # numbers in metres, or "inf"

Other keys per kind: hdr-streak ``arms`` ("+", "h" or "v"), ``arm_width_px``,
``arm_length_px``, ``peak_penalty``; hyperspectral ``period_m``, ``orders``,
``order_weights``, ``spot_px``, ``wavelengths_nm`` (default 400-700 nm, 31 bands);
depth ``depths_m`` and ``radii_px`` (default 1..5 m, 25 - 5 d px), ``ring_width_px``;
image ``path`` (relative to the TOML file), ``wavelengths_nm``, ``depths_m``.
The camera (window shape, axis pixel, sensor distance) comes from the run configuration.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from .camera import Camera
from .errors import DoeError

__all__ = ["HYPERSPECTRAL_WAVELENGTHS_M", "KINDS", "RGB_WAVELENGTHS_M", "SEED_GRATING_PERIOD_M", "Target",
           "bayer", "build", "combine", "depth_ring", "from_dict", "grating_order_offset_px", "hdr_streak",
           "hyperspectral", "image", "load_toml", "seed_ring_radius_px", "spots"]

log = logging.getLogger(__name__)

RGB_WAVELENGTHS_M = (656e-9, 589e-9, 486e-9)
HYPERSPECTRAL_WAVELENGTHS_M = tuple(np.arange(400, 701, 10) * 1e-9)
SEED_GRATING_PERIOD_M = 86.4e-6
KINDS = ("bayer", "hdr-streak", "hyperspectral", "depth", "spots", "image")


@dataclass
class Target:
    """Wanted sensor intensity per depth and wavelength.

    Attributes
    ----------
    intensity : ndarray (depths, wavelengths, rows, cols)
        Fraction of the coded view's light wanted in each window pixel; row 0 at the top.
    wavelengths_m, depths_m : ndarray
        Axes of ``intensity`` (``inf`` is optical infinity).
    pixel_weight : ndarray, broadcastable to ``intensity``
        Loss weight of each pixel (0 masks it out).
    channel_weight : ndarray (depths, wavelengths)
        Relative loss weight of each depth and wavelength.
    peak_penalty : float
        Weight of a penalty on each plane's brightest pixel (HDR streaks).
    axis_pixel : (int, int)
        Window pixel on the optical axis.
    name : str
    """

    intensity: np.ndarray
    wavelengths_m: np.ndarray
    depths_m: np.ndarray
    pixel_weight: np.ndarray | float = 1.0
    channel_weight: np.ndarray | None = None
    peak_penalty: float = 0.0
    axis_pixel: tuple = (256, 256)
    name: str = "target"
    meta: dict = field(default_factory=dict)

    def __post_init__(self):
        self.wavelengths_m = np.atleast_1d(np.asarray(self.wavelengths_m, dtype=float))
        self.depths_m = np.atleast_1d(np.asarray(self.depths_m, dtype=float))
        self.intensity = np.asarray(self.intensity, dtype=float)
        shape = (self.depths_m.size, self.wavelengths_m.size)
        if self.intensity.ndim != 4 or self.intensity.shape[:2] != shape:
            raise DoeError(f"target {self.name!r}: intensity must be (depths, wavelengths, rows, cols) = "
                           f"({shape[0]}, {shape[1]}, rows, cols), got shape {self.intensity.shape}")
        if not np.all(np.isfinite(self.intensity)):
            raise DoeError(f"target {self.name!r}: intensity holds NaN or infinite values")
        if np.any(self.intensity < 0):
            raise DoeError(f"target {self.name!r}: intensity is negative at {np.count_nonzero(self.intensity < 0)} "
                           "pixels; a target intensity must be >= 0")
        sums = self.intensity.sum(axis=(-2, -1))
        if np.any(sums <= 0):
            d, w = np.argwhere(sums <= 0)[0]
            raise DoeError(f"target {self.name!r}: empty at depth {self.depths_m[d]:g} m, "
                           f"wavelength {self.wavelengths_m[w] * 1e9:.1f} nm (no pixel wants light)")
        if np.any(sums > 1 + 1e-9):
            raise DoeError(f"target {self.name!r}: asks for {sums.max():.3g} of the light in the window; "
                           "the energy per depth and wavelength is at most 1")
        if np.any(self.wavelengths_m <= 0) or np.any(self.wavelengths_m > 20e-6):
            raise DoeError(f"target {self.name!r}: wavelengths must be positive and in metres, got {self.wavelengths_m}")
        if np.any(~(self.depths_m > 0)):
            raise DoeError(f"target {self.name!r}: depths must be positive metres (or inf), got {self.depths_m}")
        pw = np.asarray(self.pixel_weight, dtype=float)
        try:
            np.broadcast_to(pw, self.intensity.shape)
        except ValueError:
            raise DoeError(f"target {self.name!r}: pixel_weight of shape {pw.shape} does not fit the intensity "
                           f"{self.intensity.shape}") from None
        if not np.all(np.isfinite(pw)) or np.any(pw < 0):
            raise DoeError(f"target {self.name!r}: pixel_weight must be finite and >= 0")
        self.pixel_weight = pw
        cw = np.ones(shape) if self.channel_weight is None else np.asarray(self.channel_weight, dtype=float)
        if cw.shape != shape or np.any(cw < 0) or not np.all(np.isfinite(cw)) or cw.sum() <= 0:
            raise DoeError(f"target {self.name!r}: channel_weight must be {shape} non-negative numbers, not all zero")
        self.channel_weight = cw
        self.axis_pixel = tuple(int(v) for v in self.axis_pixel)
        self.peak_penalty = float(self.peak_penalty)

    @property
    def window_shape(self):
        return self.intensity.shape[-2:]

    @property
    def mask(self):
        """Boolean (depths, wavelengths, rows, cols): the pixels that should receive light."""
        return self.intensity > 0

    @property
    def energy(self):
        """Energy wanted in the window per (depth, wavelength)."""
        return self.intensity.sum(axis=(-2, -1))

    def with_weights(self, wavelengths=None, depths=None, pixel=None, peak_penalty=None):
        """A copy with new loss weights per wavelength, per depth, per pixel or for the peak."""
        cw = self.channel_weight.copy()
        if wavelengths is not None:
            cw = cw * _vector(wavelengths, self.wavelengths_m.size, "wavelength weights", self.name)[None, :]
        if depths is not None:
            cw = cw * _vector(depths, self.depths_m.size, "depth weights", self.name)[:, None]
        return replace(self, channel_weight=cw,
                       pixel_weight=self.pixel_weight if pixel is None else pixel,
                       peak_penalty=self.peak_penalty if peak_penalty is None else peak_penalty,
                       meta=dict(self.meta))

    def __add__(self, other):
        return combine(self, other)

    def summary(self):
        """Plain dictionary for reports."""
        return {"name": self.name, "wavelengths_nm": (self.wavelengths_m * 1e9).round(3).tolist(),
                "depths_m": [float(d) if np.isfinite(d) else "inf" for d in self.depths_m],
                "window_shape": list(self.window_shape), "axis_pixel": list(self.axis_pixel),
                "energy": self.energy.tolist(), "target_pixels": self.mask.sum(axis=(-2, -1)).tolist(),
                "peak_penalty": self.peak_penalty, **self.meta}


def _vector(values, n, what, name):
    v = np.atleast_1d(np.asarray(values, dtype=float))
    if v.shape != (n,) or np.any(v < 0) or not np.all(np.isfinite(v)):
        raise DoeError(f"target {name!r}: {what} must be {n} non-negative numbers, got {values!r}")
    return v


def _index_of(values, axis_values):
    """Position of each of ``values`` in the union ``axis_values`` (matched to 1e-12 relative)."""
    out = []
    for v in values:
        hit = np.flatnonzero(np.isclose(axis_values, v, rtol=1e-9, atol=0) | ((axis_values == v)))
        out.append(int(hit[0]))
    return out


def combine(*targets, name=None):
    """Sum targets over the union of their wavelengths and depths.

    Intensities add; a (depth, wavelength) plane present in several targets gets the sum of
    their channel weights and the pixel-weight maximum. All must share window and axis.
    """
    if not targets:
        raise DoeError("combine: no targets given")
    first = targets[0]
    for t in targets[1:]:
        if t.window_shape != first.window_shape or t.axis_pixel != first.axis_pixel:
            raise DoeError(f"combine: target {t.name!r} has window {t.window_shape} / axis {t.axis_pixel}, "
                           f"{first.name!r} has {first.window_shape} / {first.axis_pixel}")
    wls = _union([t.wavelengths_m for t in targets])
    deps = _union([t.depths_m for t in targets])
    shape = (deps.size, wls.size) + tuple(first.window_shape)
    intensity = np.zeros(shape)
    pixel_weight = np.zeros(shape)
    channel_weight = np.zeros(shape[:2])
    present = np.zeros(shape[:2], dtype=bool)
    for t in targets:
        di, wi = _index_of(t.depths_m, deps), _index_of(t.wavelengths_m, wls)
        sel = np.ix_(di, wi)
        intensity[sel] += t.intensity
        pixel_weight[sel] = np.maximum(pixel_weight[sel], np.broadcast_to(t.pixel_weight, t.intensity.shape))
        channel_weight[sel] += t.channel_weight
        present[sel] = True
    if not present.all():
        d, w = np.argwhere(~present)[0]
        raise DoeError(f"combine: no target defines depth {deps[d]:g} m at {wls[w] * 1e9:.1f} nm; "
                       "combined targets must share wavelengths at each depth")
    total = intensity.sum(axis=(-2, -1), keepdims=True)
    if np.any(total > 1 + 1e-9):
        log.info("combined target asks for %.3g of the light; rescaling each plane to 1", total.max())
        intensity = intensity / np.maximum(total, 1.0)
    return Target(intensity, wls, deps, pixel_weight=pixel_weight, channel_weight=channel_weight,
                  peak_penalty=max(t.peak_penalty for t in targets), axis_pixel=first.axis_pixel,
                  name=name or "+".join(t.name for t in targets))


def _union(arrays):
    out = []
    for arr in arrays:
        for v in arr:
            if not any((v == u) or np.isclose(v, u, rtol=1e-9, atol=0) for u in out):
                out.append(float(v))
    return np.array(out)


# -- helpers ----------------------------------------------------------------------------------
def _camera(camera):
    return camera if camera is not None else Camera()


def _check_pixels(rows, cols, window_shape, name):
    rows, cols = np.asarray(rows), np.asarray(cols)
    bad = (rows < 0) | (rows >= window_shape[0]) | (cols < 0) | (cols >= window_shape[1])
    if np.any(bad):
        i = int(np.flatnonzero(bad)[0])
        raise DoeError(f"target {name!r}: pixel ({int(rows.flat[i])}, {int(cols.flat[i])}) is outside the "
                       f"{window_shape[0]} x {window_shape[1]} window")


def _normalize(plane, energy, name):
    s = plane.sum()
    if s <= 0:
        raise DoeError(f"target {name!r}: no pixel of the window receives light")
    return plane * (energy / s)


def _check_energy(energy, name):
    if not (0 < energy <= 1):
        raise DoeError(f"target {name!r}: energy must be in (0, 1] (fraction of the light), got {energy}")
    return float(energy)


# -- built-in targets ------------------------------------------------------------------------
def bayer(camera=None, wavelengths_m=RGB_WAVELENGTHS_M, rggb=False, energy=1.0):
    """Colour-sorting target of the seed supplement, Eq. (1), at optical infinity.

    Red (first wavelength) on the axis pixel (256, 256), green (second) one row below
    (257, 256), blue (third) on (257, 257): each 2 x 2 RGGB cell then records R, G and B of
    one scene point. ``rggb=True`` splits the green between (257, 256) and (256, 257).
    """
    cam = _camera(camera)
    energy = _check_energy(energy, "bayer")
    wls = np.asarray(wavelengths_m, dtype=float)
    if wls.shape != (3,):
        raise DoeError(f"target 'bayer': needs three wavelengths (R, G, B), got {wls.size}")
    r0, c0 = cam.axis_pixel
    spots_rc = [[(0, 0)], [(1, 0), (0, 1)] if rggb else [(1, 0)], [(1, 1)]]
    intensity = np.zeros((1, 3) + cam.window_shape)
    for w, cells in enumerate(spots_rc):
        for dr, dc in cells:
            _check_pixels(r0 + dr, c0 + dc, cam.window_shape, "bayer")
            intensity[0, w, r0 + dr, c0 + dc] = energy / len(cells)
    return Target(intensity, wls, [np.inf], axis_pixel=cam.axis_pixel, name="bayer-rggb" if rggb else "bayer",
                  meta={"kind": "bayer", "rggb": bool(rggb)})


def hdr_streak(camera=None, wavelengths_m=(550e-9,), arms="+", arm_width_px=2, arm_length_px=None,
               energy=1.0, peak_penalty=1.0, depths_m=None):
    """Streaks through the axis: ``"+"`` cross, ``"h"`` (along the axis row) or ``"v"``.

    Each arm is ``arm_width_px`` wide (2 px: rows/cols axis-1 and axis for even widths) and
    reaches ``arm_length_px`` from the axis (default: a quarter of the window). The light is
    spread evenly over the streak pixels. ``peak_penalty`` weights a penalty on the brightest
    pixel (see :func:`doedesign.losses.peak_loss`), which keeps the streak from collapsing
    into the central spot.
    """
    cam = _camera(camera)
    energy = _check_energy(energy, "hdr-streak")
    if arms not in ("+", "h", "v"):
        raise DoeError(f"target 'hdr-streak': arms must be '+', 'h' or 'v', got {arms!r}")
    rows, cols = cam.window_shape
    r0, c0 = cam.axis_pixel
    length = int(arm_length_px if arm_length_px is not None else min(rows, cols) // 4)
    width = int(arm_width_px)
    if width < 1 or length < 1:
        raise DoeError("target 'hdr-streak': arm width and length must be at least 1 px")
    lo = -(width // 2)
    band = np.arange(lo, lo + width)
    along = np.arange(-length, length + 1)
    plane = np.zeros(cam.window_shape)
    if arms in ("+", "h"):
        _check_pixels(r0 + band[[0, -1]], c0 + along[[0, -1]], cam.window_shape, "hdr-streak")
        plane[np.ix_(r0 + band, c0 + along)] = 1.0
    if arms in ("+", "v"):
        _check_pixels(r0 + along[[0, -1]], c0 + band[[0, -1]], cam.window_shape, "hdr-streak")
        plane[np.ix_(r0 + along, c0 + band)] = 1.0
    plane = _normalize(plane, energy, "hdr-streak")
    depths = np.atleast_1d(np.asarray(depths_m if depths_m is not None else [cam.focus_distance_m], float))
    wls = np.atleast_1d(np.asarray(wavelengths_m, dtype=float))
    intensity = np.broadcast_to(plane, (depths.size, wls.size) + plane.shape).copy()
    return Target(intensity, wls, depths, peak_penalty=peak_penalty, axis_pixel=cam.axis_pixel,
                  name=f"hdr-streak{arms}", meta={"kind": "hdr-streak", "arms": arms, "arm_width_px": width,
                                                  "arm_length_px": length})


def grating_order_offset_px(wavelength_m, period_m, order, camera=None):
    """Column offset (px) of diffraction order ``order`` on the sensor: ``z tan(asin(m lambda / period))``."""
    cam = _camera(camera)
    s = order * np.asarray(wavelength_m) / period_m
    if np.any(np.abs(s) >= 1):
        raise DoeError(f"order {order} of a {period_m * 1e6:.2f} um period is evanescent at {wavelength_m}")
    return cam.sensor_distance_m * np.tan(np.arcsin(s)) / cam.pixel_pitch_m


def hyperspectral(camera=None, wavelengths_m=HYPERSPECTRAL_WAVELENGTHS_M, period_m=SEED_GRATING_PERIOD_M,
                  orders=(1,), order_weights=None, spot_px=3, energy=1.0, depths_m=None):
    """Dispersion along the axis row: each order ``m`` of each band on ``spot_px`` pixels.

    The centre of order ``m`` at wavelength ``lambda`` follows the grating equation
    (:func:`grating_order_offset_px`); for the seed's 86.4 um period the first order sits
    42.9 / 58.9 / 75.0 px from the axis at 400 / 550 / 700 nm, toward higher column.
    ``order_weights`` split ``energy`` between the orders (default: equal).
    """
    cam = _camera(camera)
    energy = _check_energy(energy, "hyperspectral")
    orders = [int(m) for m in np.atleast_1d(orders)]
    ow = np.ones(len(orders)) if order_weights is None else _vector(order_weights, len(orders), "order_weights",
                                                                   "hyperspectral")
    if ow.sum() <= 0:
        raise DoeError("target 'hyperspectral': order_weights are all zero")
    ow = ow / ow.sum()
    wls = np.atleast_1d(np.asarray(wavelengths_m, dtype=float))
    r0, c0 = cam.axis_pixel
    half = np.arange(spot_px) - (spot_px - 1) // 2
    intensity = np.zeros((1, wls.size) + cam.window_shape)
    for wi, wl in enumerate(wls):
        for m, weight in zip(orders, ow):
            centre = c0 + int(np.rint(grating_order_offset_px(wl, period_m, m, cam)))
            cols = centre + half
            _check_pixels(np.full(cols.size, r0), cols, cam.window_shape, "hyperspectral")
            intensity[0, wi, r0, cols] += energy * weight / spot_px
    depths = [cam.focus_distance_m] if depths_m is None else depths_m
    intensity = np.broadcast_to(intensity, (len(np.atleast_1d(depths)),) + intensity.shape[1:]).copy()
    return Target(intensity, wls, depths, axis_pixel=cam.axis_pixel, name="hyperspectral",
                  meta={"kind": "hyperspectral", "period_m": period_m, "orders": orders})


def seed_ring_radius_px(depth_m):
    """The seed's depth schedule: ring radius 25 - 5 d px for d in metres."""
    return 25.0 - 5.0 * np.asarray(depth_m, dtype=float)


def depth_ring(camera=None, depths_m=(1.0, 2.0, 3.0, 4.0, 5.0), radii_px=None, wavelengths_m=(550e-9,),
               ring_width_px=1.0, energy=1.0):
    """A ring about the axis whose radius changes with depth.

    ``radii_px`` is one radius per depth, or a callable of depth (default
    :func:`seed_ring_radius_px`). Pixels whose centre lies within ``ring_width_px / 2`` of
    the radius get light; a radius of 0 is the axis pixel itself.
    """
    cam = _camera(camera)
    energy = _check_energy(energy, "depth")
    depths = np.atleast_1d(np.asarray(depths_m, dtype=float))
    if radii_px is None:
        radii_px = seed_ring_radius_px
    radii = np.asarray(radii_px(depths) if callable(radii_px) else radii_px, dtype=float)
    if radii.shape != depths.shape or np.any(radii < 0):
        raise DoeError(f"target 'depth': need one non-negative radius per depth ({depths.size}), got {radii}")
    rows, cols = cam.window_shape
    r0, c0 = cam.axis_pixel
    rr = np.hypot(*np.meshgrid(np.arange(rows) - r0, np.arange(cols) - c0, indexing="ij"))
    max_r = min(r0, c0, rows - 1 - r0, cols - 1 - c0)
    if radii.max() + ring_width_px / 2 > max_r:
        raise DoeError(f"target 'depth': a ring of radius {radii.max():g} px leaves the window (max {max_r} px)")
    wls = np.atleast_1d(np.asarray(wavelengths_m, dtype=float))
    intensity = np.zeros((depths.size, wls.size, rows, cols))
    for di, radius in enumerate(radii):
        plane = (np.abs(rr - radius) <= max(ring_width_px / 2, 0.5)).astype(float)
        intensity[di] = _normalize(plane, energy, "depth")
    return Target(intensity, wls, depths, axis_pixel=cam.axis_pixel, name="depth",
                  meta={"kind": "depth", "radii_px": radii.tolist()})


def spots(positions_px, weights=None, camera=None, wavelengths_m=(550e-9,), depths_m=None, energy=1.0):
    """Spots on absolute window pixels ``positions_px`` = [(row, col), ...] with relative ``weights``."""
    cam = _camera(camera)
    energy = _check_energy(energy, "spots")
    pos = np.asarray(positions_px, dtype=float)
    if pos.ndim != 2 or pos.shape[1] != 2 or pos.shape[0] == 0:
        raise DoeError(f"target 'spots': positions_px must be a list of (row, col) pairs, got shape {pos.shape}")
    if not np.allclose(pos, np.rint(pos)):
        raise DoeError("target 'spots': positions_px must be whole pixels")
    pos = np.rint(pos).astype(int)
    _check_pixels(pos[:, 0], pos[:, 1], cam.window_shape, "spots")
    w = np.ones(len(pos)) if weights is None else _vector(weights, len(pos), "weights", "spots")
    plane = np.zeros(cam.window_shape)
    np.add.at(plane, (pos[:, 0], pos[:, 1]), w)
    plane = _normalize(plane, energy, "spots")
    depths = np.atleast_1d(np.asarray(depths_m if depths_m is not None else [cam.focus_distance_m], float))
    wls = np.atleast_1d(np.asarray(wavelengths_m, dtype=float))
    intensity = np.broadcast_to(plane, (depths.size, wls.size) + plane.shape).copy()
    return Target(intensity, wls, depths, axis_pixel=cam.axis_pixel, name="spots",
                  meta={"kind": "spots", "positions_px": pos.tolist()})


def image(source, camera=None, wavelengths_m=(550e-9,), depths_m=None, energy=1.0):
    """A user image as the target intensity, centred on the axis pixel.

    ``source`` is an array or a path to a ``.npy`` or image file (PNG, TIFF...). A colour
    image with one channel per wavelength gives each wavelength its own channel; otherwise
    the image is averaged to grey and used for all wavelengths.
    """
    cam = _camera(camera)
    energy = _check_energy(energy, "image")
    name = str(source) if not isinstance(source, np.ndarray) else "image"
    arr = _read_image(source) if not isinstance(source, np.ndarray) else np.asarray(source, dtype=float)
    wls = np.atleast_1d(np.asarray(wavelengths_m, dtype=float))
    if arr.ndim == 3 and arr.shape[2] == wls.size and wls.size > 1:
        planes = np.moveaxis(arr, 2, 0)
    elif arr.ndim == 3:
        planes = np.broadcast_to(arr[..., :3].mean(axis=2), (wls.size,) + arr.shape[:2])
    elif arr.ndim == 2:
        planes = np.broadcast_to(arr, (wls.size,) + arr.shape)
    else:
        raise DoeError(f"{name}: an image target must be 2-D (rows, cols) or (rows, cols, channels), got {arr.shape}")
    if not np.all(np.isfinite(planes)) or np.any(planes < 0):
        raise DoeError(f"{name}: image values must be finite and >= 0")
    rows, cols = cam.window_shape
    h, w = planes.shape[1:]
    r0, c0 = cam.axis_pixel[0] - h // 2, cam.axis_pixel[1] - w // 2
    if r0 < 0 or c0 < 0 or r0 + h > rows or c0 + w > cols:
        raise DoeError(f"{name}: a {h} x {w} image centred on the axis pixel {cam.axis_pixel} does not fit the "
                       f"{rows} x {cols} window")
    depths = np.atleast_1d(np.asarray(depths_m if depths_m is not None else [cam.focus_distance_m], float))
    intensity = np.zeros((depths.size, wls.size, rows, cols))
    for wi in range(wls.size):
        plane = np.zeros((rows, cols))
        plane[r0:r0 + h, c0:c0 + w] = planes[wi]
        intensity[:, wi] = _normalize(plane, energy, name)
    return Target(intensity, wls, depths, axis_pixel=cam.axis_pixel, name=Path(name).stem,
                  meta={"kind": "image", "source": name})


def _read_image(path):
    path = Path(path)
    if not path.is_file():
        raise DoeError(f"{path}: no such image file")
    try:
        if path.suffix.lower() == ".npy":
            return np.load(path, allow_pickle=False).astype(float)
        import imageio.v3 as iio

        return np.asarray(iio.imread(path), dtype=float)
    except (OSError, ValueError) as exc:
        raise DoeError(f"{path}: cannot read the image: {exc}") from None


# -- by name and from TOML --------------------------------------------------------------------
def build(kind, camera=None, **options):
    """Build a built-in target by its name (see :data:`KINDS`) with keyword options."""
    builders = {"bayer": bayer, "hdr-streak": hdr_streak, "hyperspectral": hyperspectral,
                "depth": depth_ring, "spots": spots, "image": image}
    if kind not in builders:
        raise DoeError(f"unknown target kind {kind!r}; choose from {', '.join(KINDS)}")
    if kind == "spots" and "positions_px" not in options:
        cam = _camera(camera)
        r0, c0 = cam.axis_pixel
        # A default 3 x 3 spot array 20 px apart around the axis, for quick trials.
        options["positions_px"] = [(r0 + 20 * i, c0 + 20 * j) for i in (-1, 0, 1) for j in (-1, 0, 1)]
    try:
        return builders[kind](camera=camera, **options)
    except TypeError as exc:
        raise DoeError(f"target {kind!r}: {exc}") from None


_TOML_KEYS = {
    "wavelengths_nm": ("wavelengths_m", lambda v: np.asarray(v, dtype=float) * 1e-9),
    "depths_m": ("depths_m", lambda v: [math.inf if str(x).lower() == "inf" else float(x) for x in v]),
}


def from_dict(spec, camera=None, base_dir=".", source="target"):
    """Build a (combined) target from a parsed TOML document (see the module docstring)."""
    tables = spec.get("target")
    if tables is None:
        raise DoeError(f"{source}: no [target] or [[target]] table")
    if isinstance(tables, dict):
        tables = [tables]
    if not tables:
        raise DoeError(f"{source}: the target list is empty")
    built = []
    for i, table in enumerate(tables):
        table = dict(table)
        kind = table.pop("kind", None)
        if kind is None:
            raise DoeError(f"{source}: target {i + 1} has no 'kind' (one of {', '.join(KINDS)})")
        weight = float(table.pop("weight", 1.0))
        options = {}
        for key, value in table.items():
            name, conv = _TOML_KEYS.get(key, (key, lambda v: v))
            options[name] = conv(value)
        if kind == "image" and "path" in options:
            options["source"] = Path(base_dir) / options.pop("path")
        try:
            target = build(kind, camera=camera, **options)
        except DoeError as exc:
            raise DoeError(f"{source}: target {i + 1}: {exc}") from None
        built.append(target.with_weights(wavelengths=np.full(target.wavelengths_m.size, weight)))
    return built[0] if len(built) == 1 else combine(*built)


def load_toml(path, camera=None):
    """Read a target TOML file (schema in the module docstring)."""
    import tomllib

    path = Path(path)
    if not path.is_file():
        raise DoeError(f"{path}: no such target file")
    try:
        spec = tomllib.loads(path.read_text())
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise DoeError(f"{path}: not valid TOML: {exc}") from None
    return from_dict(spec, camera=camera, base_dir=path.parent, source=str(path))
