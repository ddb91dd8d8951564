"""A diagnosed print through the aligner's gap, taken out by pre-distorted masks (``doe correct``).

When the fields' combined ``proximity_print`` is systematic (its gap, :mod:`.systematic`; the
resist threshold is a shape of the print, carried by the gap's significance as a trench's width
by its depth), no aligner, etch or edge-offset knob removes it: each mask is drawn pre-distorted
instead, optical proximity correction (:func:`masks.opc_element.correct_element`: the density
stage with the minimum feature, then the level-set polish). The print it corrects for is the
diagnosis's own (the effect's ``apply`` on the ideal process at the nominal depths): gap and
threshold at their means over the fields, the process model's collimation, resist blur and
undercut, and each mask's linewidth bias where it is systematic. That bias is then folded into the
correction (the mask is drawn so that, grown by it, it prints the design) rather than drawn as an
edge offset: an offset and a pre-distortion are one drawing of one mask.

What the sheet shows for it: the print check of the drawn and of the corrected masks through the
diagnosed print over the central window (field overlap at 550 nm, per mask the printed area and
edge placement), and the correction's figures per mask. The corrected wafer's predicted merit
takes the corrected masks to print as a contact print would (gap 0): the print check is the
measure of how close they come.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING

import numpy as np

from doedesign.design import Design
from doedesign.levels import design_levels
from metrology.diagnosis.effects import get_effect

from .systematic import Estimate, find_estimate

if TYPE_CHECKING:
    from masks.process import ProcessParams

__all__ = ["diagnosed_print", "no_opc", "proximity_correction"]

EFFECT = "proximity_print"


def diagnosed_print(estimates: Sequence[Estimate], jobs: Sequence[dict],
                    depths_m: Sequence[float]) -> ProcessParams | None:
    """The process the fields' combined ``proximity_print`` describes, or None when it is not corrected.

    Parameters
    ----------
    estimates : sequence of Estimate
    jobs : sequence of dict
        The job entries (:func:`metrology.correction.jobsheet.job_entries`): each mask's
        linewidth bias taken out (``linewidth_bias_um``, 0 where none is corrected).
    depths_m : sequence of float
        The diagnosed nominal etch depths.

    Returns
    -------
    masks.process.ProcessParams or None
    """
    from masks.process import ProcessParams

    gap = find_estimate(estimates, EFFECT, None, "gap")
    if gap is None:
        return None
    threshold = find_estimate(estimates, EFFECT, None, "threshold", corrected_only=False)
    base = ProcessParams.ideal(depths_m=depths_m)
    params = get_effect(EFFECT).apply(base, np.array([gap.mean, threshold.mean if threshold else 0.5]))
    return params.copy(linewidth_bias=np.array([job["linewidth_bias_um"] * 1e-6 for job in jobs]))


def proximity_correction(design: Design, estimates: Sequence[Estimate], jobs: list[dict], depths_m: Sequence[float],
                         min_feature_m: float | None, source: str) -> dict | None:
    """Pre-distort every mask for the diagnosed print (module docstring); None when it is not corrected.

    The job entries are updated in place: a mask's edge offset goes into its correction (its
    ``drawn_edge_offset_um`` becomes 0, ``opc`` says so) and the correction is listed.

    Returns
    -------
    dict or None
        ``check`` (the print check, JSON-ready), ``corrected`` (the masks and their cells per
        design pixel, for :func:`masks.element.write_element`) and ``entry`` (the sheet's
        ``proximity_correction``).
    """
    from masks.corrected import MIN_FEATURE_M
    from masks.opc_element import check_opc_memory, correct_element, default_print_region, opc_settings, print_upsample

    params = diagnosed_print(estimates, jobs, depths_m)
    if params is None:
        return None
    levels = design_levels(design, source=source)
    u = print_upsample(design.pitch_m, params, opc=True)
    check_opc_memory(levels.shape, u, design.pitch_m, f"{source} (doe correct --no-opc draws the masks uncorrected "
                                                        "for the gap)")
    settings = opc_settings(design.pitch_m / u, MIN_FEATURE_M if min_feature_m is None else float(min_feature_m))
    check, corrected = correct_element(levels, design.pitch_m, params, u, settings, default_print_region(levels.shape),
                                       material=design.material)
    assert params.linewidth_bias is not None  # ProcessParams fills every per-mask field
    gap_um, threshold = params.proximity_gap * 1e6, params.resist_threshold
    for job in jobs:
        bias_um = float(params.linewidth_bias[job["mask"]]) * 1e6
        job["opc"] = {"gap_um": gap_um, "resist_threshold": threshold, "linewidth_bias_um": bias_um}
        job["drawn_edge_offset_um"] = 0.0
        job["corrections"] = [c for c in job["corrections"] if not c.startswith(("none:", "edges drawn"))] + [
            f"drawn pre-distorted for the {gap_um:.1f} um gap at threshold {threshold:.3f}"
            + (f" with its {bias_um:+.3f} um linewidth bias" if bias_um else "") + " (OPC)"]
    entry = {"gap_um": gap_um, "resist_threshold": threshold,
             "linewidth_bias_um": [float(b) * 1e6 for b in params.linewidth_bias],
             "field_overlap_drawn": check["uncorrected"]["field_overlap"],
             "field_overlap_corrected": check["field_overlap"], "region_px": check["region_px"],
             "print_check": "masks/print_check.json", "method": check["opc"]["method"],
             "min_feature_um": check["opc"]["min_feature_um"], "mask_grid_um": check["opc"]["mask_grid_um"],
             "merit_note": "the corrected wafer's merit takes the corrected masks to print as a contact print "
                           "(gap 0); the print check through the diagnosed gap measures how close they come"}
    return {"check": check, "corrected": corrected, "entry": entry}


def no_opc(estimates: Sequence[Estimate]) -> list[str]:
    """``--no-opc``: a systematic ``proximity_print`` stays uncorrected (its estimates say so); the warning."""
    out = []
    for e in estimates:
        if e.effect == EFFECT and e.corrected:
            e.corrected = False
            e.notes.append("not corrected: --no-opc")
            out.append(f"{EFFECT} {e.param} = {e.mean:.4g} {e.unit} is systematic and --no-opc draws the masks "
                       "uncorrected for it: they will print through the gap as the diagnosis found")
    return out
