"""``doe rigorous``: one period of a design scored by the Fourier modal method beside the thin-element model."""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

import numpy as np

from ..design import Design
from ..errors import DoeError
from ..fileio import ensure_output_dir, output_run, write_json
from .common import Number, print_json

__all__ = ["cmd_rigorous", "register"]

log = logging.getLogger(__name__)


def _patch(design: Design, text: str | None, where: str) -> np.ndarray:
    """The period to score: ROW,COL,ROWS,COLS (row 0 at the top) or the whole design."""
    h = design.height_m
    if not text:
        return h
    try:
        r0, c0, nr, nc = (int(v) for v in text.split(","))
    except ValueError:
        raise DoeError(f"{where}: --patch must be ROW,COL,ROWS,COLS (four integers), got {text!r}") from None
    if r0 < 0 or c0 < 0 or nr < 1 or nc < 1 or r0 + nr > h.shape[0] or c0 + nc > h.shape[1]:
        raise DoeError(f"{where}: --patch {text} does not fit the {h.shape[0]} x {h.shape[1]} px design")
    return h[r0:r0 + nr, c0:c0 + nc]


def _markdown(report: dict) -> list[str]:
    from ..report_md import fmt, json_link, table, verdict

    v = report["validity"]
    parts = ["# Rigorous check", "",
             f"Design `{report['design']}`, period {report['period_px'][0]} x {report['period_px'][1]} px at "
             f"{fmt(report['pitch_m'] * 1e6)} um, {report['material']}, {report['layers']} binary layers, "
             f"{report['n_terms']} Fourier terms (fmmax, {report['formulation']}), light through the "
             f"{report['incidence']}, {report['comparison']['polarization']}.", "",
             "## Where the thin-element model holds", "",
             verdict(v["holds"], v["statement"], v["statement"]), "",
             "## Efficiencies", "",
             "Rigorous: transmitted efficiency; relative: over the transmitted total (what the thin-element "
             "model, which has no interface reflection, predicts).", ""]
    for w in report["comparison"]["wavelengths"]:
        parts.append(f"### {fmt(w['wavelength_nm'], 4)} nm: transmitted {fmt(w['transmitted'])}, "
                     f"largest difference {fmt(w['max_difference'])}")
        rows = [(f"({o['order'][0]}, {o['order'][1]})", o["rigorous"], o["rigorous_relative"], o["thin_element"])
                for o in w["orders"][:25]]
        parts.append(table(rows, ["order (p, q)", "rigorous", "rigorous relative", "thin element"]))
    parts += ["## Verdict", "",
              verdict(not report["warnings"], f"the two models agree within {report['tolerance']:g} in every order",
                      "; ".join(report["warnings"])), "", json_link()]
    return parts


def cmd_rigorous(args: argparse.Namespace) -> int:
    """Run ``doe rigorous`` with the parsed options; return the exit code."""
    from ..engine.psf import parse_wavelengths_nm
    from ..report_md import write_markdown
    from ..rigorous import score_design

    out = ensure_output_dir(args.out)
    design = Design.load(args.design)
    height = _patch(design, args.patch, args.design)
    wls = parse_wavelengths_nm(args.wavelengths_nm) if args.wavelengths_nm else np.array([design.design_wavelength_m])
    report = score_design(height, design.pitch_m, design.material, wls, n_terms=args.terms,
                          polarization=args.polarization, incidence=args.incidence, tolerance=args.tolerance)
    report = {"design": str(args.design), "patch": args.patch, **report}
    with output_run(out, "doe rigorous"):
        write_json(out / "report.json", report)
        write_markdown(out / "report.md", _markdown(report))
    for line in report["warnings"]:
        log.warning(line)
    print_json({"report": str(Path(out) / "report.json"), "holds": report["validity"]["holds"],
                "max_difference": [w["max_difference"] for w in report["comparison"]["wavelengths"]],
                "warnings": report["warnings"]})
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    """Add ``doe rigorous`` to the subcommands ``sub``."""
    from ..rigorous import DEFAULT_TERMS, DEFAULT_TOLERANCE, INCIDENCES, POLARIZATIONS

    p = sub.add_parser("rigorous", help="rigorous (Fourier modal) efficiencies of one period beside the thin-element ones",
                       description="Score one period of a design (the whole design, or --patch) as a periodic element "
                                   "with the Fourier modal method (fmmax; optional extra: pip install "
                                   "'doe-toolkit[rigorous]') and with the thin-element model, at normal incidence. "
                                   "Writes OUT/report.json and OUT/report.md: transmitted efficiency per order "
                                   "(p along columns, q toward row 0), the validity figures (smallest feature over "
                                   "wavelength, depth over feature) and a warning where the models differ by more "
                                   "than --tolerance.")
    p.add_argument("design", help="design .npz (doe design, doe import)")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--patch", help="ROW,COL,ROWS,COLS of one period (row 0 at the top); default the whole design")
    p.add_argument("--wavelengths-nm", help="list (486,589,656) or range start:stop:step; default the design wavelength")
    p.add_argument("--polarization", choices=POLARIZATIONS, default="unpolarised",
                   help="te: E along y (along the lines of a grating along x); tm: E along x; unpolarised: their mean")
    p.add_argument("--incidence", choices=INCIDENCES, default="substrate", help="side the light comes from")
    p.add_argument("--terms", type=Number(int, 1, 5000), default=DEFAULT_TERMS, help="Fourier terms (more: slower, "
                   "more accurate)")
    p.add_argument("--tolerance", type=Number(float, 0, 1, lo_open=True), default=DEFAULT_TOLERANCE,
                   help="largest efficiency difference in any order that passes without a warning")
    p.set_defaults(func=cmd_rigorous)
