"""``doe inspect`` and ``doe psf``."""

from __future__ import annotations

import importlib
import logging
from pathlib import Path

import numpy as np

from .camera import Camera
from .design import Design
from .errors import DoeError
from .progress import Progress
from .psf import PSFEngine, parse_wavelengths_nm

log = logging.getLogger(__name__)


def add_camera_options(parser):
    """Camera options shared by the commands that simulate PSFs."""
    g = parser.add_argument_group("camera (defaults: the seed camera)")
    g.add_argument("--side", choices=("left", "right", "full"), default="left",
                   help="half of the aperture carrying the DOE (default left)")
    g.add_argument("--aperture-mm", type=float, default=8.64, help="clear aperture diameter (mm); 0 = square pupil on the design grid")
    g.add_argument("--focus-m", type=float, default=5.0, help="distance the lens is focused at (m); inf allowed")
    g.add_argument("--window", type=int, default=512, help="sensor window size in pixels (square, axis at the centre)")


def camera_from_args(args):
    window = int(args.window)
    return Camera(aperture_diameter_m=None if args.aperture_mm == 0 else args.aperture_mm * 1e-3,
                  focus_distance_m=float(args.focus_m), window_shape=(window, window),
                  axis_pixel=(window // 2, window // 2), doe_side=args.side)


def is_design_file(path):
    """True when ``path`` is a ``.npz`` with the design file's required fields."""
    path = Path(path)
    if path.suffix.lower() != ".npz" or not path.is_file():
        return False
    try:
        with np.load(path, allow_pickle=False) as npz:
            return {"height_m", "pitch_m", "metadata"} <= set(npz.files)
    except Exception:  # not a zip: the measurement readers report the problem
        return False


def inspect_file(path, pixel_size_m=None):
    """Summary dictionary of a design or a measurement file."""
    if is_design_file(path):
        return Design.load(path).summary()
    try:
        readers = importlib.import_module("metrology.readers")
    except ModuleNotFoundError:
        raise DoeError(f"{path}: not a design file, and no measurement readers are installed") from None
    return readers.read_measurement(path, pixel_size_m=pixel_size_m).summary()


def cmd_inspect(args):
    from .cli import print_json

    summary = inspect_file(args.file, args.pixel_size_m)
    if args.json:
        print_json(summary)
    else:
        for key, value in summary.items():
            if key != "metadata":
                print(f"{key:>20}: {value}")
    return 0


def cmd_psf(args):
    from .plots import psf_figure, save

    design = Design.load(args.design)
    camera = camera_from_args(args)
    wavelengths = parse_wavelengths_nm(args.wavelengths_nm)
    depths = [float(v) for v in str(args.depth_m).split(",")] if args.depth_m else None
    engine = PSFEngine(camera, design.pitch_m, design.shape, design.material, wavelengths, depths,
                       doe_oversample=args.doe_oversample)
    steps = 2 * engine.depths_m.size * wavelengths.size
    with Progress(steps, desc="psf") as bar:
        result = engine.psf(design.height_m, progress=bar)
    result.save(args.out)
    if args.png:
        save(psf_figure(result, title=design.name), args.png)
    for vi, view in enumerate(result.views):
        log.info("%s view: energy in window %s", view, np.round(result.energy_in_window[vi].ravel(), 4))
    return 0


def register(sub):
    p = sub.add_parser("inspect", help="summarize a design or measurement file",
                       description="Summarize a design (.npz) or a profilometer measurement (.dat, .datx, .xyz, "
                                   ".asc, .csv, .npy, .npz, .tif).")
    p.add_argument("file")
    p.add_argument("--json", action="store_true", help="print JSON")
    p.add_argument("--pixel-size-m", type=float, default=None,
                   help="lateral pixel size for files that do not carry one (.npy, TIFF without tags)")
    p.set_defaults(func=cmd_inspect)

    p = sub.add_parser("psf", help="coded and uncoded PSFs of a design",
                       description="Compute the split-aperture PSFs of a design on the sensor window. Writes psf "
                                   "(views, depths, wavelengths, rows, cols): fraction of each view's light per "
                                   "sensor pixel, row 0 at the top, axis at the window centre.")
    p.add_argument("design")
    p.add_argument("--wavelengths-nm", default="486,589,656", help="list (486,589,656) or range start:stop:step (400:700:10)")
    p.add_argument("--depth-m", default=None, help="point-source distance(s), comma separated (default: in focus)")
    p.add_argument("--doe-oversample", type=int, default=1, help="pupil samples per DOE pixel for strong defocus")
    p.add_argument("--out", required=True, help="output PSF .npz")
    p.add_argument("--png", help="optional PNG montage")
    add_camera_options(p)
    p.set_defaults(func=cmd_psf)
