"""``doe tolerance``: Monte Carlo of the process through the PSF engine, on Dask."""

from __future__ import annotations

import argparse

from doedesign.cli.common import Number, add_device_option
from doedesign.errors import DoeError

__all__ = ["cmd_tolerance", "register"]

TOLERANCE_HELP = """\
Each sample draws the process parameters from the spec (seeded from --seed and the sample
index, so results do not depend on workers or scheduler), makes the fabricated surface with
the process model, computes the coded PSF at the design's wavelengths and depths and
measures the design's figure of merit. Finished samples are written to OUT/samples as they
complete; rerunning with the same --out resumes. Without --spec the built-in default (overlay
sigma 0.25 um per axis, etch depth sigma 2 %, linewidth bias sigma 0.1 um) is used and printed
in the report. --spec may also be a `doe compare` report.json (measured values, standard errors
as sigma). The yield is judged against --yield-goal, else the spec's [yield] goal, else 0.9.
Spec schema: python -c "import masks.tolerance.spec as s; help(s)".
Writes OUT/report.json (samples, nominal, metrics, yield, sensitivity), report.md,
distributions.png and tornado.png.
"""


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add ``doe tolerance`` to ``subparsers``."""
    p = subparsers.add_parser("tolerance", help="Monte Carlo tolerance analysis, yield and sensitivity",
                              description=TOLERANCE_HELP, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("design", help="design file (.npz)")
    p.add_argument("--spec", help="process spec (.toml) or a doe compare report (.json); default built in")
    p.add_argument("--samples", type=Number(int, 1, 1_000_000), default=200, help="Monte Carlo samples (default 200)")
    p.add_argument("--out", required=True, help="output folder (resumed when it holds this run)")
    p.add_argument("--seed", type=Number(int, 0, 2**63 - 1), default=0, help="run seed S; sample k uses SeedSequence([S, k])")
    p.add_argument("--scheduler", default="processes",
                   help="processes (default, a LocalCluster), threads, inline (no dask) or tcp://HOST:PORT")
    p.add_argument("--workers", type=Number(int, 1, 4096), help="local workers (default: the machine's cores; on GPUs one per visible GPU, each pinned to it)")
    add_device_option(p)
    p.add_argument("--oversample", type=Number(int, 1, 16), default=2, help="PSF samples per design pixel (default 2)")
    p.add_argument("--process-upsample", type=Number(int, 1, 64),
                   help="process-model samples per design pixel, a multiple of --oversample (default equal)")
    p.add_argument("--wavelengths", help="nm, e.g. 486,589,656 or 400:700:10 (default: the design's target)")
    p.add_argument("--threshold", action="append", default=[],
                   help="yield threshold 'metric>=value' (repeatable; default: primary metric >= 90 %% of nominal)")
    p.add_argument("--yield-goal", type=Number(float, 0, 1, lo_open=True, hi_open=True),
                   help="share of elements that must meet the thresholds (default: the spec's [yield] goal, else 0.9)")
    p.add_argument("--metric-script", help="Python file defining metric_<name>(psf, info) functions")
    p.add_argument("--sobol-base", type=Number(int, 0, 100_000), default=8,
                   help="Saltelli base N for Sobol indices (N (groups + 2) extra runs; 0 = off; default 8)")
    p.add_argument("--no-oat", action="store_true", help="skip the one-at-a-time sensitivity runs")
    p.set_defaults(func=cmd_tolerance)


def cmd_tolerance(args: argparse.Namespace) -> int:
    """Run ``doe tolerance`` with the parsed options; return the exit code."""
    from doedesign.cli.common import print_json
    from doedesign.design import Design
    from doedesign.engine.psf import parse_wavelengths_nm

    from doedesign.fileio import ensure_output_dir

    from .analysis import nominal_depths, tolerance_analysis
    from .scheduler import parse_address
    from .spec import default_spec, load_spec, parse_threshold

    # Refuse a bad --out or --scheduler before any work.
    ensure_output_dir(args.out)
    if "://" in args.scheduler:
        parse_address(args.scheduler)
    design = Design.load(args.design)
    depths = nominal_depths(design)
    spec = load_spec(args.spec, depths) if args.spec else default_spec(depths)
    thresholds = {}
    for text in args.threshold:
        name, t = parse_threshold(text, "--threshold")
        if not name:
            raise DoeError(f"--threshold {text!r}: name the metric, e.g. on_target_mean>=0.2")
        thresholds[name] = t
    wls = parse_wavelengths_nm(args.wavelengths) if args.wavelengths else None
    report = tolerance_analysis(design, spec, args.samples, args.out, design_name=args.design, seed=args.seed,
                                scheduler=args.scheduler, workers=args.workers, oversample=args.oversample,
                                process_upsample=args.process_upsample, wavelengths_m=wls,
                                sobol_base=args.sobol_base, one_at_a_time=not args.no_oat, thresholds=thresholds,
                                metric_script=args.metric_script, yield_goal=args.yield_goal, device=args.device)
    primary = report["primary_metric"]
    m = report["metrics"][primary]
    print_json({"report": f"{args.out}/report.json", "spec": report["spec"]["source"], "primary_metric": primary,
                "nominal": m["nominal"], "mean": m["mean"], "worst_decile_mean": m["worst_decile_mean"],
                "yield": report["yield"]["fraction"], "yield_ci95": report["yield"]["ci95"],
                "seconds_per_sample": report["timing"]["seconds_per_sample"]})
    return 0
