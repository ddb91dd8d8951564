"""Optical proximity correction (OPC) of a binary mask for the aligner's gap.

A mask printed through a proximity gap does not print as drawn (:mod:`masks.proximity`): edges
move by the local image slope's error (a feature-size dependent linewidth), corners round, a
narrow line prints thinner or not at all and a narrow gap bridges. OPC draws the mask
pre-distorted so that its print matches the drawn design.

Method: level-set inverse lithography on a sub-grid of the print model's fine grid (model-based
pixel OPC). The corrected mask is the zero set of a function ``psi`` on the *mask grid*
(``subgrid`` mask cells per print cell a side), started as the drawn mask's signed distance (mask
cells, positive in the openings), so the mask is binary at every step. Each iteration images the
current mask through the gap (:func:`masks.proximity.aerial_image_vjp`: the same band-limited
angular spectrum, Hg lines, collimation disc and resist blur as :func:`masks.proximity.print_coverage`;
the mask cells averaged to the print grid's area coverage), prints it with the real resist
(:func:`masks.proximity.resist_print`: threshold, chromium undercut) to score it, and takes the
gradient over the coverage of ``sum (printed - drawn) sigmoid(b (I - t))``: the real print's error
carried back to the image through a soft resist's slope (``level_set_steepness``; measured on a
32 px fine element at 30 um, 40 steps: field overlap 0.928 with the real print's error at b = 8,
0.915 with a soft print's own error at b = 25). ``psi`` moves against that gradient, scaled so that the
95th percentile of it on the mask's edge cells moves an edge by ``step_cells`` mask cells; ``psi``
accumulates, so moves below a cell add up until the edge steps. The gradient holds the
interference of the Fresnel pattern: an opening near the resolution ``sqrt(lambda g)`` (3.5 um at
30 um) may print *smaller* when drawn larger, which a rule that moves each edge by its own
placement error gets wrong (measured: such a loop diverged on a one-edge-per-pixel element, its
printed area error grew 50 % in 12 steps). So edges move by feature size and neighbourhood,
outer corners grow serifs and inner corners are cut where the print rounds them, on the mask grid.

With ``method="density"`` the level set starts instead from :mod:`masks.opc_density`'s mask (a
density optimized with the minimum feature's length scale, cut to binary, made manufacturable):
the level set alone finds corrections near the drawn edges, the density stage the larger serifs and
assist shapes a print through 30 um needs (measured on that element: 0.933 after 100 level-set
steps, 0.976 with the density stage and 5 polishing steps, 0.9 um features).

Stopping rule (deterministic, never a clock): ``iterations`` gradient steps; the mask kept is the
iterate whose real print has the smallest area error ``sum |printed - drawn| step^2`` (ties to the
earlier; the drawn mask is iterate 0, the density stage's mask iterate 1, so the correction never
makes that error worse).

Manufacturable: after each step every opening and every chrome area is made at least
``min_feature_cells`` mask cells wide by a morphological opening, then a closing, with a square of
that side (isolated specks and slivers below the writer's resolution removed, hairline gaps
filled). Defaults: a 0.45 um print grid for 5.4 um pixels (12 cells), 2 mask cells per print cell
(a 0.225 um mask-writer grid, whole nanometres) and a 4-cell (0.9 um) minimum feature, inside a
laser mask writer's ~0.6-1 um resolution for chrome on quartz. The result is reported with its
measured narrowest opening and gap (:func:`masks.grid.narrowest_runs_px`).

Limits: the whole mask is corrected in one window (no tiles), so the element's fine grid must fit
memory (:func:`opc_bytes`); the minimum feature bounds what the correction recovers on an element
with a mask edge in every pixel (measured at 30 um: 0.976 of the field overlap with 0.9 um
features, 0.995 with 0.45 um; docs/guide/proximity.md).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from scipy import fft as sfft
from scipy import ndimage, special

from doedesign.errors import DoeError
from doedesign.progress import Progress

from . import litho
from .grid import PRECISION_M
from .proximity import ProximityOptics, aerial_image_vjp, reach_m, resist_print

#: The quantile of the gradient on the mask's edge cells that moves an edge by ``step_cells``
#: (a few extreme cells, at corners, would otherwise set the scale for all).
_EDGE_QUANTILE = 0.95
#: Mask cells per print cell a side that ``doe masks --opc`` uses (0.225 um for 5.4 um pixels).
OPC_SUBGRID = 2
#: The correction's methods (:class:`OpcSettings`).
METHODS = ("level-set", "density")
# Opening-closing passes of the minimum-feature cleanup (it usually settles in two).
_CLEANUP_PASSES = 8

__all__ = ["METHODS", "OPC_SUBGRID", "MaskCorrection", "OpcSettings", "correct_mask", "correct_masks", "correction_report",
           "opc_bytes", "opc_upsample"]


@dataclass(frozen=True)
class OpcSettings:
    """How the correction runs.

    Attributes
    ----------
    iterations : int
        Prints after the first (1..200); the best of all ``iterations + 1`` masks is kept.
    subgrid : int
        Mask-grid cells per print-grid cell a side (1..8).
    min_feature_cells : int
        Narrowest opening and chrome area on the mask grid (1..64 cells).
    step_cells : float
        Largest edge move of one iteration, in mask cells (0 < step_cells <= 8).
    steepness : float
        Slope of the soft resist ``sigmoid(steepness (I - threshold))`` the density stage's
        objective is taken through, per unit of the normalized image (1..1000).
    level_set_steepness : float
        Slope of the soft resist whose derivative carries the level set's error (the real
        print's) back to the image (1..1000; measured better at 8 than 25: it reaches further
        from the printed contour, into a rounded corner).
    method : str
        ``"level-set"``: the level set from the drawn mask; ``"density"``: the density stage of
        :mod:`masks.opc_density` first, the level set polishing its result.
    density_iterations : int
        L-BFGS-B iterations per slope stage of the density stage (1..500).
    """

    iterations: int = 20
    subgrid: int = 2
    min_feature_cells: int = 4
    step_cells: float = 1.0
    steepness: float = 25.0
    level_set_steepness: float = 8.0
    method: str = "level-set"
    density_iterations: int = 20

    def __post_init__(self) -> None:
        if self.method not in METHODS:
            raise DoeError(f"OPC: method must be one of {', '.join(METHODS)}, got {self.method!r}")
        for name, lo, hi in (("iterations", 1, 200), ("subgrid", 1, 8), ("min_feature_cells", 1, 64),
                             ("density_iterations", 1, 500)):
            v = getattr(self, name)
            if not (isinstance(v, (int, np.integer)) and lo <= v <= hi):
                raise DoeError(f"OPC: {name} must be an integer in [{lo}, {hi}], got {v!r}")
        for name, low, high in (("step_cells", 0.0, 8.0), ("steepness", 1.0, 1000.0),
                                ("level_set_steepness", 1.0, 1000.0)):
            x = float(getattr(self, name))
            if not (math.isfinite(x) and low < x <= high):
                raise DoeError(f"OPC: {name} must lie in ({low:g}, {high:g}], got {x}")


@dataclass
class MaskCorrection:
    """One corrected mask.

    Attributes
    ----------
    mask : ndarray of bool (rows * subgrid, cols * subgrid)
        The corrected opening on the mask grid (row 0 at the top).
    printed : ndarray of float32 (rows, cols)
        Its printed coverage on the print grid.
    area_error_m2 : list of float
        ``sum |printed - drawn| * step**2`` of every iterate (index 0: the drawn mask).
    best_iteration : int
        The iterate kept.
    """

    mask: np.ndarray
    printed: np.ndarray
    area_error_m2: list = field(default_factory=list)
    best_iteration: int = 0


def _signed_distance(mask):
    """Signed distance (cells) from each cell's centre to the mask's edge, positive inside."""
    inside = ndimage.distance_transform_edt(np.pad(mask, 1, constant_values=False))[1:-1, 1:-1]
    outside = ndimage.distance_transform_edt(np.pad(~mask, 1, constant_values=True))[1:-1, 1:-1]
    return np.where(mask, inside - 0.5, 0.5 - outside)


def _manufacturable(mask, cells):
    """Every opening and every chrome area at least ``cells`` wide: a morphological closing (each
    chrome cell then lies in a chrome square of that side), then an opening (each open cell in an
    open square: no opening narrower, ever), repeated until the mask no longer changes (at most
    :data:`_CLEANUP_PASSES`; a chrome gap may stay narrower where two openings meet corner to corner)."""
    if cells <= 1:
        return mask
    square = np.ones((cells, cells), dtype=bool)
    pad = cells  # the plate beyond the array is chrome and stays so
    for _ in range(_CLEANUP_PASSES):
        closed = ndimage.binary_closing(np.pad(mask, pad), structure=square)[pad:-pad, pad:-pad]
        opened = ndimage.binary_opening(closed, structure=square)
        if np.array_equal(opened, mask):
            break
        mask = opened
    return mask


def _soft_target(target, step_m, cr_undercut_m):
    """What the resist itself must clear: the drawn opening less the chromium undercut that follows."""
    if cr_undercut_m <= 0:
        return target.astype(np.float32)
    return np.asarray(litho.grow(target.astype(np.float32), -float(cr_undercut_m) / float(step_m)))


def correct_mask(drawn: np.ndarray, step_m: float, optics: ProximityOptics, threshold: float,
                 cr_undercut_m: float = 0.0, settings: OpcSettings | None = None,
                 bias_m: float = 0.0) -> MaskCorrection:
    """Pre-distort one binary mask so that its print through the gap matches it.

    Parameters
    ----------
    drawn : ndarray of bool, shape (rows, cols)
        The drawn opening on the print grid (row 0 at the top; chrome beyond the array).
    step_m : float
        Print-grid step (m); the mask grid's is ``step_m / settings.subgrid``.
    optics, threshold, cr_undercut_m
        The exposure, as for :func:`masks.proximity.print_coverage`.
    settings : OpcSettings, optional
    bias_m : float
        The mask's own linewidth bias (m, positive = openings wider than drawn, as
        ``ProcessParams.linewidth_bias``: the opening grows before it prints). The correction
        draws the mask that, grown by it, prints the target; the level set's step ignores the
        growth (an edge moved moves its grown edge as much).

    Returns
    -------
    MaskCorrection
    """
    settings = settings or OpcSettings()
    target = np.asarray(drawn, dtype=bool)
    if target.ndim != 2:
        raise DoeError(f"OPC: the drawn mask must be 2-D, got shape {target.shape}")
    step_m, threshold = float(step_m), float(threshold)
    s = settings.subgrid
    rows, cols = target.shape
    pad = int(math.ceil(reach_m(optics, step_m) / step_m)) + 1
    shape = (sfft.next_fast_len(rows + 2 * pad), sfft.next_fast_len(cols + 2 * pad))
    inner = (slice(pad, pad + rows), slice(pad, pad + cols))
    soft_target = _soft_target(target, step_m, cr_undercut_m)
    mask = np.repeat(np.repeat(target, s, axis=0), s, axis=1)
    starts = [mask]
    if settings.method == "density":
        from .opc_density import density_mask, density_sigma_cells

        start = density_mask(soft_target, step_m, optics, threshold, s, density_sigma_cells(settings.min_feature_cells),
                             settings.density_iterations, settings.steepness)
        starts.append(_manufacturable(start, settings.min_feature_cells))
    psi = _signed_distance(mask)
    cell_m2 = step_m ** 2
    bias_cells = float(bias_m) * s / step_m
    result = None
    for k in range(settings.iterations + len(starts)):
        if k < len(starts):
            mask = starts[k]
            psi = _signed_distance(mask)
        padded = np.zeros(shape, dtype=np.float32)
        padded[inner] = litho.block_coverage(litho.grow(mask.astype(np.float32), bias_cells), s)
        image, vjp = aerial_image_vjp(padded, step_m, optics)
        printed = np.asarray(resist_print(image[inner], step_m, threshold, cr_undercut_m))
        cost = float(np.abs(printed - target).sum()) * cell_m2
        if result is None:
            result = MaskCorrection(mask=mask, printed=printed)
        elif cost < result.area_error_m2[result.best_iteration]:
            result.mask, result.printed, result.best_iteration = mask, printed, k
        result.area_error_m2.append(cost)
        if k == settings.iterations + len(starts) - 1 or k < len(starts) - 1:
            continue
        # The real print's error, carried back to the image through a soft resist's slope.
        b = settings.level_set_steepness
        soft = special.expit(b * (image[inner] - threshold))
        cot = np.zeros(shape, dtype=np.float32)
        cot[inner] = 2 * b * (printed - target) * soft * (1 - soft)
        speed = np.repeat(np.repeat(vjp(cot)[inner], s, axis=0), s, axis=1)
        band = np.abs(speed[np.abs(_signed_distance(mask)) < 1.0])
        scale = float(np.quantile(band, _EDGE_QUANTILE)) if band.size else 0.0
        if scale == 0:
            break
        psi = psi - settings.step_cells * speed / scale
        mask = _manufacturable(psi > 0, settings.min_feature_cells)
    assert result is not None  # the first iteration sets it
    return result


def correct_masks(masks: np.ndarray, upsample: int, pitch_m: float, optics: ProximityOptics, threshold: float,
                  cr_undercut_m: float = 0.0, settings: OpcSettings | None = None,
                  progress: bool | None = None, biases_m: Sequence[float] | np.ndarray | None = None) -> list[MaskCorrection]:
    """:func:`correct_mask` for every binary design mask, drawn on a print grid of ``pitch_m / upsample``.

    Parameters
    ----------
    masks : ndarray of bool, shape (n_masks, rows, cols)
        Design-pixel masks (:func:`masks.decompose.levels_to_masks`).
    upsample : int
        Print cells per design pixel a side.
    pitch_m : float
        Design pixel pitch (m).
    optics, threshold, cr_undercut_m, settings
        As for :func:`correct_mask`.
    progress : bool, optional
        Show a progress bar (default: when the stream is a terminal).
    biases_m : sequence of float, optional
        Each mask's linewidth bias (``bias_m`` of :func:`correct_mask`; default none).
    """
    masks = np.asarray(masks, dtype=bool)
    u = int(upsample)
    biases = [0.0] * masks.shape[0] if biases_m is None else [float(b) for b in biases_m]
    if len(biases) != masks.shape[0]:
        raise DoeError(f"OPC: {len(biases)} linewidth biases for {masks.shape[0]} masks")
    out = []
    with Progress(masks.shape[0], "OPC masks", enabled=progress) as bar:
        for m, bias in zip(masks, biases):
            fine = np.repeat(np.repeat(m, u, axis=0), u, axis=1)
            out.append(correct_mask(fine, pitch_m / u, optics, threshold, cr_undercut_m, settings, bias))
            bar.update()
    return out


#: Bytes per mask-grid cell (the level set's mask, ``psi``, its signed distance and the speed; the
#: density stage's float64 density, bounds, filtered and projected copies, gradient and L-BFGS-B's
#: ten correction pairs) and per padded print cell (the image, its soft print and cotangent, three
#: complex line fields, FFT work).
_MASK_CELL_BYTES = 280
_PRINT_CELL_BYTES = 96


def opc_bytes(shape: tuple[int, int], upsample: int, subgrid: int) -> int:
    """Peak bytes of correcting one mask of a ``shape`` design at ``upsample`` print cells a pixel
    (for ``budget.check_memory``); the corrected masks of all layers are kept besides (1 byte a cell)."""
    rows, cols = (int(n) * int(upsample) for n in shape)
    s = int(subgrid)
    return _MASK_CELL_BYTES * rows * cols * s * s + _PRINT_CELL_BYTES * (rows + 256) * (cols + 256) \
        + 4 * rows * cols * s * s


def opc_upsample(pitch_m: float, step_m: float, subgrid: int) -> int:
    """Print cells per design pixel: the fewest, at least ``pitch_m / step_m``, whose mask grid
    ``pitch_m / (upsample * subgrid)`` is a whole number of the 1 nm database unit (so the GDS
    holds the corrected edges exactly). 12 for 5.4 um pixels, a 0.5 um step and a subgrid of 2."""
    pitch_nm = pitch_m / PRECISION_M
    first = max(int(math.ceil(pitch_m / step_m - 1e-9)), 1)
    for u in range(first, 4 * first + 1):
        cell = pitch_nm / (u * int(subgrid))
        if abs(cell - round(cell)) < 1e-6 * cell and cell >= 1:
            return u
    raise DoeError(f"OPC: no mask grid between {pitch_m / (4 * first * subgrid) * 1e9:.1f} and "
                   f"{pitch_m / (first * subgrid) * 1e9:.1f} nm divides the {pitch_m * 1e9:.1f} nm pixel into whole "
                   "nanometres")


def correction_report(corrections: list[MaskCorrection], step_m: float, settings: OpcSettings) -> dict:
    """JSON-ready summary (lengths in um): the settings and, per mask, the iterate kept, the printed
    area error before and after, and the corrected mask's narrowest opening and chrome gap."""
    from .grid import narrowest_runs_px

    cell_um = float(step_m) / settings.subgrid * 1e6
    rows = []
    for j, c in enumerate(corrections):
        narrow_open, narrow_gap = narrowest_runs_px(c.mask)
        rows.append({"mask": j, "best_iteration": c.best_iteration,
                     "printed_area_error_um2_drawn": c.area_error_m2[0] * 1e12,
                     "printed_area_error_um2_corrected": c.area_error_m2[c.best_iteration] * 1e12,
                     "narrowest_opening_um": None if narrow_open is None else narrow_open * cell_um,
                     "narrowest_gap_um": None if narrow_gap is None else narrow_gap * cell_um})
    method = {"level-set": "level-set inverse lithography (masks.opc)",
              "density": "density inverse lithography with a length scale (masks.opc_density), level-set polish "
                         "(masks.opc)"}[settings.method]
    return {"method": method, "iterations": settings.iterations,
            "print_step_um": float(step_m) * 1e6, "mask_grid_um": cell_um,
            "min_feature_um": settings.min_feature_cells * cell_um, "step_cells": settings.step_cells,
            "steepness": settings.steepness, "masks": rows}
