"""Reading the diagnoses a correction starts from, and making sure they are of this design.

``doe diagnose`` records the design it diagnosed against (:func:`design_fingerprint`: the
file's sha256, a sha256 of its 16-level map, its shape and pitch) in its report's
``inputs``; :func:`read_diagnosis` refuses a report of another design, of another domain
than heights, or one written before the fingerprint existed whose shape or pitch differ.

A field carries information only about the effects its diagnosis tested (the report's
``tested``: what it named, and what the round that ended it by the criterion found absent); a
diagnosis that a user's limit ended (``incomplete``) tested only what it named. An effect the
report lists as a partial match (it explains most of the residual on its footprint but leaves
that footprint above the floor, so it was neither named nor found absent: typically an
instrument the model does not describe closely enough) counts as not tested on that field: read
as "absent" it would pull the fields' mean toward zero (a 7 % deep etch seen on two fields and a
partial match on the third averaged to 4.4 % and was dropped as not significant). A report from
before ``tested`` existed counts as having tested every effect when it ran to its end, and only
what it named when it says it stopped early.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from doedesign.design import Design
from doedesign.errors import DoeError
from doedesign.fileio import check_input_file
from doedesign.levels import design_levels

__all__ = ["FieldDiagnosis", "design_fingerprint", "read_diagnosis"]


def design_fingerprint(design: Design, path: str | Path | None = None) -> dict:
    """What identifies a design: ``design_levels_sha256`` (its 16-level map with shape and pitch,
    the geometry the masks carry), ``design_shape_px``, ``design_pitch_m`` and, given its file,
    ``design_sha256`` of the file's bytes."""
    levels = np.ascontiguousarray(design_levels(design), dtype=np.int16)
    digest = hashlib.sha256(f"{levels.shape}|{design.pitch_m!r}|".encode() + levels.tobytes()).hexdigest()
    out = {"design_levels_sha256": digest, "design_shape_px": list(levels.shape), "design_pitch_m": design.pitch_m}
    if path is not None:
        out["design_sha256"] = hashlib.sha256(Path(path).read_bytes()).hexdigest()
    return out


@dataclass
class FieldDiagnosis:
    """One diagnosed field: its fabrication effects' fitted parameters and their uncertainties.

    Attributes
    ----------
    source : str
        The diagnosis folder.
    params : dict
        Effect -> {parameter: value} (the diagnosis's names and units), fabrication effects only.
    uncertainties : dict
        Effect -> {parameter: standard error}.
    nominal_depths_m : list of float
        The etch depths the diagnosis took as the ideal process.
    unexplained : bool
        Whether the diagnosis left a structured residual unexplained.
    noise_floor_m : float
    tested : list of str or None
        The effects the diagnosis tested (None: every effect).
    incomplete : bool
        Whether a limit ended the diagnosis (its summary says INCOMPLETE).
    summary : str
        The diagnosis's summary line.
    """

    source: str
    params: dict
    uncertainties: dict
    nominal_depths_m: list
    unexplained: bool = False
    noise_floor_m: float | None = None
    artefacts: list = field(default_factory=list)
    tested: list | None = None
    incomplete: bool = False
    summary: str = ""

    def tested_effect(self, effect: str) -> bool:
        """Whether this field's diagnosis tested ``effect`` (named it or found it absent)."""
        return effect in self.params or self.tested is None or effect in self.tested


def read_diagnosis(folder: str | Path, design: Design, fingerprint: dict | None = None) -> FieldDiagnosis:
    """The fabrication effects of ``doe diagnose``'s report in ``folder``, checked against ``design``.

    Raises
    ------
    DoeError
        No readable report, a PSF-domain diagnosis (it names no per-mask effects), or a
        report of another design (fingerprint, shape or pitch differ).
    """
    folder = Path(folder)
    path = folder / "report.json" if folder.is_dir() else folder
    check_input_file(path)
    try:
        rep = json.loads(path.read_text())
        steps = rep["steps"]
        inputs = rep.get("inputs") or {}
    except (json.JSONDecodeError, UnicodeDecodeError, KeyError, TypeError) as exc:
        raise DoeError(f"{path}: not a doe diagnose report ({type(exc).__name__}: {exc})") from None
    if rep.get("domain") != "height":
        raise DoeError(f"{path}: a {rep.get('domain')!r}-domain diagnosis names no per-mask effects; "
                       "doe correct needs diagnoses of height maps")
    mine = fingerprint or design_fingerprint(design)
    theirs = inputs.get("design_levels_sha256")
    if theirs is not None and theirs != mine["design_levels_sha256"]:
        raise DoeError(f"{path}: diagnosed against another design (level map sha256 {theirs[:12]}..., "
                       f"this design's {mine['design_levels_sha256'][:12]}...)")
    if theirs is None:
        shape, pitch = inputs.get("design_shape_px"), inputs.get("design_pitch_m")
        if shape is not None and list(shape) != mine["design_shape_px"] or \
                pitch is not None and not np.isclose(pitch, mine["design_pitch_m"], rtol=1e-9):
            raise DoeError(f"{path}: diagnosed against a design of {shape} px of {pitch} m, this one is "
                           f"{mine['design_shape_px']} px of {mine['design_pitch_m']} m")
        if shape is None:
            raise DoeError(f"{path}: the report does not say which design it diagnosed (no design fingerprint; "
                           "rerun doe diagnose)")
    params, errs = {}, {}
    for st in steps:
        if st.get("kind", "fabrication") != "fabrication":
            continue
        params[st["effect"]] = {k: float(v) for k, v in st["params"].items()}
        errs[st["effect"]] = {k: float(st["uncertainties"].get(k, np.nan)) for k in st["params"]}
    incomplete = bool(rep.get("incomplete", rep.get("stopped_early") is not None))
    tested = rep.get("tested")
    if tested is None and incomplete:
        tested = list(params)
    partial = {str(p.get("effect")) for p in rep.get("partial_matches") or []} - set(params)
    if tested is not None and partial:
        tested = [t for t in tested if t not in partial]
    depths = inputs.get("nominal_depths_m")
    if depths is None:
        raise DoeError(f"{path}: the report does not record the nominal etch depths it diagnosed against")
    return FieldDiagnosis(source=str(folder), params=params, uncertainties=errs,
                          nominal_depths_m=[float(v) for v in depths], unexplained=bool(rep.get("unexplained")),
                          noise_floor_m=rep.get("noise_floor"),
                          artefacts=list(rep.get("measurement_artefacts") or []),
                          tested=None if tested is None else [str(t) for t in tested], incomplete=incomplete,
                          summary=str(rep.get("summary") or ""))
