"""The seed's other three elements designed by the tool, each scored against its bound.

- HDR streak: the light on the streak pixels (fraction of the coded half's light) against
  two bounds: the envelope limit (no phase-only DOE puts more than the largest DOE pixel
  envelope ``sinc^2`` over the streak on it; about 1 at 5.4 um) and the light of one
  diffraction-limited spot on the streak (:func:`doedesign.bounds.spot_bound`).
- Hyperspectral: first-order light per band on its spot against the 16-level staircase limit
  ``eta_1 = sinc^2(1/N) * [sin(pi (a - 1)) / (N sin(pi (a - 1) / N))]^2`` with ``a`` the phase
  depth of one period in waves at that band (``a = 1`` at the design wavelength, where it is
  ``sinc^2(1/16) = 0.9872``), times the light of a spot on the order's pixels.
- Depth: the ring radius per depth (the radius holding most light, from the azimuthal sum about
  the axis) against a ring schedule the optics can reach (:func:`geometric_ring_radius_px`).
  The seed's schedule, 25 - 5 d px, cannot be reached: defocus moves the ray from pupil radius
  ``rho`` by ``rho s (1/d - 1/d_f)`` on the sensor (``s`` the sensor distance, ``d_f`` the focus),
  affine in 1/d, at most 1.7 px between 3 and 4 m at 800 px (3.3 px at 1600 px) where the seed
  asks 5. The design starts from an axicon (:func:`axicon_ring_start`), whose ring radius
  follows that geometry; from the lens start the L1 design formed no rings (8 / 1 / 1 / 1 px).

Sizes are reduced (``size_px`` DOE pixels of 5.4 um, so the spot is ``1600 / size_px`` times the
camera's; ``doe demo --all`` uses 800 px, a spot twice the camera's, where the arms, orders and
rings are several spots long) and iterations few; the bounds are those of the same reduced
aperture. The streak starts from two cylindrical lenses (:func:`cylinder_streak_start`): from
the random rank-1 start the L1 design kept under 2 % of the light on the streak.
"""

from __future__ import annotations

import logging
import time

import numpy as np
from numpy.typing import ArrayLike

from . import targets
from .bounds import spot_bound
from .camera import Camera
from .levels import N_LEVELS
from .materials import get_material
from .optimizer.optimize import OptimizerSettings, design_doe

__all__ = ["AXIS", "PITCH_M", "RING_R0_PX", "RING_ZONE", "WINDOW", "axicon_ring_start", "cylinder_streak_start",
           "depth_element", "design_seed_elements", "geometric_ring_radius_px", "hyperspectral_element",
           "mean_ring_radius_px", "ring_radius_px", "staircase_first_order", "streak_element"]

log = logging.getLogger(__name__)

PITCH_M = 5.4e-6
# A 192 x 192 window holds the streak arms (48 px), the 400-700 nm first orders (43-75 px) and
# the rings (<= 25 px) about its centre, at a seventh of the full window's cost.
WINDOW = (192, 192)
AXIS = (96, 96)
# The depth element's ring: radius at the focus depth, and the pupil zone (fraction of the pupil
# radius) whose defocus sets the schedule: 2/3 is the light-weighted mean over the half disk.
RING_R0_PX = 10.0
RING_ZONE = 2.0 / 3.0


def staircase_first_order(wavelengths_m: ArrayLike, material: str = "fused_silica",
                          design_wavelength_m: float = 550e-9, n_levels: int = N_LEVELS) -> np.ndarray:
    """First-order efficiency of an ``n_levels`` blazed staircase of one 2 pi period at the design wavelength."""
    mat = get_material(material)
    wl = np.asarray(wavelengths_m, dtype=float)
    a = (mat.n(wl) - 1.0) / (mat.n(design_wavelength_m) - 1.0) * design_wavelength_m / wl
    d = a - 1.0
    ratio = np.where(np.abs(d) < 1e-12, 1.0, np.sin(np.pi * d) / (n_levels * np.sin(np.pi * d / n_levels) + 1e-300))
    return np.sinc(1.0 / n_levels) ** 2 * ratio ** 2


def ring_radius_px(psf: np.ndarray, axis_pixel: tuple[int, int]) -> int:
    """Radius (px) of the brightest ring about the axis: the 1-px radial bin holding most light."""
    rows, cols = psf.shape
    rr, cc = np.meshgrid(np.arange(rows) - axis_pixel[0], np.arange(cols) - axis_pixel[1], indexing="ij")
    r = np.rint(np.hypot(rr, cc)).astype(int)
    sums = np.bincount(r.ravel(), weights=psf.ravel())
    return int(np.argmax(sums))


def mean_ring_radius_px(psf: np.ndarray, axis_pixel: tuple[int, int]) -> float:
    """Light-weighted mean distance (px) of the PSF from the axis pixel."""
    rows, cols = psf.shape
    rr, cc = np.meshgrid(np.arange(rows) - axis_pixel[0], np.arange(cols) - axis_pixel[1], indexing="ij")
    return float(np.sum(np.hypot(rr, cc) * psf) / np.sum(psf))


def geometric_ring_radius_px(camera: Camera, size_px: int, depths_m: ArrayLike, r0_px: float = RING_R0_PX,
                             zone: float = RING_ZONE) -> np.ndarray:
    """Ring radius (px) of an axicon of in-focus radius ``r0_px`` at each depth, by ray optics.

    The ray through pupil radius ``rho`` lands ``rho s (1/d - 1/d_f)`` further out than in
    focus (``s`` the sensor distance, ``d_f`` the focus distance; exact for a thin lens), so
    the light of the zone ``rho = zone * D / 2`` (``D = size_px * 5.4 um``) lies at
    ``r0 + zone (D / 2) (s / p) (1/d - 1/d_f)`` pixels of pitch ``p``.
    """
    d = np.asarray(depths_m, dtype=float)
    rim_px = size_px * PITCH_M / 2 * camera.sensor_distance_m / camera.pixel_pitch_m
    return r0_px + zone * rim_px * (1.0 / d - 1.0 / camera.focus_distance_m)


def axicon_ring_start(camera: Camera, size_px: int, r0_px: float = RING_R0_PX, material: str = "fused_silica",
                      design_wavelength_m: float = 550e-9) -> np.ndarray:
    """An axicon about the optical axis that puts an in-focus ring of radius ``r0_px`` on the sensor.

    The phase ``2 pi theta rho / lambda`` deflects every ray outward by ``theta = r0 p / s``;
    heights wrapped into one wave at the design wavelength (z up, etched negative).
    """
    mat = get_material(material)
    x = (np.arange(size_px) - (size_px - 1) / 2) * PITCH_M
    rho = np.hypot(*np.meshgrid(x, x, indexing="ij"))
    theta = r0_px * camera.pixel_pitch_m / camera.sensor_distance_m
    phase = 2 * np.pi * theta * rho / design_wavelength_m
    h2pi = mat.height_2pi_m(design_wavelength_m)
    return -np.mod(-phase / (2 * np.pi) * h2pi, h2pi)


def _run(target, camera, size_px, settings, init_height_m=None):
    cpu = time.process_time()
    run = design_doe(target, camera, PITCH_M, (size_px, size_px), settings=settings, init_height_m=init_height_m)
    # CPU time beside wall time: on a shared machine the wall time mostly measures the load.
    run.report["cpu_time_s"] = time.process_time() - cpu
    return run


def _times(run):
    return {"run_time_s": run.report["run_time_s"], "cpu_time_s": run.report["cpu_time_s"]}


def cylinder_streak_start(camera: Camera, size_px: int, arm_length_px: int, material: str = "fused_silica",
                          design_wavelength_m: float = 550e-9) -> np.ndarray:
    """A "+" streak start: cylindrical lenses that spread each half of the aperture over one arm.

    The top half's phase is quadratic along columns (a horizontal line), the bottom half's along
    rows (a vertical line), each centred on its own half so the line is centred on the axis; a
    quadratic phase of focal length ``f`` over a width ``w`` spreads the light over ``z w / f``
    on the sensor, set here to the arm's full length ``2 L`` pixels. Heights wrapped into one
    wave at the design wavelength (z up, etched negative).
    """
    mat = get_material(material)
    n = size_px
    x = (np.arange(n) - (n - 1) / 2) * PITCH_M
    half = n * PITCH_M / 2
    f = camera.sensor_distance_m * half / (2 * arm_length_px * camera.pixel_pitch_m)
    # Columns of the coded (left) half centred on their middle; rows of each half likewise.
    u = x + half / 2
    v_top, v_bottom = x + half / 2, x - half / 2
    phase_h = -np.pi * u ** 2 / (design_wavelength_m * f)
    phase_v = -np.pi * np.where(x < 0, v_top, v_bottom) ** 2 / (design_wavelength_m * f)
    phase = np.where((np.arange(n) < n // 2)[:, None], phase_h[None, :], phase_v[:, None])
    h2pi = mat.height_2pi_m(design_wavelength_m)
    return -np.mod(-phase / (2 * np.pi) * h2pi, h2pi)


def streak_element(size_px: int = 160, iterations: int = 30) -> dict:
    """Design the HDR streak element and score the light on the streak against its two bounds."""
    cam = Camera(aperture_diameter_m=size_px * PITCH_M, window_shape=WINDOW, axis_pixel=AXIS)
    target = targets.hdr_streak(cam)
    start = cylinder_streak_start(cam, size_px, WINDOW[0] // 4)
    run = _run(target, cam, size_px, OptimizerSettings(max_iter=iterations, anneal_iter=4), start)
    on = float(run.report["quantized"]["energy_on_target"][0][0])
    spot = float(spot_bound(cam, PITCH_M, (size_px, size_px), target)[0, 0])
    return {"element": "hdr-streak", "figure_of_merit": "light on the streak pixels (quantized)", "value": on,
            "envelope_bound": 1.0, "spot_on_streak": spot, "fraction_of_envelope_bound": on, **_times(run)}


def hyperspectral_element(size_px: int = 160, iterations: int = 30,
                          wavelengths_m: ArrayLike = (450e-9, 550e-9, 650e-9)) -> dict:
    """Design the hyperspectral element and score each band's first-order light against the staircase limit."""
    cam = Camera(aperture_diameter_m=size_px * PITCH_M, window_shape=WINDOW, axis_pixel=AXIS)
    target = targets.hyperspectral(cam, wavelengths_m=wavelengths_m)
    run = _run(target, cam, size_px, OptimizerSettings(max_iter=iterations, anneal_iter=4, init="grating"))
    on = np.array(run.report["quantized"]["energy_on_target"][0])
    eta = staircase_first_order(target.wavelengths_m)
    spot = spot_bound(cam, PITCH_M, (size_px, size_px), target)[0]
    bound = eta * spot
    return {"element": "hyperspectral", "figure_of_merit": "first-order light on each band's spot (quantized)",
            "wavelengths_nm": (target.wavelengths_m * 1e9).round(1).tolist(), "value": on.tolist(),
            "staircase_limit": eta.tolist(), "spot_on_order": spot.tolist(), "bound": bound.tolist(),
            "fraction_of_bound": (on / bound).tolist(), **_times(run)}


def depth_element(size_px: int = 160, iterations: int = 30, depths_m: ArrayLike = (1.0, 2.0, 3.0, 4.0)) -> dict:
    """Design the depth element (a ring per depth) and score its ring radii against the reachable schedule."""
    from .engine.psf import PSFEngine

    cam = Camera(aperture_diameter_m=size_px * PITCH_M, focus_distance_m=3.5, window_shape=WINDOW, axis_pixel=AXIS)
    radii = geometric_ring_radius_px(cam, size_px, depths_m)
    target = targets.depth_ring(cam, depths_m=depths_m, radii_px=radii)
    run = _run(target, cam, size_px, OptimizerSettings(max_iter=iterations, anneal_iter=4),
               axicon_ring_start(cam, size_px))
    engine = PSFEngine(cam, PITCH_M, (size_px, size_px), wavelengths_m=target.wavelengths_m, depths_m=target.depths_m)
    psf = engine.psf(run.design.height_m, views=("coded",)).psf[0]
    measured = [ring_radius_px(psf[d, 0], cam.axis_pixel) for d in range(target.depths_m.size)]
    mean = [mean_ring_radius_px(psf[d, 0], cam.axis_pixel) for d in range(target.depths_m.size)]
    return {"element": "depth", "figure_of_merit": "ring radius (px) per depth (quantized)",
            "depths_m": target.depths_m.tolist(), "radius_px": measured, "mean_radius_px": mean,
            "target_radius_px": radii.tolist(), "seed_radius_px": targets.seed_ring_radius_px(depths_m).tolist(),
            "energy_on_ring": run.report["quantized"]["energy_on_target"], **_times(run)}


def design_seed_elements(size_px: int = 160, iterations: int = 30) -> dict:
    """Design the HDR streak, hyperspectral and depth elements; their figures of merit and bounds."""
    t0, cpu = time.perf_counter(), time.process_time()
    out = [streak_element(size_px, iterations), hyperspectral_element(size_px, iterations),
           depth_element(size_px, iterations)]
    log.info("seed elements designed in %.0f s", time.perf_counter() - t0)
    return {"size_px": size_px, "aperture_m": size_px * PITCH_M, "iterations": iterations, "elements": out,
            "run_time_s": time.perf_counter() - t0, "cpu_time_s": time.process_time() - cpu}
