"""Independent generator of profilometer files printed on a proximity aligner.

The tests' own implementation of proximity printing, written apart from the model code (it
never reads or calls :mod:`masks` or :mod:`metrology` beyond the file writer that
:class:`filegen.FileCase` uses), so a diagnosis tested on these files is checked against a
different implementation of the physics.

Physics
-------
A 16-level fused-silica DOE (5.4 um pixels) is made with 4 binary chrome masks (mask j open where
bit j of the level is set, etch depth 75 nm * 2**j, :func:`filegen.masks_of`). Each mask is
printed with a gap ``g`` between mask and resist:

1. Transmission ``t(x, y)``: 1 in the openings, 0 on chrome, chrome all around the design. It is
   sampled on the *aerial grid*, ``AERIAL_PER_PX`` = 27 samples per design pixel (0.2 um), each
   sample the exact area fraction of its cell (pixel edges fall on sample boundaries).
2. Propagation over the gap by the angular spectrum method,
   ``U = IFFT{ FFT{t} H }``, ``H = exp(i 2 pi g sqrt(1/lambda**2 - fx**2 - fy**2))``; where
   the root is imaginary the component decays as ``exp(-2 pi g sqrt(f**2 - 1/lambda**2))``
   (evanescent, gone within a fraction of a micron; kept in this exact form so that ``g = 0``
   is the identity). The array is padded on every side by
   ``g (tan 30 deg + tan(half angle)) + 4 um`` (diffraction reach of the light deflected by up
   to 30 degrees, plus the collimation spread, plus the resist blur's reach) so that the FFT's
   wrap-around of the significant diffracted light does not reach the design; light deflected
   further (a small fraction of the energy, from the edges) may wrap onto the design's outer
   border, which lies outside the camera field.
3. Mercury lamp: i, h, g lines (365, 405, 436 nm) with exposure weights 0.40, 0.25, 0.35
   (:data:`LAMP`); their intensities add incoherently.
4. Partial coherence: the collimated lamp fills a cone of half-angle 2 degrees
   (:data:`HALF_ANGLE_DEG`). The intensity is an incoherent, equal-weight-per-solid-angle sum
   over plane waves whose direction cosines ``(ux, uy)`` fill the disc of radius
   ``sin(2 deg)``: ``N_RINGS`` = 3 equal-area annuli, ring k (1..3) with ``6 k`` points at the
   annulus' rms radius, weight proportional to its area share (36 directions). A tilted wave
   multiplies ``t`` by ``exp(i 2 pi (ux x + uy y) / lambda)``; its intensity is computed exactly
   as ``|IFFT{ FFT{t} H(f + u / lambda) }|**2`` (the tilt's phase factor has modulus 1). An open
   field gives intensity 1.
5. Resist: the intensity is blurred by a Gaussian of sigma 0.1 um (acid diffusion; applied in
   the Fourier domain), then thresholded: the resist clears where the blurred intensity exceeds
   ``T`` (dose to clear / dose). Sub-cell accuracy: the signed distance to the contour,
   ``d = (I - T) / |grad I|`` (metres, positive in the opening, clipped to +-1 um) is computed on
   the aerial grid, interpolated linearly to filegen's super-fine grid (80 cells per pixel,
   0.0675 um) and turned into a coverage ``clip(0.5 + (d + b) / cell, 0, 1)``, where ``b`` is an
   optional linewidth bias (the printed contour moved outward by ``b``; a first-order shift of
   the contour along the intensity gradient).
6. Etch: each printed opening is etched to its mask's depth (times ``1 + depth_error[j]``) and
   the four etches sum, as :func:`filegen.wafer_surface` does for drawn openings; no other
   effect is added.
7. Measurement: filegen's instrument (:func:`filegen.draw_instrument`,
   :func:`filegen.instrument_view`), written with :meth:`filegen.FileCase.write`.

Coordinates as in filegen: row 0 at the top, design pixel ``i`` spans ``[i - 0.5, i + 0.5]``.
"""

from __future__ import annotations

import numpy as np
import scipy.fft as sfft

import filegen
from filegen import DEPTHS_M, FINE_PER_PX, PITCH_M, FileCase, masks_of

AERIAL_PER_PX = 27  # 0.2 um aerial samples
LAMP = ((365e-9, 0.40), (405e-9, 0.25), (436e-9, 0.35))
HALF_ANGLE_DEG = 2.0
N_RINGS = 3
RESIST_SIGMA_M = 0.1e-6
REACH_DEG = 30.0
_D_CLIP_M = 1e-6

__all__ = ["make_proximity_case", "printed_coverage", "printed_coverages", "aerial_image", "intensity_of",
           "propagate", "cone_directions", "LAMP", "HALF_ANGLE_DEG"]


def cone_directions(half_angle_deg=HALF_ANGLE_DEG, n_rings=N_RINGS):
    """Direction cosines filling a cone uniformly, and their weights.

    Parameters
    ----------
    half_angle_deg : float
        Cone half-angle; 0 gives the single normal direction.
    n_rings : int
        Equal-area annuli; ring ``k`` holds ``6 k`` points at its rms radius.

    Returns
    -------
    u : ndarray (n, 2)
        ``(ux, uy)`` direction cosines.
    w : ndarray (n,)
        Weights summing to 1.
    """
    if half_angle_deg == 0 or n_rings == 0:
        return np.zeros((1, 2)), np.ones(1)
    r_max = np.sin(np.radians(half_angle_deg))
    u, w = [], []
    for k in range(1, n_rings + 1):
        r0, r1 = r_max * (k - 1) / n_rings, r_max * k / n_rings
        r = np.sqrt((r0 ** 2 + r1 ** 2) / 2)
        n = 6 * k
        phi = 2 * np.pi * (np.arange(n) + 0.5 * (k % 2)) / n
        u.append(np.stack([r * np.cos(phi), r * np.sin(phi)], 1))
        w.append(np.full(n, (r1 ** 2 - r0 ** 2) / r_max ** 2 / n))
    return np.concatenate(u), np.concatenate(w)


def _transfer(shape, dx, gap_m, wavelength, u=(0.0, 0.0)):
    """Angular-spectrum transfer function ``H(f + u / lambda)`` (complex64) on the FFT grid."""
    fy = sfft.fftfreq(shape[0], dx)[:, None] + u[1] / wavelength
    fx = sfft.fftfreq(shape[1], dx)[None, :] + u[0] / wavelength
    q = (1.0 / wavelength ** 2 - fx ** 2 - fy ** 2).astype(np.float32)
    root = np.sqrt(np.abs(q))
    phase = np.float32(2 * np.pi * gap_m) * root
    prop = q >= 0
    h = np.where(prop, np.cos(phase), np.exp(-phase)) + 1j * np.where(prop, np.sin(phase), 0)
    return h.astype(np.complex64)


def propagate(t, dx, gap_m, wavelength, u=(0.0, 0.0)):
    """Coherent field over a gap (angular spectrum; the array is periodic).

    Parameters
    ----------
    t : ndarray (rows, cols)
        Complex transmission sampled at ``dx`` (metres).
    gap_m, wavelength : float
    u : (ux, uy)
        Direction cosines of the illuminating plane wave (x toward increasing column, y toward
        increasing row here).

    Returns
    -------
    ndarray complex
        The field ``U`` times ``exp(-i 2 pi u.x / lambda)`` (same intensity as ``U``).
    """
    spec = sfft.fft2(np.asarray(t, np.complex64), workers=2)
    return sfft.ifft2(spec * _transfer(t.shape, dx, gap_m, wavelength, u), workers=2)


def _pad_samples(gap_m, half_angle_deg, per_px):
    dx = PITCH_M / per_px
    reach = gap_m * (np.tan(np.radians(REACH_DEG)) + np.tan(np.radians(half_angle_deg))) + 4e-6
    return int(np.ceil(reach / dx))


def aerial_image(masks, gap_m, lamp=LAMP, half_angle_deg=HALF_ANGLE_DEG, n_rings=N_RINGS,
                 resist_sigma_m=RESIST_SIGMA_M, per_px=AERIAL_PER_PX, pad=None):
    """Resist-blurred intensity of binary pixel masks printed over a gap.

    Parameters
    ----------
    masks : ndarray of bool (rows, cols) or (n, rows, cols)
        Openings per design pixel; chrome all around.
    gap_m : float
        Mask-to-resist gap.
    lamp : sequence of (wavelength_m, weight)
        Weights are normalised to sum 1.
    half_angle_deg, n_rings : float, int
        Illumination cone (:func:`cone_directions`).
    resist_sigma_m : float
        Gaussian blur of the intensity (0: none).
    per_px : int
        Aerial samples per design pixel.
    pad : int, optional
        Chrome samples around the design (default from the gap, see the module docstring).

    Returns
    -------
    intensity : ndarray float32 (n, R, C)
        On the padded aerial grid (open field = 1).
    pad : int
        Samples of chrome before design sample 0 on each axis.
    """
    masks = np.asarray(masks, bool)
    single = masks.ndim == 2
    masks = masks[None] if single else masks
    if pad is None:
        pad = _pad_samples(gap_m, half_angle_deg, per_px)
    dx = PITCH_M / per_px
    rows, cols = masks.shape[1] * per_px, masks.shape[2] * per_px
    shape = (sfft.next_fast_len(rows + 2 * pad), sfft.next_fast_len(cols + 2 * pad))
    t = np.zeros((masks.shape[0],) + shape, np.complex64)
    t[:, pad:pad + rows, pad:pad + cols] = np.repeat(np.repeat(masks, per_px, 1), per_px, 2)
    inten = intensity_of(t, dx, gap_m, lamp, half_angle_deg, n_rings, resist_sigma_m)
    del t
    return (inten[0] if single else inten), pad


def intensity_of(t, dx, gap_m, lamp=LAMP, half_angle_deg=HALF_ANGLE_DEG, n_rings=N_RINGS,
                 resist_sigma_m=RESIST_SIGMA_M):
    """Resist-blurred intensity (float32, open field = 1) of transmissions ``t`` (..., R, C)
    sampled at ``dx``, printed over ``gap_m``: steps 2-5 of the module docstring on an array
    already padded with chrome (it is periodic)."""
    spec = sfft.fft2(np.asarray(t, np.complex64), axes=(-2, -1), workers=2)
    shape = spec.shape[-2:]
    u, wu = cone_directions(half_angle_deg, n_rings)
    weights = np.array([w for _, w in lamp], float)
    weights /= weights.sum()
    inten = np.zeros(spec.shape, np.float32)
    for (lam, _), wl in zip(lamp, weights):
        for (ux, uy), w in zip(u, wu):
            field = sfft.ifft2(spec * _transfer(shape, dx, gap_m, lam, (ux, uy)), axes=(-2, -1), workers=2)
            inten += np.float32(wl * w) * (field.real ** 2 + field.imag ** 2)
    if resist_sigma_m:
        fy = sfft.fftfreq(shape[0], dx)[:, None]
        fx = sfft.fftfreq(shape[1], dx)[None, :]
        g = np.exp(-2 * np.pi ** 2 * resist_sigma_m ** 2 * (fx ** 2 + fy ** 2)).astype(np.float32)
        inten = sfft.ifft2(sfft.fft2(inten, axes=(-2, -1), workers=2) * g, axes=(-2, -1), workers=2).real
    return inten.astype(np.float32)


def _interp_axis(a, src, dst, axis):
    """Linear interpolation of ``a`` along ``axis`` from sample positions ``src`` (uniform,
    increasing) to ``dst``."""
    step = src[1] - src[0]
    pos = np.clip((dst - src[0]) / step, 0, len(src) - 1 - 1e-9)
    i0 = np.floor(pos).astype(np.intp)
    w = (pos - i0).astype(np.float32)
    a0, a1 = np.take(a, i0, axis), np.take(a, i0 + 1, axis)
    shape = [1] * a.ndim
    shape[axis] = -1
    w = w.reshape(shape)
    return a0 * (1 - w) + a1 * w


def _coverage_from_intensity(inten, pad, design_shape, threshold, bias_m, fine, per_px):
    """Printed coverage on filegen's fine grid from one blurred intensity on the aerial grid."""
    dx = PITCH_M / per_px
    gr, gc = np.gradient(inten.astype(np.float64), dx)
    grad = np.hypot(gr, gc)
    d = np.clip((inten - threshold) / np.maximum(grad, 1e-30), -_D_CLIP_M, _D_CLIP_M).astype(np.float32)
    # Design pixel coordinate of aerial sample k: (k - pad + 0.5) / per_px - 0.5.
    lo_r, lo_c = pad - 2, pad - 2
    d = d[lo_r:pad + design_shape[0] * per_px + 2, lo_c:pad + design_shape[1] * per_px + 2]
    src_r = (np.arange(d.shape[0]) + lo_r - pad + 0.5) / per_px - 0.5
    src_c = (np.arange(d.shape[1]) + lo_c - pad + 0.5) / per_px - 0.5
    rows, cols = filegen.fine_grid(design_shape, fine)
    d = _interp_axis(d, src_r, rows, 0)
    d = _interp_axis(d, src_c, cols, 1)
    cell = PITCH_M / fine
    return np.clip(0.5 + (d + np.float32(bias_m)) / np.float32(cell), 0.0, 1.0)


def printed_coverages(masks, gap_m, threshold, bias_m=None, fine=FINE_PER_PX, **optics):
    """Printed coverage of several masks (see :func:`printed_coverage`); returns (n, R, C)."""
    masks = np.asarray(masks, bool)
    per_px = optics.get("per_px", AERIAL_PER_PX)
    inten, pad = aerial_image(masks, gap_m, **optics)
    bias = np.broadcast_to(np.asarray(0.0 if bias_m is None else bias_m, float), (masks.shape[0],))
    return np.stack([_coverage_from_intensity(inten[j], pad, masks.shape[1:], threshold, bias[j], fine, per_px)
                     for j in range(masks.shape[0])])


def printed_coverage(mask, gap_m, threshold, bias_m=0.0, fine=FINE_PER_PX, **optics):
    """Printed coverage of one mask on filegen's super-fine grid.

    Parameters
    ----------
    mask : ndarray of bool (rows, cols)
        The drawn openings per design pixel (e.g. ``filegen.masks_of(levels)[j]``).
    gap_m : float
        Mask-to-resist gap.
    threshold : float
        Resist clearing threshold ``T`` (dose to clear / dose).
    bias_m : float
        Printed contour moved outward by this much.
    fine : int
        Cells per design pixel (filegen's grid, :func:`filegen.fine_grid`).
    **optics
        ``lamp``, ``half_angle_deg``, ``n_rings``, ``resist_sigma_m``, ``per_px``, ``pad`` of
        :func:`aerial_image`.

    Returns
    -------
    ndarray float32 (rows * fine, cols * fine)
        Fraction of each cell where the resist cleared (and the glass is etched).
    """
    return printed_coverages(np.asarray(mask, bool)[None], gap_m, threshold, [bias_m], fine, **optics)[0]


def proximity_surface(levels, gap_m, threshold, bias_m=None, depth_error=None, fine=FINE_PER_PX, **optics):
    """Etched surface (m) on the super-fine grid: each mask's printed opening etched to its depth."""
    masks = masks_of(levels)
    depths = np.asarray(DEPTHS_M) * (1 + (np.zeros(4) if depth_error is None else np.asarray(depth_error, float)))
    cover = printed_coverages(masks, gap_m, threshold, bias_m, fine, **optics)
    height = np.zeros(cover.shape[1:])
    for j in range(4):
        height -= cover[j] * depths[j]
    return height


def make_proximity_case(seed, gap_m, threshold, design_px=48, field_px=160, fine=FINE_PER_PX,
                        bias_m=None, depth_error=None, instrument=None, levels=None, **optics):
    """A file case printed on a proximity aligner (a proximity-only case by default).

    Parameters
    ----------
    seed : int
        Draws the design (:func:`filegen.random_levels`) and the instrument, as
        :func:`filegen.make_case` does.
    gap_m : float
        Mask-to-resist gap (0-60 um; the process nominal is 30 um).
    threshold : float
        Resist threshold ``T`` (0.3-0.6 typical).
    design_px, field_px : int
        Design pixels and camera pixels per side.
    fine : int
        Super-fine cells per design pixel.
    bias_m : float or sequence of 4, optional
        Linewidth bias added on top of the print (contour moved outward).
    depth_error : sequence of 4, optional
        Relative etch depth error per mask.
    instrument : dict, optional
        Overrides of :func:`filegen.draw_instrument`.
    levels : ndarray, optional
        The design (default drawn from ``seed``).
    **optics
        Optics overrides of :func:`aerial_image`.

    Returns
    -------
    filegen.FileCase
        ``truth`` holds ``proximity_print`` (``gap_m``, ``threshold``) and, when given,
        ``linewidth_bias`` (``bias_m``, 4 values) and ``etch_depth`` (``error``); ``extra``
        holds the optics used.
    """
    rng = np.random.default_rng(seed)
    drawn = filegen.random_levels((design_px, design_px), rng)
    levels = drawn if levels is None else np.asarray(levels)
    truth = {"proximity_print": {"gap_m": float(gap_m), "threshold": float(threshold)}}
    if bias_m is not None:
        truth["linewidth_bias"] = {"bias_m": np.broadcast_to(np.asarray(bias_m, float), (4,)).copy()}
    if depth_error is not None:
        truth["etch_depth"] = {"error": np.asarray(depth_error, float)}
    inst = filegen.draw_instrument(rng, levels.shape, (field_px, field_px))
    inst.update(instrument or {})
    surface = proximity_surface(levels, gap_m, threshold, bias_m, depth_error, fine, **optics)
    height = filegen.instrument_view(surface, levels.shape, inst, (field_px, field_px), rng, fine)
    extra = {"lamp": optics.get("lamp", LAMP), "half_angle_deg": optics.get("half_angle_deg", HALF_ANGLE_DEG),
             "n_rings": optics.get("n_rings", N_RINGS), "resist_sigma_m": optics.get("resist_sigma_m", RESIST_SIGMA_M),
             "aerial_per_px": optics.get("per_px", AERIAL_PER_PX)}
    return FileCase(levels=levels, truth=truth, instrument=inst, height_m=height, seed=seed, extra=extra)
