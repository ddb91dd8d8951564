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
from .opc_element import PRINT_WINDOW_PX, default_print_region

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
    g = p.add_argument_group("print check (proximity printing through the aligner's gap)")
    g.add_argument("--gap-um", type=Number(float, 0, 200, lo_open=True, unit="um"), default=None,
                   help="mask-to-resist gap (um, up to 200); writes print_check.json and print_check.md: per mask "
                        "the printed against the drawn open area, the edge placement, the isolated pixels lost and "
                        "the one-pixel gaps bridged, and the field overlap of the printed element with the design")
    g.add_argument("--dose", type=Number(float, 0, 1e4, lo_open=True, unit="mJ/cm^2"), default=None,
                   help="exposure dose (mJ/cm^2; with --dose-to-clear): the resist clears where the image exceeds "
                        "dose-to-clear / dose of the open field")
    g.add_argument("--dose-to-clear", type=Number(float, 0, 1e4, lo_open=True, unit="mJ/cm^2"), default=None,
                   help="the resist's dose to clear an open field (mJ/cm^2, from its data sheet)")
    g.add_argument("--resist-threshold", type=Number(float, 0, 1, lo_open=True, hi_open=True), default=None,
                   help="clearing level as a fraction of the open field, instead of a dose (default: the level "
                        "that prints a long straight edge where it is drawn, about 0.25-0.3 through a gap)")
    g.add_argument("--collimation-deg", type=Number(float, 0, 10, unit="deg"), default=2.0,
                   help="illumination half-angle (deg, default 2)")
    g.add_argument("--resist-blur-um", type=Number(float, 0, 1, unit="um"), default=0.1,
                   help="resist blur sigma (um, default 0.1)")
    g.add_argument("--cr-undercut-um", type=Number(float, 0, 5, unit="um"), default=0.0,
                   help="lateral wet-etch undercut of the chromium mask (um, default 0)")
    g.add_argument("--print-window", default=None, metavar="ROW,COL,ROWS,COLS|all",
                   help=f"design pixels to check (row 0 at the top); default the central {PRINT_WINDOW_PX} x "
                        f"{PRINT_WINDOW_PX} px (the whole design when smaller); 'all' for the whole element")
    g.add_argument("--opc", action="store_true",
                   help="optical proximity correction (with --gap-um): write the masks pre-distorted on a sub-pixel "
                        "grid so that what prints through the gap matches the design (masks.opc); the print check "
                        "then reports the drawn and the corrected masks side by side")
    g.add_argument("--opc-method", choices=("density", "level-set"), default=None,
                   help="density (default): a density mask with the minimum feature's length scale (masks.opc_density), "
                        "polished by the level set; level-set: the level set alone, from the drawn masks")
    g.add_argument("--opc-iterations", type=Number(int, 1, 200), default=None,
                   help="OPC level-set steps (default 10 after the density stage, 20 alone; the iterate that prints "
                        "closest to the design is kept)")
    g.add_argument("--opc-min-feature-um", type=Number(float, 0.1, 10, unit="um"), default=None,
                   help="narrowest opening and chrome line the corrected masks may hold (um, default "
                        "1: the mask writer's resolution)")
    p.set_defaults(func=run_masks)


NO_LIMIT = "none"
# Bytes per fine cell of the print check (two surfaces, the printed masks, the aerial image's work).
PRINT_BYTES_PER_CELL = 64


class VertexLimit(Number):
    """``--max-vertices``: an integer >= :data:`~masks.grid.MIN_VERTICES`, or ``none`` (no limit)."""

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


def _print_region(text, shape):
    """``--print-window`` as a half-open (row0, row1, col0, col1) region of a design of ``shape``."""
    if text is not None and text.strip().lower() == "all":
        return (0, shape[0], 0, shape[1])
    if text is None:
        return default_print_region(shape)
    values = _int_list(text, "print-window")
    r0, c0, n_r, n_c = values if len(values) == 4 else (-1, -1, 0, 0)
    if n_r < 1 or n_c < 1 or r0 < 0 or c0 < 0 or r0 + n_r > shape[0] or c0 + n_c > shape[1]:
        raise DoeError(f"--print-window must be ROW,COL,ROWS,COLS inside the {shape[0]} x {shape[1]} px design, "
                       f"or all; got {text!r}")
    return (r0, r0 + n_r, c0, c0 + n_c)


def _print_check(args, design, depths):
    """The print check ``--gap-um`` asks for (None without it); refused whole before anything is written."""
    dose_given = (args.dose is not None, args.dose_to_clear is not None)
    opc_options = args.opc_iterations is not None or args.opc_min_feature_um is not None or args.opc_method is not None
    if opc_options and not args.opc:
        raise DoeError("--opc-method, --opc-iterations and --opc-min-feature-um need --opc")
    if args.gap_um is None:
        if any(dose_given) or args.resist_threshold is not None or args.print_window is not None or args.opc:
            raise DoeError("--dose, --dose-to-clear, --resist-threshold, --print-window and --opc need --gap-um")
        return None, None
    if any(dose_given) and not all(dose_given):
        raise DoeError("--dose and --dose-to-clear go together (the threshold is dose-to-clear / dose)")
    if all(dose_given) and args.resist_threshold is not None:
        raise DoeError("give a dose (--dose, --dose-to-clear) or --resist-threshold, not both")
    import math

    from doedesign.budget import check_memory
    from doedesign.levels import quantize_design

    from .corrected import MIN_FEATURE_M
    from .opc_element import check_opc_memory, correct_element, opc_settings, print_upsample
    from .print_check import in_place_threshold, print_check
    from .process import ProcessParams, proximity_optics
    from .proximity import threshold_for_dose

    levels, _ = quantize_design(design, None, args.design)
    region = _print_region(args.print_window, levels.shape)
    base = ProcessParams.ideal(n_masks=design.n_masks, depths_m=depths if depths is not None else design.etch_depths_m())
    params = base.copy(proximity_gap=args.gap_um * 1e-6, collimation_half_angle=math.radians(args.collimation_deg),
                       resist_blur=args.resist_blur_um * 1e-6, cr_undercut=args.cr_undercut_um * 1e-6)
    u = print_upsample(design.pitch_m, params, opc=args.opc)
    if args.opc:
        check_opc_memory(levels.shape, u, design.pitch_m, args.design)
    cells = (region[1] - region[0]) * (region[3] - region[2]) * u * u
    check_memory(PRINT_BYTES_PER_CELL * cells,
                 f"{args.design}: the print check of {region[1] - region[0]} x {region[3] - region[2]} px at "
                 f"{design.pitch_m / u * 1e6:.3g} um (a smaller --print-window)")
    if all(dose_given):
        threshold, how = threshold_for_dose(args.dose, args.dose_to_clear), "dose"
    elif args.resist_threshold is not None:
        threshold, how = args.resist_threshold, "resist threshold"
    else:
        threshold, how = in_place_threshold(proximity_optics(params), design.pitch_m / u), "in place for a long edge"
    params = params.copy(resist_threshold=threshold)
    check = print_check(levels, design.pitch_m, params, step_m=design.pitch_m / u, material=design.material,
                        region=region)
    corrected = None
    if args.opc:
        min_feature = MIN_FEATURE_M if args.opc_min_feature_um is None else args.opc_min_feature_um * 1e-6
        settings = opc_settings(design.pitch_m / u, min_feature, args.opc_method or "density", args.opc_iterations)
        check, corrected = correct_element(levels, design.pitch_m, params, u, settings, region,
                                           material=design.material, uncorrected=check)
    check["threshold_from"] = how
    if all(dose_given):
        check["dose_mj_cm2"], check["dose_to_clear_mj_cm2"] = args.dose, args.dose_to_clear
    return check, corrected


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
    design = Design.load(args.design)
    printed, corrected = _print_check(args, design, depths)  # before anything is written: a refusal leaves nothing
    report = write_element(
        design, args.out, source=str(args.design), tone=args.tone, mirrored=args.mirror,
        depths_m=depths, layers=None if args.layers is None else _int_list(args.layers, "layers"),
        etch_order=None if args.etch_order is None else _int_list(args.etch_order, "etch-order"),
        clear_aperture=None if args.clear_aperture_mm is None else args.clear_aperture_mm * 1e-3, formats=formats,
        max_vertices=max_vertices, plate=args.plate, print_check=printed, corrected_masks=corrected)
    summary = {k: report[k] for k in ("file", "file_size_bytes", "seconds", "verification", "layer_properties_file")}
    summary["files"] = [{k: f[k] for k in ("format", "file", "file_size_bytes", "max_vertices")} for f in report["files"]]
    if printed is not None:
        summary["print_check"] = {"file": "print_check.json", "field_overlap": printed["field_overlap"],
                                  "resist_threshold": printed["resist_threshold"]}
        if corrected is not None:
            summary["print_check"]["field_overlap_uncorrected"] = printed["uncorrected"]["field_overlap"]
    if args.plate:
        summary["plate"] = {k: report["plate"][k] for k in ("file", "file_size_bytes", "files", "dies", "seconds")}
    print_json(summary)
    return 0
