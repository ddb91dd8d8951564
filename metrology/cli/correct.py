"""``doe correct``: from diagnosed fields to corrected masks, a job sheet and a process spec."""

from __future__ import annotations

import argparse

from doedesign.cli.common import Number

__all__ = ["register", "run"]

HELP = """\
Combine the diagnoses of several fields (doe diagnose --out folders) of one design: per effect
parameter the mean over the fields whose diagnosis tested that effect (a field a --wall-limit-s
ended, marked INCOMPLETE, counts only for what it named; the job sheet's first lines say so, and
only INCOMPLETE diagnoses are refused) with its standard error and the spread between fields. What is
systematic (|mean| > 3 standard errors and above the effect's detection limit) and has a knob is
corrected: each mask's openings are redrawn with their edges offset against the measured
linewidth bias (OUT/masks/, the layout of doe masks, verified), and OUT/job.json (+ report.md)
gives per mask the etch target, the aligner offset and rotation to dial in (the negative of the
measured error; x toward increasing column, y up, counter-clockwise, relative to mask 0) and the
bias taken out. A systematic etch loading is taken out of the etch targets in the mean over each
mask's openings; what varies with the local pattern density no mask or etch setting removes, and
the job sheet warns with its rms per mask. A systematic proximity_print (the masks printed through
the aligner's gap) is corrected by drawing every mask pre-distorted for the diagnosed gap and
threshold (optical proximity correction, its bias folded in; --no-opc draws them uncorrected),
with the print check of the drawn and the corrected masks in OUT/masks/print_check.md. The rest is reported as spread. The figure of merit of the design, the measured
wafer and the corrected next wafer are predicted with doe tolerance's process model, and
OUT/process_spec.toml (a doe tolerance spec) carries the measured spreads as sigmas.

With --redesign, the element is also re-designed for the process as measured (the design loop
with the fitted process as its nominal process, starting from the design's levels remapped to
the fitted etch depths): for a fab whose settings cannot change, or, with --redesign-for
corrected, for what the job sheet leaves (the knobs turned, the new masks drawn offset as well).
OUT/redesign/ holds its design.npz, its masks (as doe masks writes them) and redesign.json; its
predicted merit, under the same process model and draws, stands beside the others.
"""


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add ``doe correct`` to ``subparsers``."""
    p = subparsers.add_parser("correct", help="diagnosed fields -> corrected masks, job sheet, predicted merit",
                              description=HELP, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--design", required=True, help="design file (.npz)")
    p.add_argument("--diagnosis", action="append", required=True, metavar="DIAG",
                   help="a doe diagnose output folder (repeat for each field)")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--layers", default=None, help="GDS layer per mask (as doe masks; default 1..M for the "
                                                  "design's M masks)")
    p.add_argument("--mirror", action="store_true", help="mirror x -> -x (contact printing, as doe masks)")
    p.add_argument("--samples", type=Number(int, 0, 10_000), default=12,
                   help="Monte Carlo draws per predicted wafer (default 12)")
    p.add_argument("--seed", type=Number(int, 0, 2**63 - 1), default=0, help="seed of the draws")
    p.add_argument("--min-feature-um", type=Number(float, 0, 100, unit="um"), default=None,
                   help="narrowest opening or gap the corrected masks may draw (default 1 um)")
    p.add_argument("--no-opc", action="store_true",
                   help="draw the masks uncorrected for a systematic proximity_print (default: pre-distorted for "
                        "the diagnosed gap and threshold, optical proximity correction, with the print check of "
                        "both in OUT/masks/print_check.md; --min-feature-um is its minimum feature)")
    p.add_argument("--redesign", action="store_true",
                   help="also re-design the element for the process as measured (OUT/redesign/: design.npz, "
                        "masks/, redesign.json) and predict its merit beside the plain correction")
    p.add_argument("--redesign-iterations", type=Number(int, 1, 100_000), default=None, metavar="N",
                   help="evaluations of the re-design's continuous stage (default 20; the annealing adds "
                        "5 stages of N/4)")
    p.add_argument("--redesign-for", choices=("measured", "corrected"), default=None,
                   help="the process the re-design is for: as measured, no knob turned (default), or as the "
                        "job sheet leaves it (the new masks drawn with its edge offsets)")
    p.add_argument("--redesign-samples", type=Number(int, 0, 1000), default=0, metavar="K",
                   help="draws of the measured spreads the re-design averages over, beside the fitted "
                        "process (default 0)")
    p.add_argument("--map", metavar="REPORT.json",
                   help="a doe map report: its named overlay terms set the aligner offset and rotation of their "
                        "masks, a magnification becomes a stated mask scale, a radial etch depth a warning; all in "
                        "job.json (its map entry) and the job sheet's first lines")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Run ``doe correct`` with the parsed options; return the exit code."""
    from doedesign.cli.common import print_json
    from doedesign.design import Design
    from doedesign.errors import DoeError
    from doedesign.fileio import ensure_output_dir

    from metrology.correction import correct
    from metrology.correction.redesign import DEFAULT_ITERATIONS

    ensure_output_dir(args.out)
    map_report = None
    if getattr(args, "map", None):
        from metrology.diagnosis.map_correction import read_map_report

        map_report = read_map_report(args.map)
    if not args.redesign and (args.redesign_iterations is not None or args.redesign_samples or args.redesign_for):
        raise DoeError("--redesign-iterations, --redesign-samples and --redesign-for need --redesign")
    try:
        layers = None if args.layers is None else [int(v) for v in args.layers.split(",")]
    except ValueError:
        raise DoeError(f"--layers must be comma-separated integers, got {args.layers!r}") from None
    sheet = correct(Design.load(args.design), args.diagnosis, args.out, design_path=str(args.design), layers=layers,
                    mirrored=args.mirror, samples=args.samples, seed=args.seed,
                    min_feature_m=None if args.min_feature_um is None else args.min_feature_um * 1e-6,
                    redesign_iterations=(args.redesign_iterations or DEFAULT_ITERATIONS) if args.redesign else None,
                    redesign_samples=args.redesign_samples, redesign_for=args.redesign_for or "measured",
                    map_report=map_report, map_source=str(getattr(args, "map", None)), opc=not args.no_opc)
    merit = sheet["merit"]
    primary = merit["primary_metric"]
    print_json({"job_sheet": f"{args.out}/job.json", "masks": f"{args.out}/{sheet['masks_file']}",
                "corrected": sheet["corrected"], "warnings": sheet["warnings"], "primary_metric": primary,
                "design": merit["design"]["central"][primary],
                "measured_wafer": merit["measured_wafer"]["central"][primary],
                "corrected_wafer": merit["corrected_wafer"]["central"][primary],
                **({"redesigned_wafer": merit["redesigned_wafer"]["central"][primary],
                    "redesign": f"{args.out}/redesign"} if "redesigned_wafer" in merit else {})})
    return 0
