"""``doe calibrate``: dual-pixel crosstalk calibration, measured PSF stacks and the profilometer's lateral transfer."""

from __future__ import annotations

import argparse
import logging
import re
from pathlib import Path

import numpy as np

import metrology.calibration.dualpixel as dp
import metrology.calibration.psfstack as ps
from doedesign.cli.common import MAX_WINDOW_PX, Number, NumberList
from doedesign.engine.psf import parse_wavelengths_nm
from doedesign.errors import DoeError
from doedesign.fileio import (
    check_input_file,
    ensure_output_dir,
    ensure_output_file,
    output_run,
    save_figure,
    write_json,
    write_npz,
)

log = logging.getLogger(__name__)

__all__ = ["CAPTURE_HELP", "FRAME_SUFFIXES", "find_captures", "register", "run_crosstalk", "run_instrument", "run_psf"]

FRAME_SUFFIXES = (".tif", ".tiff", ".npy") + dp.RAW_SUFFIXES
# Smallest PSF window (pixels per side), as for 'doe psf --window'.
MIN_WINDOW_PX = 8
# Largest diffraction order '--orders' may name: orders beyond a few hundred leave any sensor window.
MAX_ORDER = 1000
CAPTURE_HELP = """\
Capture naming (a directory): for each wavelength NNN in nm, NNNnm_sum.EXT (the sum frame) and
NNNnm_view.EXT (the stored single-photodiode frame), EXT one of .tif .tiff .npy or a camera raw
(.cr2, .dng, ...; needs rawpy); optionally NNNnm_spectrum.csv (two columns: wavelength in nm,
intensity) with the band's measured spectrum, and dark_sum.EXT / dark_view.EXT (a dark capture).
Example: 450nm_sum.tif 450nm_view.tif 460nm_sum.tif ...
Or a list file (.txt/.csv): one capture per line, "WAVELENGTH_NM SUM_PATH VIEW_PATH [SPECTRUM_PATH]",
an optional "dark SUM_PATH VIEW_PATH" line, '#' comments; paths relative to the list file;
wavelengths strictly increasing. Frames are row-major, row 0 at the top of the sensor.
Output (in --out): psf_stack.npz (the tool's PSF file: psf (views, depths=1, wavelengths, rows, cols),
views coded/uncoded, normalized to the uncoded view's whole-frame total), psf_network.npy
((2, H, W, C), uncoded view first), report.json, comparison.npz with --predicted, PNG plots."""


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add ``doe calibrate`` and its subcommands (crosstalk, PSF, instrument) to ``subparsers``."""
    cal = subparsers.add_parser("calibrate", help="dual-pixel crosstalk, measured PSF and profilometer calibration")
    sub = cal.add_subparsers(dest="calibrate_command", metavar="WHAT")

    p = sub.add_parser("crosstalk", help="crosstalk ratios from white-wall captures with half the aperture blocked",
                       description="Per Bayer channel and column, the share of each view's light leaking to the "
                                   "other, from a capture with the left and one with the right aperture half blocked.")
    p.add_argument("--left-blocked", nargs=2, required=True, metavar=("SUM", "VIEW"),
                   help="sum and stored-view frames with the left aperture half blocked")
    p.add_argument("--right-blocked", nargs=2, required=True, metavar=("SUM", "VIEW"),
                   help="sum and stored-view frames with the right aperture half blocked")
    p.add_argument("--out", required=True, help="calibration .npz to write")
    p.add_argument("--png", help="plot of the ratios across the columns")
    _frame_options(p)
    p.add_argument("--smoothing", type=Number(float, 0), default=None,
                   help="spline smoothing penalty (default: generalized cross-validation)")
    p.set_defaults(func=run_crosstalk)

    p = sub.add_parser("psf", help="calibrated PSF stack from narrowband point-source captures",
                       description="Split, crosstalk-compensate, background-subtract, centre, normalize and crop "
                                   "narrowband PSF captures; optionally extrapolate and compare with predictions.",
                       epilog=CAPTURE_HELP, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--captures", required=True, help="directory of captures or a list file (see below)")
    p.add_argument("--wavelengths-nm", help="wavelengths to use, e.g. 450:700:10 or 450,550 (default: all found)")
    p.add_argument("--crosstalk", help="calibration .npz from 'doe calibrate crosstalk'")
    p.add_argument("--out", required=True, help="output directory")
    p.add_argument("--doe-side", choices=("left", "right"), default="right",
                   help="aperture half carrying the DOE (the seed's measurements: right)")
    p.add_argument("--coded-view", choices=dp.VIEW_NAMES,
                   help="which frame view is coded (needed without --crosstalk, overrides it otherwise)")
    p.add_argument("--pixel-pitch-um", type=Number(float, 0, 1000, lo_open=True, unit="um"), default=5.4, help="sensor pixel pitch (5.4)")
    p.add_argument("--window", default="512,512", help="window rows,cols (512,512)")
    p.add_argument("--axis-pixel", default=None, help="window pixel of the axis row,col (default: window centre)")
    p.add_argument("--axis", default=None, help="frame pixel row,col of the optical axis (default: uncoded peak)")
    p.add_argument("--background", choices=ps.BACKGROUNDS, default="border",
                   help="background estimate when no dark capture is given (border median)")
    p.add_argument("--normalization", choices=ps.NORMALIZATIONS, default="uncoded",
                   help="uncoded: both views over the uncoded whole-frame total (keeps the coded efficiency)")
    p.add_argument("--predicted", help="predicted PSF .npz (from 'doe psf' or a measured-height PSF) to compare with")
    p.add_argument("--extrapolate-nm", help="wavelengths to extrapolate from the shortest measured band "
                                            "(e.g. 400:440:10); needs --predicted holding them")
    p.add_argument("--orders", default="0,1,2", help="diffraction orders to locate (grating-like DOEs; '' to skip)")
    _frame_options(p)
    p.set_defaults(func=run_psf)

    p = sub.add_parser("instrument", help="the profilometer's lateral transfer from a measured artefact of known geometry",
                       description="Fit the profilometer's lateral transfer (pixel fill factor, Gaussian blur, the "
                                   "objective's NA and an interferometer's batwing when the data ask for them) with "
                                   "the placement on a measured step "
                                   "or grating whose geometry a design file gives (cf. ISO 25178-600), and with "
                                   "the artefact's certified step heights the instrument's height scale; the JSON "
                                   "written is what 'doe compare --instrument' and 'doe diagnose --instrument' "
                                   "hold fixed (at the pixel size it was made at).")
    p.add_argument("measured", help="measured height map of the artefact (any supported profilometer file)")
    p.add_argument("--design", required=True, help="design file (.npz) of the artefact's geometry")
    p.add_argument("--out", required=True, help="calibration .json to write")
    p.add_argument("--depths-nm", type=NumberList(Number(float, 0, 1e5, lo_open=True, unit="nm"), max_len=16),
                   default=None, help="nominal step per mask (default: the design's binary depths)")
    p.add_argument("--step-height-nm", type=NumberList(Number(float, 0, 1e5, lo_open=True, unit="nm"), max_len=16),
                   default=None, help="the artefact's certified step height per mask (e.g. 75,150,300,600): "
                                      "also fixes the instrument's height scale, which compare and diagnose "
                                      "then apply; a height that disagrees with the measurement is refused")
    p.add_argument("--wavelength-nm", type=Number(float, 100, 2000, unit="nm"), default=570.0,
                   help="the instrument's mean wavelength (570, white light)")
    p.add_argument("--window-px", type=Number(int, 16, 4096, unit="px"), default=160,
                   help="camera pixels per side of the window fitted (160)")
    p.add_argument("--force", action="store_true", help="calibrate even when the artefact matches its design poorly")
    p.set_defaults(func=run_instrument)


def _frame_options(p):
    p.add_argument("--cfa", default="RGGB", help="Bayer pattern of the sensor's top-left 2x2 cell (RGGB), "
                                                 "or 'none' for monochrome frames")
    p.add_argument("--saturation", type=Number(float, 0, lo_open=True), default=None, help="raw saturation level (default: from the data)")
    p.add_argument("--black-level", type=Number(float, 0), default=0.0, help="raw black level of each frame (0)")


def _pair(values, name, lo=0):
    try:
        parts = [int(v) for v in str(values).split(",")]
        if len(parts) != 2:
            raise ValueError
    except ValueError:
        raise DoeError(f"{name} must be two integers like 256,256, got {values!r}") from None
    if not all(lo <= p <= MAX_WINDOW_PX for p in parts):
        raise DoeError(f"{name} {values!r}: each must lie in {lo}..{MAX_WINDOW_PX} pixels")
    return tuple(parts)


def _orders(text):
    """Diffraction orders from '--orders' ('0,1,2'; '' for none)."""
    try:
        orders = tuple(int(v) for v in str(text).split(",") if v.strip()) if text else ()
    except ValueError:
        raise DoeError(f"--orders must be integers separated by commas like 0,1,2 (or '' for none), "
                       f"got {text!r}") from None
    if any(abs(m) > MAX_ORDER for m in orders):
        raise DoeError(f"--orders {text!r}: each must lie in -{MAX_ORDER}..{MAX_ORDER}")
    return orders


# -- instrument ------------------------------------------------------------------------------------------
def run_instrument(args: argparse.Namespace) -> int:
    """Run ``doe calibrate instrument`` with the parsed options; return the exit code."""
    from doedesign.cli.common import print_json
    from doedesign.design import Design

    from metrology.calibration.instrument import calibrate_instrument
    from metrology.formats.readers import read_measurement

    ensure_output_file(args.out)
    measured = check_input_file(args.measured)
    design = Design.load(args.design)
    cal = calibrate_instrument(design, read_measurement(measured), window_px=args.window_px,
                               depths_m=None if args.depths_nm is None else [v * 1e-9 for v in args.depths_nm],
                               wavelength_m=args.wavelength_nm * 1e-9, source=str(args.measured), force=args.force,
                               step_heights_m=None if args.step_height_nm is None
                               else [v * 1e-9 for v in args.step_height_nm])
    cal["artefact"]["design"] = str(args.design)
    with output_run(Path(args.out).parent, "doe calibrate instrument"):
        write_json(args.out, cal)
    print_json({"calibration": str(args.out), **cal["lateral_transfer"], **cal["fit"],
                "height_scale": cal["height_scale"]["value"]})
    return 0


# -- crosstalk -------------------------------------------------------------------------------------------
def run_crosstalk(args: argparse.Namespace) -> int:
    """Run ``doe calibrate crosstalk`` with the parsed options; return the exit code."""
    from doedesign.cli.common import print_json

    if args.cfa.lower() == "none":
        raise DoeError("crosstalk calibration works per Bayer channel; give the sensor's --cfa pattern")
    ensure_output_file(args.out)
    if args.png:
        ensure_output_file(args.png, "--png")
    (left_sum, left_view), (right_sum, right_view) = args.left_blocked, args.right_blocked  # nargs=2
    left = (dp.load_frame(left_sum), dp.load_frame(left_view))
    right = (dp.load_frame(right_sum), dp.load_frame(right_view))
    cal = dp.calibrate_crosstalk(left, right, args.cfa, args.smoothing, args.saturation, args.black_level,
                                 names=(f"left-blocked capture {args.left_blocked[0]}",
                                        f"right-blocked capture {args.right_blocked[0]}"))
    cal.metadata["files"] = {"left_blocked": args.left_blocked, "right_blocked": args.right_blocked}
    # The calibration and its plot are one result: their folder says INCOMPLETE until both are written.
    with output_run(Path(args.out).parent, "doe calibrate crosstalk"):
        cal.save(args.out)
        if args.png:
            save_figure(_crosstalk_figure(cal), args.png)
    print_json({"calibration": str(args.out), "stored_view_half": cal.stored_view_half,
                "mean_ratio": cal.summary(), "columns": cal.width})
    return 0


def _crosstalk_figure(cal):
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(10, 3.5), sharey=True)
    cols = np.arange(cal.width)
    colours = ("tab:red", "tab:green", "tab:olive", "tab:blue")
    for vi, ax in enumerate(axes):
        for ci, ch in enumerate(dp.CHANNELS):
            ok = np.isfinite(cal.raw_ratio[vi, ci])
            ax.plot(cols[ok], 100 * cal.raw_ratio[vi, ci, ok], ".", ms=2, color=colours[ci], alpha=0.4)
            ax.plot(cols, 100 * cal.ratio[vi, ci], color=colours[ci], label=ch)
        ax.set_title(f"{dp.VIEW_NAMES[vi]} view leaking to the other")
        ax.set_xlabel("sensor column (0 = left)")
    axes[0].set_ylabel("crosstalk (% of the view's light)")
    axes[0].legend()
    return fig


# -- PSF stacks ---------------------------------------------------------------------------------------------
def find_captures(spec: str | Path, wavelengths_m: np.ndarray | None = None,
                  ) -> tuple[np.ndarray, list[tuple[Path, Path, Path | None]], tuple[Path, Path] | None]:
    """Capture files from a directory or list file (convention in ``CAPTURE_HELP``).

    Returns (wavelengths_m, [(sum_path, view_path, spectrum_path or None)], dark pair or None).
    """
    spec = Path(spec)
    if spec.is_dir():
        found: dict[float, dict[str, Path]] = {}
        dark: dict[str, Path] = {}
        for f in sorted(spec.iterdir()):
            m = re.fullmatch(r"(\d+(?:\.\d+)?)nm_(sum|view|spectrum)(\.\w+)", f.name, flags=re.IGNORECASE)
            d = re.fullmatch(r"dark_(sum|view)(\.\w+)", f.name, flags=re.IGNORECASE)
            if m and (m.group(3).lower() in FRAME_SUFFIXES or m.group(2).lower() == "spectrum"):
                found.setdefault(float(m.group(1)), {})[m.group(2).lower()] = f
            elif d and d.group(2).lower() in FRAME_SUFFIXES:
                dark[d.group(1).lower()] = f
        wl_nm = sorted(found) if wavelengths_m is None else [float(np.round(w * 1e9, 3)) for w in wavelengths_m]
        missing = [w for w in wl_nm if not {"sum", "view"} <= set(found.get(w, {}))]
        if missing:
            raise DoeError(f"{spec}: no capture (NNNnm_sum + NNNnm_view) for {', '.join(f'{w:g}' for w in missing)} nm")
        files = [(found[w]["sum"], found[w]["view"], found[w].get("spectrum")) for w in wl_nm]
        if dark and set(dark) != {"sum", "view"}:
            raise DoeError(f"{spec}: a dark capture needs both dark_sum and dark_view")
        return ps.check_wavelengths(np.array(wl_nm) * 1e-9, str(spec)), files, \
            ((dark["sum"], dark["view"]) if dark else None)
    if not spec.is_file():
        raise DoeError(f"{spec}: no such capture directory or list file")
    check_input_file(spec)
    try:
        listing = spec.read_text(encoding="utf-8")
    except UnicodeDecodeError:
        raise DoeError(f"{spec}: not a capture list (text file of 'wavelength_nm sum view' lines)") from None
    listed_nm: list[float] = []
    listed: list[tuple[Path, Path, Path | None]] = []
    pair: tuple[Path, Path] | None = None
    for n, line in enumerate(listing.splitlines(), 1):
        parts = line.split("#")[0].replace(",", " ").split()
        if not parts:
            continue
        paths = [spec.parent / p for p in parts[1:]]
        if parts[0].lower() == "dark" and len(paths) == 2:
            pair = (paths[0], paths[1])
            continue
        try:
            wl = float(parts[0])
            if len(paths) not in (2, 3):
                raise ValueError
        except ValueError:
            raise DoeError(f"{spec}, line {n}: expected 'WAVELENGTH_NM SUM VIEW [SPECTRUM]', "
                           f"got {line.strip()!r}") from None
        listed_nm.append(wl)
        listed.append((paths[0], paths[1], paths[2] if len(paths) == 3 else None))
    wls = ps.check_wavelengths(np.array(listed_nm) * 1e-9, str(spec))
    if wavelengths_m is not None:
        missing = [w for w in wavelengths_m if np.abs(wls - w).min() > ps.WAVELENGTH_TOLERANCE_M]
        if missing:
            raise DoeError(f"{spec}: no capture listed for {', '.join(f'{w * 1e9:g}' for w in missing)} nm")
        keep = [int(np.argmin(np.abs(wls - w))) for w in wavelengths_m]
        wls, listed = wls[keep], [listed[i] for i in keep]
    return wls, listed, pair


def _load_spectra(paths, band_wl):
    """Spectra on the first file's wavelength grid, or (None, None) when none is given."""
    if all(p is None for p in paths):
        return None, None
    if any(p is None for p in paths):
        missing = [f"{w * 1e9:g}" for w, p in zip(band_wl, paths) if p is None]
        raise DoeError(f"band spectra given for some wavelengths but not for {', '.join(missing)} nm")
    grid, spectra = None, []
    for p in paths:
        try:
            data = np.loadtxt(p, delimiter=None if p.suffix.lower() != ".csv" else ",", ndmin=2)
        except (OSError, ValueError) as exc:
            raise DoeError(f"{p}: cannot read spectrum (two columns: wavelength nm, intensity): {exc}") from None
        if data.shape[1] < 2 or data.shape[0] < 3:
            raise DoeError(f"{p}: a spectrum needs two columns (wavelength nm, intensity) and 3+ rows")
        wl = ps.check_wavelengths(data[:, 0] * 1e-9, str(p))
        if grid is None:
            grid = wl
        spectra.append(np.interp(grid, wl, data[:, 1], left=0.0, right=0.0))
    return grid, np.array(spectra)


def _views_of(sum_path, view_path, args, cal, coded_name):
    """Coded and uncoded monochrome views of one capture."""
    s, v = dp.load_frame(sum_path), dp.load_frame(view_path)
    stored, other, sat = dp.split_views(s, v, args.saturation, args.black_level, name=str(sum_path))
    if cal is not None:
        if cal.width != s.shape[1]:
            raise DoeError(f"{sum_path}: {s.shape[1]} columns but the crosstalk calibration has {cal.width}")
        stored, other = dp.compensate_crosstalk(stored, other, cal, saturated=sat, name=str(sum_path))
    if sat.any():
        log.warning("%s: %d saturated pixels", sum_path, int(sat.sum()))
    coded, uncoded = (stored, other) if coded_name == "stored" else (other, stored)
    return coded, uncoded


def run_psf(args: argparse.Namespace) -> int:
    """Run ``doe calibrate psf`` with the parsed options; return the exit code."""
    from doedesign.cli.common import print_json

    # Every option and the small input files are checked before the captures are read and
    # before anything is written.
    out = ensure_output_dir(args.out)
    window = _pair(args.window, "--window", lo=MIN_WINDOW_PX)
    axis_pixel = _pair(args.axis_pixel, "--axis-pixel") if args.axis_pixel else (window[0] // 2, window[1] // 2)
    centre = _pair(args.axis, "--axis") if args.axis else None
    orders = _orders(args.orders)
    wavelengths = parse_wavelengths_nm(args.wavelengths_nm) if args.wavelengths_nm else None
    if wavelengths is not None:
        ps.check_wavelengths(wavelengths, "--wavelengths-nm")
    extrapolate = parse_wavelengths_nm(args.extrapolate_nm) if args.extrapolate_nm else None
    if extrapolate is not None and not args.predicted:
        raise DoeError("--extrapolate-nm needs --predicted PSFs at those wavelengths (order positions)")
    predicted = ps.load_stack(args.predicted) if args.predicted else None
    wl, files, dark_files = find_captures(args.captures, wavelengths)
    cal = dp.CrosstalkCalibration.load(args.crosstalk) if args.crosstalk else None
    if args.coded_view:
        coded_name = args.coded_view
    elif cal is not None:
        coded_name = dp.coded_view_name(cal.stored_view_half, args.doe_side)
    else:
        raise DoeError("without --crosstalk, say which frame view is coded with --coded-view stored|other")
    cfa = None if args.cfa.lower() == "none" else args.cfa
    if cal is not None and cfa is not None and cfa.upper() != cal.cfa_pattern:
        raise DoeError(f"--cfa {cfa} differs from the calibration's pattern {cal.cfa_pattern}")

    captures, gains = [], []
    for sum_path, view_path, _ in files:
        coded, uncoded = _views_of(sum_path, view_path, args, cal, coded_name)
        if cfa is not None:
            # Narrowband light: equalize the CFA channels' responses, taken from the uncoded view.
            g = dp.mosaic_channel_gains(uncoded, cfa)
            coded, uncoded = dp.apply_channel_gains(coded, g, cfa), dp.apply_channel_gains(uncoded, g, cfa)
            gains.append(g.tolist())
        captures.append((coded, uncoded))
    darks = None
    if dark_files is not None:
        darks = np.stack(_views_of(*dark_files, args, cal, coded_name))
    spec_wl, spectra = _load_spectra([f[2] for f in files], wl)
    stack = ps.build_stack(captures, wl, args.pixel_pitch_um * 1e-6, window, axis_pixel, centre, darks,
                           args.background, args.normalization, spec_wl, spectra,
                           names=[str(f[0]) for f in files])
    stack.info["channel_gains"] = gains
    report = {"captures": str(args.captures), "wavelengths_nm": (wl * 1e9).tolist(), "coded_view": coded_name,
              "crosstalk": args.crosstalk, "normalization": args.normalization,
              "normalization_note": ("both views divided by the uncoded view's whole-frame total: window sums are the "
                                     "share of each half-aperture's light in the window, coded relative to uncoded")
              if args.normalization == "uncoded" else "each view divided by its own whole-frame total",
              "window": list(window), "axis_pixel": list(axis_pixel), "layout": "row 0 at the top",
              "per_wavelength": stack.info}
    stats = stack.band_stats()  # None without spectra
    if stats is not None:
        report["band_centroid_nm"] = (stats[:, 0] * 1e9).tolist()
        report["band_fwhm_nm"] = (stats[:, 1] * 1e9).tolist()
    comparison = None
    if predicted is not None:
        try:
            if extrapolate is not None:
                stack = ps.extrapolate_orders(stack, predicted, extrapolate)
                report["extrapolation"] = stack.info["extrapolation"]
            # The comparison is computed before anything is written: a prediction that does not
            # fit the captures leaves the output folder as it was.
            comparison = ps.compare_stacks(stack, predicted, orders, name="predicted")
        except DoeError as exc:
            raise DoeError(f"{args.predicted}: {exc}") from None
    with output_run(out, f"doe calibrate psf {args.captures}"):
        _write_psf_outputs(stack, comparison, orders, report, out)
    assert stack.measured is not None  # set by PSFStack.__post_init__
    print_json({"out": str(out), "wavelengths_nm": (stack.wavelengths_m * 1e9).round(3).tolist(),
                "measured": stack.measured.tolist(),
                "energy_in_window": {v: stack.energy_in_window[i].round(5).tolist() for i, v in enumerate(ps.VIEWS)}})
    return 0


def _write_psf_outputs(stack, comparison, orders, report, out):
    """Figures, comparison, stack, network export and report: INCOMPLETE in ``out`` until all are written.

    ``comparison`` is :func:`~metrology.calibration.orders.compare_stacks`' (report, difference)
    or None.
    """
    figures = [_stack_figure(stack, out / "psf_stack.png")]
    if comparison is not None:
        comparison, difference = comparison
        report["comparison"] = comparison
        write_npz(out / "comparison.npz", difference=difference, measured=stack.psf,
                  predicted=stack.psf - difference, views=np.array(ps.VIEWS), wavelengths_m=stack.wavelengths_m,
                  pixel_pitch_m=np.float64(stack.pixel_pitch_m), axis_pixel=np.asarray(stack.axis_pixel))
        if orders:
            figures.append(_orders_figure(comparison, out / "orders.png"))
    ps.save_stack(stack, out / "psf_stack.npz")
    ps.save_network_npy(stack, out / "psf_network.npy")
    report["outputs"] = [str(out / n) for n in ("psf_stack.npz", "psf_network.npy")] + [str(f) for f in figures]
    write_json(out / "report.json", report)


def _stack_figure(stack, path):
    import matplotlib.pyplot as plt

    pick = np.unique(np.linspace(0, stack.wavelengths_m.size - 1, min(stack.wavelengths_m.size, 6)).round().astype(int))
    fig, axes = plt.subplots(2, pick.size, figsize=(2.6 * pick.size, 5.2), squeeze=False)
    for j, i in enumerate(pick):
        for vi, view in enumerate(ps.VIEWS):
            img = np.clip(stack.psf[vi, i], 0, None)
            ax = axes[vi, j]
            ax.imshow(np.log10(img + img.max() * 1e-5 + 1e-30), cmap="magma", origin="upper")
            tag = "" if stack.measured[i] else " (extrap.)"
            ax.set_title(f"{view} {stack.wavelengths_m[i] * 1e9:.0f} nm{tag}", fontsize=8)
            ax.set_xticks([])
            ax.set_yticks([])
    fig.suptitle("measured PSFs, log10 (row 0 at the top)")
    return save_figure(fig, path)


def _orders_figure(comparison, path):
    import matplotlib.pyplot as plt

    rows = comparison["wavelengths"]
    wl = [r["wavelength_nm"] for r in rows]
    fig, ax = plt.subplots(figsize=(6, 3.5))
    for k, m in enumerate(rows[0]["orders"]):
        line, = ax.plot(wl, [100 * r["order_energies"]["measured"][k] for r in rows], "o-", label=f"order {m} measured")
        ax.plot(wl, [100 * r["order_energies"]["predicted"][k] for r in rows], "--", color=line.get_color(),
                label=f"order {m} predicted")
    ax.set_xlabel("wavelength (nm)")
    ax.set_ylabel("energy near the order (% of a half-aperture)")
    ax.legend(fontsize=7)
    return save_figure(fig, path)
