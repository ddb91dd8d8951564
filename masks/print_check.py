"""What a proximity gap and dose will print, before a run: per mask the printed against the drawn
open area and the mean edge placement, the features that print badly, and the predicted figure of
merit (the field overlap at 550 nm of the printed element with the design).

Built on :func:`masks.process.simulate_surface` (the proximity print of :mod:`masks.proximity`)
and the project's own phase of a height (:mod:`doedesign.materials`). The edge placement is the
printed minus drawn open area over the drawn mask's edge length (positive: openings grew). A
badly printed feature is an isolated open DOE pixel (no open 4-neighbour) that keeps under half
its area, or a one-pixel chrome gap (closed, open on both sides along a row or a column) that more
than half clears. Corners are not counted separately (their loss is in the area).

:func:`in_place_threshold` is the dose that prints a long straight edge where it is drawn (the
exposure at a half-plane's drawn edge, about 0.25-0.3 of the open field through a gap: Fresnel
diffraction), the default when a user states a gap but no dose. :func:`print_check_page` is
the Markdown that ``doe masks --gap-um`` writes beside its report.
"""

from __future__ import annotations

import math

import numpy as np

from doedesign.errors import DoeError
from doedesign.materials import get_material

from .decompose import mask_bit
from .process import ProcessParams, proximity_optics, simulate_surface
from .proximity import ProximityOptics, aerial_image, print_coverage, reach_m

__all__ = ["in_place_threshold", "print_check", "print_check_masks", "print_check_page"]

# Fine cells on each side of the drawn edge in the half-plane image of in_place_threshold.
_EDGE_CELLS = 512


def in_place_threshold(optics: ProximityOptics, step_m: float) -> float:
    """Resist threshold (fraction of the open field) at which a long straight edge prints in place.

    The exposure through the gap of a half-plane opening, read at its drawn edge (the mean of the
    two fine cells beside it): one period of a strip, endless along the edge, whose other edge
    lies ``_EDGE_CELLS`` cells away (many Fresnel zones at any gap the model takes).
    """
    cov = np.zeros((8, 2 * _EDGE_CELLS), dtype=np.float32)
    cov[:, _EDGE_CELLS:] = 1.0
    image = np.asarray(aerial_image(cov, step_m, optics, periodic=True))
    return float(image[4, _EDGE_CELLS - 1:_EDGE_CELLS + 1].mean())


def print_check(levels: np.ndarray, pitch_m: float, params: ProcessParams, step_m: float = 0.5e-6,
                material: str = "fused_silica", wavelength_m: float = 550e-9,
                region: tuple[int, int, int, int] | None = None) -> dict:
    """Report (JSON-ready dict, lengths in um) of what ``params`` print of ``levels``.

    ``region`` (row0, row1, col0, col1), half-open design pixels, limits the check to a window
    (effects reaching in from outside it included, as :func:`masks.process.simulate_surface`).

    Returns
    -------
    dict
        ``masks``: per mask ``drawn_open_fraction``, ``printed_open_fraction``,
        ``area_ratio``, ``edge_placement_um``, ``isolated_pixels``, ``isolated_lost``,
        ``narrow_gaps``, ``narrow_gaps_bridged``; ``field_overlap``: ``|<exp(i dphi)>|^2`` at
        ``wavelength_m`` between the printed and the ideal surface on the fine grid.
    """
    printed = simulate_surface(levels, pitch_m, params, step_m=step_m, region=region)
    ideal = simulate_surface(levels, pitch_m, ProcessParams.ideal(n_masks=params.n_masks, depths_m=params.etch_depth),
                             step_m=step_m, region=region)
    masks_printed = [np.asarray(m, dtype=float) for m in printed.masks_printed]
    return _report(levels, pitch_m, params, masks_printed, printed.upsample, printed.region,
                   np.asarray(printed.height_m), np.asarray(ideal.height_m), material, wavelength_m)


def print_check_masks(levels: np.ndarray, pitch_m: float, params: ProcessParams, masks: np.ndarray,
                      upsample: int, subgrid: int = 1, material: str = "fused_silica", wavelength_m: float = 550e-9,
                      region: tuple[int, int, int, int] | None = None) -> dict:
    """:func:`print_check` of masks drawn on their own grid (e.g. pre-distorted by
    :mod:`masks.opc`) against the design's ``levels``, with the ideal etch of ``params``' depths.

    Parameters
    ----------
    levels, pitch_m, material, wavelength_m, region
        As for :func:`print_check` (``region`` in design pixels).
    params : ProcessParams
        The gap, collimation, resist blur, threshold, undercut, each mask's linewidth bias (its
        opening grown on the mask grid before it prints, as :func:`masks.process.simulate_surface`
        grows a drawn mask) and the etch depths (no other effect).
    masks : ndarray of bool, shape (n_masks, rows * upsample * subgrid, cols * upsample * subgrid)
        The drawn openings on the mask grid (row 0 at the top).
    upsample : int
        Print cells per design pixel a side (the print grid's step is ``pitch_m / upsample``).
    subgrid : int
        Mask cells per print cell a side (their area coverage is what prints).

    Returns
    -------
    dict
        As :func:`print_check`.
    """
    from .litho import block_coverage, grow

    levels = np.asarray(levels)
    masks = np.asarray(masks, dtype=bool)
    rows, cols = levels.shape
    u, sub = int(upsample), int(subgrid)
    m, step = u * sub, pitch_m / u
    if masks.shape != (params.n_masks, rows * m, cols * m):
        raise DoeError(f"print check: masks of shape {masks.shape} do not draw {params.n_masks} masks of the "
                       f"{rows} x {cols} px design at {m} cells a pixel")
    optics = proximity_optics(params)
    r0, r1, c0, c1 = (0, rows, 0, cols) if region is None else region
    assert params.linewidth_bias is not None  # ProcessParams fills every per-mask field
    bias_reach = float(np.max(np.abs(params.linewidth_bias))) if params.n_masks else 0.0
    margin = int(math.ceil((reach_m(optics, step) + params.cr_undercut + bias_reach) / pitch_m)) + 1
    w0, w1, v0, v1 = max(r0 - margin, 0), min(r1 + margin, rows), max(c0 - margin, 0), min(c1 + margin, cols)
    inner = (slice((r0 - w0) * u, (r1 - w0) * u), slice((c0 - v0) * u, (c1 - v0) * u))
    printed = []
    for j in range(params.n_masks):
        drawn_j = masks[j, w0 * m:w1 * m, v0 * m:v1 * m]
        bias_cells = float(params.linewidth_bias[j]) * m / pitch_m
        cov = block_coverage(grow(drawn_j.astype(np.float32), bias_cells), sub)
        pc = print_coverage(cov, step, optics, params.resist_threshold, params.cr_undercut)
        printed.append(np.asarray(pc, dtype=float)[inner])
    depths = np.asarray(params.etch_depth, dtype=float)
    drawn = [np.repeat(np.repeat(mask_bit(levels[r0:r1, c0:c1], j), u, axis=0), u, axis=1)
             for j in range(params.n_masks)]
    height = -sum(d * p for d, p in zip(depths, printed))
    ideal = -sum(d * q for d, q in zip(depths, drawn))
    return _report(levels, pitch_m, params, printed, u, (r0, r1, c0, c1), height, ideal, material, wavelength_m)


def _report(levels, pitch_m, params, masks_printed, u, region, height, ideal, material, wavelength_m):
    """The print check's dict from the printed masks (fine coverage) and the two surfaces."""
    r0, r1, c0, c1 = region
    levels = np.asarray(levels)[r0:r1, c0:c1]
    rows, cols = levels.shape
    out = []
    for j in range(params.n_masks):
        drawn = mask_bit(np.asarray(levels), j)
        cov = np.asarray(masks_printed[j], dtype=float)
        per_px = cov.reshape(rows, u, cols, u).mean(axis=(1, 3))
        edges = (np.count_nonzero(np.diff(drawn, axis=0)) + np.count_nonzero(np.diff(drawn, axis=1))
                 + drawn[[0, -1], :].sum() + drawn[:, [0, -1]].sum()) * pitch_m
        d_area = (per_px.sum() - drawn.sum()) * pitch_m ** 2
        padded = np.pad(drawn, 1)
        neighbours = padded[:-2, 1:-1] | padded[2:, 1:-1] | padded[1:-1, :-2] | padded[1:-1, 2:]
        isolated = drawn & ~neighbours
        gaps = ~drawn & ((padded[:-2, 1:-1] & padded[2:, 1:-1]) | (padded[1:-1, :-2] & padded[1:-1, 2:]))
        out.append({"mask": j, "drawn_open_fraction": float(drawn.mean()),
                    "printed_open_fraction": float(per_px.mean()),
                    "area_ratio": float(per_px.sum() / drawn.sum()) if drawn.any() else None,
                    "edge_placement_um": float(d_area / edges * 1e6) if edges else None,
                    "isolated_pixels": int(isolated.sum()), "isolated_lost": int((isolated & (per_px < 0.5)).sum()),
                    "narrow_gaps": int(gaps.sum()), "narrow_gaps_bridged": int((gaps & (per_px > 0.5)).sum())})
    mat = get_material(material)
    dphi = mat.phase(height, wavelength_m) - mat.phase(ideal, wavelength_m)
    overlap = float(np.abs(np.mean(np.exp(1j * dphi))) ** 2)
    return {"gap_um": params.proximity_gap * 1e6, "resist_threshold": params.resist_threshold,
            "collimation_half_angle_deg": float(np.degrees(params.collimation_half_angle)),
            "resist_blur_um": params.resist_blur * 1e6, "cr_undercut_um": params.cr_undercut * 1e6,
            "step_um": pitch_m / u * 1e6, "region_px": [int(v) for v in region],
            "wavelength_nm": wavelength_m * 1e9, "masks": out, "field_overlap": overlap}


def print_check_page(check: dict, source: str) -> str:
    """Markdown of a :func:`print_check` report: the settings, a table per mask, the verdict."""
    rows = []
    for m in check["masks"]:
        ratio = "n/a" if m["area_ratio"] is None else f"{m['area_ratio']:.3f}"
        edge = "n/a" if m["edge_placement_um"] is None else f"{m['edge_placement_um']:+.3f}"
        rows.append(f"| {m['mask']} | {m['drawn_open_fraction']:.3f} | {m['printed_open_fraction']:.3f} | {ratio} | "
                    f"{edge} | {m['isolated_lost']} of {m['isolated_pixels']} | "
                    f"{m['narrow_gaps_bridged']} of {m['narrow_gaps']} |")
    r0, r1, c0, c1 = check["region_px"]
    lines = [f"# What a {check['gap_um']:g} um gap prints of `{source}`", "",
             f"Proximity print (angular spectrum over the gap, Hg g/h/i lines, {check['collimation_half_angle_deg']:g} deg "
             f"collimation half-angle, {check['resist_blur_um']:g} um resist blur, chromium undercut "
             f"{check['cr_undercut_um']:g} um) thresholded at {check['resist_threshold']:.3f} of the open field, "
             f"on design rows {r0}-{r1 - 1} and columns {c0}-{c1 - 1} (row 0 at the top), fine step "
             f"{check['step_um']:.3f} um.", "",
             f"**Field overlap with the design at {check['wavelength_nm']:g} nm: {check['field_overlap']:.4f}** "
             "(the share of the light that stays in the designed pattern; 1 for a perfect print).", "",
             "| mask | drawn open fraction | printed open fraction | printed / drawn area | edge placement (um, + = "
             "openings grew) | isolated open pixels lost | one-pixel chrome gaps bridged |",
             "|---|---|---|---|---|---|---|", *rows, "",
             "An isolated pixel is lost when it keeps under half its area; a gap is bridged when more than half of "
             "it clears. Numbers for the whole element need `--print-window all`.", ""]
    if "uncorrected" in check:
        lines += _opc_section(check)
    return "\n".join(lines)


def _opc_section(check):
    """The page's comparison of the corrected masks (the figures above) with the drawn ones."""
    unc, opc = check["uncorrected"], check["opc"]
    rows = []
    for a, b, m in zip(unc["masks"], check["masks"], opc["masks"]):
        edge = ["n/a" if x["edge_placement_um"] is None else f"{x['edge_placement_um']:+.3f}" for x in (a, b)]
        narrow = ["n/a" if m[k] is None else f"{m[k]:.3f}" for k in ("narrowest_opening_um", "narrowest_gap_um")]
        rows.append(f"| {a['mask']} | {a['printed_open_fraction']:.3f} / {b['printed_open_fraction']:.3f} "
                    f"(drawn {a['drawn_open_fraction']:.3f}) | {edge[0]} / {edge[1]} | "
                    f"{m['printed_area_error_um2_drawn']:.1f} / {m['printed_area_error_um2_corrected']:.1f} | "
                    f"{narrow[0]} / {narrow[1]} |")
    return ["## Optical proximity correction", "",
            f"The masks written are pre-distorted ({opc['method']}, {opc['iterations']} iterations, mask grid "
            f"{opc['mask_grid_um']:.3f} um, minimum feature {opc['min_feature_um']:.3f} um, print grid "
            f"{opc['print_step_um']:.3f} um) so that their print matches the design; the figures above are theirs.", "",
            f"**Field overlap at {check['wavelength_nm']:g} nm: {unc['field_overlap']:.4f} as drawn, "
            f"{check['field_overlap']:.4f} corrected.**", "",
            "| mask | printed open fraction, drawn / corrected masks | edge placement (um), drawn / corrected | "
            "printed area error (um^2, whole mask), drawn / corrected | corrected mask's narrowest opening / gap (um) |",
            "|---|---|---|---|---|", *rows, ""]
