"""``doe masks``: design file -> verified GDSII and/or OASIS of the binary etch masks, KLayout
layer properties, preview, report."""

from __future__ import annotations

import argparse
import logging

from doedesign.cli.common import Number, NumberList
from doedesign.errors import DoeError
from doedesign.fileio import ensure_output_dir

from .effects import effect_spec
from .grid import GDS_VERTEX_CEILING, MAX_VERTICES, MIN_VERTICES, vertex_limits

__all__ = ["VertexLimit", "register", "run_masks"]

log = logging.getLogger(__name__)

# An etch deeper than the process model's plausible bound (5 um, about 60 level steps of a
# 16-level fused-silica DOE) is no DOE etch (a 1e300 nm "depth" passed verification as chrome),
# nor is one shallower than a few atomic layers.
MAX_ETCH_DEPTH_NM = effect_spec("etch_depth").params[0].upper * 1e9
MIN_ETCH_DEPTH_NM = 1.0


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add ``doe masks`` to the root command's subparsers."""
    p = subparsers.add_parser("masks", help="quantize, decompose into binary masks, write verified GDSII/OASIS",
                              description="Write DIR/<name>.gds and/or DIR/<name>.oas (one layer per mask; design "
                                          "rows row-major, row 0 at the top, run toward decreasing y), "
                                          "DIR/<name>.lyp (KLayout layer names and colours), DIR/masks.png and "
                                          "DIR/report.json; every layout file is read back and verified pixel by "
                                          "pixel.")
    p.add_argument("design", help="design .npz")
    p.add_argument("--out", required=True, help="output directory")
    p.add_argument("--tone", choices=("dark", "clear"), default="dark",
                   help="dark: draw the etched (open) areas (default); clear: draw the chrome")
    p.add_argument("--mirror", action="store_true", help="mirror x -> -x (contact printing)")
    p.add_argument("--depths-nm", default=None,
                   type=NumberList(Number(float, MIN_ETCH_DEPTH_NM, MAX_ETCH_DEPTH_NM, unit="nm"), max_len=16),
                   help="etch depth per mask, comma separated, one per mask of the design's log2(n_levels) "
                        "(default: the design's mask_depths_m, else 2**j times the level step; each "
                        f"in [{MIN_ETCH_DEPTH_NM:g}, {MAX_ETCH_DEPTH_NM:g}] nm)")
    p.add_argument("--layers", default=None, help="GDS layer per mask (default 1..M for the design's M masks: "
                                                  "1,2,3,4 for 16 levels, 1 for a binary element)")
    p.add_argument("--etch-order", default=None, help="mask index etched in each step, e.g. 3,2,1,0")
    p.add_argument("--clear-aperture-mm", type=Number(float, 0, 1000, lo_open=True, unit="mm"), default=None,
                   help="clear circle diameter (default: camera aperture from the metadata)")
    p.add_argument("--format", choices=("gds", "oasis", "both"), default="gds", dest="layout_format",
                   help="layout file: GDSII <name>.gds (default), OASIS <name>.oas (the same verified geometry, "
                        "14-55x smaller on 1600 px elements), or both")
    p.add_argument("--max-vertices", type=VertexLimit(), default=None, metavar="N|none",
                   help=f"largest vertex count of one polygon in every file written; larger ones are fractured "
                        f"into whole pixel rows (integer >= {MIN_VERTICES}, at most {GDS_VERTEX_CEILING} for GDSII; "
                        f"'none': no limit, OASIS only). Default {MAX_VERTICES} for GDSII, none for OASIS")
    p.add_argument("--plate", action="store_true",
                   help="also write <name>_plate.gds (.oas per --format, and its .lyp): a full 4-inch wafer "
                        "of this die by array references, with global alignment marks")
    p.set_defaults(func=run_masks)


NO_LIMIT = "none"


class VertexLimit(Number):
    """``--max-vertices``: an integer >= :data:`MIN_VERTICES`, or ``none`` (no limit)."""

    def __init__(self) -> None:
        super().__init__(int, MIN_VERTICES)

    def describe(self) -> str:
        return super().describe() + " or none"

    def __call__(self, text):
        return NO_LIMIT if str(text).strip().lower() == "none" else super().__call__(text)


def _int_list(text, what):
    try:
        return [int(v) for v in text.split(",")]
    except ValueError:
        raise DoeError(f"--{what} must be comma-separated integers, got {text!r}") from None


def run_masks(args: argparse.Namespace) -> int:
    """Run ``doe masks``: write the verified GDS (and plate), preview and report."""
    from doedesign.budget import check_memory, mask_export_bytes
    from doedesign.cli.common import print_json
    from doedesign.design import Design
    from doedesign.fileio import npz_shape

    from .element import write_element

    formats = ("gds", "oasis") if args.layout_format == "both" else (args.layout_format,)
    max_vertices = {None: "default", NO_LIMIT: None}.get(args.max_vertices, args.max_vertices)
    vertex_limits(formats, max_vertices)  # a limit GDSII cannot hold costs nothing
    ensure_output_dir(args.out)  # before loading and exporting: a bad --out costs nothing
    depths = None if args.depths_nm is None else [d * 1e-9 for d in args.depths_nm]
    shape = npz_shape(args.design, "height_m")  # refused from the header, before the map is inflated
    if shape is not None and len(shape) == 2:
        check_memory(mask_export_bytes(shape), f"{args.design}: the masks of a {shape[0]} x {shape[1]} px design")
    report = write_element(
        Design.load(args.design), args.out, source=str(args.design), tone=args.tone, mirrored=args.mirror,
        depths_m=depths, layers=None if args.layers is None else _int_list(args.layers, "layers"),
        etch_order=None if args.etch_order is None else _int_list(args.etch_order, "etch-order"),
        clear_aperture=None if args.clear_aperture_mm is None else args.clear_aperture_mm * 1e-3, formats=formats,
        max_vertices=max_vertices, plate=args.plate)
    summary = {k: report[k] for k in ("file", "file_size_bytes", "seconds", "verification", "layer_properties_file")}
    summary["files"] = [{k: f[k] for k in ("format", "file", "file_size_bytes", "max_vertices")} for f in report["files"]]
    if args.plate:
        summary["plate"] = {k: report["plate"][k] for k in ("file", "file_size_bytes", "files", "dies", "seconds")}
    print_json(summary)
    return 0
