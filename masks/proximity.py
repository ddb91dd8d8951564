"""Proximity printing: the aerial image of a binary mask through the aligner's gap, and its print.

The seed's masks are printed on an EVG6200-class aligner "with a separation of 30 um" between
the chrome and 0.6 um of AZ1505 (seed supplement, Patterning). Over such a gap the mask's image
is a Fresnel diffraction pattern (a straight edge has 1/4 of the open-field intensity at its
drawn position and rings up to 1.37 beside it for coherent light), not the mask, and not the
Gaussian blur :func:`masks.litho.expose` stands in with.

Model, in order:

1. **Mask** (thin, Kirchhoff): amplitude transmission = the fine-grid area coverage of the
   opening (1 open, 0 chrome); outside the array the plate is chrome.
2. **Propagation** over the gap ``g`` in air by the *band-limited angular spectrum* method
   (Matsushima & Shimobaba, Opt. Express 17, 19662, 2009): ``H(f) = exp(i 2 pi g
   (sqrt(1/lambda^2 - |f|^2) - 1/lambda))`` (the piston dropped), evanescent waves cut, and each
   axis limited to ``|f| <= 1 / (lambda sqrt((2 g / L)^2 + 1))`` for a window of length ``L`` so
   the chirp of ``H`` is not aliased. Chosen over single-FFT Fresnel because it is exact for
   scalar waves at any gap, including gap 0 (``H = 1``: the mask as drawn), and needs no
   paraxial approximation for the fine grid's steep angles.
3. **Lamp** (partially coherent, incoherent across lines): the unfiltered mercury arc's g, h and
   i lines (435.8, 404.7, 365.0 nm) with weights 0.35 / 0.25 / 0.40 (:data:`HG_LINES_M`,
   :data:`HG_WEIGHTS`). The i line's share is the ~40 % of the 360-440 nm emission that
   MicroChemicals quote for an unfiltered Hg aligner (photoresists.eu, "exposure"); the split of
   the rest between g and h is an assumption (arc lamp line strengths), and AZ 1500 resists are
   broadband sensitive (310-450 nm, AZ 1500 technical data sheet), so every line exposes.
4. **Collimation** (partially coherent over angles): plane waves from a uniform disc of
   directions within a half-angle ``theta`` (default 2 deg; mask aligners' collimation half-angles
   run from about 1 deg (high-resolution optics) to 4 deg; this value is the issue's simulator's,
   not a number from an EVG data sheet). See "Speed" for how the sum is made.
5. **Resist**: a Gaussian blur of sigma ``resist_blur_m`` (default 0.1 um: diffusion and the
   image's spread through 0.6 um of resist, ~0.05-0.2 um for DNQ resists), then the resist
   clears where ``dose * I >= dose_to_clear``, i.e. where the normalized image exceeds the
   threshold ``t = dose_to_clear / dose`` (:func:`threshold_for_dose`); the printed coverage
   comes from :func:`masks.litho.threshold_coverage` (sub-pixel contour).
6. **Chromium undercut**: the Cr hard mask is wet-etched for a minute (ceric ammonium nitrate,
   ~1-3 nm/s, so ~0.05-0.2 um of lateral undercut once the ~100 nm film is through); isotropic,
   so the printed contour moves outward along its normal by ``cr_undercut_m`` (convex corners
   round in a wet etch; here :func:`masks.litho.grow`'s square growth keeps them square, and its
   rule for partly covered pixels moves a printed edge by 0.066 um for 0.1 um on a 0.25 um grid).

Speed, and what is exact
------------------------
A plane wave tilted by direction cosines ``s`` prints, in the paraxial limit, the normal
incidence image shifted by ``g tan(theta_s)``: ``H(f + s/lambda) = H(f) exp(-i 2 pi g
lambda f.s) x const``. The partially coherent sum over the source's angles is then one
convolution of each line's normal-incidence intensity with the source's image, a disc of radius
``R = g tan(theta)``, whose transform ``2 J1(2 pi R |f|) / (2 pi R |f|)`` multiplies the
intensity's spectrum together with the resist blur's Gaussian. The kernel does not depend on
the wavelength, so the lines' intensities are summed first: a print costs one forward FFT of the
mask, one inverse FFT per line and two FFTs of the summed intensity (6 for three lines), where a
straightforward loop (:func:`aerial_image_naive`) costs two per line and angle (174 for three
lines and 29 angles). Beyond paraxial, the tilt also changes ``H``'s curvature by a relative
``~1.5 sin^2(theta)`` (a 0.2 % gap error at the cone's rim, 55 nm at 30 um); measured against the
per-angle loop on the same 29 angles, the aerial image agrees to 0.003-0.005 rms (0.02-0.04 at
worst, where light diffracted to steep angles lands, for which the shift is not ``g tan``) and the
printed coverage to 0.02 rms per fine pixel (tests/masks/test_proximity.py).

Sampling rule
-------------
The fine step ``dx`` keeps spatial frequencies up to ``1 / (2 dx)``; light diffracted beyond
lands at least ``g lambda / (2 dx)`` from its edge, where the collimation's average washes out its
interference with the local field once that distance exceeds ``lambda / tan(theta)``: hence
``dx <= g tan(theta) / 2`` (:func:`recommended_step_m`, 0.52 um at 30 um and 2 deg; enough for
areas and the print check's field overlap). That washes out the interference, not the light: on a
coarser grid the mask's spectrum beyond ``1 / (2 dx)`` aliases, so light that should land far
from its edge lands near it, a share of an edge's power that grows with ``dx``. So the process
model's image grid (:func:`image_step_m`, what a fit of the gap reads edges to nanometres from)
also holds light diffracted up to sine 0.6 (37 deg) of the longest line, ``dx <= lambda_max /
1.2`` (0.36 um for the Hg lines), whichever is finer (0.35 um at 20 um, 0.36 um at 30-50 um); at
gap 0 any step is exact. Measured against the tests' independent simulator
(tests/metrology/proximitygen.py, a per-angle loop on a 0.2 um grid) on a random 16-level
element's masks, the process model's print (this image on the rule's grid, interpolated by a
cubic spline onto 0.2 um cells and thresholded) differs by 0.009-0.018 rms per cell at 20-40 um,
its openings' edges on average within 5 nm of the simulator's (0.016-0.024 and up to 10 nm at
50 um; 0.012-0.014 with the image on the 0.2 um grid itself at 40 um). With only
``g tan(theta) / 2`` (0.49 um at 30 um, 0.68 um at 40 um) and a bilinear interpolation it was
0.019-0.027 at 30 um and 0.022-0.027 at 40 um, with edges 16-21 nm outward: errors that a fit
through the gap took for a linewidth bias. The zero padding (chrome)
around the array is the reach of light diffracted up to the grid's frequency limit (at most
``sin = 0.9``, 64 deg) plus the disc and the blur (:func:`reach_m`); light beyond 64 deg (under
1e-3 of an edge's) may wrap around. Wrapped light crosses the padding of both sides and the
array's own chrome rim, so one window is padded by half the reach less that rim. Large arrays go
through overlapping tiles (``tile_px``) whose margins are that reach: the result is the same as
one big transform within 0.01 (measured at 1.35 um steps).

The Gaussian stand-in
---------------------
:func:`masks.litho.expose` with ``sigma = sqrt(lambda_i g) / 2`` (1.65 um at 30 um) is the
project's older approximation. Measured against this model (30 um, 2 deg, the Hg lines, 0.1 um
blur) on a random 40 x 40 mask of 5.4 um pixels at 0.49 um steps, each at the threshold that
prints a long edge in place (0.274 here, where this model's edge has 0.274 of the open field and
rings to 1.25; 0.5 for the Gaussian): the printed coverage differs by 0.22 rms per fine pixel and
each DOE pixel's printed open area by 0.10 rms, and the printed open fraction is 0.54 against the
Gaussian's 0.49 (drawn 0.50). At one threshold (0.3) for both, a long edge prints 1.0 um apart
(:data:`GAUSSIAN_ERROR`, tested). The Gaussian has no ringing and no feature-size dependence of
its own beyond the blur, so it is an approximation of the linewidth, not of the print.

Written here because no maintained Python library propagates a partially coherent, polychromatic
mask image on NumPy and CuPy alike (LightPipes, diffractsim and poppy are monochromatic and
coherent or NumPy-only); the FFTs and Bessel function come from SciPy / the array backend.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy import fft as sfft
from scipy import special

from doedesign.engine.backend import Array, Backend
from doedesign.errors import DoeError

from . import litho

__all__ = ["GAUSSIAN_ERROR", "HG_LINES_M", "HG_WEIGHTS", "ProximityOptics", "aerial_image", "aerial_image_naive",
           "aerial_image_vjp", "aerial_bytes", "image_step_m", "print_coverage", "reach_m", "resist_print", "recommended_step_m", "source_angles", "threshold_for_dose"]

#: Mercury g, h, i lines (m) and their exposure weights (sum 1), see the module docstring.
HG_LINES_M = (435.8e-9, 404.7e-9, 365.0e-9)
#: Exposure weights of the g, h and i lines of :data:`HG_LINES_M` (sum 1).
HG_WEIGHTS = (0.35, 0.25, 0.40)
#: The Gaussian stand-in's measured error (module docstring): rms printed-coverage difference per
#: fine pixel and per DOE pixel's open area (each at its in-place threshold), and a long edge's
#: placement difference (m) at one threshold 0.3; 30 um, 2 deg.
GAUSSIAN_ERROR = {"coverage_rms": 0.22, "pixel_area_rms": 0.10, "edge_offset_m": 1.0e-6}
# Diffraction sine the sampling rule's grid holds at least (37 deg; module docstring).
_GRID_SINE = 0.6
# Largest diffraction sine whose light the padding must hold (64 deg).
_MAX_SINE = 0.9
# Default largest FFT side of one tile (a 2048^2 complex64 tile is 32 MB).
TILE_PX = 2048


@dataclass(frozen=True)
class ProximityOptics:
    """The exposure: gap, lamp, collimation and resist blur, in SI units.

    Attributes
    ----------
    gap_m : float
        Mask-to-resist separation (m), 0 (contact) to 200 um.
    wavelengths_m, weights : tuple of float
        Lamp lines (m) and their exposure weights (normalized to sum 1).
    collimation_half_angle_rad : float
        Half-angle of the uniform disc of illumination directions (rad), 0 to 10 deg.
    resist_blur_m : float
        Gaussian sigma of the resist's blur (m), 0 to 1 um.
    """

    gap_m: float
    wavelengths_m: tuple = HG_LINES_M
    weights: tuple = HG_WEIGHTS
    collimation_half_angle_rad: float = math.radians(2.0)
    resist_blur_m: float = 0.1e-6

    def __post_init__(self) -> None:
        wl = tuple(float(v) for v in np.atleast_1d(self.wavelengths_m))
        w = np.asarray(self.weights, dtype=float).ravel()
        if not wl or len(w) != len(wl) or not all(150e-9 <= v <= 1e-6 for v in wl):
            raise DoeError(f"proximity optics: wavelengths must be 150..1000 nm with one weight each, got "
                           f"{[v * 1e9 for v in wl]} nm and {w.tolist()}")
        if not np.all(np.isfinite(w)) or np.any(w < 0) or w.sum() <= 0:
            raise DoeError(f"proximity optics: weights must be >= 0 and not all 0, got {w.tolist()}")
        for name, lo, hi in (("gap_m", 0.0, 200e-6), ("collimation_half_angle_rad", 0.0, math.radians(10)),
                             ("resist_blur_m", 0.0, 1e-6)):
            v = float(getattr(self, name))
            if not (math.isfinite(v) and lo <= v <= hi):
                raise DoeError(f"proximity optics: {name} must lie in [{lo:g}, {hi:g}], got {v}")
            object.__setattr__(self, name, v)
        object.__setattr__(self, "wavelengths_m", wl)
        object.__setattr__(self, "weights", tuple(float(v) for v in w / w.sum()))

    @property
    def disc_radius_m(self) -> float:
        """Radius of the collimation's disc of image shifts, ``g tan(theta)`` (m)."""
        return self.gap_m * math.tan(self.collimation_half_angle_rad)


def threshold_for_dose(dose: float, dose_to_clear: float) -> float:
    """Normalized aerial-image level at which the resist clears: ``dose_to_clear / dose``
    (any one unit for both, e.g. mJ/cm^2); the open field is 1."""
    dose, clear = float(dose), float(dose_to_clear)
    if not (math.isfinite(dose) and math.isfinite(clear) and dose > 0 and clear > 0):
        raise DoeError(f"dose and dose to clear must be positive, got {dose} and {clear}")
    t = clear / dose
    if not 0 < t < 1:
        raise DoeError(f"a dose of {dose:g} does not clear the resist (its dose to clear is {clear:g}): "
                       f"the threshold {t:.3g} of the open field must lie in (0, 1)")
    return t


def recommended_step_m(optics: ProximityOptics) -> float:
    """Largest fine step of the sampling rule, ``g tan(theta) / 2`` (m; 0.25 um where that is 0):
    the collimation washes out the interference of light diffracted beyond the grid."""
    r = optics.disc_radius_m
    return r / 2 if r > 0 else 0.25e-6


def image_step_m(optics: ProximityOptics) -> float:
    """Largest step of the process model's aerial image: :func:`recommended_step_m`, and at most
    ``lambda_max / 1.2``, a grid that holds light diffracted up to sine 0.6 of the longest line
    (module docstring; m)."""
    return min(recommended_step_m(optics), max(optics.wavelengths_m) / (2 * _GRID_SINE))


def reach_m(optics: ProximityOptics, step_m: float) -> float:
    """How far (m) the printed image of a mask point reaches: diffraction up to the grid's
    Nyquist frequency (capped at sine 0.9), the collimation's disc and 4 sigma of resist blur."""
    sine = min(max(optics.wavelengths_m) / (2.0 * step_m), _MAX_SINE)
    return optics.gap_m * sine / math.sqrt(1 - sine ** 2) + optics.disc_radius_m + 4 * optics.resist_blur_m


def aerial_bytes(shape: tuple[int, int], optics: ProximityOptics, step_m: float, tile_px: int = TILE_PX) -> int:
    """Peak bytes of :func:`aerial_image` on an array of ``shape`` (for ``budget.check_memory``):
    the padded image and result (float32 each) plus one tile's complex work arrays."""
    pad = int(math.ceil(reach_m(optics, step_m) / step_m))
    rows, cols = (n + 2 * pad for n in shape)
    tile = min(max(rows, cols), max(int(tile_px), 4 * pad + 64))
    return 8 * rows * cols + 6 * 8 * tile * tile


@functools.lru_cache(maxsize=32)
def _transfer_host(shape, step_m, wavelength_m, gap_m):
    """Band-limited angular-spectrum transfer (complex64, FFT order) of one line over the gap."""
    fy = sfft.fftfreq(shape[0], step_m)[:, None]
    fx = sfft.fftfreq(shape[1], step_m)[None, :]
    inv = 1.0 / wavelength_m
    arg = inv ** 2 - fx ** 2 - fy ** 2
    # Matsushima & Shimobaba's limit for a window of length L: frequency step 1 / L.
    lim_y = inv / math.sqrt((2 * gap_m / (shape[0] * step_m)) ** 2 + 1)
    lim_x = inv / math.sqrt((2 * gap_m / (shape[1] * step_m)) ** 2 + 1)
    keep = (arg > 0) & (np.abs(fx) <= lim_x) & (np.abs(fy) <= lim_y)
    # sqrt(a) - 1/lambda as -f^2 / (sqrt(a) + 1/lambda): no cancellation at low frequencies.
    root = np.sqrt(np.maximum(arg, 0.0))
    phase = 2 * math.pi * gap_m * (-(fx ** 2 + fy ** 2) / (root + inv))
    return np.where(keep, np.exp(1j * phase), 0).astype(np.complex64)


@functools.lru_cache(maxsize=8)
def _image_kernel_host(shape, step_m, radius_m, blur_m, angles_key):
    """Transform (float32 or complex64, FFT order) of the collimation's shift distribution times
    the resist blur's Gaussian: the uniform disc's ``2 J1(2 pi R f) / (2 pi R f)``, or, with
    ``angles_key`` ``((dx_m, dy_m, weight), ...)``, that discrete set of shifts."""
    fy = sfft.fftfreq(shape[0], step_m)[:, None]
    fx = sfft.fftfreq(shape[1], step_m)[None, :]
    f2 = fx ** 2 + fy ** 2
    kernel = np.exp(-2 * math.pi ** 2 * blur_m ** 2 * f2)
    if angles_key is not None:
        disc = np.zeros(shape, dtype=np.complex128)
        for dx, dy, w in angles_key:
            # A shift of +dx (toward higher column) and +dy (toward higher row index).
            disc += w * np.exp(-2j * math.pi * fy * dy) * np.exp(-2j * math.pi * fx * dx)
        return (kernel * disc).astype(np.complex64)
    if radius_m > 0:
        z = 2 * math.pi * radius_m * np.sqrt(f2)
        safe = np.where(z > 0, z, 1.0)
        kernel = kernel * np.where(z > 0, 2 * special.j1(safe) / safe, 1.0)
    return kernel.astype(np.float32)


def source_angles(half_angle_rad: float, rings: int = 3) -> np.ndarray:
    """A uniform disc of illumination directions, sampled on a square grid of direction cosines.

    Returns
    -------
    ndarray, shape (n, 3)
        ``(sx, sy, weight)`` per direction: ``sx`` toward increasing column, ``sy`` toward
        increasing row; the points of a grid of spacing ``sin(theta) / rings`` inside the disc,
        equal weights summing to 1 (29 directions for 3 rings; one at normal incidence for 0).
    """
    s_max = math.sin(float(half_angle_rad))
    if rings <= 0 or s_max == 0:
        return np.array([[0.0, 0.0, 1.0]])
    k = np.arange(-rings, rings + 1)
    sy, sx = np.meshgrid(k, k, indexing="ij")
    inside = sx ** 2 + sy ** 2 <= rings ** 2 + 1e-9
    ux, uy = sx[inside] * s_max / rings, sy[inside] * s_max / rings
    return np.stack([ux, uy, np.full(ux.size, 1.0 / ux.size)], axis=1)


def _shift_key(optics, angles):
    """The geometric image shifts ``g tan(theta)`` of a discrete set of directions."""
    if angles is None:
        return None
    out = []
    for sx, sy, w in np.asarray(angles, dtype=float):
        c = math.sqrt(1 - sx ** 2 - sy ** 2)
        out.append((optics.gap_m * sx / c, optics.gap_m * sy / c, float(w)))
    return tuple(out)


def _tile_image(tile, step_m, optics, be, shift_key):
    """Aerial image of one periodic tile (a backend float32 array), the fast path."""
    xp = be.xp
    shape = tuple(int(n) for n in tile.shape)
    spectrum = be.fftn(xp.astype(tile, xp.complex64))
    intensity = xp.zeros(shape, dtype=xp.float32)
    for wl, w in zip(optics.wavelengths_m, optics.weights):
        if optics.gap_m > 0:
            field = be.ifftn(spectrum * be.asarray(_transfer_host(shape, step_m, wl, optics.gap_m)))
        else:
            field = xp.astype(tile, xp.complex64)
        re, im = xp.real(field), xp.imag(field)
        intensity += float(w) * (re * re + im * im)
    if optics.disc_radius_m > 0 or optics.resist_blur_m > 0 or shift_key is not None:
        kernel = be.asarray(_image_kernel_host(shape, step_m, optics.disc_radius_m, optics.resist_blur_m,
                                               shift_key))
        intensity = xp.real(be.ifftn(be.fftn(xp.astype(intensity, xp.complex64)) * kernel))
    return intensity


def aerial_image(coverage: Array, step_m: float, optics: ProximityOptics, backend: str | Backend | None = None,
                 periodic: bool = False, tile_px: int = TILE_PX, angles: np.ndarray | None = None) -> Array:
    """The resist's exposure image of a mask, normalized to the open field (= 1).

    Parameters
    ----------
    coverage : array of float, shape (rows, cols)
        Opening area coverage 0..1 on the fine grid (row 0 at the top); chrome outside.
    step_m : float
        Fine-grid step (m); see the module's sampling rule.
    optics : ProximityOptics
    backend : str or Backend, optional
        Array backend (default the CPU's NumPy); the result is its array.
    periodic : bool
        Treat the array as one period of a periodic mask (no padding, no tiles).
    tile_px : int
        Largest FFT side of one tile; larger arrays go through overlapping tiles.
    angles : ndarray (n, 3), optional
        A discrete set of directions (:func:`source_angles`) instead of the uniform disc
        (to compare with :func:`aerial_image_naive` on the same directions).

    Returns
    -------
    array of float32, shape (rows, cols)
        Exposure (weighted over the lines, averaged over the directions, blurred by the resist).
    """
    be = litho.backend_of(backend)
    xp = be.xp
    step_m = float(step_m)
    if not (math.isfinite(step_m) and step_m > 0):
        raise DoeError(f"proximity print: step_m must be a positive length, got {step_m}")
    cov = xp.astype(be.asarray(coverage), xp.float32)
    key = _shift_key(optics, angles)
    if periodic:
        return _tile_image(cov, step_m, optics, be, key)
    rows, cols = (int(n) for n in cov.shape)
    pad = int(math.ceil(reach_m(optics, step_m) / step_m)) + 1
    side = sfft.next_fast_len(max(int(tile_px), 4 * pad + 64))
    # One window: the light wrapped around by the FFT reaches the array only after crossing the
    # chrome of both sides, the padding twice and the array's own chrome rim once (``b``
    # samples), so the padding need only be ``(reach - b) / 2``.
    one = max(-(-(pad - _chrome_rim(cov, be)) // 2), 1)
    if rows + 2 * one <= side and cols + 2 * one <= side:
        shape = (sfft.next_fast_len(rows + 2 * one), sfft.next_fast_len(cols + 2 * one))
        padded = xp.zeros(shape, dtype=xp.float32)
        padded[one:one + rows, one:one + cols] = cov
        return _tile_image(padded, step_m, optics, be, key)[one:one + rows, one:one + cols]
    # Overlap-save tiles: each keeps its interior, its margins (twice the reach: the band-limited
    # kernel's tails) see the neighbours.
    pad *= 2
    side = sfft.next_fast_len(max(int(tile_px), 4 * pad + 64))
    inner = side - 2 * pad
    n_r, n_c = -(-rows // inner), -(-cols // inner)
    big = xp.zeros((n_r * inner + 2 * pad, n_c * inner + 2 * pad), dtype=xp.float32)
    big[pad:pad + rows, pad:pad + cols] = cov
    out = xp.empty((n_r * inner, n_c * inner), dtype=xp.float32)
    for i in range(n_r):
        for j in range(n_c):
            tile = big[i * inner:i * inner + side, j * inner:j * inner + side]
            image = _tile_image(tile, step_m, optics, be, key)
            out[i * inner:(i + 1) * inner, j * inner:(j + 1) * inner] = image[pad:pad + inner, pad:pad + inner]
    return out[:rows, :cols]


def _chrome_rim(coverage, be):
    """Width (samples) of the all-chrome band that surrounds the openings of ``coverage`` on every
    side (the narrowest of the four; the array's size when it has no opening)."""
    xp = be.xp
    rows_open = be.to_host(xp.any(coverage > 0, axis=1))
    cols_open = be.to_host(xp.any(coverage > 0, axis=0))
    if not rows_open.any():
        return int(max(coverage.shape))
    r, c = np.flatnonzero(rows_open), np.flatnonzero(cols_open)
    return int(min(r[0], len(rows_open) - 1 - r[-1], c[0], len(cols_open) - 1 - c[-1]))


def aerial_image_vjp(coverage: np.ndarray, step_m: float, optics: ProximityOptics
                     ) -> tuple[np.ndarray, Callable[[np.ndarray], np.ndarray]]:
    """The periodic aerial image of ``coverage`` and its vector-Jacobian product (for inverse
    lithography): ``vjp(g)`` is the gradient of ``sum(g * image)`` with respect to the coverage.

    The image is :func:`aerial_image` with ``periodic=True`` (pad the array with chrome first for
    an isolated mask): per line ``U_w = F^-1 H_w F c``, ``I = K * sum_w w |U_w|^2`` with ``K`` the
    collimation disc and resist blur (real and even, so its own adjoint), hence
    ``vjp(g) = sum_w 2 w Re(F^-1 conj(H_w) F ((K * g) U_w))``. CPU (NumPy) only; holds one complex
    field per line.

    Returns
    -------
    image : ndarray of float32, shape of ``coverage``
    vjp : callable, float array of that shape -> ndarray of float32
    """
    cov = np.asarray(coverage, dtype=np.float32)
    shape = tuple(int(n) for n in cov.shape)
    step_m = float(step_m)
    spectrum = sfft.fftn(cov.astype(np.complex64))
    kernel = None
    if optics.disc_radius_m > 0 or optics.resist_blur_m > 0:
        kernel = _image_kernel_host(shape, step_m, optics.disc_radius_m, optics.resist_blur_m, None)
    lines = []
    intensity = np.zeros(shape, dtype=np.float32)
    for wl, w in zip(optics.wavelengths_m, optics.weights):
        h = _transfer_host(shape, step_m, wl, optics.gap_m) if optics.gap_m > 0 else np.complex64(1)
        field = sfft.ifftn(spectrum * h)
        intensity += np.float32(w) * (field.real ** 2 + field.imag ** 2)
        lines.append((np.float32(2 * w), h, field))
    if kernel is not None:
        intensity = sfft.ifftn(sfft.fftn(intensity) * kernel).real.astype(np.float32)

    def vjp(cotangent: np.ndarray) -> np.ndarray:
        g = np.asarray(cotangent, dtype=np.float32)
        if kernel is not None:
            g = sfft.ifftn(sfft.fftn(g) * kernel).real.astype(np.float32)
        grad = np.zeros(shape, dtype=np.float32)
        for w2, h, field in lines:
            grad += w2 * sfft.ifftn(np.conj(h) * sfft.fftn(g * field)).real
        return grad

    return intensity, vjp


def aerial_image_naive(coverage: np.ndarray, step_m: float, optics: ProximityOptics,
                       angles: np.ndarray | None = None) -> np.ndarray:
    """The same image by the straightforward loop: per line and per direction, the mask times the
    tilted plane wave, propagated by two FFTs, its intensity summed; then the resist blur.

    The reference the fast path is measured against (speed and the paraxial shift's error); on
    the CPU, one padded window (no tiles). ``angles`` default: :func:`source_angles` (29).
    """
    if angles is None:
        angles = source_angles(optics.collimation_half_angle_rad)
    cov = np.asarray(coverage, dtype=np.float32)
    rows, cols = cov.shape
    pad = int(math.ceil(reach_m(optics, step_m) / step_m)) + 1
    shape = (sfft.next_fast_len(rows + 2 * pad), sfft.next_fast_len(cols + 2 * pad))
    padded = np.zeros(shape, dtype=np.complex64)
    padded[pad:pad + rows, pad:pad + cols] = cov
    y = (np.arange(shape[0]) * step_m)[:, None]
    x = (np.arange(shape[1]) * step_m)[None, :]
    intensity = np.zeros(shape, dtype=np.float32)
    for wl, w in zip(optics.wavelengths_m, optics.weights):
        h = _transfer_host(shape, step_m, wl, optics.gap_m)
        for sx, sy, wa in angles:
            tilt = (np.exp(2j * math.pi * sy * y / wl) * np.exp(2j * math.pi * sx * x / wl)).astype(np.complex64)
            field = sfft.ifftn(sfft.fftn(padded * tilt) * h)
            intensity += np.float32(w * wa) * (field.real ** 2 + field.imag ** 2)
    if optics.resist_blur_m > 0:
        blur = _image_kernel_host(shape, step_m, 0.0, optics.resist_blur_m, None)
        intensity = sfft.ifftn(sfft.fftn(intensity) * blur).real.astype(np.float32)
    return intensity[pad:pad + rows, pad:pad + cols]


def print_coverage(coverage: Array, step_m: float, optics: ProximityOptics, threshold: float,
                   cr_undercut_m: float = 0.0, backend: str | Backend | None = None, **image_options: Any) -> Array:
    """Printed opening coverage (0..1): the aerial image through the gap, thresholded by the
    resist, the contour moved outward by the chromium undercut.

    Parameters
    ----------
    coverage, step_m, optics, backend
        As for :func:`aerial_image` (``image_options`` passed on).
    threshold : float
        Clearing level of the normalized image, in (0, 1) (:func:`threshold_for_dose`).
    cr_undercut_m : float
        Lateral wet-etch undercut of the chromium hard mask (m, >= 0).
    """
    if not 0 < float(threshold) < 1:
        raise DoeError(f"proximity print: threshold must lie in (0, 1), got {threshold}")
    if not (math.isfinite(float(cr_undercut_m)) and cr_undercut_m >= 0):
        raise DoeError(f"proximity print: cr_undercut_m must be >= 0 m, got {cr_undercut_m}")
    be = litho.backend_of(backend)
    return resist_print(aerial_image(coverage, step_m, optics, be, **image_options), step_m, threshold,
                        cr_undercut_m, be)


def resist_print(image: Array, step_m: float, threshold: float, cr_undercut_m: float = 0.0,
                 backend: str | Backend | None = None) -> Array:
    """Printed coverage from an aerial image: the resist clears above ``threshold`` (sub-pixel
    contour, :func:`masks.litho.threshold_coverage`), the contour then moves outward by the
    chromium undercut (:func:`masks.litho.grow`)."""
    be = litho.backend_of(backend)
    printed = litho.threshold_coverage(image, float(threshold), 0.0, be)
    return litho.grow(printed, float(cr_undercut_m) / float(step_m), be)
