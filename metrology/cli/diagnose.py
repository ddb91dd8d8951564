"""``doe diagnose``: name the effects that separate a measurement from the ideal model.

Writes ``OUT/report.json`` (steps, noise floor, residuals, whether a structured residual is
left unexplained; its ``inputs`` identify the design: file and level-map sha256, shape, pitch),
``OUT/residual_steps.png`` and ``OUT/breakdown.png``.

No default time limit or CPU budget: what is tried and named depends only on the file and the
options. ``--wall-limit-s`` and ``--cpu-budget-s`` are a user's opt-in limits; a diagnosis one of
them ended is written whole, says ``INCOMPLETE`` in the first line of its summary with the
candidates not tried, and the command exits with :data:`EXIT_INCOMPLETE`.
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
from pathlib import Path

from doedesign.cli.common import Number, NumberList, add_device_option

log = logging.getLogger(__name__)
#: Exit status of a diagnosis a user's limit ended (its report written whole, marked INCOMPLETE):
#: not 0 (a finished diagnosis) and not 2 (bad input, nothing written).
EXIT_INCOMPLETE = 3

__all__ = ["EXIT_INCOMPLETE", "load_effects_file", "parse_effects", "register", "run"]


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add ``doe diagnose`` to ``subparsers``."""
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
    p.add_argument("--effects-file", action="append", default=[], metavar="FILE.py",
                   help="Python file that registers user effects (metrology.diagnosis.register_effect); "
                        "they join the candidates (repeatable)")
    p.add_argument("--region-px", type=Number(int, 8, 4096, unit="px"), default=40,
                   help="design pixels per side of the window diagnosed with --frame design (default 40)")
    p.add_argument("--upsample", type=Number(int, 1, 32), default=5,
                   help="model samples per design pixel per axis with --frame design (default 5)")
    p.add_argument("--frame", choices=("design", "camera"), default="camera",
                   help="height maps: render the model into the profilometer's own pixels with blur, pixel "
                        "integration and placement fitted as nuisances (camera, the default: the data are never "
                        "resampled), or fit on the design's model grid after resampling the data (design; "
                        "faster, for maps already on the design grid)")
    p.add_argument("--window-px", type=Number(int, 16, 4096, unit="px"), default=160,
                   help="camera pixels per side of the window diagnosed with --frame camera (default 160)")
    p.add_argument("--depths-nm", type=NumberList(Number(float, 0, 1e5, lo_open=True, unit="nm"), max_len=16),
                   default=None,
                   help="etch depths the process was asked for, one per mask of the design (the ideal model; "
                        "default: the design's mask_depths_m, else 75,150,300,600 for a 16-level design, else "
                        "2**j level steps as in doe masks)")
    add_device_option(p)
    p.add_argument("--threshold", type=Number(float, 0, 1e6, lo_open=True), default=10.0,
                   help="criterion drop an effect must achieve to be named (default 10)")
    p.add_argument("--instrument", metavar="FILE.json",
                   help="the profilometer's calibrated lateral transfer and batwing ('doe calibrate instrument'), held fixed, "
                        "and its height scale, divided out of the measured heights "
                        "(default: fitted with the placement)")
    p.add_argument("--wall-limit-s", type=Number(float, 0, 1e6, lo_open=True, unit="s"), default=None,
                   help="opt-in: wall-clock seconds from the command's start after which the selection stops where "
                        "it is (a round under way names nothing); the report is then written, says INCOMPLETE in "
                        "its summary's first line with the candidates not tried, and the command exits with status "
                        f"{EXIT_INCOMPLETE}. Default: no limit, so the answer depends on the file and the options "
                        "alone, never on the machine's speed or load")
    p.add_argument("--cpu-budget-s", type=Number(float, 0, 1e6, lo_open=True, unit="s"), default=None,
                   help="opt-in: CPU seconds (all threads together) after which the selection stops, as "
                        f"--wall-limit-s does (INCOMPLETE, exit status {EXIT_INCOMPLETE}); default none")
    p.add_argument("--x3p", action="store_true",
                   help="height maps, --frame camera: also write levelled.x3p (the levelled measurement) and "
                        "residual.x3p (measured minus the fitted model after every named effect, on the diagnosed "
                        "window), ISO 25178-72, into --out")
    p.add_argument("--force", action="store_true",
                   help="diagnose even when the field does not show the design (another design, off the element, "
                        "turned by a quarter turn)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Run ``doe diagnose`` on one BLAS thread from its start (:func:`metrology.diagnosis.parallel.one_thread`):
    the registration and levelling before the fits too, so that the answer does not depend on the
    machine's core count (a least-squares SVD split over two threads differs in its last bits, and
    a fit's path with it)."""
    from metrology.diagnosis.parallel import one_thread

    with one_thread():
        return _run(args)


def _run(args: argparse.Namespace) -> int:
    from metrology.diagnosis.budget import Deadline

    args.limit = Deadline.after(args.cpu_budget_s, args.wall_limit_s)  # from the command's start
    from doedesign.cli.common import print_json
    from doedesign.design import Design
    from doedesign.fileio import ensure_output_dir, output_run
    from metrology.correction.diagnoses import design_fingerprint

    for path in args.effects_file:
        load_effects_file(path)
    candidates = parse_effects(args.effects, "psf" if args.measured_psf else "height")
    if getattr(args, "x3p", False) and not (args.measured and args.frame == "camera"):
        from doedesign.errors import DoeError

        raise DoeError("--x3p writes height maps in the camera's frame: it needs --measured and --frame camera")
    args.calibration = args.transfer = None
    if getattr(args, "instrument", None):
        from metrology.calibration.instrument import read_calibration

        args.calibration = read_calibration(args.instrument)
        args.transfer = args.calibration.transfer
    out = ensure_output_dir(args.out)
    design = Design.load(args.design)
    if args.measured and args.frame == "camera":
        diag, inputs = _camera(design, Path(args.measured), args, candidates)
    elif args.measured:
        diag, inputs = _heights(design, Path(args.measured), args, candidates)
    else:
        diag, inputs = _psf(design, Path(args.measured_psf), args, candidates)
    # What the design was, so that a later `doe correct` refuses a diagnosis of another one.
    inputs.update(design_fingerprint(design, args.design))
    maps = inputs.pop("_x3p_maps", None)
    with output_run(out, "doe diagnose"):
        if maps is not None:
            from metrology.formats.x3p import write_levelled_and_residual

            inputs["x3p"] = write_levelled_and_residual(out, *maps)
        report = diag.save(out, dict(design=str(args.design), **inputs))
    print_json({"report": str(out / "report.json"), "summary": report["summary"], "incomplete": diag.incomplete,
                "untried": diag.untried, "effects_found": diag.named,
                "measurement_artefacts": report["measurement_artefacts"],
                "initial_residual_rms": diag.initial_residual_rms, "final_residual_rms": diag.final_residual_rms,
                "noise_floor": diag.noise_floor, "unexplained": diag.unexplained})
    return EXIT_INCOMPLETE if diag.incomplete else 0


def parse_effects(text: str | None, domain: str) -> list[str] | None:
    """The ``--effects`` candidates (None: every registered effect of ``domain``).

    Raises
    ------
    DoeError
        The list names no effect (a diagnosis with nothing to try would call any residual
        explained), an unknown effect or one of the other domain.
    """
    from doedesign.errors import DoeError
    from metrology.diagnosis.effects import REGISTRY, effects_for

    if text is None:
        return None
    names = [c.strip() for c in text.split(",") if c.strip()]
    if not names:
        known = sorted(n for n, e in REGISTRY.items() if e.domain == domain)
        raise DoeError(f"--effects {text!r} names no effect; give a comma-separated list of {', '.join(known)} "
                       "(or leave --effects out for all)")
    effects_for(domain, names)  # unknown names and effects of the other domain are refused here
    return names


def load_effects_file(path: str | Path) -> None:
    """Run a user's Python file that registers diagnosis effects; a failure is one line."""
    import runpy

    from doedesign.errors import DoeError

    path = Path(path)
    if not path.is_file():
        raise DoeError(f"{path}: effects file not found")
    try:
        runpy.run_path(str(path), run_name="doe_user_effects")
    except Exception as exc:  # the user's code: any failure is reported as one line
        raise DoeError(f"{path}: the effects file failed: {type(exc).__name__}: {exc}") from None


def _check_field(measurement, path):
    from doedesign.budget import check_memory, measurement_bytes

    rows, cols = measurement.height_m.shape
    check_memory(measurement_bytes((rows, cols)), f"{path}: diagnosing this {rows} x {cols} px field")


def _heights(design, path, args, candidates):
    from metrology.calibration.instrument import apply_calibration
    from metrology.diagnosis import diagnose_measurement
    from metrology.formats.readers import read_measurement

    measurement = read_measurement(path).square_pixels()
    _check_field(measurement, path)
    measurement = apply_calibration(measurement, args.calibration, str(path))
    diag, inputs = diagnose_measurement(design, measurement, region_px=args.region_px,
                                        upsample=args.upsample, depths_m=_depths(args),
                                        candidates=candidates, threshold=args.threshold, source=str(path),
                                        force=args.force, limit=args.limit)
    return diag, {"measured": str(path), **_held(args), **inputs}


def _camera(design, path, args, candidates):
    from metrology.calibration.instrument import apply_calibration
    from metrology.diagnosis.camera_measurement import diagnose_camera_measurement
    from metrology.formats.readers import read_measurement

    depths = _depths(args)
    measurement = read_measurement(path).square_pixels()
    _check_field(measurement, path)
    measurement = apply_calibration(measurement, args.calibration, str(path))
    comparison = None
    if getattr(args, "x3p", False):
        from doedesign.errors import DoeError
        from metrology.matching.compare import compare_measurement

        try:
            comparison = compare_measurement(measurement, design, force=args.force, transfer=args.transfer,
                                             texture=False)
        except DoeError as exc:
            raise DoeError(f"{path}: {exc}") from None
    diag, inputs = diagnose_camera_measurement(design, measurement, depths_m=depths, candidates=candidates,
                                               threshold=args.threshold, window_px=args.window_px, source=str(path),
                                               force=args.force, comparison=comparison, transfer=args.transfer,
                                               limit=args.limit,
                                               batwing=None if args.calibration is None else args.calibration.batwing)
    if comparison is not None:
        r0, r1, c0, c1 = diag.window_camera_px
        inputs["_x3p_maps"] = (comparison.height_m, diag.residual_maps[-1], measurement.pixel_size_m,
                               f"levelled {path}",
                               f"{path} minus the fitted model ({', '.join(diag.named) or 'ideal'}), "
                               f"camera window rows {r0}:{r1}, columns {c0}:{c1}", diag.map_step_m)
    return diag, {"measured": str(path), **_held(args), **inputs}


def _depths(args):
    """``--depths-nm`` in metres, or None (the design's own: masks.decompose.process_depths_m)."""
    return None if args.depths_nm is None else [v * 1e-9 for v in args.depths_nm]


def _held(args):
    """The calibration's height scale, when one was applied (the transfer is in the placement)."""
    cal = args.calibration
    return {} if cal is None else {"instrument_calibration": cal.path, "height_scale": cal.height_scale}


def _psf(design, path, args, candidates):
    from metrology.calibration.psfstack import read_stack
    from metrology.diagnosis import diagnose_psf

    stack = read_stack(path)
    camera = design.camera()
    rows, cols = stack["psf"].shape[-2:]
    axis = stack["axis_pixel"] or (rows // 2, cols // 2)
    camera = dataclasses.replace(camera, window_shape=(rows, cols), axis_pixel=axis,
                                 pixel_pitch_m=stack["pixel_pitch_m"])
    diag = diagnose_psf(design, camera, stack["psf"], stack["wavelengths_m"], views=stack["views"],
                        depth_m=stack["depth_m"], candidates=candidates, threshold=args.threshold,
                        device=args.device, limit=args.limit)
    return diag, {"measured_psf": str(path), "camera": camera.to_dict(), "views": list(stack["views"])}
