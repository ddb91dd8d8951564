"""Process model: from design levels to the etched surface a profilometer would see.

A 2**n-level element is made with n binary masks (see :mod:`masks.decompose`): mask j is
open where bit j of the level is set and its etch removes ``d_j``. This module prints each
mask with the fabrication effects listed in :mod:`masks.effects` (``etch_depth``,
``mask_overlay``, ``linewidth_bias``, ``proximity_blur``, ``sidewall_slope``,
``etch_loading``, ``roughness``, ``mask_rotation``, ``microtrenching``, ``etch_gradient``)
and sums the etches on a fine grid.

Conventions: SI units; height z up, 0 = unetched top, negative where etched; arrays
row-major with row 0 at the top; overlay x toward increasing column, y up (toward
decreasing row), rotation counter-clockwise about the centre of the whole design grid.

The surface varies continuously with every parameter (area coverage, never pixel-snapped
edges), because metrology and diagnosis fit these parameters with least squares.

Approximations, in words:

- with ``proximity_gap > 0`` each mask prints through the gap by :mod:`masks.proximity`
  (scalar diffraction, the lamp's lines, collimation, resist threshold and blur, chromium
  undercut); otherwise the contact-gap aerial image is a Gaussian blur (the real one is a Fresnel pattern
  with ripples; a Gaussian of sigma ~ sqrt(lambda g) / 2 captures shrinkage and corner
  rounding, not the ripples);
- linewidth bias grows every opening edge by the same amount with a square structuring
  element (corners stay square);
- the sidewall ramp has the same width for every etch (a fixed sidewall angle would give
  deeper etches wider ramps), so it is applied once to the summed height; the etch order
  therefore does not matter here, although in a real run a later etch over an earlier
  step's sidewall does depend on it;
- the local open fraction that drives etch loading is taken from the *designed* mask at
  design-pixel resolution (Gaussian-averaged over ``loading_radius``), not the printed one;
- microtrenching is an extra depth ``t exp(-s / w)`` at distance ``s`` from the nearest
  sidewall, made from the printed coverage by a chessboard distance transform (exact for
  straight Manhattan edges; at corners and in openings narrower than ``w`` the nearest wall
  sets the depth, the feet of two walls do not add); it scales with the local etch depth of
  its mask;
- the etch gradient multiplies every mask's depth by ``1 + g . r``, r from the field centre;
- outside the design array the wafer is unetched (masks closed).

The fine-grid work runs on the arrays of a ``backend`` (:mod:`doedesign.engine.backend`; the
CPU's NumPy by default, a GPU's CuPy for ``doe tolerance --device gpu``) through the
functions of :mod:`masks.litho`: one copy of every formula. The design-pixel masks, the
roughness noise (NumPy's generator, so a seed gives the same surface everywhere) and the
small coordinate vectors are made on the host and copied over.
"""

from __future__ import annotations

import logging
import math
import threading
from collections import OrderedDict
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from doedesign.engine.backend import Array, Backend
from doedesign.errors import DoeError

from . import litho, proximity
from .decompose import mask_bit
from .effects import EFFECTS
from .moments import moment_corrected
from .process_params import ProcessParams, finite_float

__all__ = ["EFFECTS", "ProcessParams", "SimulatedSurface", "check_levels", "etch_key", "fine_upsample",
           "finish_surface", "design_centre", "mask_etch", "mask_motion", "proximity_optics", "simulate_surface", "surface_key",
           "without_motion"]

log = logging.getLogger(__name__)

# Extra design pixels of margin around a simulated region, beyond every effect's reach.
_MARGIN_PX = 2
# Gaussian tails are cut at this many sigma (the scipy default).
_TRUNCATE = 4.0
# Microtrench feet reach this many decay widths (exp(-12) ~ 6e-6) into the margin.
_TRENCH_REACH = 12.0
# Bytes of aerial images through the gap kept between prints (:func:`_gap_image`).
IMAGE_CACHE_BYTES = 96 * 2 ** 20


@dataclass
class SimulatedSurface:
    """Etched surface on the fine grid of a design region.

    Attributes
    ----------
    height_m : array of float64, shape (H, W)
        Height (m), z up, 0 = unetched top, negative where etched; row 0 at the top; an
        array of the backend it was simulated on (NumPy by default).
    step_m : float
        Fine-grid spacing (m), ``pitch_m / upsample``.
    upsample : int
        Fine pixels per design pixel along each axis.
    region : tuple of int
        ``(row0, row1, col0, col1)`` of the design that was simulated (half-open).
    masks_printed : array of float32, shape (n_masks, H, W)
        Area coverage 0..1 of each mask's printed opening after lithography (overlay,
        bias, blur and threshold; before the etch's sidewall, loading and roughness).
    """

    height_m: Array
    step_m: float
    upsample: int
    region: tuple
    masks_printed: Array

    def design_coords(self) -> tuple[np.ndarray, np.ndarray]:
        """Fine-pixel centres in design-pixel units.

        Returns
        -------
        rows, cols : ndarray of float, shapes (H,) and (W,)
            Design-pixel coordinate of each fine row / column centre; design pixel (i, j)
            is centred at (i, j) and spans +-0.5 around it.
        """
        row0, _, col0, _ = self.region
        u = self.upsample
        rows = row0 + (np.arange(self.height_m.shape[0]) + 0.5) / u - 0.5
        cols = col0 + (np.arange(self.height_m.shape[1]) + 0.5) / u - 0.5
        return rows, cols


def fine_upsample(pitch_m: float, step_m: float) -> int:
    """Fine samples per design pixel per axis, ``ceil(pitch_m / step_m)``."""
    return max(int(math.ceil(pitch_m / step_m - 1e-9)), 1)


def simulate_surface(levels: np.ndarray, pitch_m: float, params: ProcessParams | None = None,
                     step_m: float = 0.25e-6, region: tuple[int, int, int, int] | None = None,
                     backend: str | Backend | None = None) -> SimulatedSurface:
    """Simulate the etched surface of (a region of) a multi-level element.

    Parameters
    ----------
    levels : ndarray of int, shape (rows, cols)
        Design levels 0 .. 2**n_masks - 1, row 0 at the top.
    pitch_m : float
        Design pixel pitch (m).
    params : ProcessParams, optional
        Process; default :meth:`ProcessParams.ideal <masks.process_params.ProcessParams.ideal>` with 4 masks.
    step_m : float
        Requested fine-grid spacing (m); the actual one is ``pitch_m / upsample`` with
        ``upsample = ceil(pitch_m / step_m)``.
    region : (row0, row1, col0, col1), optional
        Half-open design-pixel window to simulate (default: the whole design). Effects
        reaching in from outside the window are included (the window is padded before
        filtering), so the result does not depend on the crop.
    backend : str or Backend, optional
        Where the fine grid is computed (:mod:`doedesign.engine.backend`; default the CPU);
        the surface's arrays are that backend's.

    Returns
    -------
    SimulatedSurface
        Fine pixel (a, b) is centred at design coordinates
        ``(row0 + (a + 0.5) / upsample - 0.5, col0 + (b + 0.5) / upsample - 0.5)``.

    Raises
    ------
    DoeError
        Non-integer or out-of-range levels, bad pitch/step/region, bad parameters.
    """
    if params is None:
        params = ProcessParams.ideal()
    if not isinstance(params, ProcessParams):
        raise DoeError(f"params must be a ProcessParams, got {type(params).__name__}")
    n = params.n_masks
    levels = check_levels(levels, n)
    pitch_m = _positive(pitch_m, "pitch_m")
    step_m = _positive(step_m, "step_m")
    region = _check_region(region, levels.shape)
    u = fine_upsample(pitch_m, step_m)
    step = pitch_m / u
    row0, row1, col0, col1 = region
    centre_design = design_centre(levels.shape)

    margin = _margin_px(params, pitch_m, region, centre_design, upsample=u)
    window = (row0 - margin, row1 + margin, col0 - margin, col1 + margin)
    log.debug("process model: region %s + %d px margin, %d fine px per design px (step %.4g m)",
              region, margin, u, step)
    pad = margin * u
    fine_shape = ((row1 - row0) * u + 2 * pad, (col1 - col0) * u + 2 * pad)
    crop = (slice(pad, fine_shape[0] - pad), slice(pad, fine_shape[1] - pad))
    be = litho.backend_of(backend)
    xp = be.xp
    height = xp.zeros(fine_shape, dtype=xp.float64)
    printed = xp.empty((n, (row1 - row0) * u, (col1 - col0) * u), dtype=xp.float32)
    for j in range(n):
        coverage, etched = _print_and_etch(levels, window, params, j, pitch_m, u, centre_design, be)
        printed[j, ...] = coverage[crop]
        height -= etched
    height = finish_surface(height, params, step, pad, be)
    return SimulatedSurface(height_m=height, step_m=step, upsample=u, region=region,
                            masks_printed=printed)


def mask_etch(levels: np.ndarray, pitch_m: float, params: ProcessParams, mask: int, step_m: float = 0.25e-6,
              region: tuple[int, int, int, int] | None = None, pad_px: int = 0,
              backend: str | Backend | None = None, moments: bool = False,
              levels_checked: bool = False, density_cache: dict | None = None) -> Array:
    """Depth (m, >= 0) that one mask's etch removes, on the fine grid of a region.

    :func:`simulate_surface` is ``finish_surface(-sum of mask_etch over the masks, ...)``; one
    mask alone lets a caller recompute only the mask whose parameters changed.

    Parameters
    ----------
    levels, pitch_m, params, step_m, region
        As for :func:`simulate_surface`.
    mask : int
        Mask index.
    pad_px : int
        Fine pixels added on every side of the region (beyond the design: unetched).
    backend : str or Backend, optional
        Where it is computed (default the CPU).
    moments : bool
        The printed coverage's partly covered pixels with their first moments folded into their
        neighbours (:func:`masks.moments.moment_corrected`): for a model that treats each fine
        pixel as uniform (the camera render), not an area coverage.
    levels_checked : bool
        ``levels`` is what :func:`check_levels` returned for ``params.n_masks`` masks: not
        checked again (the check reads the whole design, where the etch reads a window: a map
        tile's model evaluations on a 1024 px design spent half their time in it).
    density_cache : dict, optional
        Kept by the caller for one design and backend: the etch loading's pattern density of
        each window and mask, on the fine grid, which depends on neither the depths nor the
        loading's strength (a fit that moves them reuses it; the same array, so the same etch).

    Returns
    -------
    array of float64 (of ``backend``), shape ``((row1 - row0) * u + 2 pad_px, (col1 - col0) * u + 2 pad_px)``
    """
    if not levels_checked:
        levels = check_levels(levels, params.n_masks)
    region = _check_region(region, levels.shape)
    u = fine_upsample(_positive(pitch_m, "pitch_m"), _positive(step_m, "step_m"))
    row0, row1, col0, col1 = region
    centre_design = design_centre(levels.shape)
    margin = max(_margin_px(params, pitch_m, region, centre_design, masks=[mask], upsample=u), -(-int(pad_px) // u))
    window = (row0 - margin, row1 + margin, col0 - margin, col1 + margin)
    _, etched = _print_and_etch(levels, window, params, mask, pitch_m, u, centre_design,
                                litho.backend_of(backend), moments, density_cache)
    a = margin * u - int(pad_px)
    return etched[a:etched.shape[0] - a, a:etched.shape[1] - a]


def finish_surface(height_m: Array, params: ProcessParams, step_m: float, pad_px: int,
                   backend: str | Backend | None = None, moments: bool = False) -> Array:
    """The summed etches (negative heights, m) with the sidewall ramp, cropped by ``pad_px``
    fine pixels on every side, plus roughness: the last stage of :func:`simulate_surface`
    (on ``backend``'s arrays, default the CPU's). ``moments``: the ramp's slopes inside the
    pixels folded into their neighbours (:func:`masks.moments.box_moment_taps`), for
    :func:`mask_etch`'s ``moments``."""
    be = litho.backend_of(backend)
    height = height_m
    if params.sidewall_slope > 0:
        kernel = be.asarray(litho.box_kernel(params.sidewall_slope / step_m, moments))
        for axis in (0, 1):
            height = be.ndimage.correlate1d(height, kernel, axis=axis, mode="nearest")
    p = int(pad_px)
    height = be.xp.asarray(height[p:height.shape[0] - p, p:height.shape[1] - p], copy=True)
    if params.roughness > 0:
        rng = np.random.default_rng(params.seed)
        height += params.roughness * be.asarray(rng.standard_normal(tuple(height.shape), dtype=np.float32))
    return height


def etch_key(params: ProcessParams, mask: int) -> tuple:
    """Everything of ``params`` that :func:`mask_etch` of ``mask`` depends on, hashable: equal
    keys give equal etches (for callers that cache one mask's etch)."""
    j = int(mask)
    # ProcessParams.__post_init__ fills every per-mask array left None.
    assert params.mask_overlay is not None and params.linewidth_bias is not None
    assert params.mask_rotation is not None and params.microtrenching is not None and params.etch_gradient is not None
    return (params.n_masks, j, float(params.etch_depth[j]), tuple(params.mask_overlay[j]),
            float(params.linewidth_bias[j]), float(params.mask_rotation[j]), tuple(params.microtrenching[j]),
            params.proximity_blur, params.resist_threshold, params.etch_loading,
            params.loading_radius if params.etch_loading else None, tuple(params.etch_gradient),
            params.proximity_gap, params.collimation_half_angle if params.proximity_gap else None,
            params.resist_blur if params.proximity_gap else None, params.cr_undercut if params.proximity_gap else None)


def surface_key(params: ProcessParams) -> tuple:
    """Everything of ``params`` that :func:`simulate_surface` depends on, hashable (with
    ``roughness`` and no ``seed``, the noise is fresh each call: the key cannot tell)."""
    return (tuple(etch_key(params, j) for j in range(params.n_masks)), params.sidewall_slope, params.roughness,
            params.seed)


def proximity_optics(params: ProcessParams) -> proximity.ProximityOptics:
    """The exposure of ``params``' proximity printing (gap, collimation, resist blur; the Hg lines)."""
    return proximity.ProximityOptics(params.proximity_gap, collimation_half_angle_rad=params.collimation_half_angle,
                                     resist_blur_m=params.resist_blur)


def design_centre(shape: tuple[int, int]) -> tuple[float, float]:
    """Centre of a design of ``shape`` pixels in design-pixel coordinates (pixel (i, j) centred
    at (i, j)): the point every mask's rotation turns about."""
    return ((shape[0] - 1) / 2.0, (shape[1] - 1) / 2.0)


def mask_motion(params: ProcessParams, mask: int, pitch_m: float) -> tuple[tuple[float, float], float]:
    """The rigid motion with which mask ``mask`` was printed: the shift (design pixels along
    row and column, row down) and the counter-clockwise rotation (rad) about the design's centre
    that its overlay and its rotation amount to (see :func:`masks.litho.move`,
    :func:`design_centre`)."""
    # ProcessParams.__post_init__ fills every per-mask array left None.
    assert params.mask_overlay is not None and params.mask_rotation is not None
    dx, dy, rotation = (float(v) for v in params.mask_overlay[mask])
    return (-dy / pitch_m, dx / pitch_m), rotation + math.radians(float(params.mask_rotation[mask]))


def without_motion(params: ProcessParams) -> ProcessParams:
    """``params`` with every mask printed in place (no overlay, no rotation): each mask's etch
    then differs from the real one only by :func:`mask_motion`."""
    return params.copy(mask_overlay=np.zeros_like(params.mask_overlay),
                       mask_rotation=np.zeros_like(params.mask_rotation))


def _print_and_etch(levels, window, params, j, pitch_m, u, centre_design, be, moments=False, density_cache=None):
    """Printed coverage (float32) and etched depth (float64, m) of mask ``j`` on the fine grid
    of ``window`` (design pixels, may extend beyond the design), arrays of backend ``be``;
    ``moments``: the etch from the moment-corrected coverage (:func:`mask_etch`), and the area
    coverage None where neither the trench nor the exposure needs it."""
    xp = be.xp
    step = pitch_m / u
    mask = mask_bit(_window(levels, window), j)
    # Rotation centre in fine-pixel indices of the window.
    centre_fine = ((centre_design[0] - window[0] + 0.5) * u - 0.5,
                   (centre_design[1] - window[2] + 0.5) * u - 0.5)
    grown = litho.grown_mask(mask, u, float(params.linewidth_bias[j] / step), be)
    shift_px, rotation = mask_motion(params, j, pitch_m)
    shift_fine = (shift_px[0] * u, shift_px[1] * u)
    trench_m, trench_width_m = params.microtrenching[j]
    trenched = trench_m > 0 and params.etch_depth[j] > 0
    coverage = printed = None
    gap = params.proximity_gap > 0
    if not moments or params.proximity_blur > 0 or trenched or gap:
        if gap:
            image = _gap_image(mask, params, j, pitch_m, u, centre_design, window, be)
            coverage = proximity.resist_print(image, step, params.resist_threshold, params.cr_undercut, be)
        else:
            coverage = litho.move(grown, shift_fine, rotation, centre_fine, be)
            coverage = litho.expose(coverage, params.proximity_blur / step, params.resist_threshold, u, be)
        printed = coverage
    if moments:
        # The grown edges' moments, then a move that keeps them (a linear one leaves a biased and
        # shifted edge in two partial pixels, which the rule cannot read); an exposure prints its
        # own edges from the blurred image.
        if params.proximity_blur > 0 or gap:
            printed = moment_corrected(coverage, be)
        else:
            printed = litho.move(moment_corrected(grown, be), shift_fine, rotation, centre_fine, be, order=3)
    depth = _depth_map(levels, window, params, j, pitch_m, u, be, density_cache)
    gradient = _gradient_map(window, params.etch_gradient, pitch_m, u, centre_design, be)
    if gradient is not None:
        depth = depth * gradient
    if trenched:
        foot = litho.edge_foot(coverage, trench_width_m / step, be)
        depth = depth * (1.0 + float(trench_m / params.etch_depth[j]) * foot)
    # In float64, so that the ideal surface is exact to double precision (a float32 depth map
    # multiplies in float32, as NumPy's loop for two float32 arrays does).
    if isinstance(depth, float):
        etched = xp.astype(printed, xp.float64)
        etched *= depth
    else:
        etched = xp.astype(printed * depth, xp.float64, copy=False)
    return coverage, etched


def image_upsample(params: ProcessParams, pitch_m: float, upsample: int) -> int:
    """Samples per design pixel of the aerial image through the gap: the coarsest that keeps the
    print model's sampling rule (:func:`masks.proximity.image_step_m`), never finer than the
    fine grid's ``upsample``."""
    rule = proximity.image_step_m(proximity_optics(params))
    return min(fine_upsample(pitch_m, rule), int(upsample))


def _gap_image(mask, params, j, pitch_m, u, centre_design, window, be):
    """Mask ``j``'s aerial image through the gap on the fine grid (``u`` per design pixel).

    The image is computed on the grid of :func:`image_upsample` (the print model's sampling rule)
    and interpolated onto the fine grid by a cubic spline, where the resist's threshold reads it
    (a bilinear interpolant's chords lie on one side of the curved image near an edge: on the
    0.7 um grid of 40 um it printed every opening about 20 nm wider, which a fit took for a bias). It does not depend on the threshold or
    the chromium undercut, so it is kept (:data:`_IMAGES`): a fit that moves only the dose
    reprints a mask for the cost of a threshold."""
    uc = image_upsample(params, pitch_m, u)
    step_c = pitch_m / uc
    optics = proximity_optics(params)
    shift_px, rotation = mask_motion(params, j, pitch_m)
    centre_c = ((centre_design[0] - window[0] + 0.5) * uc - 0.5, (centre_design[1] - window[2] + 0.5) * uc - 0.5)
    key = (np.packbits(mask).tobytes(), mask.shape, uc, float(params.linewidth_bias[j]), shift_px, rotation,
           centre_c, optics, pitch_m) if be.is_numpy else None
    image = _IMAGES.get(key) if key is not None else None
    if image is None:
        grown = litho.grown_mask(mask, uc, float(params.linewidth_bias[j] / step_c), be)
        cov = litho.move(grown, (shift_px[0] * uc, shift_px[1] * uc), rotation, centre_c, be)
        image = proximity.aerial_image(cov, step_c, optics, be)
        if key is not None:
            _IMAGES.put(key, image)
    if uc == u:
        return be.xp.asarray(image, copy=True)  # the threshold overwrites its input
    n_r, n_c = mask.shape[0] * u, mask.shape[1] * u
    # Fine pixel a sits at design coordinate (a + 0.5) / u - 0.5 of the window, image sample k at
    # (k + 0.5) / uc - 0.5.
    return litho.interpolate_separable(image, (np.arange(n_r) + 0.5) * uc / u - 0.5,
                                       (np.arange(n_c) + 0.5) * uc / u - 0.5, be, order=3)


class _ImageStore:
    """The last aerial images through the gap (host arrays, bounded in bytes), thread-safe; an
    image is a deterministic function of its key, so keeping it changes no result."""

    def __init__(self, max_bytes: int) -> None:
        self.max_bytes = int(max_bytes)
        self._items: OrderedDict = OrderedDict()
        self._bytes = 0
        self._lock = threading.Lock()

    def get(self, key):
        with self._lock:
            value = self._items.get(key)
            if value is not None:
                self._items.move_to_end(key)
            return value

    def put(self, key, value) -> None:
        with self._lock:
            if key in self._items or value.nbytes > self.max_bytes:
                return
            self._items[key] = value
            self._bytes += value.nbytes
            while self._bytes > self.max_bytes:
                _, old = self._items.popitem(last=False)
                self._bytes -= old.nbytes

    def clear(self) -> None:
        with self._lock:
            self._items.clear()
            self._bytes = 0


# Aerial images through the gap kept between prints (a fit's dose steps reuse them).
_IMAGES = _ImageStore(IMAGE_CACHE_BYTES)


def _depth_map(levels, window, params, j, pitch_m, u, be, density_cache=None):
    """Etch depth of mask ``j`` (m): a float, or a fine-grid map with etch loading (its pattern
    density kept in ``density_cache`` where one is given)."""
    if params.etch_loading == 0:
        return float(params.etch_depth[j])
    key = (tuple(window), int(j), float(params.loading_radius), float(pitch_m), int(u))
    cached = None if density_cache is None else density_cache.get(key)
    if cached is None:
        cached = _density_map(levels, window, params.loading_radius, j, pitch_m, u, be)
        if density_cache is not None:
            density_cache[key] = cached
    rho_fine = be.xp.asarray(cached, copy=True)
    rho_fine *= float(np.float32(-params.etch_loading * params.etch_depth[j]))
    rho_fine += float(np.float32(params.etch_depth[j]))
    return rho_fine


def _density_map(levels, window, loading_radius, j, pitch_m, u, be):
    """Mask ``j``'s pattern density (the loading's Gaussian of its openings) on the window's fine grid."""
    sigma_px = loading_radius / pitch_m
    reach = int(math.ceil(_TRUNCATE * sigma_px)) + 1
    wide = (window[0] - reach, window[1] + reach, window[2] - reach, window[3] + reach)
    wide_mask = mask_bit(_window(levels, wide), j).astype(np.float32)
    rows = window[1] - window[0]
    cols = window[3] - window[2]
    # Fine pixel a of the window sits at design coordinate (a + 0.5) / u - 0.5 from the window
    # start, i.e. at index reach + that in the wide array.
    fine_r = reach + (np.arange(rows * u) + 0.5) / u - 0.5
    fine_c = reach + (np.arange(cols * u) + 0.5) / u - 0.5
    rho = be.ndimage.gaussian_filter(be.asarray(wide_mask), sigma_px, mode="constant", cval=0.0,
                                     truncate=_TRUNCATE)
    return litho.interpolate_separable(rho, fine_r, fine_c, be)


def _gradient_map(window, gradient, pitch_m, u, centre_design, be):
    """``1 + g . r`` on the fine grid of the window (float64), or None for a uniform etch."""
    if not np.any(gradient):
        return None
    # Fine pixel a sits at design coordinate window_start + (a + 0.5) / u - 0.5.
    rows = window[0] + (np.arange((window[1] - window[0]) * u) + 0.5) / u - 0.5
    cols = window[2] + (np.arange((window[3] - window[2]) * u) + 0.5) / u - 0.5
    x_m = (cols - centre_design[1]) * pitch_m
    y_m = be.asarray((centre_design[0] - rows) * pitch_m)          # y up: toward row 0
    x_m = be.asarray(x_m)
    return 1.0 + float(gradient[1]) * y_m[:, None] + float(gradient[0]) * x_m[None, :]


def _gap_reach_m(params, pitch_m, upsample):
    """How far (m) a mask point's print through the gap reaches on its image grid, or the
    farthest any grid holds when the fine grid is not known."""
    optics = proximity_optics(params)
    step = 1e-9 if upsample is None else pitch_m / image_upsample(params, pitch_m, upsample)
    return proximity.reach_m(optics, step)


def _margin_px(params, pitch_m, region, centre_design, masks=slice(None), upsample=None):
    """Design pixels of padding so that no effect of ``masks`` reaching the region is cut off."""
    row0, row1, col0, col1 = region
    corners = np.array([[r - 0.5, c - 0.5] for r in (row0, row1) for c in (col0, col1)])
    radius_m = np.max(np.hypot(corners[:, 0] - centre_design[0], corners[:, 1] - centre_design[1])) * pitch_m
    ovl, rot, trenches = params.mask_overlay[masks], params.mask_rotation[masks], params.microtrenching[masks]
    rotation = np.abs(ovl[:, 2]) + np.radians(np.abs(rot))
    overlay = np.hypot(ovl[:, 0], ovl[:, 1]) + rotation * radius_m
    trench = _TRENCH_REACH * np.max(trenches[:, 1] * (trenches[:, 0] > 0))
    reach = (np.max(overlay) + np.max(np.abs(params.linewidth_bias[masks]))
             + _TRUNCATE * params.proximity_blur + params.sidewall_slope + trench
             + (_gap_reach_m(params, pitch_m, upsample) + params.cr_undercut
                if params.proximity_gap > 0 else 0.0))
    return _MARGIN_PX + int(math.ceil(reach / pitch_m))


def _window(levels, window):
    """Levels in a window that may extend beyond the design; level 0 (unetched) outside."""
    r0, r1, c0, c1 = window
    out = np.zeros((r1 - r0, c1 - c0), dtype=levels.dtype)
    rows, cols = levels.shape
    sr0, sr1, sc0, sc1 = max(r0, 0), min(r1, rows), max(c0, 0), min(c1, cols)
    if sr1 > sr0 and sc1 > sc0:
        out[sr0 - r0:sr1 - r0, sc0 - c0:sc1 - c0] = levels[sr0:sr1, sc0:sc1]
    return out


def check_levels(levels: ArrayLike, n_masks: int) -> np.ndarray:
    """``levels`` as the integer array the simulation reads (whole-number floats converted).

    Raises
    ------
    DoeError
        Not a non-empty 2-D array, non-integer values, or levels outside ``0 .. 2**n_masks - 1``.
    """
    arr = np.asarray(levels)
    if arr.ndim != 2 or arr.size == 0:
        raise DoeError(f"levels must be a non-empty 2-D array, got shape {arr.shape}")
    if np.issubdtype(arr.dtype, np.floating):
        if not np.all(np.isfinite(arr)):
            raise DoeError("levels contain NaN or infinite values")
        if not np.all(arr == np.round(arr)):
            raise DoeError("levels must be whole numbers (got fractional values)")
        arr = arr.astype(np.int64)
    elif arr.dtype == bool or not np.issubdtype(arr.dtype, np.integer):
        raise DoeError(f"levels must be an integer array, got dtype {arr.dtype}")
    lo, hi = int(arr.min()), int(arr.max())
    if lo < 0 or hi >= 2 ** n_masks:
        raise DoeError(f"levels must lie in 0..{2 ** n_masks - 1} for {n_masks} masks, found {lo}..{hi}")
    return arr


def _check_region(region, shape):
    if region is None:
        return (0, shape[0], 0, shape[1])
    try:
        values = [float(v) for v in region]
    except (TypeError, ValueError):
        raise DoeError(f"region must be (row0, row1, col0, col1), got {region!r}") from None
    if len(values) != 4 or not all(v.is_integer() for v in values):
        raise DoeError(f"region must be four integers (row0, row1, col0, col1), got {region!r}")
    row0, row1, col0, col1 = (int(v) for v in values)
    if not (0 <= row0 < row1 <= shape[0] and 0 <= col0 < col1 <= shape[1]):
        raise DoeError(f"region {tuple(region)} is empty or outside the design of shape {shape}")
    return (row0, row1, col0, col1)


def _positive(value, name):
    value = finite_float(value, name)
    if not value > 0:
        raise DoeError(f"{name} must be a positive length in metres, got {value}")
    return value
