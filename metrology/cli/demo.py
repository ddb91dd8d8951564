"""``doe demo``: the main job on the built-in default design (see :mod:`metrology.pipeline`)."""

from __future__ import annotations

import argparse
import logging

from doedesign.cli.common import Number
from doedesign.progress import Progress

log = logging.getLogger(__name__)

__all__ = ["ELEMENTS_ITERATIONS", "ELEMENTS_PX", "cmd_demo", "register", "seed_elements"]

# --all designs the three elements at this DOE size (5.4 um pixels, a spot twice the camera's;
# about 160 s of CPU); --quick at 48 px.
ELEMENTS_PX, ELEMENTS_ITERATIONS = 800, 30


def cmd_demo(args: argparse.Namespace) -> int:
    """Run ``doe demo`` with the parsed options; return the exit code."""
    from doedesign.fileio import ensure_output_dir
    from metrology.pipeline import DemoConfig, run_demo

    ensure_output_dir(args.out)  # an existing file or an unwritable folder costs nothing
    if args.all:
        seed_elements(args)
    cfg = DemoConfig.quick() if args.quick else DemoConfig()
    if args.iterations is not None:
        cfg.iterations = args.iterations
    if args.doe_px is not None:
        cfg.doe_px = args.doe_px
    cfg.instrument = args.instrument
    with Progress(1, desc="demo", enabled=None) as bar:
        report = run_demo(args.out, cfg)
        bar.update(1, status="done")
    total = sum(s["seconds"] for s in report["timings"])
    log.warning("demo finished in %.0f s; open %s/report.md", total, args.out)
    return 0


def seed_elements(args: argparse.Namespace) -> None:
    """``--all``: the seed's HDR streak, hyperspectral and depth elements with their figures against their bounds."""
    from pathlib import Path

    from doedesign.elements import design_seed_elements
    from doedesign.fileio import write_json

    size, iterations = (48, 4) if args.quick else (ELEMENTS_PX, ELEMENTS_ITERATIONS)
    if args.elements_px is not None:
        size = args.elements_px
    write_json(Path(args.out) / "elements.json", design_seed_elements(size, iterations))


def register(sub: argparse._SubParsersAction) -> None:
    """Add ``doe demo`` to the subcommands ``sub``."""
    p = sub.add_parser("demo", help="run the whole chain on the default Bayer element and write a report",
                       description="Design (nlopt) -> 16 levels -> four masks as GDSII (verified) -> simulated "
                                   "fabrication with a hidden process error -> simulated Zygo .datx -> read, "
                                   "level, register, compare -> PSF from measured heights -> diagnosis -> "
                                   "OUT/report.md with figures and a 3-D rendering.")
    p.add_argument("--out", default="demo-output", help="output folder (default demo-output)")
    p.add_argument("--quick", action="store_true", help="small sizes (about a minute)")
    p.add_argument("--all", action="store_true",
                   help="also design the seed's HDR streak, hyperspectral and depth elements (OUT/elements.json)")
    p.add_argument("--elements-px", type=Number(int, 16, 4096, unit="px"), default=None,
                   help=f"DOE size of the --all elements (aperture = size x 5.4 um; default {ELEMENTS_PX}, --quick 48)")
    p.add_argument("--iterations", type=Number(int, 1, 10**6), default=None, help="optimizer iterations")
    p.add_argument("--doe-px", type=Number(int, 16, 4096, unit="px"), default=None, help="DOE size in pixels (aperture = size x 5.4 um)")
    p.add_argument("--instrument", choices=("boxcar", "point", "optical"), default="boxcar",
                   help="lateral transfer of the simulated profilometer: boxcar (Gaussian blur, whole pixel area "
                        "integrated; default), point (blur, read at each pixel's centre) or optical (NA 0.4 "
                        "objective, 60 %% pixel fill factor)")
    p.set_defaults(func=cmd_demo)
