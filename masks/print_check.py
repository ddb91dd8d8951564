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

import numpy as np

from doedesign.materials import get_material

from .decompose import mask_bit
from .process import ProcessParams, simulate_surface
from .proximity import ProximityOptics, aerial_image

__all__ = ["in_place_threshold", "print_check", "print_check_page"]

# Fine cells on each side of the drawn edge in the half-plane image of in_place_threshold.
_EDGE_CELLS = 512


def in_place_threshold(optics: ProximityOptics, step_m: float) -> float:
    """Resist threshold (fraction of the open field) at which a long straight edge prints in place.

    The exposure through the gap of a half-plane opening, read at its drawn edge (the mean of the
    two fine cells beside it): one period of a strip, endless along the edge, whose other edge
    lies :data:`_EDGE_CELLS` cells away (many Fresnel zones at any gap the model takes).
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
    u = printed.upsample
    r0, r1, c0, c1 = printed.region
    levels = np.asarray(levels)[r0:r1, c0:c1]
    rows, cols = levels.shape
    out = []
    for j in range(params.n_masks):
        drawn = mask_bit(np.asarray(levels), j)
        cov = np.asarray(printed.masks_printed[j], dtype=float)
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
    dphi = mat.phase(np.asarray(printed.height_m), wavelength_m) - mat.phase(np.asarray(ideal.height_m), wavelength_m)
    overlap = float(np.abs(np.mean(np.exp(1j * dphi))) ** 2)
    return {"gap_um": params.proximity_gap * 1e6, "resist_threshold": params.resist_threshold,
            "collimation_half_angle_deg": float(np.degrees(params.collimation_half_angle)),
            "resist_blur_um": params.resist_blur * 1e6, "cr_undercut_um": params.cr_undercut * 1e6,
            "step_um": printed.step_m * 1e6, "region_px": [int(v) for v in printed.region],
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
    return "\n".join(lines)
