"""``doe inspect``: a summary of a design file or of any measurement file the readers know."""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from doedesign.cli.common import Number, print_json
from doedesign.design import Design
from metrology.formats import readers
from metrology.formats.plausibility import RANGES


__all__ = ["cmd_inspect", "inspect_file", "is_design_file", "is_psf_file", "register"]


def is_design_file(path: str | Path) -> bool:
    """True when ``path`` is a ``.npz`` with the design file's required fields."""
    path = Path(path)
    if path.suffix.lower() != ".npz" or not path.is_file():
        return False
    try:
        with np.load(path, allow_pickle=False) as npz:
            return {"height_m", "pitch_m", "metadata"} <= set(npz.files)
    except Exception:  # not a zip: the measurement readers report the problem
        return False


def is_psf_file(path: str | Path) -> bool:
    """True when ``path`` is a ``.npz`` with the PSF file's fields (``doe psf``)."""
    path = Path(path)
    if path.suffix.lower() != ".npz" or not path.is_file():
        return False
    try:
        with np.load(path, allow_pickle=False) as npz:
            return {"psf", "views", "wavelengths_m", "pixel_pitch_m"} <= set(npz.files)
    except Exception:  # not a zip: the measurement readers report the problem
        return False


def inspect_file(path: str | Path, pixel_size_m: float | None = None) -> dict:
    """Summary dictionary of a design, a PSF or a measurement file."""
    if is_design_file(path):
        return Design.load(path).summary()
    if is_psf_file(path):
        from doedesign.engine.result import PSFResult

        return PSFResult.load(path).summary()
    return readers.read_measurement(path, pixel_size_m=pixel_size_m).summary()


def cmd_inspect(args: argparse.Namespace) -> int:
    """Run ``doe inspect`` with the parsed options; return the exit code."""
    summary = inspect_file(args.file, args.pixel_size_m)
    if args.json:
        print_json(summary)
    else:
        for key, value in summary.items():
            if key != "metadata":
                print(f"{key:>20}: {value}")
    return 0




def register(sub: argparse._SubParsersAction) -> None:
    """Add ``doe inspect`` to the subcommands ``sub``."""
    p = sub.add_parser("inspect", help="summarize a design or measurement file",
                       description="Summarize a design (.npz) or a measurement: Zygo .dat, .datx, .xyz, .asc, "
                                   "Mx profile or Dektak .csv, .x3p, AFM and profiler formats (.nid, "
                                   ".spm, .di, .mdt, .plu, .sur, .opd, .opdx, .vk4, .gwy), .npy, "
                                   ".npz, .tif.")
    p.add_argument("file")
    p.add_argument("--json", action="store_true", help="print JSON")
    p.add_argument("--pixel-size-m", type=Number(float, 0, RANGES["pixel_size_m"].hi, lo_open=True, unit="m"), default=None,
                   help="lateral pixel size for files that do not carry one (.npy, TIFF without tags)")
    p.set_defaults(func=cmd_inspect)
