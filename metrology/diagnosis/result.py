"""What a diagnosis found: its named steps and the :class:`~metrology.diagnosis.result.Diagnosis` a report is written from.

A diagnosis is *complete* when its selection ended by its own rules (the criterion); a limit the
user asked for (:class:`~metrology.diagnosis.budget.Deadline`) that ended any part of it makes it
*incomplete*: ``stopped_early`` says where, its summary's first line says ``INCOMPLETE`` and lists
the candidates not tried, and ``tested`` holds only what it named. A field's ``tested`` effects
are those it carries information about (:mod:`metrology.correction.systematic` combines each
effect over the fields that tested it).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["Diagnosis", "Step", "summary_line"]


@dataclass
class Step:
    """One named effect of a diagnosis."""

    effect: str
    kind: str
    description: str
    params: dict
    uncertainties: dict
    units: dict
    residual_rms_before: float
    residual_rms_after: float
    criterion_change: float
    candidates: dict
    ambiguous_with: list = field(default_factory=list)
    revised: str | None = None

    def to_dict(self) -> dict[str, Any]:
        return {"effect": self.effect, "kind": self.kind, "description": self.description,
                "measurement_artefact": self.kind == "artefact",
                "params": self.params, "uncertainties": self.uncertainties, "units": self.units,
                "residual_rms_before": self.residual_rms_before, "residual_rms_after": self.residual_rms_after,
                "criterion_change": self.criterion_change, "candidates": self.candidates,
                "ambiguous_with": self.ambiguous_with, "revised": self.revised}


@dataclass
class Diagnosis:
    """Result of :func:`~metrology.diagnosis.heights.diagnose_heights` or :func:`~metrology.diagnosis.psf.diagnose_psf`.

    Attributes
    ----------
    domain : {"height", "psf"}
    steps : list of Step
        Named effects in the order found, each with the parameters of the final joint fit.
    model : dict
        Effect name -> fitted parameter values (final joint fit).
    noise_floor : float
    initial_residual_rms, final_residual_rms : float
    unexplained : bool
        Whether a significant structured residual remains (binned residual model earns its
        parameters under the same criterion).
    unexplained_where : dict or None
        When ``unexplained``: where the residual departs from the noise (which mask's edges,
        levels, part of the field, spatial frequencies; :func:`~metrology.diagnosis.locate.locate_residual`).
    partial_matches : list of dict
        Fabrication effects the loop chose that explain only part of a residual they overlap
        (the residual on their own footprint stays above the floor): not named, listed here.
    breakdown_initial, breakdown_final : dict
        Residual broken down by what may explain it (see ``residual_breakdown``).
    residual_maps : list of ndarray
        Residual map before the first step and after each step (row 0 at the top).
    stopped_early : dict or None
        Where a limit the user asked for ended the diagnosis before its own rules did
        (``reason``, ``limit``: ``"wall"`` or ``"cpu"``, ``untried``: the candidates not tried,
        the residual over the noise floor and the CPU seconds spent); None for a complete one.
    candidates : list of str
        The candidate effects the selection was given (nuisances excluded).
    tested : list of str
        The candidates the diagnosis carries information about: named, or scored and found not to
        pay in the round that ended the selection by the criterion (every candidate once the
        residual reached the floor). An incomplete diagnosis tested only what it named; one whose
        instrument's fit left no room for a candidate tested none.
    below_resolution : dict or None
        The candidate that earned its parameters but would explain under
        ``MIN_POWER_SHARE`` (:mod:`metrology.diagnosis.engine`) of the floor's power (``effect``, ``criterion_change``,
        ``floor_power_share``): not named, and the selection ended there.
    placement, excluded_pixels, window_camera_px : dict, int, list of int, or None
        Set by the camera-frame diagnosis (:func:`metrology.diagnosis.camera_diagnosis.diagnose_camera`):
        the refined placement with uncertainties, the pixels left out, the window diagnosed
        (``[row0, row1, col0, col1]``); None for any other.
    """

    domain: str
    steps: list
    model: dict
    noise_floor: float
    corr_area_px: float
    n_samples: int
    n_eff: float
    initial_residual_rms: float
    final_residual_rms: float
    unexplained: bool
    structure_criterion: float
    units: str
    breakdown_initial: dict = field(default_factory=dict)
    breakdown_final: dict = field(default_factory=dict)
    residual_maps: list = field(default_factory=list)
    map_step_m: float | None = None
    unexplained_where: dict | None = None
    partial_matches: list = field(default_factory=list)
    stopped_early: dict | None = None
    below_resolution: dict | None = None
    candidates: list = field(default_factory=list)
    tested: list = field(default_factory=list)
    placement: dict | None = None
    excluded_pixels: int | None = None
    window_camera_px: list[int] | None = None

    @property
    def named(self) -> list[str]:
        """Names of the effects found, in order."""
        return [s.effect for s in self.steps]

    @property
    def incomplete(self) -> bool:
        """Whether a limit the user asked for ended any part of it."""
        return self.stopped_early is not None

    @property
    def untried(self) -> list[str]:
        """The candidates it carries no information about (not in ``tested``)."""
        return [c for c in self.candidates if c not in self.tested]

    def to_dict(self) -> dict[str, Any]:
        """The diagnosis as a JSON-ready dict (the body of the ``report.json`` that :meth:`save` writes)."""
        return {"summary": summary_line(self), "incomplete": self.incomplete,
                "candidates": list(self.candidates), "tested": list(self.tested), "untried": self.untried,
                "domain": self.domain, "units": self.units,
                "steps": [s.to_dict() for s in self.steps],
                "effects_found": self.named,
                "measurement_artefacts": [s.effect for s in self.steps if s.kind == "artefact"],
                "model": {k: np.asarray(v).tolist() for k, v in self.model.items()},
                "noise_floor": self.noise_floor, "corr_area_px": self.corr_area_px,
                "n_samples": self.n_samples, "n_eff": self.n_eff,
                "initial_residual_rms": self.initial_residual_rms,
                "final_residual_rms": self.final_residual_rms,
                "unexplained": self.unexplained, "structure_criterion": self.structure_criterion,
                "unexplained_where": self.unexplained_where, "partial_matches": self.partial_matches,
                "stopped_early": self.stopped_early, "below_resolution": self.below_resolution,
                "breakdown_initial": self.breakdown_initial, "breakdown_final": self.breakdown_final}
    def plot(self, out_dir: str | Path) -> list[Path]:
        """Write ``residual_steps.png`` (residual map before and after each step) and
        ``breakdown.png`` (residual by edge distance, level, density, position, frequency).

        Returns
        -------
        list of Path
        """
        from metrology.diagnosis.plots import plot_breakdown, plot_steps

        if len(self.residual_maps) == len(self.steps) + 1:
            titles = ["ideal model"] + [f"+ {s.effect}" for s in self.steps]
            rms = [self.initial_residual_rms] + [s.residual_rms_after for s in self.steps]
        else:  # the backward pass revised the steps: show the ideal and the final model
            titles = ["ideal model", "final: " + ", ".join(self.named)]
            rms = [self.initial_residual_rms, self.final_residual_rms]
        return [plot_steps(self.residual_maps, titles, rms, self.domain, Path(out_dir) / "residual_steps.png"),
                plot_breakdown(self.breakdown_initial, self.breakdown_final, self.domain,
                               Path(out_dir) / "breakdown.png")]

    def save(self, out_dir: str | Path, inputs: dict[str, Any] | None = None) -> dict[str, Any]:
        """Write the figures (:meth:`plot`), ``report.json`` (:meth:`to_dict` with ``inputs``
        and ``plots``) and the page a person reads, ``report.md``, into ``out_dir``; return the report."""
        from doedesign.fileio import json_ready, write_json
        from metrology.report_pages import diagnose_page

        report = self.to_dict()
        report["inputs"] = dict(inputs or {})
        report["plots"] = [p.name for p in self.plot(out_dir)]
        write_json(Path(out_dir) / "report.json", report)
        diagnose_page(json_ready(report), Path(out_dir))
        return report




def summary_line(diag: Diagnosis) -> str:
    """The first line of a diagnosis's summary: ``INCOMPLETE`` and the candidates not tried when a
    limit ended it, else what it named."""
    named = ", ".join(diag.named) or "nothing"
    if diag.incomplete:
        stop = diag.stopped_early
        assert stop is not None  # incomplete means stopped early
        which = {"wall": "--wall-limit-s", "cpu": "--cpu-budget-s"}.get(stop.get("limit", ""), "a time limit")
        return (f"INCOMPLETE: the limit asked for ({which}) ended the diagnosis ({stop.get('reason')}); "
                f"not tried: {', '.join(diag.untried) or 'none'}; named before it: {named}")
    return f"complete: named {named}; tested {len(diag.tested)} of {len(diag.candidates)} candidates"
