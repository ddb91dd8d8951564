"""Helpers shared by every package's ``doe`` subcommands: JSON on stdout and the camera
options. They sit at the bottom of the chain so that masks and metrology commands can use
them without reaching into the root command.
"""

from __future__ import annotations

import argparse
import math
import sys
from typing import Any

from ..camera import MAX_WINDOW_PX, Camera
from ..fileio import dumps_json

__all__ = ["add_camera_options", "camera_from_args", "print_json", "Number", "NumberList", "MAX_WINDOW_PX"]


class Number:
    """An argparse ``type``: a finite number of ``kind`` within [lo, hi] (NaN always refused).

    Parameters
    ----------
    kind : type
        ``int`` or ``float``.
    lo, hi : float, optional
        Inclusive bounds (``lo_open`` / ``hi_open`` make them exclusive, e.g. "positive").
    allow_inf : bool
        Accept ``inf`` (a focus distance at infinity).
    unit : str
        Said in the message.

    Every numeric option of every command uses this type, so a zero, a NaN or an absurd
    size is refused by argparse as one line (exit status 2) before any work starts.
    """

    def __init__(self, kind: type = float, lo: float | None = None, hi: float | None = None, lo_open: bool = False,
                 allow_inf: bool = False, unit: str = "", hi_open: bool = False) -> None:
        self.kind, self.lo, self.hi, self.lo_open, self.allow_inf, self.unit = kind, lo, hi, lo_open, allow_inf, unit
        self.hi_open = hi_open
        self.__name__ = kind.__name__

    def describe(self) -> str:
        parts = []
        if self.lo is not None:
            parts.append(f"{'>' if self.lo_open else '>='} {self.lo:g}")
        if self.hi is not None:
            parts.append(f"{'<' if self.hi_open else '<='} {self.hi:g}")
        what = "an integer" if self.kind is int else "a number"
        return f"{what} {' and '.join(parts)}{' ' + self.unit if self.unit else ''}".rstrip()

    def __call__(self, text):
        try:
            value = float(text) if self.kind is float else int(str(text).strip())
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not {self.describe()}") from None
        if math.isnan(value) or (math.isinf(value) and not self.allow_inf):
            raise argparse.ArgumentTypeError(f"{text!r} is not {self.describe()}")
        too_low = self.lo is not None and (value <= self.lo if self.lo_open else value < self.lo)
        too_high = (self.hi is not None and (value >= self.hi if self.hi_open else value > self.hi)
                    and not (self.allow_inf and math.isinf(value)))
        if too_low or too_high:
            raise argparse.ArgumentTypeError(f"{text} is out of range: need {self.describe()}")
        return value


class NumberList:
    """An argparse ``type``: comma-separated numbers, each checked by ``item`` (a :class:`Number`)."""

    def __init__(self, item: Number, max_len: int = 1000) -> None:
        self.item, self.max_len = item, max_len
        self.__name__ = "list"

    def __call__(self, text):
        parts = [v for v in str(text).split(",") if v.strip()]
        if not parts or len(parts) > self.max_len:
            raise argparse.ArgumentTypeError(f"{text!r}: give 1 to {self.max_len} comma-separated values, "
                                             f"each {self.item.describe()}")
        return [self.item(v) for v in parts]


def print_json(obj: Any) -> None:
    """Print ``obj`` as strict JSON on stdout (:func:`doedesign.fileio.dumps_json`)."""
    sys.stdout.write(dumps_json(obj) + "\n")


def add_device_option(parser: argparse.ArgumentParser) -> None:
    """``--device cpu|gpu|auto`` (:func:`doedesign.engine.backend.select_backend`)."""
    from ..engine.backend import DEVICES

    parser.add_argument("--device", choices=DEVICES, default="auto",
                        help="where PSFs and gradients are computed: gpu (CuPy), cpu, or auto (the GPU when "
                             "CuPy finds a usable one, else the CPU; default)")


def add_camera_options(parser: argparse.ArgumentParser) -> None:
    """Camera options shared by the commands that simulate PSFs."""
    g = parser.add_argument_group("camera (defaults: the seed camera)")
    g.add_argument("--side", choices=("left", "right", "full"), default="left",
                   help="half of the aperture carrying the DOE (default left)")
    g.add_argument("--aperture-mm", type=Number(float, 0, 1000, unit="mm"), default=8.64, help="clear aperture diameter (mm); 0 = square pupil on the design grid")
    g.add_argument("--focus-m", type=Number(float, 0, lo_open=True, allow_inf=True, unit="m"), default=5.0, help="distance the lens is focused at (m); inf allowed")
    g.add_argument("--window", type=Number(int, 8, MAX_WINDOW_PX, unit="px"), default=512, help="sensor window size in pixels (square, axis at the centre)")


def camera_from_args(args: argparse.Namespace) -> Camera:
    """The :class:`~doedesign.camera.Camera` the options of :func:`add_camera_options` describe."""
    window = int(args.window)
    return Camera(aperture_diameter_m=None if args.aperture_mm == 0 else args.aperture_mm * 1e-3,
                  focus_distance_m=float(args.focus_m), window_shape=(window, window),
                  axis_pixel=(window // 2, window // 2), doe_side=args.side)
