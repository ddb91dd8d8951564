"""Whether a measured field shows the design it is compared with: the refusal rule of
``doe compare`` and ``doe diagnose``.

The decision rests on how well the field registers to the design, never on how far its
heights lie from nominal: a wafer with strong etch loading, a depth error on every mask or a
large linewidth bias is what the comparison and the diagnosis are for. The figures:

- relief: a field without steps (the unetched surface beside the element) has nothing to
  register (:func:`check_relief`, before registration);
- correlation of the registered read-out (the measurement at the centre of every design
  pixel in the field) with the heights the masks print, a plane taken out of both (levelling
  residue): scale-free, so depth errors and loading, which scale the steps, barely move it;
- share of design edges found: between two neighbouring design pixels of different levels
  the measurement must step the same way, by more than a quarter level step (far beyond the
  nm noise); a depth error flips only the few one-step edges where a deep mask takes over
  (7 -> 8), a wrong design leaves the sign to chance;
- placement: a part sits on the stage turned by a degree or two and the camera may be
  mirrored; a quarter turn means the part or the design file is turned; camera pixels are
  square, so both axes of the lattice give the same pixel size (a raster scan's two axes are
  calibrated apart: its aspect is reported, not judged);
- enough design edges in the field for the share to mean something.

Measured on profilometer files from the tests' independent generator (tests/metrology/
filegen.py: 16-level maps, 0.8-1.2 um camera pixels, blur, noise, spikes): 32 right designs
(nulls; 30 % etch loading, also on a design whose mask density changes across the field,
alone and with +-12 % depths and 0.5 um bias; +-12 % depth errors on every mask, with equal
and alternating signs; +-0.5 um linewidth bias; random overlay, rotation, microtrenching,
gradient; a 60 px field) gave a read-out correlation of at least 0.990 and at least 96 % of
the design edges found. Designs with 20 % or 30 % of their pixels redrawn gave at most 0.79
and 71 %; 10 % redrawn, 0.86-0.92 and 79-85 % (refused in two fields of three). The
thresholds sit between, nearer the wrong side, so that a wafer worse than any of these still
passes. An unrelated design does not register at all (:mod:`.register`); a field turned by a
quarter turn registers perfectly (correlation 1.00) and is refused on its placement alone.

Arrays are row-major, row 0 at the top, in the measurement and in the design.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from doedesign.errors import DoeError
from metrology.matching.register import Registration, resample_to_design

__all__ = ["MAX_PIXEL_ASPECT", "MIN_CORRELATION", "MIN_DESIGN_EDGES", "MIN_EDGES_FOUND", "MIN_RELIEF_STEPS",
           "MIN_STEP_FOUND_STEPS", "MatchCheck", "assess_match", "check_relief"]

log = logging.getLogger(__name__)

# Read-out correlation with the printed heights below which the field is not this design
# (right designs >= 0.990; 20-30 % of the pixels redrawn <= 0.79, 10 % redrawn 0.86-0.92).
MIN_CORRELATION = 0.9
# Share of the design's edges in the field that must be found (right designs >= 0.96 with
# +-12 % depth errors of alternating sign, which flip the 7 -> 8 edges; 20-30 % redrawn <= 0.71).
MIN_EDGES_FOUND = 0.8
# A found edge steps the design's way by at least this many level steps (19 nm: twenty times
# a profiler's 1 nm noise, so noise never makes an edge).
MIN_STEP_FOUND_STEPS = 0.25
# Below this many design edges in the field a share is too coarse to judge on (a wrong design
# finds about 60 +- 7 % of 50 edges; the threshold is three of those deviations away).
MIN_DESIGN_EDGES = 50
#: Largest relative difference of the pixel size along the two axes of the lattice (camera
#: pixels are square; lateral calibration holds 0.1-1 % per axis; right fields gave < 0.4 %).
#: A raster scan's axes are two piezo drives calibrated apart (an open-loop scanner's creep
#: alone can exceed 10 % of a move; the real Nanosurf scans of the tests differ by 2.3 %): its
#: aspect is measured and reported, never refused.
MAX_PIXEL_ASPECT = 0.02
# A field whose heights (0.5-99.5 percentile, after levelling) span less than this many level
# steps shows no etched step: unetched surface or off the element.
MIN_RELIEF_STEPS = 0.5


def check_relief(height_m: np.ndarray, step_m: float) -> float:
    """The field's relief (m); raises when it shows no etched step.

    Parameters
    ----------
    height_m : ndarray
        Levelled heights (m), NaN where invalid, spikes removed.
    step_m : float
        The design's level step (m).

    Raises
    ------
    DoeError
        The relief is below ``MIN_RELIEF_STEPS`` level steps (a flat field).
    """
    h = np.asarray(height_m, float)
    ok = np.isfinite(h)
    relief = float(np.subtract(*np.percentile(h[ok], [99.5, 0.5]))) if ok.sum() > 100 else 0.0
    if relief < MIN_RELIEF_STEPS * step_m:
        raise DoeError(f"the field is off the element: it is flat (heights span {relief * 1e9:.1f} nm, less than "
                       f"{MIN_RELIEF_STEPS} level step of {step_m * 1e9:.1f} nm), as the unetched surface beside "
                       "the element is; measure a field on the element")
    return relief


@dataclass
class MatchCheck:
    """How well a registered field shows its design.

    Attributes
    ----------
    correlation : float
        Correlation of the read-out (the measurement at each design pixel's centre) with the
        printed design heights.
    edges_found : float
        Share of the design edges in the field across which the measurement steps the
        design's way by at least ``MIN_STEP_FOUND_STEPS`` level steps.
    n_edges : int
        Design edges (neighbouring design pixels of different levels) read in the field.
    field_on_design : float
        Share of the field's valid pixels that fall on the design.
    quarter_turn : bool
        The field is turned by a quarter turn against the design (rows along its columns).
    pixel_aspect : float
        Relative difference of the lattice's pixel size along the two axes.
    problem : str or None
        One line saying why the field does not show the design, None when it does.
    aspect_judged : bool
        False for a raster scan, whose two axes are calibrated apart: its aspect is reported only.
    """

    correlation: float
    edges_found: float
    n_edges: int
    field_on_design: float
    quarter_turn: bool
    pixel_aspect: float
    problem: str | None
    aspect_judged: bool = True

    @property
    def ok(self) -> bool:
        return self.problem is None

    def report(self, forced: bool = False) -> dict:
        """The ``match`` entry of a comparison report."""
        return {"confidence": "high" if self.ok else "low", "forced": bool(forced), "problem": self.problem,
                "readout_correlation": self.correlation, "edges_found": self.edges_found,
                "design_edges": self.n_edges, "field_on_design": self.field_on_design,
                "quarter_turn": self.quarter_turn, "pixel_aspect": self.pixel_aspect,
                "pixel_aspect_judged": self.aspect_judged,
                "thresholds": {"readout_correlation": MIN_CORRELATION, "edges_found": MIN_EDGES_FOUND,
                               "design_edges": MIN_DESIGN_EDGES, "pixel_aspect": MAX_PIXEL_ASPECT,
                               "step_found_steps": MIN_STEP_FOUND_STEPS},
                "meaning": ("registration quality, not the process: readout_correlation = correlation of the "
                            "measurement at each design pixel's centre with the printed design heights; "
                            "edges_found = share of the design edges in the field across which the measurement "
                            "steps the design's way by at least step_found_steps level steps")}


def _field_region(registration: Registration, shape: tuple[int, int]) -> tuple[int, int, int, int]:
    """Half-open design-pixel box (row0, row1, col0, col1) that holds the field, clipped to the design."""
    rows = np.array([0, 0, shape[0] - 1, shape[0] - 1], float)
    cols = np.array([0, shape[1] - 1, 0, shape[1] - 1], float)
    r, c = registration.to_design(rows, cols)
    dr, dc = registration.design_shape
    r0, r1 = int(np.clip(np.floor(r.min()), 0, dr)), int(np.clip(np.ceil(r.max()) + 1, 0, dr))
    c0, c1 = int(np.clip(np.floor(c.min()), 0, dc)), int(np.clip(np.ceil(c.max()) + 1, 0, dc))
    return r0, r1, c0, c1


def _partial_correlation(readout, design, ok):
    """Correlation of read-out and design with a plane taken out of both (a levelling residue
    of a few nm per micrometre would otherwise pull a right field's correlation down)."""
    if ok.sum() < 8:
        return 0.0
    rows, cols = np.nonzero(ok)
    basis = np.column_stack([np.ones(rows.size), rows, cols]).astype(float)
    x, y = readout[ok], design[ok]
    x = x - basis @ np.linalg.lstsq(basis, x, rcond=None)[0]
    y = y - basis @ np.linalg.lstsq(basis, y, rcond=None)[0]
    norm = np.sqrt(np.sum(x * x) * np.sum(y * y))
    return float(np.sum(x * y) / norm) if norm > 0 else 0.0


def _edge_steps(readout, design, ok, span):
    """Measured and design steps across every design edge, each side read ``span`` design pixels
    in from the edge (the last pixel of a run of ``span`` of its own level)."""
    steps_meas, steps_design = [], []
    for axis in (0, 1):
        n = design.shape[axis]
        if n < 2 * span:
            continue

        def cut(start, stop, axis=axis):
            index = [slice(None)] * 2
            index[axis] = slice(start, stop)
            return tuple(index)

        # Edge between i and i + 1 for i = span - 1 .. n - span - 1.
        left, right = cut(span - 1, n - span), cut(span, n - span + 1)
        use = ok[cut(0, n - 2 * span + 1)] & ok[cut(2 * span - 1, n)] & (design[left] != design[right])
        for j in range(1, span):
            use &= design[cut(span - 1 - j, n - span - j)] == design[left]
            use &= design[cut(span + j, n - span + 1 + j)] == design[right]
        steps_meas.append((readout[cut(2 * span - 1, n)] - readout[cut(0, n - 2 * span + 1)])[use])
        steps_design.append((design[right] - design[left])[use])
    if not steps_meas:
        return np.zeros(0), np.zeros(0)
    return np.concatenate(steps_meas), np.concatenate(steps_design)


def assess_match(height_m: np.ndarray, printed_m: np.ndarray, step_m: float,
                 registration: Registration, scanned: bool = False, edge_span: int = 1) -> MatchCheck:
    """Judge whether a registered field shows the design (see the module docstring).

    Parameters
    ----------
    height_m : ndarray
        Levelled measurement (m), NaN where invalid; row 0 at the top (camera order).
    printed_m : ndarray
        The heights the masks print from the design (:func:`doedesign.levels.printed_height_m`).
    step_m : float
        Level step (m).
    registration : Registration
    scanned : bool
        A raster scan (AFM, stylus): its x and y scales are the scanner's own calibration, so
        a lattice longer along one axis is measured and reported (``pixel_aspect``), never
        refused (:data:`MAX_PIXEL_ASPECT` holds for camera pixels only).
    edge_span : int
        Design pixels in from each side of an edge at which the step is read: 1 (the
        neighbouring pixels) for a design whose pixels the instrument resolves; more for one
        whose pixels are finer than the instrument's edge (a lattice drawn on a fine grid,
        seen by an AFM tip), else a blurred edge reads as less than a quarter step.

    Returns
    -------
    MatchCheck
    """
    h = np.asarray(height_m, float)
    printed = np.asarray(printed_m, float)
    r0, r1, c0, c1 = _field_region(registration, h.shape)
    readout = resample_to_design(h, registration, region=(r0, r1, c0, c1))
    design = printed[r0:r1, c0:c1]
    ok = np.isfinite(readout)
    correlation = _partial_correlation(readout, design, ok)
    dm, dd = _edge_steps(readout, design, ok, int(edge_span))
    n_edges = int(dd.size)
    found = (np.sign(dm) == np.sign(dd)) & (np.abs(dm) >= MIN_STEP_FOUND_STEPS * step_m)
    edges_found = float(found.mean()) if n_edges else 0.0
    valid = np.isfinite(h)
    rr, cc = registration.to_design(*np.nonzero(valid))
    ri, ci = np.rint(rr), np.rint(cc)
    on = (ri >= 0) & (ri < printed.shape[0]) & (ci >= 0) & (ci < printed.shape[1])
    field_on_design = float(on.mean()) if on.size else 0.0
    parts = registration.decompose()
    quarter_turn = bool(parts["orientation"][0])
    sx, sy = parts["scale_xy"]
    aspect = float(abs(sx - sy) / (0.5 * (sx + sy)))
    problem = None
    if n_edges < MIN_DESIGN_EDGES:
        problem = (f"the field is off the element: only {n_edges} design edges lie in it (need {MIN_DESIGN_EDGES}; "
                   f"{field_on_design:.0%} of the field falls on the design)")
    elif correlation < MIN_CORRELATION or edges_found < MIN_EDGES_FOUND:
        problem = (f"the field shows another design or a region outside this one: its heights correlate "
                   f"{correlation:.2f} with the printed design (need {MIN_CORRELATION}) and step the design's way "
                   f"at {edges_found:.0%} of the {n_edges} design edges (need {MIN_EDGES_FOUND:.0%})")
    elif quarter_turn:
        problem = ("the field is turned by a quarter turn against the design (its rows run along the design's "
                   "columns): the part sat turned under the objective or the design file is turned")
    elif aspect > MAX_PIXEL_ASPECT and not scanned:
        problem = (f"the field's lattice has pixels {aspect:.1%} longer along one axis than the other (camera "
                   f"pixels are square; at most {MAX_PIXEL_ASPECT:.0%}): the design's pitch does not fit the field")
    log.info("match: correlation %.3f, edges found %.3f of %d, field on design %.2f, quarter turn %s, aspect %.4f",
             correlation, edges_found, n_edges, field_on_design, quarter_turn, aspect)
    return MatchCheck(correlation=correlation, edges_found=edges_found, n_edges=n_edges,
                      field_on_design=field_on_design, quarter_turn=quarter_turn, pixel_aspect=aspect,
                      problem=problem, aspect_judged=not scanned)
