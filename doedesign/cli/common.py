"""Helpers shared by every package's ``doe`` subcommands: JSON on stdout and the camera
options. They sit at the bottom of the chain so that masks and metrology commands can use
them without reaching into the root command.
"""

from __future__ import annotations

import sys

from ..camera import Camera
from ..fileio import dumps_json

__all__ = ["add_camera_options", "camera_from_args", "print_json"]


def print_json(obj) -> None:
    """Print ``obj`` as strict JSON on stdout (:func:`doedesign.fileio.dumps_json`)."""
    sys.stdout.write(dumps_json(obj) + "\n")


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
