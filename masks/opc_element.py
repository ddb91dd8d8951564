"""A whole element's masks pre-distorted for the aligner's gap, with the print check of both.

What ``doe masks --gap-um G --opc`` and ``doe correct`` (a diagnosed ``proximity_print``) share:
the print grid the correction runs on, its settings from a minimum feature, the memory it needs,
and the run itself (:func:`correct_element`): the drawn masks' print check, the correction of
every mask (:func:`masks.opc.correct_masks`) and the corrected masks' print check
(:func:`masks.print_check.print_check_masks`) over the same window. The print check's window
defaults to the central :data:`PRINT_WINDOW_PX` design pixels (:func:`default_print_region`).
The heavy modules are imported where they are used: ``doe``'s parser reads
:data:`PRINT_WINDOW_PX` at start-up.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from .opc import OpcSettings
    from .process import ProcessParams

__all__ = ["PRINT_WINDOW_PX", "check_opc_memory", "correct_element", "default_print_region", "opc_settings",
           "print_upsample"]

#: Side of the print check's default window (design pixels): a whole 1600 px element at the
#: sampling rule's 0.5 um step is 17280^2 cells, minutes and gigabytes; a central window holds
#: the element's feature sizes.
PRINT_WINDOW_PX = 128


def default_print_region(shape: tuple[int, int]) -> tuple[int, int, int, int]:
    """The central :data:`PRINT_WINDOW_PX` window (row0, row1, col0, col1, half-open) of a design."""
    n_r, n_c = min(PRINT_WINDOW_PX, shape[0]), min(PRINT_WINDOW_PX, shape[1])
    r0, c0 = (shape[0] - n_r) // 2, (shape[1] - n_c) // 2
    return (r0, r0 + n_r, c0, c0 + n_c)


def print_upsample(pitch_m: float, params: ProcessParams, opc: bool) -> int:
    """Print cells per design pixel: at most 0.5 um and the gap's sampling rule
    (:func:`masks.proximity.recommended_step_m`); with ``opc``, the nearest grid whose mask cells
    are whole database units (:func:`masks.opc.opc_upsample`)."""
    from .opc import OPC_SUBGRID, opc_upsample
    from .process import fine_upsample, proximity_optics
    from .proximity import recommended_step_m

    step = min(0.5e-6, recommended_step_m(proximity_optics(params)))
    return opc_upsample(pitch_m, step, OPC_SUBGRID) if opc else fine_upsample(pitch_m, step)


def check_opc_memory(shape: tuple[int, int], upsample: int, pitch_m: float, source: str) -> None:
    """Refuse (``budget.check_memory``) a correction of the whole element that does not fit in memory."""
    from doedesign.budget import check_memory

    from .opc import OPC_SUBGRID, opc_bytes

    check_memory(opc_bytes(shape, upsample, OPC_SUBGRID),
                 f"{source}: the proximity correction of the whole {shape[0]} x {shape[1]} px element at "
                 f"{pitch_m / upsample * 1e6:.3g} um (it is not tiled)")


def opc_settings(step_m: float, min_feature_m: float, method: str = "density",
                 iterations: int | None = None) -> OpcSettings:
    """The correction's settings on a print grid of ``step_m``: the minimum feature in mask cells
    (rounded up), and after the density stage a level-set polish of half-cell steps (measured best
    within 5-10 of them: 10 by default), else 20 full-cell steps."""
    from .opc import OPC_SUBGRID, OpcSettings

    cell = step_m / OPC_SUBGRID
    polish = method == "density"
    return OpcSettings(iterations=iterations or (10 if polish else 20), subgrid=OPC_SUBGRID,
                       min_feature_cells=max(1, math.ceil(min_feature_m / cell - 1e-9)), method=method,
                       step_cells=0.5 if polish else 1.0)


def correct_element(levels: np.ndarray, pitch_m: float, params: ProcessParams, upsample: int,
                    settings: OpcSettings, region: tuple[int, int, int, int], material: str = "fused_silica",
                    uncorrected: dict | None = None) -> tuple[dict, tuple[np.ndarray, int]]:
    """Every mask of ``levels`` corrected for the print ``params`` describe, and the print check.

    Parameters
    ----------
    levels : ndarray of int, shape (rows, cols)
        The design's levels (row 0 at the top).
    pitch_m : float
        Design pixel pitch (m).
    params : ProcessParams
        The exposure (gap, collimation, resist blur, threshold, undercut), each mask's linewidth
        bias (the correction draws the mask that, grown by it, prints the design) and the depths.
    upsample : int
        Print cells per design pixel (:func:`print_upsample` with ``opc``).
    settings : OpcSettings
    region : (int, int, int, int)
        The print check's window, half-open design pixels.
    material : str
    uncorrected : dict, optional
        The drawn masks' print check when the caller has it (else it is run here).

    Returns
    -------
    check : dict
        The corrected masks' :func:`~masks.print_check.print_check_masks` report with
        ``uncorrected`` (the drawn masks') and ``opc`` (:func:`~masks.opc.correction_report`).
    corrected : (ndarray of bool, int)
        The masks on their grid and its cells per design pixel (``write_element``'s ``corrected_masks``).
    """
    from .decompose import levels_to_masks
    from .opc import OPC_SUBGRID, correct_masks, correction_report
    from .print_check import print_check, print_check_masks
    from .process import proximity_optics

    step = pitch_m / upsample
    if uncorrected is None:
        uncorrected = print_check(levels, pitch_m, params, step_m=step, material=material, region=region)
    n_masks = params.n_masks
    fixes = correct_masks(levels_to_masks(levels, n_masks), upsample, pitch_m, proximity_optics(params),
                          params.resist_threshold, params.cr_undercut, settings,
                          biases_m=np.asarray(params.linewidth_bias, float))
    masks = np.stack([f.mask for f in fixes])
    check = print_check_masks(levels, pitch_m, params, masks, upsample, OPC_SUBGRID, material=material, region=region)
    check["uncorrected"] = uncorrected
    check["opc"] = correction_report(fixes, step, settings)
    return check, (masks, upsample * OPC_SUBGRID)
