"""``doe masks``: design file -> verified GDSII of the binary etch masks, preview, report."""

from __future__ import annotations

import argparse
import logging

import numpy as np

from doedesign.cli.common import Number
from doedesign.errors import DoeError
from doedesign.fileio import ensure_output_dir

__all__ = ["register", "run_masks"]

log = logging.getLogger(__name__)


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add ``doe masks`` to the root command's subparsers."""
    p = subparsers.add_parser("masks", help="quantize, decompose into binary masks, write verified GDSII",
                              description="Write DIR/<name>.gds (one layer per mask), DIR/masks.png and "
                                          "DIR/report.json; the GDS is read back and verified pixel by pixel.")
    p.add_argument("design", help="design .npz")
    p.add_argument("--out", required=True, help="output directory")
    p.add_argument("--tone", choices=("dark", "clear"), default="dark",
                   help="dark: draw the etched (open) areas (default); clear: draw the chrome")
    p.add_argument("--mirror", action="store_true", help="mirror x -> -x (contact printing)")
    p.add_argument("--depths-nm", default=None,
                   help="etch depth per mask, comma separated (default 2**j times the level step)")
    p.add_argument("--layers", default="1,2,3,4", help="GDS layer per mask")
    p.add_argument("--etch-order", default=None, help="mask index etched in each step, e.g. 3,2,1,0")
    p.add_argument("--clear-aperture-mm", type=Number(float, 0, 1000, lo_open=True, unit="mm"), default=None,
                   help="clear circle diameter (default: camera aperture from the metadata)")
    p.add_argument("--oasis", action="store_true", help="also write <name>.oas")
    p.add_argument("--plate", action="store_true",
                   help="also write <name>_plate.gds: a full 4-inch wafer of this die by array references, "
                        "with global alignment marks")
    p.set_defaults(func=run_masks)


def _int_list(text, what):
    try:
        return [int(v) for v in text.split(",")]
    except ValueError:
        raise DoeError(f"--{what} must be comma-separated integers, got {text!r}") from None


def _float_list(text, what):
    try:
        vals = [float(v) for v in text.split(",")]
    except ValueError:
        raise DoeError(f"--{what} must be comma-separated numbers, got {text!r}") from None
    if not all(np.isfinite(vals)) or min(vals) <= 0:
        raise DoeError(f"--{what} must be positive, got {text!r}")
    return vals


def run_masks(args: argparse.Namespace) -> int:
    """Run ``doe masks``: write the verified GDS (and plate), preview and report."""
    from doedesign.cli.common import print_json
    from doedesign.design import Design

    from .element import write_element

    ensure_output_dir(args.out)  # before loading and exporting: a bad --out costs nothing
    depths = None if args.depths_nm is None else [d * 1e-9 for d in _float_list(args.depths_nm, "depths-nm")]
    report = write_element(
        Design.load(args.design), args.out, source=str(args.design), tone=args.tone, mirrored=args.mirror,
        depths_m=depths, layers=_int_list(args.layers, "layers"),
        etch_order=None if args.etch_order is None else _int_list(args.etch_order, "etch-order"),
        clear_aperture=None if args.clear_aperture_mm is None else args.clear_aperture_mm * 1e-3, oasis=args.oasis,
        plate=args.plate)
    summary = {k: report[k] for k in ("file", "file_size_bytes", "seconds", "verification")}
    if args.plate:
        summary["plate"] = {k: report["plate"][k] for k in ("file", "file_size_bytes", "dies", "seconds")}
    print_json(summary)
    return 0
