"""The comparison's files: ``report.json`` and its figures, for ``doe compare`` and the demo.

Writes into the output directory ``report.json`` (etch depths, level heights, overlay, bias,
edge width, roughness, registration, height errors, PSF summary), ``levels.png`` (level
histogram), ``error_map.png`` (against the design and the fitted process model),
``masks.png`` (per-mask results), ``psf.png`` and ``psf.npz`` (design and fabricated coded
PSFs) and ``surface3d.png`` (pyvista, when an OpenGL context exists). All maps are drawn
with row 0 at the top, in the measurement's camera orientation.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike

from doedesign.design import Design
from doedesign.errors import DoeError
from doedesign.fileio import ensure_output_dir, json_ready, output_run, write_json, write_npz
from doedesign.progress import Progress
from metrology.formats.measurement import Measurement
from metrology.matching.compare import Comparison, compare_measurement
from metrology.matching.transfer import LateralTransfer
from metrology.report_pages import compare_page

__all__ = ["write_comparison"]

log = logging.getLogger(__name__)


def write_comparison(measurement: Measurement, design: Design, out: str | Path, *,
                     measurement_source: str = "measurement", design_source: str = "design",
                     wavelengths_m: ArrayLike | None = None, psf_oversample: int = 1,
                     psf: bool = True, render: bool = True, force: bool = False,
                     comparison: Comparison | None = None, transfer: LateralTransfer | None = None,
                     x3p: bool = False, batwing: tuple[float, float] | None = None) -> dict:
    """Compare ``measurement`` with ``design`` and write the report and figures into ``out``.

    Parameters
    ----------
    measurement : Measurement
    design : Design
    out : path
        Output directory (created).
    measurement_source, design_source : str
        File names for the report and error messages.
    wavelengths_m : sequence of float, optional
        PSF wavelengths; default the design target's (see
        :func:`metrology.matching.measured_psf.compare_psf`).
    psf_oversample : int
        PSF samples per DOE pixel per axis (see :func:`metrology.matching.measured_psf.compare_psf`).
    psf, render : bool
        Compare the PSFs; render the 3-D surface.
    force : bool
        Go on when the field does not show the design (see :mod:`metrology.matching.match`).
    comparison : Comparison, optional
        The :func:`~metrology.matching.compare.compare_measurement` result, if already made.
    transfer : LateralTransfer, optional
        The instrument's calibrated lateral transfer, held fixed in the camera-frame fit.
    batwing : (float, float), optional
        The calibration's batwing (amplitude, sigma_m), held beside ``transfer``.
    x3p : bool
        Also write ``levelled.x3p`` (the levelled measurement) and ``residual.x3p`` (measured
        minus design), ISO 25178-72, row 0 first, through :func:`metrology.formats.x3p.write_x3p`.

    Returns
    -------
    dict
        The report written to ``report.json``.
    """
    out = ensure_output_dir(out)
    with Progress(6 + (2 if psf else 0), desc="compare") as prog:
        comp = comparison
        if comp is None:
            try:
                comp = compare_measurement(measurement, design, progress=prog, force=force, transfer=transfer,
                                           batwing=batwing)
            except DoeError as exc:
                raise DoeError(f"{measurement_source}: {exc}") from None
        report = {"measurement": measurement_source, "design": design_source, **comp.report()}
        psf_cmp = None
        if psf:
            from metrology.matching.measured_psf import compare_psf

            psf_cmp = compare_psf(design, comp.fitted_params(), wavelengths_m=wavelengths_m,
                                  oversample=psf_oversample, progress=prog)
            report["psf"] = psf_cmp.report()
    # The folder says INCOMPLETE until every output below is written.
    with output_run(out, f"doe compare {measurement_source}"):
        if psf_cmp is not None:
            write_npz(out / "psf.npz", wavelengths_m=psf_cmp.wavelengths_m, design_psf=psf_cmp.design_psf,
                      measured_psf=psf_cmp.measured_psf, target=psf_cmp.target)
        figures = _figures(comp, measurement.pixel_size_m, psf_cmp, out)
        if not render:
            report["render3d"] = "skipped (--no-render)"
        else:
            from metrology.matching.render3d import render_surface

            failure = render_surface(comp.height_m, comp.registration.pixel_size_m, out / "surface3d.png")
            report["render3d"] = failure or "surface3d.png"
            if not failure:
                figures.append("surface3d.png")
        report["figures"] = figures
        if x3p:
            from metrology.formats.x3p import write_levelled_and_residual

            # The file's pitch: the maps are in the camera frame.
            report["x3p"] = write_levelled_and_residual(out, comp.height_m, comp.error_design_m,
                                                        measurement.pixel_size_m, f"levelled {measurement_source}",
                                                        f"{measurement_source} minus design {design_source}")
        write_json(out / "report.json", report)
        compare_page(json_ready(report), out)
    return report


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

    if comp.texture is not None and comp.texture.q_per_m.size:
        from metrology.matching.texture import BAND_EDGES_PITCH

        t = comp.texture
        fig, ax = plt.subplots(figsize=(6.4, 4))
        wl_um = 2 * np.pi / t.q_per_m * 1e6
        ax.loglog(wl_um, t.psd_m4 * 1e36, color="C0")
        for e in BAND_EDGES_PITCH:
            ax.axvline(e * comp.registration.pitch_m * 1e6, color="0.5", lw=0.6, ls="--")
        ax.invert_xaxis()
        ax.set_xlabel("spatial wavelength (um); dashed: 1 and 10 DOE pitches")
        ax.set_ylabel("PSD C(q) (nm^2 um^2)")
        ax.set_title(f"residual (measured - design), radially averaged PSD; Sq {t.residual['Sq_m'] * 1e9:.2f} nm",
                     fontsize=9)
        save_figure(fig, out / "texture.png")
        names.append("texture.png")

    if psf_cmp is not None:
        nw = len(psf_cmp.wavelengths_m)
        fig, axes = plt.subplots(3, nw, figsize=(3.2 * nw, 9), squeeze=False)
        for i in range(nw):
            d, m = psf_cmp.design_psf[i], psf_cmp.measured_psf[i]
            vmax = max(d.max(), m.max())
            for r, (img, name) in enumerate(((d, "design"), (m, "fabricated"))):
                axes[r, i].imshow(np.log10(np.maximum(img, vmax * 1e-5)), cmap="magma")
                on = psf_cmp.design_on_target[i] if r == 0 else psf_cmp.measured_on_target[i]
                where = "on target" if psf_cmp.target_source == "design_target" else "in PSF core"
                axes[r, i].set_title(f"{name} {psf_cmp.wavelengths_m[i] * 1e9:.0f} nm, {where} {on:.3f}",
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
