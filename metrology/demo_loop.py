"""The demo's closing fab loop: its diagnosis -> ``doe correct`` -> the next wafer, diagnosed.

:func:`correct_step` hands the demo's diagnosed field to :func:`metrology.correction.run.correct`
(corrected masks, job sheet, the predicted figure of merit of the design, the measured wafer and
the corrected next wafer), short: no Monte Carlo draws, the central values only.
:func:`next_wafer_params` is the demo fab following the job sheet: its hidden process with the
aligner dials added to the overlay and rotation, the drawn edge offsets added to the linewidth
bias and the etch aimed at the targets. The pipeline makes, measures, compares and diagnoses
that wafer like the first; :func:`loop_summary` and :func:`loop_sections` put the two wafers
side by side in the demo's report, every number read from the job sheet and the diagnoses.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from doedesign.design import Design

if TYPE_CHECKING:
    from masks.process import ProcessParams

__all__ = ["correct_step", "loop_sections", "loop_summary", "loop_verdict", "next_wafer_params"]


def correct_step(design: Design, design_path: Path, out: Path, samples: int = 0, seed: int = 0) -> dict:
    """``doe correct`` of the demo's diagnosis (``out/diagnose``) into ``out/correct``; the job sheet.

    The demo's short version: the merits at one process sample per design pixel (``doe correct``
    uses 2), which keeps the whole demo under two minutes on two cores."""
    from metrology.correction import correct

    return correct(design, [out / "diagnose"], out / "correct", design_path=str(design_path), samples=samples,
                   seed=seed, merit_oversample=1)


def next_wafer_params(params: ProcessParams, sheet: dict) -> ProcessParams:
    """The process of the next wafer when the fab follows the job sheet ``sheet``.

    Parameters
    ----------
    params : masks.process.ProcessParams
        The (hidden) process of the measured wafer.
    sheet : dict
        The job sheet (``job.json``).

    Returns
    -------
    masks.process.ProcessParams
        The aligner's dials added to each mask's overlay (m) and rotation (deg), the drawn edge
        offset added to its linewidth bias (a printed opening is the drawn one grown by the
        bias), and each etch aimed at its target: the actual depth scales by target / nominal.
    """
    n = len(params.etch_depth)
    overlay = np.zeros((n, 3)) if params.mask_overlay is None else np.array(params.mask_overlay, float)
    rotation = np.zeros(n) if params.mask_rotation is None else np.array(params.mask_rotation, float)
    bias = np.zeros(n) if params.linewidth_bias is None else np.array(params.linewidth_bias, float)
    depth = np.array(params.etch_depth, float)
    for m in sheet["masks"]:
        j = m["mask"]
        overlay[j, :2] += np.asarray(m["align_offset_um"], float) * 1e-6
        rotation[j] += m["align_rotation_deg"]
        bias[j] += m["drawn_edge_offset_um"] * 1e-6
        depth[j] *= m["etch_depth_target_nm"] / m["etch_depth_nm"]
    return params.copy(mask_overlay=overlay, mask_rotation=rotation, linewidth_bias=bias, etch_depth=depth)


def _fab_params(diag: dict) -> dict:
    """Fabrication parameter -> (value, uncertainty) of a diagnosis report (artefacts left out)."""
    out = {}
    for s in diag.get("steps") or []:
        if s.get("measurement_artefact") or s.get("kind", "fabrication") != "fabrication":
            continue
        for k, v in (s.get("params") or {}).items():
            out[f"{s['effect']}.{k}"] = (v, (s.get("uncertainties") or {}).get(k))
    return out


def loop_summary(sheet: dict, next_diagnosis: dict | None, next_sheet: dict | None = None) -> dict:
    """What the demo's report shows of the loop (strict-JSON ready).

    ``corrected``: per corrected parameter, its unit, the measured value on wafer 1 and on the
    next wafer (0 where that diagnosis no longer names it), the detection limit, and whether the
    next wafer's value is below the limit or at most 20 % of the first's. ``merit``: the primary
    metric of the design, the measured wafer and the predicted corrected wafer (and the next
    wafer as measured, from its own ``doe correct`` when given).
    """
    merit = sheet["merit"]
    primary = merit["primary_metric"]
    wafers = {k: {"value": merit[k]["central"][primary], "change_percent": merit[k]["primary_change_percent"]}
              for k in ("design", "measured_wafer", "corrected_wafer")}
    if next_sheet is not None:
        m2 = next_sheet["merit"]["measured_wafer"]
        wafers["next_wafer_measured"] = {"value": m2["central"][primary], "change_percent": m2["primary_change_percent"]}
    after = _fab_params(next_diagnosis or {})
    rows = []
    for e in sheet["estimates"]:
        if not e["corrected"]:
            continue
        key = f"{e['effect']}.{e['param']}"
        value2, err2 = after.get(key, (0.0, None))
        closed = abs(value2) < e["detection_limit"] or abs(value2) <= 0.2 * abs(e["mean"])
        rows.append({"parameter": key, "unit": e["unit"], "wafer1": e["mean"], "wafer1_error": e["standard_error"],
                     "wafer2": value2 if next_diagnosis is not None else None, "wafer2_error": err2,
                     "detection_limit": e["detection_limit"], "closed": closed if next_diagnosis is not None else None})
    named2 = sorted({k.split(".")[0] for k in after})
    return {"primary_metric": primary, "direction": merit["direction"], "metric_unit": merit["metric_unit"],
            "merit": wafers, "corrected": rows, "warnings": sheet["warnings"],
            "masks": [{k: m[k] for k in ("mask", "align_offset_um", "align_rotation_deg", "drawn_edge_offset_um",
                                         "etch_depth_target_nm", "etch_depth_nm", "corrections")}
                      for m in sheet["masks"]],
            "next_wafer_named": named2 if next_diagnosis is not None else None,
            "next_wafer_unexplained": bool(next_diagnosis.get("unexplained")) if next_diagnosis else None,
            "masks_verified": bool((sheet.get("masks_verification") or {}).get("passed"))}


_SCALE = {"m": (1e6, "um"), "1": (100.0, "%"), "deg": (1.0, "deg"), "1/m": (0.1, "%/mm")}


def loop_verdict(loop: dict) -> str:
    """One sentence: did the loop close, and what it does to the figure of merit (from the numbers)."""
    from doedesign import report_md as md

    w = loop["merit"]
    closed = [r["closed"] for r in loop["corrected"]]
    gain = w["corrected_wafer"]["change_percent"] - w["measured_wafer"]["change_percent"]
    if not loop["corrected"]:
        verdict = "nothing systematic and significant to correct: the job sheet changes nothing"
    elif all(c is None for c in closed):
        verdict = (f"{len(closed)} parameter(s) corrected; the corrected next wafer is predicted "
                   f"{md.fmt(abs(gain), 3)} % {'better' if gain > 0 else 'worse'} than wafer 1 against the design")
    else:
        verdict = md.verdict(all(closed), "the loop closed: every corrected parameter of the next wafer is below its "
                             "detection limit or at most 20 % of wafer 1's",
                             f"{closed.count(False)} corrected parameter(s) still there on the next wafer")
        verdict += (f"; predicted merit {md.fmt(w['measured_wafer']['change_percent'], 3)} % -> "
                    f"{md.fmt(w['corrected_wafer']['change_percent'], 3)} % against the design")
        if "next_wafer_measured" in w:
            verdict += f", the next wafer as measured {md.fmt(w['next_wafer_measured']['change_percent'], 3)} %"
    return verdict


def loop_sections(loop: dict) -> list[str]:
    """Markdown parts of the loop for the demo's report (folders relative to the report)."""
    from doedesign import report_md as md

    primary, unit = loop["primary_metric"], loop["metric_unit"]
    w = loop["merit"]
    labels = {"design": "design (ideal process)", "measured_wafer": "wafer 1 as measured",
              "corrected_wafer": "next wafer, corrected (predicted)", "next_wafer_measured": "next wafer as measured"}
    merit_table = md.table([(labels[k], md.fmt(v["value"], 4), md.fmt(v["change_percent"], 3))
                            for k, v in w.items()], ("wafer", f"{primary} ({unit})", "change against design (%)"))
    rows = []
    for r in loop["corrected"]:
        scale, u = _SCALE.get(r["unit"], (1.0, r["unit"]))
        if r["wafer2"] is None:
            two = "not made"
        elif r["wafer2_error"] is None:
            two = "not named (below what the diagnosis resolves)"
        else:
            two = md.fmt_pm(r["wafer2"] * scale, r["wafer2_error"] * scale, 3, u)
        rows.append((r["parameter"], md.fmt_pm(r["wafer1"] * scale, r["wafer1_error"] * scale, 3, u), two,
                     md.fmt(r["detection_limit"] * scale, 2, u),
                     md.verdict(r["closed"], "closed", "still there") if r["closed"] is not None else "n/a"))
    dials = [(f"mask {m['mask']}", "; ".join(m["corrections"])) for m in loop["masks"]]
    parts = ["## Closing the fab loop (doe correct)",
             "The diagnosis above goes through `doe correct` (one field, central values, no Monte Carlo draws): "
             "corrected masks (`correct/masks/`, "
             + ("verified" if loop["masks_verified"] else "**not** verified")
             + "), a job sheet (`correct/report.md`) and the figure of merit predicted with the process model "
             "(the short loop: one process sample per design pixel, where `doe correct` uses two). "
             + ("The demo's fab then follows the job sheet with the same hidden process: the next wafer is made, "
                "measured, compared (without its PSF comparison and 3-D view) and diagnosed like the first, on a "
                "smaller window (`next_wafer/`)." if loop["next_wafer_named"] is not None else ""), "",
             f"**Verdict**: {loop_verdict(loop)}.", "",
             md.table(dials, ("mask", "job sheet: what the next run changes")),
             merit_table,
             md.table(rows, ("corrected parameter", "wafer 1 (diagnosed)", "next wafer (diagnosed)", "detection limit",
                             "verdict")) if rows else "No parameter was corrected.\n"]
    if loop["next_wafer_named"] is not None:
        parts.append(f"The next wafer's diagnosis names: {', '.join(loop['next_wafer_named']) or 'no fabrication effect'}"
                     + ("; a structured residual remains unexplained" if loop["next_wafer_unexplained"] else "")
                     + ".\n")
    if loop["warnings"]:
        parts.append("Job sheet warnings: " + " ".join(f"{x}." for x in loop["warnings"]) + "\n")
    return parts
