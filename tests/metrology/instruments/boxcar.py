"""A pixel-integrating profilometer: Gaussian blur, then the mean over each pixel's footprint.

Physics. The objective blurs the wafer surface by a Gaussian (sigma 0.25-0.5 um); each camera
pixel then reports the mean of the blurred surface over its whole square footprint on the
sample (side ``pixel_m``, turned with the camera). Both are linear and shift-invariant, so
both are applied at once in the Fourier domain of the fine grid: the Gaussian's transfer
``exp(-2 pi^2 sigma^2 |f|^2)`` times the footprint's ``sinc(a f.u) sinc(a f.v)`` (``a`` the
pixel side, ``u`` and ``v`` the camera's row and column directions on the design). That is the
exact area mean of the blurred surface, with nothing left near the grid's Nyquist frequency,
so the filtered map is then read at each pixel's centre by a cubic spline.

Placement. Pixels of ``pixel_m`` (0.7-1.3 um; the header within 0.5 %), the camera image
mirrored (rows, columns or neither), turned counter-clockwise (y up) by ``rotation_deg`` (up
to 1 degree) and centred within half a design pixel of the design's centre. ``matrix`` and
``offset`` take a camera pixel's centre (row, col) to design pixel coordinates,
``design = matrix @ [row, col] + offset``; design pixel (r, c) spans [r - 0.5, r + 0.5] x
[c - 0.5, c + 0.5], row 0 at the top, x along increasing column, y up.

Artefacts, in the camera frame: tilt (up to 2e-4 rad about each axis; x right, y up, from the
image centre), piston, white noise 0.5-1.5 nm rms, 0-12 spikes of 0.1-1 um (either sign) on
single pixels, and up to 1 % invalid pixels (NaN).

The input is ``filegen.wafer_surface``'s fine grid (cell (i, j) centred at design coordinates
((i + 0.5) / fine - 0.5, (j + 0.5) / fine - 0.5)); beyond it the wafer is unetched (0). The
grid is zero-padded before the FFT so that nothing wraps into the field.
"""

from __future__ import annotations

import numpy as np
import scipy.fft as sfft
import scipy.ndimage as ndi

from filegen import PITCH_M


def _random_parameters(rng, design_shape):
    a = rng.uniform(0.7e-6, 1.3e-6)
    mirror = int(rng.integers(0, 3))  # 0: none, 1: rows, 2: columns
    return {"pixel_m": a, "header_pixel_m": a * (1 + rng.uniform(-0.005, 0.005)),
            "rotation_deg": rng.uniform(-1.0, 1.0), "flip_rows": mirror == 1, "flip_cols": mirror == 2,
            "centre_px": np.array([(design_shape[0] - 1) / 2, (design_shape[1] - 1) / 2]) + rng.uniform(-0.5, 0.5, 2),
            "blur_sigma_m": rng.uniform(0.25e-6, 0.5e-6), "tilt_rad": rng.uniform(-2e-4, 2e-4, 2),
            "piston_m": rng.uniform(-0.5e-6, 0.5e-6), "noise_m": rng.uniform(0.5e-9, 1.5e-9),
            "n_spikes": int(rng.integers(0, 13)), "invalid_fraction": rng.uniform(0.0, 0.01)}


def _axes(inst):
    """Design-pixel displacement of one camera step down a column (``u``) and along a row (``v``)."""
    t = np.radians(inst["rotation_deg"])
    scale = inst["pixel_m"] / PITCH_M
    # A camera step along +col is +x; turned counter-clockwise by t it is (x, y) = (cos t, sin t),
    # i.e. (row, col) = (-sin t, cos t). A step along +row (y down) turns to (cos t, sin t).
    u = scale * np.array([np.cos(t), np.sin(t)]) * (-1 if inst["flip_rows"] else 1)
    v = scale * np.array([-np.sin(t), np.cos(t)]) * (-1 if inst["flip_cols"] else 1)
    return u, v


def _filtered(surface, fine, inst, pad):
    """Blurred and footprint-averaged surface on the zero-padded fine grid."""
    grid = np.pad(surface, pad, mode="constant")
    f_r = sfft.fftfreq(grid.shape[0])[:, None]          # cycles per cell along rows
    f_c = sfft.rfftfreq(grid.shape[1])[None, :]
    sigma = inst["blur_sigma_m"] / PITCH_M * fine       # cells
    transfer = np.exp(-2 * np.pi ** 2 * sigma ** 2 * (f_r ** 2 + f_c ** 2))
    u, v = _axes(inst)
    side = inst["pixel_m"] / PITCH_M * fine             # footprint side, cells
    unit_u, unit_v = u / np.hypot(*u), v / np.hypot(*v)
    transfer = transfer * np.sinc(side * (f_r * unit_u[0] + f_c * unit_u[1]))
    transfer = transfer * np.sinc(side * (f_r * unit_v[0] + f_c * unit_v[1]))
    spectrum = sfft.rfft2(grid, workers=1)
    return sfft.irfft2(spectrum * transfer, grid.shape, workers=1)


def measure(surface_m, fine, design_shape, out_shape, rng, **overrides):
    """Camera image of ``surface_m`` through a pixel-integrating profilometer.

    Parameters
    ----------
    surface_m : ndarray (design rows * fine, design cols * fine)
        Wafer height (m, z up, 0 at the unetched top), super-fine grid.
    fine : int
        Fine cells per design pixel and axis.
    design_shape : tuple of int
        Design (rows, cols).
    out_shape : tuple of int
        Camera (rows, cols); the caller sizes it so the field lies inside the design.
    rng : numpy.random.Generator
    **overrides
        Values replacing the drawn ones (same keys as the drawn parameters).

    Returns
    -------
    height_m : ndarray (out_shape)
        Heights (m), NaN where invalid, row 0 at the top of the camera image.
    inst : dict
        Drawn parameters, ``matrix``, ``offset``, ``spikes`` (row, col, m) and ``n_invalid``.
    """
    inst = _random_parameters(rng, design_shape)
    if set(overrides) - set(inst):
        raise KeyError(f"unknown instrument parameters {sorted(set(overrides) - set(inst))}")
    inst.update(overrides)
    inst["instrument"] = "boxcar"
    surface = np.asarray(surface_m, float)
    if surface.shape != (design_shape[0] * fine, design_shape[1] * fine):
        raise ValueError(f"surface {surface.shape} does not hold {design_shape} pixels of {fine} cells")
    u, v = _axes(inst)
    matrix = np.column_stack([u, v])
    offset = np.asarray(inst["centre_px"], float) - matrix @ ((np.asarray(out_shape) - 1) / 2)
    inst["matrix"], inst["offset"] = matrix, offset
    # The field's outer corners (pixel edges) must stay on the design.
    edge = np.array([[r, c] for r in (-0.5, out_shape[0] - 0.5) for c in (-0.5, out_shape[1] - 0.5)])
    corner = edge @ matrix.T + offset
    if np.any(corner < -0.5) or np.any(corner > np.asarray(design_shape) - 0.5):
        raise ValueError(f"field {out_shape} leaves the {design_shape} design under this placement")

    # Zero padding: the Gaussian's 6 sigma plus a pixel and a half, so nothing wraps.
    pad = int(np.ceil(6 * inst["blur_sigma_m"] / PITCH_M * fine + 1.5 * inst["pixel_m"] / PITCH_M * fine)) + 8
    smooth = _filtered(surface, fine, inst, pad)
    cam_r, cam_c = np.indices(out_shape, dtype=float)
    d_r = matrix[0, 0] * cam_r + matrix[0, 1] * cam_c + offset[0]
    d_c = matrix[1, 0] * cam_r + matrix[1, 1] * cam_c + offset[1]
    at = [(d_r + 0.5) * fine - 0.5 + pad, (d_c + 0.5) * fine - 0.5 + pad]
    # Spline only the part of the grid the field reads (the prefilter of the whole grid is slow).
    lo = [max(int(np.floor(a.min())) - 12, 0) for a in at]
    hi = [min(int(np.ceil(a.max())) + 13, n) for a, n in zip(at, smooth.shape)]
    part = smooth[lo[0]:hi[0], lo[1]:hi[1]]
    height = ndi.map_coordinates(part, [at[0] - lo[0], at[1] - lo[1]], order=3, mode="nearest")

    x_m = (cam_c - (out_shape[1] - 1) / 2) * inst["pixel_m"]
    y_m = ((out_shape[0] - 1) / 2 - cam_r) * inst["pixel_m"]
    height = height + inst["tilt_rad"][0] * x_m + inst["tilt_rad"][1] * y_m + inst["piston_m"]
    height = height + rng.normal(0.0, inst["noise_m"], out_shape)
    flat = height.reshape(-1)
    picks = rng.permutation(flat.size)
    k = int(inst["n_spikes"])
    spike_at = picks[:k]
    spike = rng.uniform(0.1e-6, 1e-6, k) * np.where(rng.random(k) < 0.5, -1.0, 1.0)
    flat[spike_at] += spike
    inst["spikes"] = [(int(i) // out_shape[1], int(i) % out_shape[1], float(s)) for i, s in zip(spike_at, spike)]
    n_bad = int(round(inst["invalid_fraction"] * flat.size))
    flat[picks[k:k + n_bad]] = np.nan
    inst["n_invalid"] = n_bad
    return flat.reshape(out_shape), inst
