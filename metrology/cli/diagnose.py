"""``doe diagnose``: name the effects that separate a measurement from the ideal model.

Writes ``OUT/report.json`` (steps, noise floor, residuals, whether a structured residual is
left unexplained), ``OUT/residual_steps.png`` and ``OUT/breakdown.png``.
"""

from __future__ import annotations

import dataclasses
import logging
from pathlib import Path

import numpy as np

from doedesign.cli.common import Number, NumberList
from doedesign.errors import DoeError

log = logging.getLogger(__name__)


def register(subparsers):
    p = subparsers.add_parser(
        "diagnose", help="find and fit the effects explaining a measurement (heights or PSFs)",
        description="Compare a measured height map or PSF stack with the design's ideal model, name the "
                    "fabrication effects and measurement artefacts that explain the difference (each must "
                    "lower an information criterion with an effective sample count), fit their parameters "
                    "and report each step.")
    p.add_argument("--design", required=True, help="design file (.npz)")
    source = p.add_mutually_exclusive_group(required=True)
    source.add_argument("--measured", help="measured height map (any supported profilometer file)")
    source.add_argument("--measured-psf", help="measured PSF stack (.npz: psf, wavelengths_m, pixel_pitch_m, "
                                               "views when two, optional depth_m and axis_pixel)")
    p.add_argument("--out", required=True, help="output directory")
    p.add_argument("--effects", help="comma-separated candidate effects (default: all of the domain)")
    p.add_argument("--region-px", type=Number(int, 8, 4096, unit="px"), default=40,
                   help="design pixels per side of the window diagnosed (height maps; default 40)")
    p.add_argument("--upsample", type=Number(int, 1, 32), default=5,
                   help="model samples per design pixel per axis (height maps; default 5)")
    p.add_argument("--depths-nm", type=NumberList(Number(float, 0, 1e5, lo_open=True, unit="nm"), max_len=16), default=[75, 150, 300, 600],
                   help="etch depths the process was asked for, one per mask (the ideal model; "
                        "default 75,150,300,600 as in doe masks)")
    p.add_argument("--threshold", type=Number(float, 0, 1e6, lo_open=True), default=10.0,
                   help="criterion drop an effect must achieve to be named (default 10)")
    p.set_defaults(func=run)


def run(args):
    from doedesign.cli.common import print_json
    from doedesign.design import Design
    from doedesign.fileio import ensure_output_dir, output_run, write_json

    out = ensure_output_dir(args.out)
    design = Design.load(args.design)
    candidates = [c.strip() for c in args.effects.split(",") if c.strip()] if args.effects else None
    if args.region_px < 8:
        raise DoeError(f"--region-px must be at least 8, got {args.region_px}")
    if args.measured:
        diag, inputs = _heights(design, Path(args.measured), args, candidates)
    else:
        diag, inputs = _psf(design, Path(args.measured_psf), args, candidates)
    report = diag.to_dict()
    report["inputs"] = dict(design=str(args.design), **inputs)
    with output_run(out, "doe diagnose"):
        plots = diag.plot(out)
        report["plots"] = [p.name for p in plots]
        write_json(out / "report.json", report)
    print_json({"report": str(out / "report.json"), "effects_found": diag.named,
                "measurement_artefacts": report["measurement_artefacts"],
                "initial_residual_rms": diag.initial_residual_rms, "final_residual_rms": diag.final_residual_rms,
                "noise_floor": diag.noise_floor, "unexplained": diag.unexplained})
    return 0


def _heights(design, path, args, candidates):
    from metrology.matching.compare import compare_measurement, design_levels, shift_registration
    from metrology.diagnosis.diagnose import diagnose_heights
    from metrology.formats.readers import read_measurement
    from metrology.matching.register import resample_to_design

    if args.upsample < 1:
        raise DoeError(f"--upsample must be a positive integer, got {args.upsample}")
    meas = read_measurement(path)
    # The comparison's preparation: despiked, levelled jointly on the registered levels, and
    # registered with the edge fit's sub-pixel refinement of the whole pattern's position.
    comp = compare_measurement(meas, design)
    levelled = comp.height_m
    reg = shift_registration(comp.registration, comp.edge_fit.shift_m[0], design.pitch_m)
    # Diagnose the window of the design best covered by the measurement.
    coverage = np.isfinite(resample_to_design(levelled, reg, upsample=1))
    if coverage.sum() < 64:
        raise DoeError(f"{path}: the measurement covers only {int(coverage.sum())} design pixels after registration")
    rows, cols = np.nonzero(coverage)
    size = min(args.region_px, rows.max() - rows.min() + 1, cols.max() - cols.min() + 1)
    r0 = int(np.clip(round(rows.mean() - size / 2), 0, design.shape[0] - size))
    c0 = int(np.clip(round(cols.mean() - size / 2), 0, design.shape[1] - size))
    region = (r0, r0 + size, c0, c0 + size)
    fine = resample_to_design(levelled, reg, upsample=args.upsample, region=region)
    depths = [v * 1e-9 for v in args.depths_nm]
    diag = diagnose_heights(design_levels(design), design.pitch_m, fine, design.pitch_m / args.upsample,
                            region=region, region_px=size, depths_m=depths, candidates=candidates,
                            threshold=args.threshold)
    return diag, {"measured": str(path), "region_design_px": list(region), "upsample": args.upsample,
                  "registration_ncc": getattr(reg, "match_ncc", None), "nominal_depths_m": list(depths)}


def load_psf_stack(path):
    """Read a measured PSF stack ``.npz``.

    Returns
    -------
    dict with ``psf`` (views, wavelengths, rows, cols), ``views``, ``wavelengths_m``,
    ``pixel_pitch_m``, ``depth_m`` (None when absent) and ``axis_pixel`` (None when absent).
    """
    from doedesign.psf import read_psf_arrays

    data = read_psf_arrays(path, ("psf", "wavelengths_m", "pixel_pitch_m"), what="measured PSF stack")
    psf = np.asarray(data["psf"], dtype=float)
    wl = np.atleast_1d(np.asarray(data["wavelengths_m"], dtype=float))
    if psf.ndim == 5 and psf.shape[1] == 1:  # a PSFResult file of one source distance
        psf = psf[:, 0]
    if psf.ndim == 3:
        psf = psf[None]
    if psf.ndim != 4 or psf.shape[1] != wl.size:
        raise DoeError(f"{path}: psf must be (wavelengths, rows, cols) or (views, wavelengths, rows, cols) "
                       f"with {wl.size} wavelengths, got shape {psf.shape}")
    if np.any(~(wl > 100e-9)) or np.any(wl > 20e-6):
        raise DoeError(f"{path}: wavelengths_m must be in metres, got {wl.tolist()}")
    views = tuple(str(v) for v in data["views"]) if "views" in data else ("coded",)
    if len(views) != psf.shape[0]:
        raise DoeError(f"{path}: {psf.shape[0]} view(s) in psf but views lists {list(views)}")
    depth = float(data["depth_m"]) if "depth_m" in data else None
    axis = tuple(int(v) for v in data["axis_pixel"]) if "axis_pixel" in data else None
    return {"psf": psf, "views": views, "wavelengths_m": wl, "pixel_pitch_m": float(data["pixel_pitch_m"]),
            "depth_m": depth, "axis_pixel": axis}


def _psf(design, path, args, candidates):
    from doedesign.camera import Camera

    from metrology.diagnosis.diagnose import diagnose_psf

    stack = load_psf_stack(path)
    cam_dict = design.metadata.get("camera")
    camera = Camera.from_dict(cam_dict) if isinstance(cam_dict, dict) else Camera()
    rows, cols = stack["psf"].shape[-2:]
    axis = stack["axis_pixel"] or (rows // 2, cols // 2)
    camera = dataclasses.replace(camera, window_shape=(rows, cols), axis_pixel=axis,
                                 pixel_pitch_m=stack["pixel_pitch_m"])
    diag = diagnose_psf(design, camera, stack["psf"], stack["wavelengths_m"], views=stack["views"],
                        depth_m=stack["depth_m"], candidates=candidates, threshold=args.threshold)
    return diag, {"measured_psf": str(path), "camera": camera.to_dict(), "views": list(stack["views"])}
