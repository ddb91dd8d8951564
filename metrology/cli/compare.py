"""``doe compare``: a profilometer measurement against its design.

Writes into ``--out`` the report and figures of :mod:`metrology.matching.report`.
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

from doedesign.cli.common import Number
from metrology.formats.plausibility import RANGES

log = logging.getLogger(__name__)

__all__ = ["register", "run_compare"]


def register(sub: argparse._SubParsersAction) -> None:
    """Add ``doe compare`` to the subcommands ``sub``."""
    p = sub.add_parser("compare", help="compare a profilometer measurement with its design",
                       description="Level, register and compare a measurement with its design; etch depths, "
                                   "overlay and linewidth bias are fitted in the camera's own pixels (objective "
                                   "blur, pixel-area integration and placement as nuisances, the data never "
                                   "resampled); write report.json, levels.png, error_map.png, masks.png, "
                                   "psf.png/psf.npz and surface3d.png.")
    p.add_argument("measurement", help="height map (.dat, .datx, .xyz, .asc, .npz, .npy, .tif)")
    p.add_argument("--design", required=True, help="design .npz")
    p.add_argument("--out", required=True, help="output directory")
    p.add_argument("--pixel-size-um", type=Number(float, 0, RANGES["pixel_size_m"].hi * 1e6, lo_open=True, unit="um"),
                   default=None,
                   help="measurement pixel size (um) when the file has none or it is wrong (a starting value: "
                        "registration measures it against the DOE pitch)")
    p.add_argument("--wavelengths-nm", default=None,
                   help="PSF wavelengths: list or start:stop:step (default: those of the design's target, on "
                        "which its figure of merit is counted; 486,589,656 when it names none)")
    p.add_argument("--psf-oversample", type=Number(int, 1, 8), default=1,
                   help="PSF samples per DOE pixel per axis: 1 is fast (about 20 s for a 1600-pixel aperture) "
                        "but averages mask slivers over whole DOE pixels; 2 resolves slivers of half a pixel "
                        "at 2-3x the time and memory")
    p.add_argument("--no-psf", action="store_true", help="skip the PSF comparison")
    p.add_argument("--no-render", action="store_true", help="skip the 3-D rendering")
    p.add_argument("--x3p", action="store_true",
                   help="also write levelled.x3p and residual.x3p (ISO 25178-72) into --out")
    p.add_argument("--force", action="store_true",
                   help="compare even when the field does not show the design (another design, off the element, "
                        "turned by a quarter turn)")
    p.add_argument("--instrument", metavar="FILE.json",
                   help="the profilometer's calibrated lateral transfer ('doe calibrate instrument'), held fixed, "
                        "and its height scale, divided out of the measured heights "
                        "in the camera-frame fit (default: its blur fitted)")
    p.set_defaults(func=run_compare)


def run_compare(args: argparse.Namespace) -> int:
    """Run ``doe compare`` on one BLAS thread (:func:`metrology.diagnosis.parallel.one_thread`), so
    that its fits do not depend on the machine's core count."""
    from metrology.diagnosis.parallel import one_thread

    with one_thread():
        return _run_compare(args)


def _run_compare(args: argparse.Namespace) -> int:
    from doedesign.budget import check_memory, measurement_bytes
    from doedesign.cli.common import print_json
    from doedesign.design import Design
    from doedesign.engine.psf import parse_wavelengths_nm
    from doedesign.fileio import ensure_output_dir
    from metrology.formats.readers import read_measurement
    from metrology.matching.report import write_comparison

    from metrology.calibration.instrument import apply_calibration, read_calibration

    cal = read_calibration(args.instrument) if args.instrument else None
    transfer = cal.transfer if cal is not None else None
    ensure_output_dir(args.out)  # before any work: a bad --out costs nothing
    design = Design.load(args.design)
    pixel = args.pixel_size_um * 1e-6 if args.pixel_size_um is not None else None
    meas = read_measurement(args.measurement, pixel_size_m=pixel).square_pixels()
    rows, cols = meas.height_m.shape
    check_memory(measurement_bytes((rows, cols)), f"{args.measurement}: comparing this {rows} x {cols} px field")
    meas = apply_calibration(meas, cal, str(args.measurement))
    report = write_comparison(meas, design, args.out, measurement_source=str(args.measurement),
                              design_source=str(args.design),
                              wavelengths_m=parse_wavelengths_nm(args.wavelengths_nm) if args.wavelengths_nm else None,
                              psf_oversample=args.psf_oversample, psf=not args.no_psf, render=not args.no_render,
                              force=args.force, transfer=transfer, x3p=args.x3p,
                              batwing=cal.batwing if cal is not None else None)
    print_json({k: report[k] for k in ("etch_depths_nm", "overlay_um", "linewidth_bias_um",
                                       "height_error_rms_nm", "render3d")}
               | {"report": str(Path(args.out) / "report.json")})
    return 0
