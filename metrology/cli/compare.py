"""``doe compare``: a profilometer measurement against its design.

Writes into ``--out``: ``report.json`` (etch depths, level heights, overlay, bias, edge
width, roughness, registration, height errors, PSF summary), ``levels.png`` (level
histogram), ``error_map.png`` (against the design and the fitted process model),
``masks.png`` (per-mask results), ``psf.png`` and ``psf.npz`` (design and fabricated coded
PSFs) and ``surface3d.png`` (pyvista, when an OpenGL context exists). All maps are drawn
with row 0 at the top, in the measurement's camera orientation.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from doedesign.cli.common import Number
from doedesign.errors import DoeError

log = logging.getLogger(__name__)


def register(sub):
    p = sub.add_parser("compare", help="compare a profilometer measurement with its design",
                       description=__doc__.split("\n\n")[1])
    p.add_argument("measurement", help="height map (.dat, .datx, .xyz, .asc, .npz, .npy, .tif)")
    p.add_argument("--design", required=True, help="design .npz")
    p.add_argument("--out", required=True, help="output directory")
    p.add_argument("--pixel-size-um", type=Number(float, 0, 1e4, lo_open=True, unit="um"), default=None,
                   help="measurement pixel size (um) when the file has none or it is wrong (a starting value: "
                        "registration measures it against the DOE pitch)")
    p.add_argument("--wavelengths-nm", default="486,589,656", help="PSF wavelengths: list or start:stop:step")
    p.add_argument("--psf-oversample", type=Number(int, 1, 8), default=1,
                   help="PSF samples per DOE pixel per axis: 1 is fast (about 20 s for a 1600-pixel aperture) "
                        "but averages mask slivers over whole DOE pixels; 2 resolves slivers of half a pixel "
                        "at 2-3x the time and memory")
    p.add_argument("--no-psf", action="store_true", help="skip the PSF comparison")
    p.add_argument("--no-render", action="store_true", help="skip the 3-D rendering")
    p.add_argument("--force", action="store_true",
                   help="compare even when the measurement matches the design poorly (wrong design or field)")
    p.set_defaults(func=run_compare)


def run_compare(args):
    from doedesign.cli.common import print_json
    from doedesign.design import Design
    from doedesign.fileio import ensure_output_dir, output_run
    from doedesign.progress import Progress
    from doedesign.psf import parse_wavelengths_nm

    from metrology.matching.compare import compare_measurement
    from metrology.formats.readers import read_measurement

    out = ensure_output_dir(args.out)
    design = Design.load(args.design)
    pixel = args.pixel_size_um * 1e-6 if args.pixel_size_um is not None else None
    meas = read_measurement(args.measurement, pixel_size_m=pixel)
    wavelengths = parse_wavelengths_nm(args.wavelengths_nm)
    with Progress(6 + (0 if args.no_psf else 2), desc="compare") as prog:
        try:
            comp = compare_measurement(meas, design, progress=prog, force=args.force)
        except DoeError as exc:
            raise DoeError(f"{args.measurement}: {exc}") from None
        report = {"measurement": str(args.measurement), "design": str(args.design), **comp.report()}
        psf_cmp = None
        if not args.no_psf:
            from metrology.matching.measured_psf import compare_psf

            psf_cmp = compare_psf(design, comp.fitted_params(), wavelengths_m=wavelengths,
                                  oversample=args.psf_oversample, progress=prog)
            report["psf"] = psf_cmp.report()
    with output_run(out, f"doe compare {args.measurement}"):
        if psf_cmp is not None:
            from doedesign.fileio import write_npz

            write_npz(out / "psf.npz", wavelengths_m=psf_cmp.wavelengths_m, design_psf=psf_cmp.design_psf,
                      measured_psf=psf_cmp.measured_psf, target=psf_cmp.target)
        _write_outputs(args, comp, meas, psf_cmp, report, out)
    print_json({k: report[k] for k in ("etch_depths_nm", "overlay_um", "linewidth_bias_um",
                                       "height_error_rms_nm", "render3d")}
               | {"report": str(out / "report.json")})
    return 0


def _write_outputs(args, comp, meas, psf_cmp, report, out):
    """Figures, the 3-D rendering and report.json (strict JSON) into ``out``; ``report`` is completed."""
    from doedesign.fileio import write_json

    figures = _figures(comp, meas.pixel_size_m, psf_cmp, out)
    if args.no_render:
        report["render3d"] = "skipped (--no-render)"
    else:
        from metrology.matching.render3d import render_surface

        failure = render_surface(comp.height_m, comp.registration.pixel_size_m, out / "surface3d.png")
        report["render3d"] = failure or "surface3d.png"
        if not failure:
            figures.append("surface3d.png")
    report["figures"] = figures
    report.update(_strict_json(report))
    write_json(out / "report.json", report)
    from metrology.report_pages import compare_page

    compare_page(report, out)


def _strict_json(obj):
    """Arrays to lists and NaN / inf to None, so the report is strict JSON (jq, browsers)."""
    if isinstance(obj, dict):
        return {k: _strict_json(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple, np.ndarray)):
        return [_strict_json(v) for v in (obj.tolist() if isinstance(obj, np.ndarray) else obj)]
    if isinstance(obj, np.generic):
        obj = obj.item()
    if isinstance(obj, float) and not np.isfinite(obj):
        return None
    return obj


def _figures(comp, pixel_size_m, psf_cmp, out):
    """Level histogram, error maps, per-mask results and PSFs; returns the file names."""
    import matplotlib.pyplot as plt

    from doedesign.fileio import save_figure

    names = []
    rep = comp.report()
    h = comp.height_m
    ok = np.isfinite(h)

    fig, ax = plt.subplots(figsize=(7, 3.6))
    # Histograms drawn as outlines: 600 bars per histogram would make the figure slow.
    edges = np.linspace(np.nanmin(h), np.nanmax(h), 601) * 1e9
    inner = ok & comp.interior
    ax.stairs(np.histogram(h[ok] * 1e9, edges)[0], edges, color="0.5", label="all pixels")
    ax.stairs(np.histogram(h[inner] * 1e9, edges)[0], edges, color="C0",
              label="feature interiors (ISO central third)")
    ax.set_yscale("log")
    for v in rep["level_heights_nm"]:
        if np.isfinite(v):
            ax.axvline(v, color="C3", lw=0.6)
    ax.set_xlabel("height (nm), 0 = unetched top")
    ax.set_ylabel("pixels")
    ax.set_title("level histogram; red: fitted level means")
    ax.legend(fontsize=8)
    save_figure(fig, out / "levels.png")
    names.append("levels.png")

    fig, axes = plt.subplots(1, 2, figsize=(11, 4.4))
    rows, cols = h.shape
    extent = (0, cols * pixel_size_m * 1e6, rows * pixel_size_m * 1e6, 0)
    for ax, err, title in ((axes[0], comp.error_design_m, f"measured - design (rms {rep['height_error_rms_nm']:.1f} nm)"),
                           (axes[1], comp.error_model_m,
                            f"measured - fitted process model (rms {rep['height_error_model_rms_nm']:.1f} nm)")):
        lim = np.nanpercentile(np.abs(err), 99) * 1e9 if np.isfinite(err).any() else 1.0
        im = ax.imshow(err * 1e9, cmap="RdBu_r", vmin=-lim, vmax=lim, extent=extent, interpolation="nearest")
        ax.set_title(title, fontsize=9)
        ax.set_xlabel("x (um, file pixel size)")
        ax.set_ylabel("y (um, row 0 at top)")
        plt.colorbar(im, ax=ax, label="height error (nm)")
    save_figure(fig, out / "error_map.png")
    names.append("error_map.png")

    fig, axes = plt.subplots(1, 3, figsize=(12, 3.6))
    n = len(rep["etch_depths_nm"])
    idx = np.arange(n)
    axes[0].bar(idx, rep["etch_depths_error_percent"], yerr=np.asarray(rep["etch_depths_err_nm"])
                / np.asarray(rep["etch_depths_nominal_nm"]) * 100, color="C0")
    axes[0].set_title("etch depth error (%)")
    ov = np.asarray(rep["overlay_um"])
    ov_err = np.asarray(rep["overlay_err_um"])
    axes[1].bar(idx - 0.2, ov[:, 0], 0.4, yerr=ov_err[:, 0], label="dx")
    axes[1].bar(idx + 0.2, ov[:, 1], 0.4, yerr=ov_err[:, 1], label="dy (up)")
    axes[1].set_title("overlay vs mask 0 (um)")
    axes[1].legend(fontsize=8)
    axes[2].bar(idx, rep["linewidth_bias_um"], yerr=rep["linewidth_bias_err_um"], color="C2")
    axes[2].set_title("linewidth bias per edge (um)")
    for ax in axes:
        ax.set_xticks(idx, [f"mask {j}\n{d:.0f} nm" for j, d in enumerate(rep["etch_depths_nominal_nm"])])
        ax.axhline(0, color="k", lw=0.5)
    save_figure(fig, out / "masks.png")
    names.append("masks.png")

    if psf_cmp is not None:
        nw = len(psf_cmp.wavelengths_m)
        fig, axes = plt.subplots(3, nw, figsize=(3.2 * nw, 9), squeeze=False)
        for i in range(nw):
            d, m = psf_cmp.design_psf[i], psf_cmp.measured_psf[i]
            vmax = max(d.max(), m.max())
            for r, (img, name) in enumerate(((d, "design"), (m, "fabricated"))):
                axes[r, i].imshow(np.log10(np.maximum(img, vmax * 1e-5)), cmap="magma")
                on = psf_cmp.design_on_target[i] if r == 0 else psf_cmp.measured_on_target[i]
                axes[r, i].set_title(f"{name} {psf_cmp.wavelengths_m[i] * 1e9:.0f} nm, on target {on:.3f}",
                                     fontsize=8)
            diff = m - d
            lim = np.abs(diff).max() or 1.0
            axes[2, i].imshow(diff, cmap="RdBu_r", vmin=-lim, vmax=lim)
            axes[2, i].set_title("fabricated - design", fontsize=8)
        for ax in axes.ravel():
            ax.set_xticks([])
            ax.set_yticks([])
        save_figure(fig, out / "psf.png")
        names.append("psf.png")
    return names
