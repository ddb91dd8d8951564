"""What a proximity gap and dose will print, before a run: per mask the printed against the drawn
open area and the mean edge placement, the features that print badly, and the predicted figure of
merit (the field overlap at 550 nm of the printed element with the design).

Built on :func:`masks.process.simulate_surface` (the proximity print of :mod:`masks.proximity`)
and the project's own phase of a height (:mod:`doedesign.materials`). The edge placement is the
printed minus drawn open area over the drawn mask's edge length (positive: openings grew). A
badly printed feature is an isolated open DOE pixel (no open 4-neighbour) that keeps under half
its area, or a one-pixel chrome gap (closed, open on both sides along a row or a column) that more
than half clears. Corners are not counted separately (their loss is in the area).
"""

from __future__ import annotations

import numpy as np

from doedesign.materials import get_material

from .decompose import mask_bit
from .process import ProcessParams, simulate_surface

__all__ = ["print_check"]


def print_check(levels: np.ndarray, pitch_m: float, params: ProcessParams, step_m: float = 0.5e-6,
                material: str = "fused_silica", wavelength_m: float = 550e-9) -> dict:
    """Report (JSON-ready dict, lengths in um) of what ``params`` print of ``levels``.

    Returns
    -------
    dict
        ``masks``: per mask ``drawn_open_fraction``, ``printed_open_fraction``,
        ``area_ratio``, ``edge_placement_um``, ``isolated_pixels``, ``isolated_lost``,
        ``narrow_gaps``, ``narrow_gaps_bridged``; ``field_overlap``: ``|<exp(i dphi)>|^2`` at
        ``wavelength_m`` between the printed and the ideal surface on the fine grid.
    """
    printed = simulate_surface(levels, pitch_m, params, step_m=step_m)
    ideal = simulate_surface(levels, pitch_m, ProcessParams.ideal(depths_m=params.etch_depth), step_m=step_m)
    u = printed.upsample
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
            "step_um": printed.step_m * 1e6, "masks": out, "field_overlap": overlap}
