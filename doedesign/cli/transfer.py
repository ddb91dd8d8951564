"""``doe import`` (a phase or height map made elsewhere -> a design file) and ``doe export``
(a design's phase, height or levels -> a map for other tools)."""

from __future__ import annotations

import argparse

from .common import Number

__all__ = ["register", "run_export", "run_import"]

CONVENTION = ("Row 0 of every map is the top row (of an image, of a CSV's first line); the array is centred on the "
              "optical axis. Phase: radians, more glass = more phase. Height: z up, 0 at the unetched top, negative "
              "where etched (--height-sign depth: etch depth, positive into the glass).")


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add ``doe import`` and ``doe export`` to the root command's subparsers."""
    p = subparsers.add_parser("import", help="a phase or height map (.npy .npz .mat .tif .png .csv .txt .h5) -> design file",
                              description="Quantize a phase or height map made elsewhere into a design file that "
                                          "every command takes. " + CONVENTION)
    p.add_argument("source", help="the map; a 1-D array is a radial profile (r = 0 first, one pitch apart)")
    p.add_argument("--out", required=True, help="design file to write (.npz)")
    p.add_argument("--pitch-um", type=Number(float, 0, 1000, lo_open=True, unit="um"), default=None,
                   help="pixel pitch (um), required")
    p.add_argument("--phase-at-nm", type=Number(float, 100, 20000, unit="nm"), default=None,
                   help="the map is phase in radians at this wavelength (nm); also the design wavelength")
    p.add_argument("--height-unit", choices=("m", "um", "nm"), default=None, help="the map is height in this unit")
    p.add_argument("--height-sign", choices=("z_up", "depth"), default="z_up",
                   help="z_up: 0 top, negative etched (default); depth: etch depth, positive")
    p.add_argument("--wrapped", action="store_true", help="the phase is wrapped (refused when it spans over 2 pi)")
    p.add_argument("--full-scale-rad", type=Number(float, 0, 1e4, lo_open=True, unit="rad"), default=None,
                   help="8/16-bit image: the full grey scale (256 or 65536 counts) stands for R radians")
    p.add_argument("--levels", type=Number(int, 2, 32), default=16, help="level count: 2, 4, 8, 16 or 32 (default 16)")
    p.add_argument("--material", default="fused_silica", help="material (default fused_silica)")
    p.add_argument("--design-wavelength-nm", type=Number(float, 100, 20000, unit="nm"), default=None,
                   help="design wavelength (default --phase-at-nm, else 550)")
    p.add_argument("--aperture", default=None, help="mask file (nonzero = clear); NaN pixels are outside too")
    p.add_argument("--array", default=None, help="array name in a .npz / .mat / .h5 holding several")
    p.set_defaults(func=run_import)
    e = subparsers.add_parser("export", help="a design's phase, height or levels -> .npy .npz .mat .tif .png .csv .h5",
                              description="Write a design's phase (rad), height (m) or levels for other tools. "
                                          + CONVENTION)
    e.add_argument("design", help="design .npz")
    e.add_argument("--what", choices=("phase", "height", "levels"), required=True)
    e.add_argument("--out", required=True, help="file to write; the format follows its extension")
    e.add_argument("--wavelength-nm", type=Number(float, 100, 20000, unit="nm"), default=None,
                   help="phase at this wavelength (default the design wavelength)")
    e.set_defaults(func=run_export)


def run_import(args: argparse.Namespace) -> int:
    """Run ``doe import`` with the parsed options; return the exit code."""
    from ..fileio import ensure_output_file
    from ..importer import import_design
    from .common import print_json

    ensure_output_file(args.out)
    design = import_design(args.source, pitch_m=None if args.pitch_um is None else args.pitch_um * 1e-6,
                           phase_at_m=None if args.phase_at_nm is None else args.phase_at_nm * 1e-9,
                           height_unit=args.height_unit, sign=args.height_sign, full_scale_rad=args.full_scale_rad,
                           wrapped=args.wrapped, n_levels=args.levels, material=args.material,
                           design_wavelength_m=None if args.design_wavelength_nm is None
                           else args.design_wavelength_nm * 1e-9, aperture=args.aperture, array=args.array)
    design.save(args.out)
    print_json({"design": str(args.out), "shape": list(design.shape), "n_levels": design.n_levels,
                "quantization": design.metadata["import"]["quantization"]})
    return 0


def run_export(args: argparse.Namespace) -> int:
    """Run ``doe export`` with the parsed options; return the exit code."""
    from ..design import Design
    from ..fileio import ensure_output_file
    from ..importer import export_map
    from .common import print_json

    ensure_output_file(args.out)
    out = export_map(Design.load(args.design), args.what, args.out,
                     None if args.wavelength_nm is None else args.wavelength_nm * 1e-9)
    print_json({"file": str(out), "what": args.what})
    return 0
