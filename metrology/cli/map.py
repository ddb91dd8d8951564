"""``doe map``: a whole-element height map diagnosed tile by tile on Dask, maps and models.

Writes ``OUT/tiles.jsonl`` (one tile per line, as they finish; a rerun resumes), ``OUT/report.json``,
``OUT/report.md``, ``overlay.png`` and ``depth_bias.png``.
"""

from __future__ import annotations

import argparse

from doedesign.cli.common import Number, NumberList

__all__ = ["register", "run"]


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add ``doe map`` to ``subparsers``."""
    p = subparsers.add_parser("map", help="diagnose a whole-element height map in tiles; overlay and depth models",
                              description="Cut a height map on the design grid into overlapping tiles, diagnose each "
                                          "(as doe diagnose --frame design) on Dask, and fit overlay (translation, "
                                          "rotation, magnification, orthogonality) and etch-depth (plane + radial) "
                                          "models to the maps.")
    p.add_argument("--design", required=True, help="design file (.npz)")
    p.add_argument("--measured", required=True, help="height map on the design grid: .npy or .h5 (dataset height_m), "
                                                     "row 0 at the top, pixel (0, 0) on design pixel (0, 0)")
    p.add_argument("--upsample", type=Number(int, 1, 32), default=2, help="map pixels per design pixel (default 2)")
    p.add_argument("--out", required=True, help="output folder (resumed when it holds tiles.jsonl)")
    p.add_argument("--tile-px", type=Number(int, 12, 4096, unit="px"), default=40,
                   help="design pixels per tile side (default 40)")
    p.add_argument("--overlap-px", type=Number(int, 0, 4095, unit="px"), default=8,
                   help="design pixels shared by neighbouring tiles (default 8)")
    p.add_argument("--depths-nm", type=NumberList(Number(float, 0, 1e5, lo_open=True, unit="nm"), max_len=16),
                   default=[75, 150, 300, 600], help="nominal etch depths per mask (default 75,150,300,600)")
    p.add_argument("--effects", help="comma-separated candidate effects of the selection (default: all)")
    p.add_argument("--threshold", type=Number(float, 0, 1e6, lo_open=True), default=10.0,
                   help="criterion drop an effect must achieve to be named in a tile (default 10)")
    p.add_argument("--scheduler", default="processes",
                   help="processes (default, a LocalCluster), threads, inline (no dask) or tcp://HOST:PORT")
    p.add_argument("--workers", type=Number(int, 1, 4096), help="local workers (default: the machine's cores)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Run ``doe map`` with the parsed options; return the exit code."""
    from doedesign.cli.common import print_json
    from doedesign.design import Design
    from doedesign.fileio import ensure_output_dir, output_run
    from doedesign.levels import design_levels
    from masks.tolerance.scheduler import parse_address
    from metrology.cli.diagnose import parse_effects
    from metrology.diagnosis.map_report import assemble, write_report
    from metrology.diagnosis.tiles_map import open_map, run_map

    out = ensure_output_dir(args.out)
    if "://" in args.scheduler:
        parse_address(args.scheduler)
    design = Design.load(args.design)
    open_map(args.measured)
    candidates = parse_effects(args.effects, "height")
    levels = design_levels(design)
    depths = [v * 1e-9 for v in args.depths_nm]
    with output_run(out, "doe map", keep_partial=True):
        tiles = run_map(levels, design.pitch_m, args.measured, args.upsample, out, tile_px=args.tile_px,
                        overlap_px=args.overlap_px, depths_m=depths, candidates=candidates, threshold=args.threshold,
                        scheduler=args.scheduler, workers=args.workers)
        result = assemble(tiles, levels.shape, design.pitch_m)
        write_report(result, out, {"design": str(args.design), "measured": str(args.measured),
                                   "upsample": args.upsample, "tile_px": args.tile_px, "overlap_px": args.overlap_px,
                                   "nominal_depths_m": depths})
    print_json({"report": str(out / "report.json"), "tiles": result["n_tiles"], "diagnosed": result["n_diagnosed"],
                "named_terms": result.get("named_terms", [])})
    return 0
