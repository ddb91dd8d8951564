"""The built-in targets (Bayer, HDR streaks, hyperspectral orders, depth rings, spots, images)
and each kind's optimizer defaults. Positions are (row, col) offsets from the axis pixel unless stated."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike

from ..camera import Camera
from ..errors import DoeError
from .base import Target, _camera, _check_energy, _check_pixels, _normalize, _vector

__all__ = ["DEFAULT_INIT", "DEFAULT_LOSS", "DEFAULT_OBJECTIVE", "HYPERSPECTRAL_WAVELENGTHS_M", "KINDS",
           "RGB_WAVELENGTHS_M", "SEED_GRATING_PERIOD_M", "bayer", "depth_ring", "grating_order_offset_px",
           "hdr_streak", "hyperspectral", "image", "seed_ring_radius_px", "spots"]

RGB_WAVELENGTHS_M = (656e-9, 589e-9, 486e-9)
HYPERSPECTRAL_WAVELENGTHS_M = tuple(np.arange(400, 701, 10) * 1e-9)
SEED_GRATING_PERIOD_M = 86.4e-6
#: Names of the built-in target kinds, as a target file or ``doe design`` names them.
KINDS = ("bayer", "hdr-streak", "hyperspectral", "depth", "spots", "image")
# The optimizer's start for each kind (names from doedesign.optimizer.starts.INITS).
DEFAULT_INIT = {"bayer": "router", "hdr-streak": "streak", "hyperspectral": "grating", "depth": "lens",
                "spots": "random", "image": "random"}
# L1 alone (the seed's Eq. 2) also falls when light leaves the simulated window, which on a
# real sensor is still stray light; spot targets add the energy-on-target term.
DEFAULT_LOSS = {"bayer": "l1,energy", "spots": "l1,energy"}
# Colour sorting is judged by its weakest colour: the soft minimum of the per-colour energies,
# L-BFGS on the target pixels alone. The hard max-min (LD_MMA) reaches the same weakest colour
# (0.217 against 0.218 quantized at 1600 px) but nlopt's MMA step costs seconds per iteration
# at 1.28 million heights, more than the evaluations themselves.
DEFAULT_OBJECTIVE = {"bayer": "softmin"}


def bayer(camera: Camera | None = None, wavelengths_m: ArrayLike = RGB_WAVELENGTHS_M, rggb: bool = False,
          energy: float = 1.0) -> Target:
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
    return Target(intensity, wls, np.array([np.inf]), axis_pixel=cam.axis_pixel, name="bayer-rggb" if rggb else "bayer",
                  meta={"kind": "bayer", "rggb": bool(rggb)})


def hdr_streak(camera: Camera | None = None, wavelengths_m: ArrayLike = (550e-9,), arms: str = "+",
               arm_width_px: int = 2, arm_length_px: int | None = None, energy: float = 1.0,
               peak_penalty: float = 1.0, depths_m: ArrayLike | None = None) -> Target:
    """Streaks through the axis: ``"+"`` cross, ``"h"`` (along the axis row) or ``"v"``.

    Each arm is ``arm_width_px`` wide (2 px: rows/cols axis-1 and axis for even widths) and
    reaches ``arm_length_px`` from the axis (default: a quarter of the window). The light is
    spread evenly over the streak pixels. ``peak_penalty`` weights a penalty on the brightest
    pixel (see :func:`doedesign.optimizer.losses.peak_loss`), which keeps the streak from collapsing
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


def grating_order_offset_px(wavelength_m: ArrayLike, period_m: float, order: int,
                            camera: Camera | None = None) -> np.ndarray:
    """Column offset (px) of diffraction order ``order`` on the sensor: ``z tan(asin(m lambda / period))``."""
    cam = _camera(camera)
    wl = np.asarray(wavelength_m)
    s = order * wl / period_m
    if np.any(np.abs(s) >= 1):
        raise DoeError(f"order {order} of a {period_m * 1e6:.2f} um period is evanescent at {wl}")
    return cam.sensor_distance_m * np.tan(np.arcsin(s)) / cam.pixel_pitch_m


def hyperspectral(camera: Camera | None = None, wavelengths_m: ArrayLike = HYPERSPECTRAL_WAVELENGTHS_M,
                  period_m: float = SEED_GRATING_PERIOD_M, orders: tuple[int, ...] = (1,),
                  order_weights: ArrayLike | None = None, spot_px: int = 3, energy: float = 1.0,
                  depths_m: ArrayLike | None = None) -> Target:
    """Dispersion along the axis row: each order ``m`` of each band on ``spot_px`` pixels.

    The centre of order ``m`` at wavelength ``lambda`` follows the grating equation
    (:func:`grating_order_offset_px`); for the seed's 86.4 um period the first order sits
    42.9 / 58.9 / 75.0 px from the axis at 400 / 550 / 700 nm, toward higher column.
    ``order_weights`` split ``energy`` between the orders (default: equal).
    """
    cam = _camera(camera)
    energy = _check_energy(energy, "hyperspectral")
    order_list = [int(m) for m in np.atleast_1d(orders)]
    ow = np.ones(len(order_list)) if order_weights is None else _vector(order_weights, len(order_list),
                                                                       "order_weights", "hyperspectral")
    if ow.sum() <= 0:
        raise DoeError("target 'hyperspectral': order_weights are all zero")
    ow = ow / ow.sum()
    wls = np.atleast_1d(np.asarray(wavelengths_m, dtype=float))
    r0, c0 = cam.axis_pixel
    half = np.arange(spot_px) - (spot_px - 1) // 2
    intensity = np.zeros((1, wls.size) + cam.window_shape)
    for wi, wl in enumerate(wls):
        for m, weight in zip(order_list, ow):
            centre = c0 + int(np.rint(grating_order_offset_px(wl, period_m, m, cam)))
            cols = centre + half
            _check_pixels(np.full(cols.size, r0), cols, cam.window_shape, "hyperspectral")
            intensity[0, wi, r0, cols] += energy * weight / spot_px
    depths = np.atleast_1d(np.asarray([cam.focus_distance_m] if depths_m is None else depths_m, dtype=float))
    intensity = np.broadcast_to(intensity, (len(depths),) + intensity.shape[1:]).copy()
    return Target(intensity, wls, depths, axis_pixel=cam.axis_pixel, name="hyperspectral",
                  meta={"kind": "hyperspectral", "period_m": period_m, "orders": order_list})


def seed_ring_radius_px(depth_m: ArrayLike) -> np.ndarray:
    """The seed's depth schedule: ring radius 25 - 5 d px for d in metres."""
    return 25.0 - 5.0 * np.asarray(depth_m, dtype=float)


def depth_ring(camera: Camera | None = None, depths_m: ArrayLike = (1.0, 2.0, 3.0, 4.0, 5.0),
               radii_px: ArrayLike | Callable[[np.ndarray], ArrayLike] | None = None, wavelengths_m: ArrayLike = (550e-9,),
               ring_width_px: float = 1.0, energy: float = 1.0) -> Target:
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


def spots(positions_px: ArrayLike, weights: ArrayLike | None = None, camera: Camera | None = None,
          wavelengths_m: ArrayLike = (550e-9,), depths_m: ArrayLike | None = None, energy: float = 1.0) -> Target:
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


def image(source: np.ndarray | str | Path, camera: Camera | None = None, wavelengths_m: ArrayLike = (550e-9,),
          depths_m: ArrayLike | None = None, energy: float = 1.0) -> Target:
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


def _read_image(path: str | Path) -> np.ndarray:
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
