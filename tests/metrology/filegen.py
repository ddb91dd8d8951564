"""Independent generator of profilometer files with hidden fabrication effects.

This is the tests' own implementation of the physics, written apart from the model code: it
never calls :mod:`masks.process`, :mod:`masks.litho` or the diagnosis's rendering, so a test
that compares the two checks the model against a different implementation, not itself.

How a case is made (every number drawn from a seed):

1. A DOE-like level map (16 levels, features of a few design pixels) and its 4 binary masks
   (mask j open where bit j of the level is set, etch depth 75 nm * 2**j).
2. The wafer on a super-fine grid (``pitch / 80``, about 0.07 um). Each cell's coverage by a
   mask's printed opening comes from the signed Chebyshev distance of the cell centre to the
   drawn opening, moved back through the overlay and rotation: ``clip(0.5 + (bias - d) /
   cell, 0, 1)``, exact for the straight Manhattan edges of a DOE. Etch depth per mask,
   microtrenching (extra depth ``m exp(-d_in / w)`` inside the opening), an etch gradient
   across the field and etch loading (the depth falls with the local open fraction) scale the
   etch; the etches are summed. Outside the diagnosis's vocabulary, a depth nonlinearity
   ``h + k h**2`` of the summed surface.
3. The instrument: a Gaussian objective blur, optional batwing, and camera pixels of 0.8-1.2 um
   (not a multiple of anything in the design) rotated by up to 1 degree, possibly mirrored,
   each reporting the mean of the blurred surface over its footprint (8 x 8 sub-samples).
   Then tilt, piston, white noise, spikes and invalid pixels.

Arrays are row-major with row 0 at the top, in the design and in the camera. Overlay and
gradient directions: x toward increasing column, y up (toward decreasing row). An overlay or a
rotation may name several masks at once: ``{"mask": [1, 3], "shift_m": [[dx, dy], [dx, dy]]}``,
``{"mask": [2, 3], "angle_deg": [a, b]}``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import scipy.ndimage as ndi

PITCH_M = 5.4e-6
DEPTHS_M = (75e-9, 150e-9, 300e-9, 600e-9)
# Super-fine cells per design pixel. A partly covered cell is blurred as a uniform grey one; at
# 40 cells (0.135 um) that alone left 0.2-0.5 nm rms on a mask moved by a few tenths of a micron,
# an error of the same kind and size as a model rendering moved masks on its own 0.12 um grid
# (the two agreed with each other better than with the truth). At 80 cells the generator agrees
# with a model that moves the masks exactly to 0.07 nm rms.
FINE_PER_PX = 80
SUBSAMPLES = 8
# Fabrication effects the generator can hide, and measurement artefacts it always or sometimes adds.
FAB_EFFECTS = ("etch_depth", "mask_overlay", "linewidth_bias", "etch_loading", "mask_rotation",
               "microtrenching", "etch_gradient")
# Effects the generator can hide that no built-in diagnosis effect describes.
OUTSIDE_VOCABULARY = ("depth_nonlinearity",)


@dataclass
class FileCase:
    """One generated measurement and the truth behind it.

    Attributes
    ----------
    levels : ndarray of int16 (rows, cols)
        Design levels, row 0 at the top.
    truth : dict
        Hidden fabrication effects: name -> dict of physical parameters (SI).
    instrument : dict
        ``pixel_m`` (true), ``header_pixel_m`` (written to the file), ``rotation_deg``,
        ``flip_rows``, ``flip_cols``, ``blur_sigma_m``, ``batwing``, ``tilt_rad``,
        ``noise_m``, ``n_spikes``, ``invalid_fraction``, ``matrix`` and ``offset`` (camera
        pixel (row, col) centre -> design pixel coordinates).
    height_m : ndarray (rows, cols)
        The camera's height map (NaN = invalid), row 0 at the top of the camera image.
    """

    levels: np.ndarray
    truth: dict
    instrument: dict
    height_m: np.ndarray
    seed: int = 0
    extra: dict = field(default_factory=dict)

    def write(self, directory, metadata=None, design=True):
        """Write ``design.npz`` (with ``metadata``; skipped when ``design`` is False) and
        ``measured.datx`` into ``directory``; return both paths."""
        from doedesign.design import Design
        from metrology.formats.writers import write_datx

        directory = Path(directory)
        directory.mkdir(parents=True, exist_ok=True)
        d_path, m_path = directory / "design.npz", directory / "measured.datx"
        if design:
            height = -np.asarray(DEPTHS_M) @ masks_of(self.levels).reshape(4, -1)
            Design(height_m=height.reshape(self.levels.shape), pitch_m=PITCH_M, levels=self.levels.astype(np.int16),
                   metadata=dict(metadata or {})).save(d_path)
        write_datx(m_path, self.height_m, self.instrument["header_pixel_m"])
        return d_path, m_path


def masks_of(levels):
    """Binary masks (4, rows, cols): mask j open where bit j of the level is set."""
    return np.stack([(np.asarray(levels) >> j) & 1 for j in range(4)]).astype(bool)


def random_levels(shape, rng):
    """A feature-rich 16-level map: a smooth random phase plus a ramp, wrapped; an unetched disc
    gives the pattern density a range (etch loading needs one)."""
    phase = ndi.gaussian_filter(rng.standard_normal(shape), 3.0, mode="wrap")
    phase *= 2.5 / phase.std()
    ramp = rng.uniform(0.5, 1.5) * np.arange(shape[1])[None, :] / 6.0
    levels = np.floor(np.mod((phase + ramp) * 16 / (2 * np.pi), 16)).astype(np.int16)
    rr, cc = np.mgrid[:shape[0], :shape[1]]
    cy, cx = rng.uniform(0.3, 0.7, 2) * np.array(shape)
    levels[np.hypot(rr - cy, cc - cx) < rng.uniform(0.12, 0.2) * min(shape)] = 0
    return levels


def density_split_levels(shape, rng):
    """Random levels in 2 x 2 blocks whose two deepest masks are open on 85 % of the left half and
    15 % of the right: the same level sits in dense and sparse surroundings, so etch loading
    spreads each level's height across the field."""
    coarse = ((shape[0] + 1) // 2, (shape[1] + 1) // 2)

    def blocks(a):
        return np.repeat(np.repeat(a, 2, 0), 2, 1)[:shape[0], :shape[1]]

    levels = blocks(rng.integers(0, 16, coarse))
    dense = np.arange(shape[1])[None, :] < shape[1] / 2
    for bit in (2, 3):
        open_ = blocks(rng.random(coarse)) < np.where(dense, 0.85, 0.15)
        levels = np.where(open_, levels | (1 << bit), levels & ~(1 << bit))
    return levels.astype(np.int16)


def _chebyshev_signed(mask, r, c):
    """Signed Chebyshev distance (design px) of points (r, c) to the edge of a pixel mask:
    negative inside the opening. Only the 3 x 3 neighbouring pixels are searched: distances
    under one pixel are exact, larger ones read as 1 (beyond every bias and trench here);
    outside the design the mask is closed. ``r`` and ``c`` broadcast against each other (a
    column of rows and a row of columns for a mask that is not rotated)."""
    rows, cols = mask.shape
    # Two closed pixels around the design: every neighbour of a clipped index is inside.
    padded = np.zeros((rows + 4, cols + 4), bool)
    padded[2:-2, 2:-2] = mask
    ir = np.clip(np.rint(r).astype(np.intp), -1, rows)
    ic = np.clip(np.rint(c).astype(np.intp), -1, cols)
    here = padded[ir + 2, ic + 2]
    best = np.ones(here.shape)
    for di in (-1, 0, 1):
        dist_r = np.maximum(np.abs(r - (ir + di)) - 0.5, 0.0)
        for dj in (-1, 0, 1):
            dist_c = np.maximum(np.abs(c - (ic + dj)) - 0.5, 0.0)
            other = padded[ir + 2 + di, ic + 2 + dj] != here
            np.minimum(best, np.where(other, np.maximum(dist_r, dist_c), 1.0), out=best)
    return np.where(here, -best, best)


def fine_grid(shape, fine=FINE_PER_PX):
    """Cell centres of the super-fine grid in design-pixel coordinates (rows, cols)."""
    return ((np.arange(shape[0] * fine) + 0.5) / fine - 0.5, (np.arange(shape[1] * fine) + 0.5) / fine - 0.5)


def wafer_surface(levels, truth, fine=FINE_PER_PX):
    """The etched surface (m) on the super-fine grid, with the hidden effects in ``truth``."""
    levels = np.asarray(levels)
    masks = masks_of(levels)
    rows, cols = fine_grid(levels.shape, fine)
    rr, cc = rows[:, None], cols[None, :]
    centre = ((levels.shape[0] - 1) / 2, (levels.shape[1] - 1) / 2)
    cell = 1.0 / fine
    depths = np.array(DEPTHS_M) * (1 + np.asarray(truth.get("etch_depth", {}).get("error", np.zeros(4))))
    overlay = np.zeros((4, 2))
    if "mask_overlay" in truth:
        overlay[truth["mask_overlay"]["mask"]] = truth["mask_overlay"]["shift_m"]
    rotation = np.zeros(4)
    if "mask_rotation" in truth:
        rotation[truth["mask_rotation"]["mask"]] = np.radians(truth["mask_rotation"]["angle_deg"])
    bias = np.asarray(truth.get("linewidth_bias", {}).get("bias_m", np.zeros(4))) / PITCH_M
    # Position on the wafer in mm from the field centre (x right, y up), for the gradient.
    x_mm = (cc - centre[1]) * PITCH_M * 1e3
    y_mm = -(rr - centre[0]) * PITCH_M * 1e3
    height = np.zeros((rows.size, cols.size))
    for j in range(4):
        # Undo this mask's placement: a point p of the wafer saw the drawn mask at q.
        dr, dc = -overlay[j, 1] / PITCH_M, overlay[j, 0] / PITCH_M
        a = rotation[j]
        pr, pc = rr - centre[0] - dr, cc - centre[1] - dc
        # Counter-clockwise with y up is clockwise on (row, col); q = R(-a) p. Unrotated, the
        # rows and columns stay separable (a column and a row that broadcast).
        qr = np.cos(a) * pr + np.sin(a) * pc + centre[0] if a else pr + centre[0]
        qc = -np.sin(a) * pr + np.cos(a) * pc + centre[1] if a else pc + centre[1]
        dist = _chebyshev_signed(masks[j], qr, qc) - bias[j]
        cover = np.clip(0.5 - dist / cell, 0.0, 1.0)
        depth = np.full(height.shape, depths[j])
        if "etch_loading" in truth:
            density = ndi.gaussian_filter(masks[j].astype(float), 50e-6 / PITCH_M, mode="constant")
            qr_full, qc_full = np.broadcast_arrays(qr, qc)
            dens_fine = ndi.map_coordinates(density, [qr_full, qc_full], order=1, mode="nearest")
            depth *= 1 - truth["etch_loading"]["loading"] * dens_fine
        if "etch_gradient" in truth:
            g = truth["etch_gradient"]
            ang = np.radians(g["direction_deg"])
            depth *= 1 + g["per_mm"] * (np.cos(ang) * x_mm + np.sin(ang) * y_mm)
        if "microtrenching" in truth and truth["microtrenching"]["mask"] == j:
            t = truth["microtrenching"]
            inside = np.maximum(-dist, 0.0) * PITCH_M
            depth = depth + t["depth_m"] * np.exp(-inside / t["width_m"])
        height -= cover * depth
    if "depth_nonlinearity" in truth:
        # Outside the diagnosis's vocabulary: the etch rate changed with depth, so every level
        # departs from its nominal height by k h**2 (not a per-mask sum).
        height = height + truth["depth_nonlinearity"]["per_m"] * height ** 2
    return height


def instrument_view(surface, shape_design, inst, out_shape, rng, fine=FINE_PER_PX):
    """What the camera reports: blur, batwing, pixel-area mean over each footprint, levelling
    errors, noise, spikes and invalid pixels."""
    cell_m = PITCH_M / fine
    blurred = ndi.gaussian_filter(surface, inst["blur_sigma_m"] / cell_m, mode="nearest")
    if inst.get("batwing"):
        amp, sig = inst["batwing"]
        lap = ndi.gaussian_laplace(surface, sig / cell_m, mode="nearest") / cell_m ** 2
        blurred = blurred - amp * sig ** 2 * np.sqrt(2 * np.pi * np.e) * lap
    m, t = np.asarray(inst["matrix"]), np.asarray(inst["offset"])
    sub = (np.arange(SUBSAMPLES) + 0.5) / SUBSAMPLES - 0.5
    r, c = np.mgrid[:out_shape[0], :out_shape[1]].astype(float)
    total = np.zeros(out_shape)
    for a in sub:
        for b in sub:
            R = m[0, 0] * (r + a) + m[0, 1] * (c + b) + t[0]
            C = m[1, 0] * (r + a) + m[1, 1] * (c + b) + t[1]
            total += ndi.map_coordinates(blurred, [(R + 0.5) * fine - 0.5, (C + 0.5) * fine - 0.5],
                                         order=1, mode="nearest")
    height = total / SUBSAMPLES ** 2
    pix = inst["pixel_m"]
    height += inst["piston_m"] + inst["tilt_rad"][0] * c * pix + inst["tilt_rad"][1] * r * pix
    height += inst["noise_m"] * rng.standard_normal(out_shape)
    flat = height.ravel()
    idx = rng.choice(flat.size, inst["n_spikes"], replace=False)
    flat[idx] += rng.choice([-1, 1], idx.size) * rng.uniform(0.1e-6, 1e-6, idx.size)
    idx = rng.choice(flat.size, int(inst["invalid_fraction"] * flat.size), replace=False)
    flat[idx] = np.nan
    return flat.reshape(out_shape)


def draw_effect(name, rng):
    """Realistic random parameters of one hidden fabrication effect."""
    if name == "etch_depth":
        err = np.zeros(4)
        err[rng.integers(0, 4)] = rng.choice([-1, 1]) * rng.uniform(0.03, 0.08)
        return {"error": err}
    if name == "mask_overlay":
        mag, ang = rng.uniform(0.25e-6, 0.6e-6), rng.uniform(0, 2 * np.pi)
        return {"mask": int(rng.integers(1, 4)), "shift_m": np.array([mag * np.cos(ang), mag * np.sin(ang)])}
    if name == "linewidth_bias":
        return {"bias_m": np.full(4, rng.choice([-1, 1]) * rng.uniform(0.2e-6, 0.4e-6))}
    if name == "etch_loading":
        return {"loading": rng.uniform(0.06, 0.12)}
    if name == "mask_rotation":
        return {"mask": int(rng.integers(1, 4)), "angle_deg": rng.choice([-1, 1]) * rng.uniform(0.02, 0.05)}
    if name == "microtrenching":
        j = int(rng.integers(2, 4))
        return {"mask": j, "depth_m": rng.uniform(0.08, 0.15) * DEPTHS_M[j], "width_m": rng.uniform(0.3e-6, 0.6e-6)}
    if name == "etch_gradient":
        # Relative depth change per mm; steeper than across a whole wafer so that it shows over a
        # 0.3 mm field at all (a few nm on the 600 nm step).
        return {"per_mm": rng.choice([-1, 1]) * rng.uniform(0.02, 0.05), "direction_deg": rng.uniform(0, 360)}
    if name == "depth_nonlinearity":
        return {"per_m": rng.choice([-1, 1]) * rng.uniform(2e4, 4e4)}
    raise KeyError(name)


def draw_instrument(rng, design_shape, out_shape, batwing=None):
    """A NewView-like camera placement and its artefacts."""
    pix = rng.uniform(0.8e-6, 1.2e-6)
    rot = rng.uniform(-1.0, 1.0)
    fr, fc = bool(rng.integers(0, 2)), bool(rng.integers(0, 2))
    a = np.radians(rot)
    # Camera pixel -> design pixel: mirror, turn counter-clockwise (y up), scale.
    rotm = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    matrix = pix / PITCH_M * rotm @ np.diag([-1.0 if fr else 1.0, -1.0 if fc else 1.0])
    centre_design = (np.array(design_shape) - 1) / 2 + rng.uniform(-0.5, 0.5, 2)
    offset = centre_design - matrix @ ((np.array(out_shape) - 1) / 2)
    return {"pixel_m": pix, "header_pixel_m": pix * (1 + rng.uniform(-0.005, 0.005)), "rotation_deg": rot,
            "flip_rows": fr, "flip_cols": fc, "blur_sigma_m": rng.uniform(0.3e-6, 0.45e-6),
            "batwing": batwing, "tilt_rad": rng.uniform(-2e-4, 2e-4, 2), "piston_m": rng.uniform(-1e-6, 1e-6),
            "noise_m": rng.uniform(0.5e-9, 1.5e-9), "n_spikes": int(rng.integers(0, 12)),
            "invalid_fraction": rng.uniform(0.0, 0.01), "matrix": matrix, "offset": offset}


def make_case(effects, seed, design_px=48, field_px=160, truth=None, instrument=None, fine=FINE_PER_PX,
              levels=None):
    """A file case with ``effects`` hidden (empty = null case).

    Parameters
    ----------
    effects : sequence of str
        Names from :data:`FAB_EFFECTS`.
    seed : int
    design_px : int
        Design size (pixels of 5.4 um per side).
    field_px : int
        Camera field (pixels per side); it must fit inside the design at any rotation.
    truth, instrument : dict, optional
        Override the drawn values (keys of :func:`draw_effect` / :func:`draw_instrument`).
    fine : int
        Super-fine cells per design pixel (fewer for a large design timed, not judged: the
        surface takes ``(design_px * fine)**2`` cells).
    levels : ndarray, optional
        The design to make (another field of the same design); default drawn from ``seed``.
    """
    rng = np.random.default_rng(seed)
    drawn = random_levels((design_px, design_px), rng)
    levels = drawn if levels is None else np.asarray(levels)
    hidden = {name: draw_effect(name, rng) for name in effects}
    hidden.update(truth or {})
    inst = draw_instrument(rng, levels.shape, (field_px, field_px))
    inst.update(instrument or {})
    surface = wafer_surface(levels, hidden, fine)
    height = instrument_view(surface, levels.shape, inst, (field_px, field_px), rng, fine)
    return FileCase(levels=levels, truth=hidden, instrument=inst, height_m=height, seed=seed)


def planned_cases(n, seed):
    """``n`` (effect names, case seed) pairs drawn from ``seed``: nulls, each effect alone, and pairs
    (the mix of :func:`random_cases`, for harnesses that make each case their own way)."""
    rng = np.random.default_rng(seed)
    out = []
    for k in range(n):
        kind = k % 4
        if kind == 0:
            names = []
        elif kind == 3:
            names = [str(v) for v in rng.choice(FAB_EFFECTS, 2, replace=False)]
        else:
            names = [str(rng.choice(FAB_EFFECTS))]
        out.append((names, int(rng.integers(0, 2 ** 31))))
    return out


def random_cases(n, seed):
    """``n`` cases: nulls, each effect alone, and pairs, drawn from ``seed``."""
    return [make_case(names, case_seed) for names, case_seed in planned_cases(n, seed)]
