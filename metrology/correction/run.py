"""``correct``: diagnosed fields -> corrected masks, job sheet, merit prediction, process spec.

What ``doe correct`` does and what the demo or a notebook calls. Everything is computed and
checked before the first file is written (a refusal leaves nothing); the writes are wrapped
in :func:`doedesign.fileio.output_run`.
"""

from __future__ import annotations

import logging
import tomllib
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from doedesign.design import Design
from doedesign.errors import DoeError
from doedesign.fileio import atomic_path, ensure_output_dir, output_run, write_json
from doedesign.levels import design_levels

from .diagnoses import design_fingerprint, read_diagnosis
from .jobsheet import check_offsets, check_same_process, job_entries, mask_label, warnings_for
from .merit import predict_merit
from .page import job_page
from .process_spec import spec_table, toml_text
from .proximity import no_opc, proximity_correction
from .redesign import redesign, write_redesign
from .systematic import DETECTION_LIMITS, SIGNIFICANCE, combine_fields

__all__ = ["CONVENTIONS", "correct"]

log = logging.getLogger(__name__)

CONVENTIONS = {
    "frame": "x toward increasing design column, y up (toward row 0), rotation counter-clockwise with row 0 on top, "
             "about the centre of the design grid; every mask relative to mask 0",
    "aligner": "align_offset_um and align_rotation_deg are the values to dial in: the negative of the measured error",
    "etch": "etch_depth_target_nm is what to aim the etch at so that it lands on etch_depth_nm (nominal)",
    "edges": "linewidth_bias_um is the measured bias taken out; the drawn edges moved by drawn_edge_offset_um "
             "(its negative; positive = openings drawn wider)",
    "systematic": f"corrected only where |mean| > {SIGNIFICANCE:g} standard errors and above the detection limit",
}


def correct(design: Design, diagnoses: Sequence[str | Path], out: str | Path, *, design_path: str | None = None,
            layers: Sequence[int] | None = None, mirrored: bool = False, samples: int = 12, seed: int = 0,
            min_feature_m: float | None = None, redesign_iterations: int | None = None,
            redesign_samples: int = 0, redesign_for: str = "measured", merit_oversample: int = 2,
            map_report: dict | None = None, map_source: str = "map", opc: bool = True) -> dict:
    """Correct the next run from diagnosed fields of this design; write ``out``; return the job sheet.

    Parameters
    ----------
    design : Design
    diagnoses : sequence of path
        ``doe diagnose`` output folders (fields of one wafer, or wafers of one process).
    out : path
        Output folder: ``masks/`` (as ``doe masks`` writes it, edges offset), ``job.json``,
        ``report.md``, ``process_spec.toml``.
    design_path : str, optional
        The design's file name, for the sheet.
    layers, mirrored
        As for ``doe masks`` (default layers 1 .. M for the design's M masks).
    samples, seed
        Monte Carlo draws of each predicted wafer and their seed.
    min_feature_m : float, optional
        Narrowest opening or gap the corrected masks may draw (default
        :data:`masks.corrected.MIN_FEATURE_M`).
    redesign_iterations, redesign_samples : int, optional
        Also re-design the element for the fitted process (:mod:`.redesign`) with this many
        iterations and process draws, into ``out/redesign/``; its merit is ``redesigned_wafer``.
    redesign_for : {"measured", "corrected"}
        The process the re-design is for: as measured (no knob turned) or as the job sheet leaves it.
    merit_oversample : int
        Process-model samples per design pixel of the predicted merits (``doe tolerance``'s
        ``--oversample``, default 2; 1 is 4x faster and height-averages sub-pixel slivers).
    map_report : dict, optional
        A ``doe map`` report (:func:`metrology.diagnosis.map_correction.read_map_report`): its
        named overlay terms set the aligner dials of their masks, a magnification becomes a
        stated mask scale, the radial etch term a warning (:mod:`metrology.diagnosis.map_correction`);
        all of it under the sheet's ``map`` entry.
    map_source : str
        The map report's file name, for the sheet.
    opc : bool
        Draw the masks pre-distorted for a systematic ``proximity_print``
        (:mod:`metrology.correction.proximity`);
        False draws them uncorrected for it, with a warning.

    Returns
    -------
    dict
        The job sheet written to ``job.json``.
    """
    from masks.corrected import write_offset_element
    from masks.decompose import levels_to_masks
    from masks.element import write_element
    from masks.tolerance.spec import build_spec

    if not diagnoses:
        raise DoeError("give at least one --diagnosis folder")
    out = ensure_output_dir(out)
    name = design_path or design.name
    fingerprint = design_fingerprint(design, design_path)
    fields = [read_diagnosis(p, design, fingerprint) for p in diagnoses]
    if all(f.incomplete for f in fields):
        raise DoeError("every diagnosis given is INCOMPLETE (a time limit ended it: "
                       f"{', '.join(f.source for f in fields)}); they say nothing about the effects they did not try. "
                       "Rerun doe diagnose without --wall-limit-s / --cpu-budget-s")
    depths = check_same_process(fields)
    if len(depths) != design.n_masks:
        raise DoeError(f"{name}: the diagnoses name {len(depths)} mask depth(s); this {design.n_levels}-level design "
                       f"has {design.n_masks} mask(s)")
    layers = tuple(range(1, design.n_masks + 1)) if layers is None else tuple(layers)
    masks = levels_to_masks(design_levels(design, source=name), len(depths))
    estimates = combine_fields(fields)
    jobs = job_entries(estimates, masks, design.pitch_m, depths, layers)
    printed = proximity_correction(design, estimates, jobs, depths, min_feature_m, name) if opc else None
    unprinted = [] if opc else no_opc(estimates)
    check_offsets(masks, design.pitch_m, jobs, min_feature_m, name)
    warnings = [*warnings_for(estimates, fields, jobs), *unprinted]
    merit = predict_merit(design, estimates, jobs, depths, samples=samples, seed=seed, source=name,
                          oversample=merit_oversample)
    if redesign_iterations:
        redesign_jobs = jobs if redesign_for == "corrected" else None
        new_design, new_report = redesign(design, estimates, depths, iterations=redesign_iterations,
                                          robust_samples=redesign_samples, samples=samples, seed=seed, source=name,
                                          merit=merit, jobs=redesign_jobs, min_feature_m=min_feature_m)
        merit["redesigned_wafer"] = new_report["merit"]
    from_map = None
    if map_report is not None:
        from metrology.diagnosis.map_correction import apply_to_jobs, map_corrections

        from_map = {"source": map_source, **map_corrections(map_report)}
        warnings = [*warnings, *apply_to_jobs(jobs, from_map, map_source), *from_map["warnings"]]
    table, spec_notes = spec_table(estimates, jobs)
    header = [f"doe tolerance spec from doe correct of {name}: the sigmas are the spreads measured between "
              f"{len(fields)} field(s); means are what the corrected next run still carries",
              *spec_notes]
    text = toml_text(table, header)
    build_spec(tomllib.loads(text), np.asarray(depths, float), "process_spec.toml")  # refuse to write what doe tolerance would refuse
    sheet = {
        "incomplete_diagnoses": [f.source for f in fields if f.incomplete],
        "design": name, "design_fingerprint": fingerprint, "diagnoses": [f.source for f in fields],
        "nominal_depths_nm": [d * 1e9 for d in depths], "conventions": CONVENTIONS,
        "detection_limits": DETECTION_LIMITS, "significance_standard_errors": SIGNIFICANCE,
        "masks": jobs,
        "corrected": [f"{e.effect}.{e.param}" for e in estimates if e.corrected],
        "spread_only": [f"{e.effect}.{e.param}" for e in estimates if not e.systematic],
        "estimates": [e.to_dict() for e in estimates], "warnings": warnings, "merit": merit,
        "masks_folder": "masks", "process_spec": "process_spec.toml",
        "process_spec_notes": spec_notes,
        **({"map": from_map} if from_map is not None else {}),
        **({"proximity_correction": printed["entry"]} if printed is not None else {}),
    }
    notes = {job["mask"]: mask_label(job) for job in jobs}
    with output_run(out, f"doe correct {name}"):
        masks_dir = ensure_output_dir(out / "masks", create=True)
        if printed is not None:
            report = write_element(design, masks_dir, source=name, mirrored=mirrored, depths_m=depths, layers=layers,
                                   print_check=printed["check"], corrected_masks=printed["corrected"])
        else:
            report = write_offset_element(design, masks_dir, [j["drawn_edge_offset_um"] * 1e-6 for j in jobs],
                                          notes=notes, source=name, mirrored=mirrored, depths_m=depths, layers=layers)
        sheet["masks_file"] = str(Path("masks") / Path(report["file"]).name)
        sheet["masks_verification"] = report["verification"]
        with atomic_path(out / "process_spec.toml") as tmp:
            tmp.write_text(text)
        if redesign_iterations:
            sheet["redesign"] = write_redesign(out / "redesign", new_design, new_report, depths_m=depths,
                                               layers=layers, mirrored=mirrored, jobs=redesign_jobs)
            sheet["redesign_folder"] = "redesign"
        write_json(out / "job.json", sheet)
        job_page(sheet, out)
    return sheet
