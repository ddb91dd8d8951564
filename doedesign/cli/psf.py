"""``doe psf``: the coded and uncoded PSFs of a design file."""

from __future__ import annotations

import argparse
import logging

import numpy as np

from ..budget import check_memory, psf_bytes
from ..design import Design
from ..engine.psf import DEFAULT_THREADS, PSFEngine, parse_wavelengths_nm
from ..progress import Progress
from ..camera import DEFAULT_SURROUND, SURROUNDS, describe_surround, resolve_surround
from .common import Number, NumberList, add_camera_options, add_device_option, camera_from_args

__all__ = ["cmd_psf", "register"]

log = logging.getLogger(__name__)


def cmd_psf(args: argparse.Namespace) -> int:
    """Run ``doe psf`` with the parsed options; return the exit code."""
    from ..fileio import ensure_output_file
    from ..plots import psf_figure, save

    ensure_output_file(args.out)
    if args.png:
        ensure_output_file(args.png, "--png")
    design = Design.load(args.design)
    camera = camera_from_args(args)
    wavelengths = parse_wavelengths_nm(args.wavelengths_nm)
    depths = args.depth_m
    n_depths = 1 if depths is None else len(depths)
    check_memory(psf_bytes(camera, design.pitch_m, design.shape, wavelengths.size, n_depths, args.doe_oversample,
                           threads=args.threads),
                 f"{args.design}: the PSFs of this {design.shape[0]} x {design.shape[1]} px design "
                 f"({design.pitch_m:.3g} m pitch) on a {args.window} px window")
    surround, origin = resolve_surround(args.surround, design.metadata, str(args.design))
    engine = PSFEngine(camera, design.pitch_m, design.shape, design.material, wavelengths, depths,
                       doe_oversample=args.doe_oversample, aperture=design.aperture, device=args.device,
                       surround=surround)
    log.info("surround: %s (%s): %s; the coded view's clear region passes %.4g of its light", surround, origin,
             describe_surround(surround), engine.clear_fraction)
    steps = 2 * engine.depths_m.size * wavelengths.size
    with Progress(steps, desc="psf") as bar:
        result = engine.psf(design.height_m, progress=bar, threads=args.threads)
    result.save(args.out)
    if args.png:
        save(psf_figure(result, title=design.name), args.png)
    for vi, view in enumerate(result.views):
        log.info("%s view: energy in window %s", view, np.round(result.energy_in_window[vi].ravel(), 4))
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    """Add ``doe psf`` to the subcommands ``sub``."""
    p = sub.add_parser("psf", help="coded and uncoded PSFs of a design",
                       description="Compute the split-aperture PSFs of a design on the sensor window. Writes psf "
                                   "(views, depths, wavelengths, rows, cols): fraction of each view's light per "
                                   "sensor pixel, row 0 at the top, axis at the window centre.")
    p.add_argument("design")
    p.add_argument("--wavelengths-nm", default="486,589,656", help="list (486,589,656) or range start:stop:step (400:700:10)")
    p.add_argument("--depth-m", default=None, type=NumberList(Number(float, 0, lo_open=True, allow_inf=True, unit="m")), help="point-source distance(s), comma separated (default: in focus)")
    p.add_argument("--doe-oversample", type=Number(int, 1, 16), default=1, help="pupil samples per DOE pixel for strong defocus")
    p.add_argument("--threads", type=Number(int, 1, 64), default=DEFAULT_THREADS,
                   help=f"wavelengths computed side by side (default {DEFAULT_THREADS}: the cores, at most 4)")
    p.add_argument("--surround", choices=SURROUNDS, default=None,
                   help="what surrounds the design inside the lens aperture: open (unetched glass), opaque "
                        "(chrome: only the design's clear region passes light) or repeat (the design tiled); "
                        f"default the design file's metadata surround, else {DEFAULT_SURROUND} (a design "
                        "smaller than the aperture then passes the light of the open rest even where its "
                        "aperture is all closed). Written into the PSF file")
    p.add_argument("--out", required=True, help="output PSF .npz")
    p.add_argument("--png", help="optional PNG montage")
    add_device_option(p)
    add_camera_options(p)
    p.set_defaults(func=cmd_psf)
