"""The duty cycle of a binary (one-mask) element: its unetched area fraction, measured.

The comparison fits the edge position as a linewidth bias ``b`` (every opening edge moved out
by ``b``, the process model's square structuring element: :mod:`masks.process`). Moving each
edge of the design by ``b`` changes the unetched area by ``-b`` times the length of the
boundary between unetched and etched pixels (the design's pixel edges, which is what that
structuring element moves), to first order in ``b``; the corner terms, ``b**2`` per corner, are
left out (for a 5 um square and a 0.1 um bias they are 0.04 % of its area).

Arrays are row-major, row 0 at the top.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from metrology.matching.register import Registration

__all__ = ["duty_cycle"]


def duty_cycle(levels: np.ndarray, labels: np.ndarray, bias_m: np.ndarray, bias_err_m: np.ndarray, pitch_m: float,
               registration: Registration) -> dict:
    """Unetched area fraction of the design under the field, with the fitted edges.

    Parameters
    ----------
    levels : ndarray of int
        The design's levels (0 = unetched top, 1 = etched).
    labels : ndarray of int
        The design's level at each measurement pixel (negative off the design): only to know
        that the field lies on the design.
    bias_m, bias_err_m : ndarray (1,)
        The fitted linewidth bias (m; + = openings wider) and its standard error.
    pitch_m : float
        Design pixel pitch (m).
    registration : Registration

    Returns
    -------
    dict
        ``unetched_fraction`` and its ``_err``, ``etched_fraction``, the design's own
        ``design_unetched_fraction``, ``edge_shift_um`` (the bias), ``boundary_um_per_um2``.
    """
    lv = np.asarray(levels)
    rows, cols = registration.measurement_shape
    rr, cc = registration.to_measurement(*np.mgrid[:lv.shape[0], :lv.shape[1]])
    inside = (rr >= 0) & (rr <= rows - 1) & (cc >= 0) & (cc <= cols - 1) & (lv >= 0)
    top = inside & (lv == 0)
    n = int(inside.sum())
    if n == 0 or not (np.asarray(labels) >= 0).any():
        return {"unetched_fraction": None, "problem": "the field lies off the design"}
    pairs = ((top[1:], top[:-1], inside[1:] & inside[:-1]), (top[:, 1:], top[:, :-1], inside[:, 1:] & inside[:, :-1]))
    edges = sum(int(np.sum((a != b) & both)) for a, b, both in pairs)
    bias_px = float(bias_m[0]) / pitch_m
    err_px = float(bias_err_m[0]) / pitch_m
    design = top.sum() / n
    fraction = design - bias_px * edges / n
    return {"unetched_fraction": float(fraction), "unetched_fraction_err": float(abs(err_px) * edges / n),
            "etched_fraction": float(1.0 - fraction), "design_unetched_fraction": float(design),
            "edge_shift_um": float(bias_m[0]) * 1e6, "edge_shift_err_um": float(bias_err_m[0]) * 1e6,
            "boundary_um_per_um2": float(edges / (n * pitch_m)) * 1e-6,
            "meaning": ("unetched (level 0) share of the field's area: the design's, with every opening edge moved "
                        "by the fitted linewidth bias (edge_shift_um, + = openings wider) along the design's "
                        "boundary; first order in the bias")}
