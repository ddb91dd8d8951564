"""A point-sampling profilometer: Gaussian blur, then the height at each camera pixel's centre.

Physics. The objective is a Gaussian blur of the wafer surface (sigma 0.25-0.5 um). The camera
does not integrate over its pixels: each pixel reports the blurred surface at the one point
of the sample its centre looks at (an ideal point detector; a real camera integrates, which is
what :mod:`instruments.boxcar` draws). The blurred surface is smooth (its Gaussian leaves
nothing near the fine grid's Nyquist frequency), so a cubic spline through the fine grid reads
it between cells to well under 0.1 nm.

Placement. Camera pixels are ``pixel_m`` wide (0.7-1.3 um, the header off by up to 0.5 %),
the camera image is mirrored (rows, columns or neither), then turned by ``rotation_deg``
(up to 1 degree, counter-clockwise with y up) and centred within half a design pixel of the
design's centre. ``matrix`` and ``offset`` map a camera pixel's centre (row, col) to design
pixel coordinates, ``design = matrix @ [row, col] + offset``; design pixel (r, c) covers
[r - 0.5, r + 0.5] x [c - 0.5, c + 0.5], row 0 at the top, x toward increasing column, y up.

Artefacts, in the camera frame: tilt (up to 2e-4 rad per axis, x right and y up from the
image centre), piston, white noise (0.5-1.5 nm rms), 0-12 spikes (single pixels off by
0.1-1 um, either sign) and invalid pixels (up to 1 %, NaN).

The surface is the fine grid of ``filegen.wafer_surface``: cell (i, j) centred at design
coordinates ((i + 0.5) / fine - 0.5, (j + 0.5) / fine - 0.5); outside the design the wafer is
unetched (height 0), which is what the blur sees beyond the grid's edge.
"""

from __future__ import annotations

import numpy as np
import scipy.ndimage as ndi

from filegen import PITCH_M

# Kernel half-width of the blur, in sigmas; the crop around the field keeps this much more.
TRUNCATE = 5.0


def draw(rng, design_shape):
    """The instrument's random parameters (SI), before any override."""
    pixel = rng.uniform(0.7e-6, 1.3e-6)
    flip = ("none", "rows", "cols")[int(rng.integers(0, 3))]
    centre = (np.asarray(design_shape, float) - 1) / 2 + rng.uniform(-0.5, 0.5, 2)
    return {"pixel_m": pixel, "header_pixel_m": pixel * (1 + rng.uniform(-0.005, 0.005)),
            "rotation_deg": rng.uniform(-1.0, 1.0), "flip_rows": flip == "rows", "flip_cols": flip == "cols",
            "centre_px": centre, "blur_sigma_m": rng.uniform(0.25e-6, 0.5e-6),
            "tilt_rad": rng.uniform(-2e-4, 2e-4, 2), "piston_m": rng.uniform(-0.5e-6, 0.5e-6),
            "noise_m": rng.uniform(0.5e-9, 1.5e-9), "n_spikes": int(rng.integers(0, 13)),
            "invalid_fraction": rng.uniform(0.0, 0.01)}


def camera_to_design(inst, out_shape):
    """``(matrix, offset)``: camera pixel centre (row, col) -> design pixel coordinates."""
    a = np.radians(inst["rotation_deg"])
    # Counter-clockwise with y up, written on (row, col) where row runs down.
    turn = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    mirror = np.diag([-1.0 if inst["flip_rows"] else 1.0, -1.0 if inst["flip_cols"] else 1.0])
    matrix = inst["pixel_m"] / PITCH_M * turn @ mirror
    middle = (np.asarray(out_shape, float) - 1) / 2
    return matrix, np.asarray(inst["centre_px"], float) - matrix @ middle


def _check_inside(matrix, offset, design_shape, out_shape):
    corners = np.array([[-0.5, -0.5], [-0.5, out_shape[1] - 0.5], [out_shape[0] - 0.5, -0.5],
                        [out_shape[0] - 0.5, out_shape[1] - 0.5]])
    at = corners @ matrix.T + offset
    if at.min() < -0.5 or np.any(at.max(axis=0) > np.asarray(design_shape) - 0.5):
        raise ValueError(f"a {out_shape} field does not fit inside the {design_shape} design under this placement")


def _sample(surface, fine, sigma_cells, rows, cols):
    """The blurred surface at design coordinates (rows, cols), through a crop of the grid."""
    fi = (rows + 0.5) * fine - 0.5
    fj = (cols + 0.5) * fine - 0.5
    margin = int(np.ceil(TRUNCATE * sigma_cells)) + 4
    i0, j0 = max(int(np.floor(fi.min())) - margin, 0), max(int(np.floor(fj.min())) - margin, 0)
    i1 = min(int(np.ceil(fi.max())) + margin + 1, surface.shape[0])
    j1 = min(int(np.ceil(fj.max())) + margin + 1, surface.shape[1])
    # Zero-pad by the kernel's reach wherever the crop meets the grid's edge (unetched wafer);
    # elsewhere the crop's own margin is real surface.
    pad = margin
    crop = np.pad(surface[i0:i1, j0:j1], pad, mode="constant")
    blurred = ndi.gaussian_filter(crop, sigma_cells, mode="constant", truncate=TRUNCATE)
    return ndi.map_coordinates(blurred, [fi - i0 + pad, fj - j0 + pad], order=3, mode="nearest")


def measure(surface_m, fine, design_shape, out_shape, rng, **overrides):
    """The camera image of ``surface_m`` and the instrument drawn.

    Parameters
    ----------
    surface_m : ndarray (design rows * fine, design cols * fine)
        Wafer height (m, z up, 0 = unetched top) on the super-fine grid.
    fine : int
        Fine cells per design pixel per axis.
    design_shape : tuple of int
        Design pixels (rows, cols).
    out_shape : tuple of int
        Camera pixels (rows, cols); the field must lie inside the design at any rotation.
    rng : numpy.random.Generator
    **overrides
        Replace drawn parameters (keys of :func:`draw`).

    Returns
    -------
    height_m : ndarray (out_shape)
        Camera image (m), NaN = invalid, row 0 at the top of the camera image.
    inst : dict
        The parameters drawn plus ``matrix``, ``offset``, ``spikes`` ((row, col, m) each) and
        ``n_invalid``.
    """
    inst = draw(rng, design_shape)
    unknown = set(overrides) - set(inst)
    if unknown:
        raise KeyError(f"unknown instrument parameters {sorted(unknown)}")
    inst.update(overrides)
    inst["instrument"] = "point"
    surface_m = np.asarray(surface_m, float)
    if surface_m.shape != (design_shape[0] * fine, design_shape[1] * fine):
        raise ValueError(f"surface {surface_m.shape} is not {design_shape} design pixels of {fine} cells")
    matrix, offset = camera_to_design(inst, out_shape)
    _check_inside(matrix, offset, design_shape, out_shape)
    inst["matrix"], inst["offset"] = matrix, offset

    r, c = np.meshgrid(np.arange(out_shape[0], dtype=float), np.arange(out_shape[1], dtype=float), indexing="ij")
    rows = matrix[0, 0] * r + matrix[0, 1] * c + offset[0]
    cols = matrix[1, 0] * r + matrix[1, 1] * c + offset[1]
    sigma_cells = inst["blur_sigma_m"] / PITCH_M * fine
    height = _sample(surface_m, fine, sigma_cells, rows.ravel(), cols.ravel()).reshape(out_shape)

    x = (c - (out_shape[1] - 1) / 2) * inst["pixel_m"]
    y = -(r - (out_shape[0] - 1) / 2) * inst["pixel_m"]
    tilt = np.asarray(inst["tilt_rad"], float)
    height = height + tilt[0] * x + tilt[1] * y + inst["piston_m"]
    height = height + inst["noise_m"] * rng.standard_normal(out_shape)
    n = height.size
    where = rng.choice(n, int(inst["n_spikes"]), replace=False)
    sizes = rng.choice([-1.0, 1.0], where.size) * rng.uniform(0.1e-6, 1e-6, where.size)
    height.flat[where] += sizes
    inst["spikes"] = [(int(k // out_shape[1]), int(k % out_shape[1]), float(s)) for k, s in zip(where, sizes)]
    bad = rng.choice(n, int(round(inst["invalid_fraction"] * n)), replace=False)
    height.flat[bad] = np.nan
    inst["n_invalid"] = int(bad.size)
    return height, inst
