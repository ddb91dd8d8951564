"""The page a person reads beside ``job.json``: what to change per mask, why, and what it buys."""

from __future__ import annotations

from pathlib import Path

from doedesign import report_md as md

__all__ = ["job_page"]

_SCALE = {"m": (1e6, "um"), "1": (100.0, "%"), "deg": (1.0, "deg"), "1/m": (0.1, "%/mm")}


def job_page(sheet: dict, folder: Path) -> Path:
    """Write ``report.md`` for a job sheet (the dict written to ``job.json``)."""
    merit = sheet["merit"]
    primary = merit["primary_metric"]
    rows = [[m["mask"], f"{m['layer']}/{m['datatype']}", f"{m['etch_depth_nm']:.1f}", f"{m['etch_depth_target_nm']:.1f}",
             f"{m['align_offset_um'][0]:+.3f}, {m['align_offset_um'][1]:+.3f}", f"{m['align_rotation_deg']:+.4f}",
             f"{m['linewidth_bias_um']:+.3f}", f"{m['etch_mean_error_measured'] * 100:+.2f}",
             "; ".join(m["corrections"])] for m in sheet["masks"]]
    job = md.table(rows, ["mask", "layer/datatype", "etch nominal (nm)", "etch target (nm)",
                          "aligner offset dx, dy (um)", "aligner rotation (deg)", "linewidth bias taken out (um)",
                          "measured mean etch error over the openings (%)", "corrections"])
    est_rows = []
    for e in sheet["estimates"]:
        scale, unit = _SCALE.get(e["unit"], (1.0, e["unit"]))
        verdict = "corrected" if e["corrected"] else ("systematic, no knob" if e["systematic"] else "spread only")
        if e["effect"] == "proximity_print" and e["param"] == "threshold" and "proximity_correction" in sheet:
            verdict = "the print's shape: corrected with the gap (OPC)"
        if e["corrected"] and e["effect"] == "etch_loading":
            verdict = "mean loss corrected (etch targets); the density-dependent rest is not (see warnings)"
        est_rows.append([e["effect"], e["param"], md.fmt_pm(e["mean"] * scale, e["standard_error"] * scale, 3, unit),
                         md.fmt(e["spread"] * scale, 3, unit), md.fmt(e["detection_limit"] * scale, 2, unit),
                         f"{e['named_in']}/{e.get('tested_in', len(e['values']))}/{e.get('fields', len(e['values']))}",
                         verdict])
    est = md.table(est_rows, ["effect", "parameter", "mean over fields ± standard error", "spread between fields",
                              "detection limit",
                              "fields naming it / testing it / given", "verdict"])
    merit_rows = []
    for key, label in (("design", "design (ideal process)"), ("measured_wafer", "measured wafer"),
                       ("corrected_wafer", "next wafer, corrected"),
                       ("redesigned_wafer", "next wafer, re-designed for the "
                        + ("corrected process" if sheet.get("redesign", {}).get("process_of") == "corrected_wafer"
                           else "process as measured"))):
        if key not in merit:
            continue
        w = merit[key]
        draws = w.get("draws", {}).get(primary)
        merit_rows.append([label, md.fmt(w["central"][primary], 4), md.fmt(w["primary_change_percent"], 3),
                           md.fmt_pm(draws["mean"], draws["std"], 4) if draws else "n/a",
                           md.fmt(draws["worst"], 4) if draws else "n/a"])
    merit_table = md.table(merit_rows, ["wafer", f"{primary} ({merit['metric_unit']})", "change against design (%)",
                                        f"over {merit['corrected_wafer']['samples']} draws: mean ± sd", "worst draw"])
    warnings = "\n".join(f"- {w}" for w in sheet["warnings"]) + "\n" if sheet["warnings"] else "None.\n"
    summary = (f"{len(sheet['diagnoses'])} diagnosed field(s); {len(sheet['corrected'])} systematic parameter(s) "
               f"corrected, {len(sheet['spread_only'])} reported as spread only. Predicted {primary}: design "
               f"{md.fmt(merit['design']['central'][primary], 4)}, measured wafer "
               f"{md.fmt(merit['measured_wafer']['central'][primary], 4)} "
               f"({md.fmt(merit['measured_wafer']['primary_change_percent'], 3)} %), next wafer "
               f"{md.fmt(merit['corrected_wafer']['central'][primary], 4)} "
               f"({md.fmt(merit['corrected_wafer']['primary_change_percent'], 3)} %).\n")
    if "redesigned_wafer" in merit:
        rd = sheet["redesign"]
        process = ("the corrected process (the job sheet applied to its masks too" if rd["process_of"] == "corrected_wafer"
                   else "the process as measured (no knob turned")
        summary += (f"\nRe-designed for {process}; `{sheet['redesign_folder']}/`): "
                    f"{primary} {md.fmt(merit['redesigned_wafer']['central'][primary], 4)} "
                    f"({md.fmt(merit['redesigned_wafer']['primary_change_percent'], 3)} %), "
                    f"{rd['levels_changed_fraction'] * 100:.1f} % of the pixels the coded view sees on another level, "
                    f"{rd['evaluations']} evaluations; level remap "
                    f"{', '.join(f'{k}->{v}' for k, v in enumerate(rd['level_remap']) if k != v) or 'none'} "
                    f"(the remap alone: {md.fmt(rd['remap_only_central'][primary], 4)}; kept: {rd['kept']})."
                    + "".join(f" Note: {n}." for n in rd["notes"]) + "\n")
    conventions = "\n".join(f"- {k}: {v}" for k, v in sheet["conventions"].items()) + "\n"
    # The first lines: what the sheet could not use (a diagnosis a limit ended says nothing about what it did not try).
    first = "".join(f"**{w}**\n\n" for w in sheet["warnings"] if w.startswith(("INCOMPLETE", "combined only")))
    from_map = _map_section(sheet)
    if from_map:
        first += (f"**The whole-element map `{sheet['map']['source']}` sets the aligner dials of mask(s) "
                  f"{', '.join(str(m['mask']) for m in sheet['masks'] if m.get('align_source') == 'map') or 'none'}; "
                  "see its section.**\n\n")
    parts = [f"# Job sheet for `{sheet['design']}`", *([first] if first else []), summary, "## Per mask", job, conventions,
             *from_map, *_opc_section(sheet),
             "## What the fields say", est, "## Predicted merit", merit_table, "## Warnings", warnings,
             f"Corrected masks: `{sheet['masks_folder']}`; process spec for `doe tolerance`: "
             f"`{sheet['process_spec']}`.\n", md.json_link("job.json")]
    return md.write_markdown(folder / "report.md", parts)


def _map_section(sheet: dict) -> list[str]:
    """The map's part of the sheet: per mask the dial it set, the mask scale, and its warnings."""
    if "map" not in sheet:
        return []
    rows = [[m["mask"], m.get("align_source", "fields"),
             f"{m['align_offset_um'][0]:+.4f}, {m['align_offset_um'][1]:+.4f}", f"{m['align_rotation_deg']:+.6f}",
             f"{m.get('mask_scale', 1.0):.8f}"] for m in sheet["masks"]]
    notes = "\n".join(f"- {w}" for w in sheet["map"]["warnings"]) + "\n" if sheet["map"]["warnings"] else "No map warning.\n"
    return [f"## From the whole-element map `{sheet['map']['source']}`",
            md.table(rows, ["mask", "aligner dial from", "aligner offset dx, dy (um)", "aligner rotation (deg)",
                            "mask scale to draw (1 = as designed)"]), notes]


def _opc_section(sheet: dict) -> list[str]:
    """The masks pre-distorted for a diagnosed print: the print it corrects, and the print check."""
    opc = sheet.get("proximity_correction")
    if opc is None:
        return []
    r0, r1, c0, c1 = opc["region_px"]
    text = (f"Every mask is drawn pre-distorted ({opc['method']}; minimum feature {opc['min_feature_um']:.3g} um on a "
            f"{opc['mask_grid_um']:.4g} um grid) for the diagnosed print: gap {opc['gap_um']:.2f} um, resist threshold "
            f"{opc['resist_threshold']:.3f} of the open field, linewidth biases "
            f"{', '.join(f'{b:+.3f}' for b in opc['linewidth_bias_um'])} um (folded into the correction). Through "
            f"that print, over design rows {r0}-{r1 - 1} and columns {c0}-{c1 - 1}, the field overlap at 550 nm with "
            f"the design is {opc['field_overlap_drawn']:.4f} for the masks as drawn and "
            f"{opc['field_overlap_corrected']:.4f} for the corrected ones (1 = a contact print); per mask: "
            f"`{opc['print_check']}` and `masks/print_check.md`. Note: {opc['merit_note']}.\n")
    return ["## Masks pre-distorted for the gap (OPC)", text]
