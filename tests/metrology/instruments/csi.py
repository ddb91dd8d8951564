"""A coherence-scanning interferometer (white-light, NewView-like) as a linear imaging system.

Physics (a linear-systems approximation of CSI, not a fringe-level simulation):

- Optical transfer. The height map is imaged incoherently through a circular pupil of
  numerical aperture ``na`` (0.25-0.55) at an effective wavelength ``wavelength_m``
  (0.55-0.6 um): its spectrum is multiplied by the diffraction-limited OTF of a circular
  pupil, the "chinese hat" ``(2 / pi) (acos(q) - q sqrt(1 - q^2))``, ``q = |f| / f_c``,
  ``f_c = 2 na / wavelength``, zero beyond the cut-off. It is applied on the zero-padded fine
  grid by FFT (its point spread function, the Airy pattern squared, falls off slowly, hence
  the wide padding).
- Batwing. At steps shallower than the coherence length the instrument reports a signed
  overshoot on both sides of each edge. Drawn here as a band-pass of the surface,
  ``b = -(batwing / phi(1)) w^2 laplacian(G_w * h)`` (``G_w`` a Gaussian of width
  ``batwing_width_m``, a fraction of a micrometre; ``phi`` the standard normal density):
  across an isolated straight step of height ``H`` it is ``batwing H (x / w) phi(x / w) /
  phi(1)``, i.e. ``+batwing H`` at ``w`` on the high side and ``-batwing H`` at ``w`` on the
  low side (``batwing`` up to 0.15; positive exaggerates the step). It is added to the imaged
  surface.
- Camera. Each pixel integrates over a centred square of side ``sqrt(fill) * pixel_m`` (fill
  factor 0.5-1 = its active area fraction), turned with the camera. The integral is a 16 x 16
  Gauss-Legendre quadrature of the imaged surface over that square, read from the fine grid
  by a cubic spline (the imaged surface holds nothing above about 3 cycles per micrometre).
- Dropouts. Where the imaged surface within a pixel's active square is steeper than the
  objective can collect (slope angle above ``asin(na)``), the pixel is invalid with
  probability ``dropout_probability``.

Placement: pixels of ``pixel_m`` (0.7-1.3 um; header within 0.5 %), the image mirrored (rows,
columns or neither), turned counter-clockwise (y up) by ``rotation_deg`` (up to 1 degree),
centred within half a design pixel of the design's centre. ``design = matrix @ [row, col] +
offset`` gives the design pixel coordinates of a camera pixel's centre; design pixel (r, c)
spans [r - 0.5, r + 0.5] x [c - 0.5, c + 0.5], row 0 at the top, x along increasing column, y
up. Then, in the camera frame: tilt (up to 2e-4 rad per axis, x right, y up), piston, white
noise (0.5-1.5 nm rms), 0-12 spikes (0.1-1 um, single pixels) and up to 1 % invalid pixels.

Input: ``filegen.wafer_surface``'s grid, cell (i, j) centred at design coordinates
((i + 0.5) / fine - 0.5, (j + 0.5) / fine - 0.5); the wafer beyond it is unetched (0).
"""

from __future__ import annotations

import numpy as np
import scipy.fft as sfft
import scipy.ndimage as ndi

from filegen import PITCH_M

# Zero padding around the grid (m): the incoherent Airy PSF keeps ~1 % of its energy beyond
# 20 um at NA 0.25, so what wraps around from 2 x 30 um away is far below the noise.
PAD_M = 30e-6
QUAD = 16


def chinese_hat(f, cutoff):
    """Diffraction-limited MTF of a circular pupil at spatial frequency ``f`` (same unit as
    ``cutoff``)."""
    q = np.clip(np.abs(f) / cutoff, 0.0, 1.0)
    return (2 / np.pi) * (np.arccos(q) - q * np.sqrt(1 - q * q))


def _draws(rng, shape):
    p = rng.uniform(0.7e-6, 1.3e-6)
    kind = rng.choice(["none", "rows", "cols"])
    return dict(pixel_m=p, header_pixel_m=p * (1 + rng.uniform(-0.005, 0.005)), rotation_deg=rng.uniform(-1, 1),
                flip_rows=bool(kind == "rows"), flip_cols=bool(kind == "cols"),
                centre_px=np.array([shape[0] / 2 - 0.5 + rng.uniform(-0.5, 0.5),
                                    shape[1] / 2 - 0.5 + rng.uniform(-0.5, 0.5)]),
                na=rng.uniform(0.25, 0.55), wavelength_m=rng.uniform(0.55e-6, 0.6e-6), fill=rng.uniform(0.5, 1.0),
                batwing=rng.uniform(0.0, 0.15), batwing_width_m=rng.uniform(0.15e-6, 0.4e-6),
                dropout_probability=rng.uniform(0.02, 0.2), tilt_rad=rng.uniform(-2e-4, 2e-4, 2),
                piston_m=rng.uniform(-0.5e-6, 0.5e-6), noise_m=rng.uniform(0.5e-9, 1.5e-9),
                n_spikes=int(rng.integers(0, 13)), invalid_fraction=rng.uniform(0.0, 0.01))


def _imaged(surface, cell_m, p):
    """(Imaged surface + batwing, imaged surface) on the padded grid, and the padding (cells)."""
    pad = int(np.ceil(PAD_M / cell_m))
    shape = [sfft.next_fast_len(n + 2 * pad, real=True) for n in surface.shape]
    grid = np.zeros(shape)
    grid[pad:pad + surface.shape[0], pad:pad + surface.shape[1]] = surface
    fy = sfft.fftfreq(shape[0], cell_m)[:, None]   # cycles per metre
    fx = sfft.rfftfreq(shape[1], cell_m)[None, :]
    f = np.sqrt(fy ** 2 + fx ** 2)
    spec = sfft.rfft2(grid)
    otf = chinese_hat(f, 2 * p["na"] / p["wavelength_m"])
    w = p["batwing_width_m"]
    phi1 = np.exp(-0.5) / np.sqrt(2 * np.pi)
    # -w^2 laplacian of G_w has the transfer w^2 (2 pi f)^2 exp(-(2 pi f w)^2 / 2).
    band = (p["batwing"] / phi1) * (2 * np.pi * f * w) ** 2 * np.exp(-0.5 * (2 * np.pi * f * w) ** 2)
    seen = sfft.irfft2(spec * otf, shape)
    wing = sfft.irfft2(spec * band, shape)
    return seen + wing, seen, pad


def measure(surface_m, fine, design_shape, out_shape, rng, **overrides):
    """A CSI's camera image of ``surface_m``.

    Parameters
    ----------
    surface_m : ndarray (design rows * fine, design cols * fine)
        Wafer heights (m, z up, 0 = unetched top) on the fine grid.
    fine : int
        Fine cells per design pixel.
    design_shape : tuple of int
        Design shape (rows, cols).
    out_shape : tuple of int
        Camera shape (rows, cols), chosen by the caller so the field lies inside the design.
    rng : numpy.random.Generator
    **overrides
        Replace drawn parameters by name.

    Returns
    -------
    height_m : ndarray (out_shape)
        Measured heights (m), NaN = invalid, row 0 at the top of the camera image.
    inst : dict
        Parameters drawn, ``matrix``, ``offset``, ``slope_limit`` (tan asin na),
        ``n_dropouts``, ``spikes`` and ``n_invalid``.
    """
    p = _draws(rng, design_shape)
    extra = sorted(set(overrides) - set(p))
    if extra:
        raise KeyError(f"unknown instrument parameters {extra}")
    p.update(overrides)
    p["instrument"] = "csi"
    surface = np.asarray(surface_m, dtype=float)
    if surface.shape != (fine * design_shape[0], fine * design_shape[1]):
        raise ValueError(f"surface {surface.shape} is not {design_shape} x {fine} cells")
    th = np.deg2rad(p["rotation_deg"])
    s = p["pixel_m"] / PITCH_M
    sr, sc = (-1.0 if p["flip_rows"] else 1.0), (-1.0 if p["flip_cols"] else 1.0)
    # Camera row step (y down) and column step (x right), turned counter-clockwise with y up,
    # written as (row, col) displacements on the design.
    matrix = s * np.array([[sr * np.cos(th), -sc * np.sin(th)], [sr * np.sin(th), sc * np.cos(th)]])
    offset = np.asarray(p["centre_px"], float) - matrix @ np.array([(out_shape[0] - 1) / 2, (out_shape[1] - 1) / 2])
    p["matrix"], p["offset"] = matrix, offset
    for r in (-0.5, out_shape[0] - 0.5):
        for c in (-0.5, out_shape[1] - 0.5):
            d = matrix @ np.array([r, c]) + offset
            if d.min() < -0.5 or d[0] > design_shape[0] - 0.5 or d[1] > design_shape[1] - 0.5:
                raise ValueError(f"camera field {out_shape} is not inside the {design_shape} design")

    cell_m = PITCH_M / fine
    seen_wing, seen, pad = _imaged(surface, cell_m, p)
    # Quadrature nodes over each pixel's active square, in camera-pixel units about its centre.
    half = 0.5 * np.sqrt(p["fill"])
    x, wgt = np.polynomial.legendre.leggauss(QUAD)
    du, dv = np.meshgrid(half * x, half * x, indexing="ij")
    wq = np.outer(wgt, wgt).ravel() / 4.0
    rows, cols = np.mgrid[0:out_shape[0], 0:out_shape[1]].astype(float)
    pr = rows.reshape(-1, 1) + du.reshape(1, -1)
    pc = cols.reshape(-1, 1) + dv.reshape(1, -1)
    fi = (matrix[0, 0] * pr + matrix[0, 1] * pc + offset[0] + 0.5) * fine - 0.5 + pad
    fj = (matrix[1, 0] * pr + matrix[1, 1] * pc + offset[1] + 0.5) * fine - 0.5 + pad
    # Ten cells of margin for the spline, inside the padded grid (a coarse grid's padding can be
    # narrower: 6 cells of 5.4 um).
    i0, j0 = max(int(fi.min()) - 10, 0), max(int(fj.min()) - 10, 0)
    i1, j1 = int(fi.max()) + 11, int(fj.max()) + 11
    window = seen_wing[i0:i1, j0:j1]
    vals = ndi.map_coordinates(window, [(fi - i0).ravel(), (fj - j0).ravel()], order=3, mode="nearest")
    height = (vals.reshape(fi.shape) @ wq).reshape(out_shape)

    gy, gx = np.gradient(seen[i0:i1, j0:j1], cell_m)
    slope = ndi.map_coordinates(np.hypot(gy, gx), [(fi - i0).ravel(), (fj - j0).ravel()], order=1, mode="nearest")
    steep = slope.reshape(fi.shape).max(axis=1).reshape(out_shape)
    p["slope_limit"] = float(np.tan(np.arcsin(p["na"])))
    drop = (steep > p["slope_limit"]) & (rng.random(out_shape) < p["dropout_probability"])
    p["n_dropouts"] = int(drop.sum())

    ym = ((out_shape[0] - 1) / 2 - rows) * p["pixel_m"]
    xm = (cols - (out_shape[1] - 1) / 2) * p["pixel_m"]
    height += p["tilt_rad"][0] * xm + p["tilt_rad"][1] * ym + p["piston_m"]
    height += rng.standard_normal(out_shape) * p["noise_m"]
    spikes = []
    for k in rng.choice(height.size, int(p["n_spikes"]), replace=False):
        r, c = divmod(int(k), out_shape[1])
        size = float(rng.uniform(0.1e-6, 1e-6) * rng.choice([-1, 1]))
        height[r, c] += size
        spikes.append((r, c, size))
    p["spikes"] = spikes
    nbad = int(round(p["invalid_fraction"] * height.size))
    bad = np.unravel_index(rng.choice(height.size, nbad, replace=False), out_shape)
    height[bad] = np.nan
    height[drop] = np.nan
    p["n_invalid"] = nbad
    return height, p
