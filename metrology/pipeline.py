"""The main job end to end (``doe demo``): design, masks, a fabricated element, its
measurement, comparison and diagnosis, written as one Markdown report with figures.

It lives in ``metrology`` because it uses all three packages (data flows
doedesign -> masks -> metrology). Every step is timed; long steps show progress.

The simulated fabrication hides one process error (by default a 0.4 um x-overlay of the
600 nm mask) that the report does not reveal until the diagnosis has named it; the
measurement adds what a white-light interferometer adds (lateral blur, tilt, noise, a few
invalid pixels, its own pixel size and a small rotation) and is written as a Zygo ``.datx``.
The demo ends with the fab loop (:mod:`metrology.demo_loop`): ``doe correct`` of the
diagnosis, and the next wafer made with the job sheet, measured, compared and diagnosed.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypeVar

import numpy as np

from doedesign.camera import Camera
from doedesign.design import Design
from doedesign.engine.psf import compute_psf
from doedesign.errors import DoeError
from doedesign.fileio import atomic_path, json_ready, write_json

if TYPE_CHECKING:
    from doedesign.engine.psf import PSFResult
    from doedesign.optimizer.optimize import DesignRun
    from masks.process import ProcessParams
    from metrology.matching.compare import Comparison

__all__ = ["DEMO_INSTRUMENTS", "DemoConfig", "RGB_NM", "Timings", "compare_step", "demo_camera", "design_step",
           "diagnose_step", "fabricate_and_measure", "hidden_process", "markdown_report", "masks_step", "psf_step", "run_demo",
           "tolerance_step"]

log = logging.getLogger(__name__)
T = TypeVar("T")

RGB_NM = (656.0, 589.0, 486.0)
# Lateral transfers the demo's synthetic measurement can be made with (keyword arguments of
# :func:`metrology.matching.forward.process_on_measurement` beside the blur): "boxcar", a
# Gaussian blur (``instrument_blur_m``) and each pixel's whole area integrated; "point", a
# 0.4 um Gaussian blur read at each pixel's centre (no pixel integration); "optical", a
# coherence-scanning interferometer's objective (NA 0.4 incoherent circular pupil at 0.57 um,
# a 0.1 um residual blur) and pixels integrating 60 % of their area.
DEMO_INSTRUMENTS: dict[str, dict[str, float]] = {
    "boxcar": {"pixel_subsamples": 8},
    "point": {"blur_m": 0.4e-6, "pixel_subsamples": 1},
    "optical": {"blur_m": 0.1e-6, "na": 0.4, "wavelength_m": 0.57e-6, "fill_factor": 0.6, "pixel_subsamples": 8},
}


@dataclass
class DemoConfig:
    """Sizes and the hidden error of the demo run.

    ``doe_px`` is the DOE grid (the camera aperture equals it, so 1600 is the seed camera);
    ``quick`` shrinks everything for tests.
    """

    doe_px: int = 1600
    iterations: int = 25
    anneal_iterations: int = 5
    field_px: int = 72            # design pixels per side seen by the profilometer
    measurement_pixel_m: float = 1.1e-6
    rotation_deg: float = 0.7
    hidden_mask: int = 3          # mask index of the hidden overlay (the 600 nm mask)
    hidden_overlay_m: tuple = (0.4e-6, 0.0)
    noise_m: float = 1.0e-9
    instrument_blur_m: float = 0.5e-6
    # The profilometer's lateral transfer behind the synthetic measurement (DEMO_INSTRUMENTS).
    instrument: str = "boxcar"
    seed: int = 7
    window: int = 512
    # Bayer objective (doedesign.optimizer.optimize.OBJECTIVES). The quick run's 160 px aperture has a spot ten
    # pixels wide, where the balanced design is nearly flat (levels 0-1) and leaves the metrology
    # chain no etch depths to measure, so it keeps the L1 loss.
    objective: str = "softmin"
    # RGGB geometry: green may land on either of its two Bayer pixels. With one green pixel (the
    # seed's Eq. 1) the weakest colour stays near 0.22 after quantization; with two, 0.26.
    rggb: bool = True
    tolerance_samples: int = 8    # the closing tolerance run (default spec, local threads)
    diagnose_window_px: int = 128  # camera pixels per side diagnosed in the camera's frame
    next_wafer: bool = True       # the fab loop makes, measures and diagnoses the corrected next wafer
    # The next wafer's check, diagnosed on a smaller window: the short loop that keeps the demo
    # under two minutes (the corrected overlay is re-measured to a few nm on it).
    next_wafer_window_px: int = 96

    @classmethod
    def quick(cls) -> DemoConfig:
        return cls(doe_px=160, iterations=6, anneal_iterations=2, field_px=48, window=128, objective="loss",
                   rggb=False, tolerance_samples=4)


@dataclass
class Timings:
    steps: list = field(default_factory=list)

    def run(self, name: str, fn: Callable[..., T], *args: Any, **kwargs: Any) -> T:
        log.info("demo: %s ...", name)
        start, cpu = time.perf_counter(), time.process_time()
        out = fn(*args, **kwargs)
        # CPU time beside wall time: on a shared machine the wall time mostly measures the load.
        self.steps.append({"step": name, "seconds": time.perf_counter() - start,
                           "cpu_seconds": time.process_time() - cpu})
        log.info("demo: %s done in %.1f s", name, self.steps[-1]["seconds"])
        return out


def demo_camera(cfg: DemoConfig) -> Camera:
    """Seed camera focused at infinity (the Bayer target is at optical infinity)."""
    w = cfg.window
    return Camera(aperture_diameter_m=cfg.doe_px * 5.4e-6, focus_distance_m=np.inf, window_shape=(w, w),
                  axis_pixel=(w // 2, w // 2), doe_side="left")


def design_step(cfg: DemoConfig, camera: Camera, out: Path) -> DesignRun:
    """The demo's design step: optimize the element of ``cfg`` for ``camera`` and save it under ``out``."""
    from doedesign import targets
    from doedesign.optimizer.losses import LossSpec
    from doedesign.optimizer.optimize import OptimizerSettings, design_doe

    target = targets.bayer(camera, rggb=cfg.rggb)
    settings = OptimizerSettings(max_iter=cfg.iterations, anneal_iter=cfg.anneal_iterations, seed=cfg.seed,
                                 init=targets.DEFAULT_INIT["bayer"] if cfg.objective != "loss" else "zeros",
                                 objective=cfg.objective)
    run = design_doe(target, camera, 5.4e-6, (cfg.doe_px, cfg.doe_px), loss=LossSpec.parse(targets.DEFAULT_LOSS["bayer"]),
                     settings=settings)
    run.design.metadata["name"] = "bayer_demo"
    run.design.save(out / "design.npz")
    write_json(out / "design_report.json", run.report)
    return run


def psf_step(design: Design, camera: Camera, out: Path) -> PSFResult:
    """The demo's PSF step: the design's PSFs at the RGB wavelengths, with their figure under ``out``."""
    from doedesign.plots import psf_figure, save

    result = compute_psf(design, camera, wavelengths_m=np.array(RGB_NM) * 1e-9)
    result.save(out / "psf.npz")
    save(psf_figure(result, crop=min(24, camera.window_shape[0] // 2 - 1), title="Bayer DOE, R/G/B"), out / "psf.png")
    return result


def masks_step(design: Design, design_path: Path, out: Path) -> dict:
    """The demo's masks step: write the design's masks (GDSII, verified) under ``out / 'masks'``."""
    from masks.element import write_element

    return write_element(design, out / "masks", source=str(design_path))


def hidden_process(cfg: DemoConfig) -> ProcessParams:
    """The demo wafer's hidden process (:class:`masks.process_params.ProcessParams`): the overlay error, roughness."""
    from masks.process import ProcessParams

    overlay = np.zeros((4, 3))
    overlay[cfg.hidden_mask, :2] = cfg.hidden_overlay_m
    return ProcessParams.ideal().copy(mask_overlay=overlay, roughness=0.5e-9, seed=cfg.seed)


def fabricate_and_measure(design: Design, cfg: DemoConfig, out: Path, params: ProcessParams | None = None,
                          seed: int | None = None) -> tuple[Path, dict]:
    """Simulate the etched surface with the hidden error (or the process ``params``) and write
    the Zygo file ``out/measurement.datx``; ``seed`` (default the config's) draws the field's
    placement and the instrument noise."""
    from metrology.formats.writers import write_datx
    from metrology.matching import compare, register
    from metrology.matching.window import busiest_window

    seed = cfg.seed if seed is None else seed
    rng = np.random.default_rng(seed)
    params = hidden_process(cfg) if params is None else params.copy(seed=seed)
    # Place the field where the pattern has structure, inside the element's inscribed circle: a
    # flat zone of a lens-like design cannot be registered or tell anything about the masks.
    # It must also hold unetched surface (1 % of the field), which compare levels on.
    levels = design.levels
    if levels is None:
        raise DoeError(f"{design.name}: the demo fabricates a quantized design; this one has no levels")
    r0, _, c0, _ = busiest_window(levels, cfg.field_px, need_flat=False, inside_circle=True,
                                  min_level0_px=max(16, cfg.field_px ** 2 // 100))
    centre = (float(r0 + cfg.field_px // 2), float(c0 + cfg.field_px // 2))
    centre = (centre[0] + rng.uniform(-2, 2), centre[1] + rng.uniform(-2, 2))
    scale = cfg.measurement_pixel_m / design.pitch_m
    shape_px = int(cfg.field_px / scale)
    truth = register.Registration.from_parameters(scale, cfg.rotation_deg, (False, False, False), centre,
                                                  design.pitch_m, design.shape, (shape_px, shape_px))
    # The camera reports the surface through the instrument's lateral transfer.
    transfer: dict[str, Any] = {"blur_m": cfg.instrument_blur_m, **DEMO_INSTRUMENTS[cfg.instrument]}
    height = compare.process_on_measurement(levels, design.pitch_m, params, truth, step_m=0.25e-6, **transfer)
    rows, cols = np.mgrid[:shape_px, :shape_px]
    tilt = 2e-6 * (rows - shape_px / 2) / shape_px - 1e-6 * (cols - shape_px / 2) / shape_px
    height = height + tilt + rng.normal(0, cfg.noise_m, height.shape)
    height[rng.random(height.shape) < 0.002] = np.nan
    out.mkdir(parents=True, exist_ok=True)
    path = out / "measurement.datx"
    write_datx(path, height, cfg.measurement_pixel_m, unit="NanoMeters")
    hidden = {"mask_overlay": {"mask": cfg.hidden_mask, "dx_um": cfg.hidden_overlay_m[0] * 1e6,
                               "dy_um": cfg.hidden_overlay_m[1] * 1e6},
              "registration": truth.to_dict(), "instrument": {"name": cfg.instrument, **transfer}}
    return path, hidden


def compare_step(measurement_path: Path, design: Design, design_path: Path, out: Path,
                 full: bool = True) -> tuple[dict, Comparison]:
    """``doe compare`` on the measurement file into ``out/compare``; returns its report and the
    comparison. Without ``full``, no predicted-PSF comparison and no 3-D render (the next wafer's
    check in the demo's short loop)."""
    from metrology.formats.readers import read_measurement
    from metrology.matching.compare import compare_measurement
    from metrology.matching.report import write_comparison

    measurement = read_measurement(measurement_path)
    comp = compare_measurement(measurement, design)
    report = write_comparison(measurement, design, out / "compare", measurement_source=str(measurement_path),
                              design_source=str(design_path), comparison=comp, psf=full, render=full)
    return report, comp


def diagnose_step(measurement_path: Path, design: Design, design_path: Path, out: Path, cfg: DemoConfig,
                  comparison: Comparison, window_px: int | None = None) -> dict:
    """The diagnosis in the camera's frame into ``out/diagnose``: the model is rendered into the
    measured pixels, started from the comparison's camera-frame placement. Its inputs carry the
    design's fingerprint, as ``doe diagnose`` writes it, so that ``doe correct`` can read it."""
    from metrology.correction.diagnoses import design_fingerprint
    from metrology.diagnosis.camera_measurement import diagnose_camera_measurement
    from metrology.formats.readers import read_measurement

    diag, inputs = diagnose_camera_measurement(design, read_measurement(measurement_path),
                                               window_px=window_px or cfg.diagnose_window_px,
                                               source=str(measurement_path),
                                               comparison=comparison)
    return diag.save(out / "diagnose", {"design": str(design_path), "measured": str(measurement_path), **inputs,
                                        **design_fingerprint(design, design_path)})


def tolerance_step(design: Design, design_path: Path, out: Path, cfg: DemoConfig) -> dict:
    """A short tolerance run of the element under the built-in spec: yield and spread of its figure."""
    from masks.tolerance.analysis import nominal_depths, tolerance_analysis
    from masks.tolerance.spec import default_spec

    rep = tolerance_analysis(design, default_spec(nominal_depths(design)), cfg.tolerance_samples, out / "tolerance",
                             design_name=str(design_path), scheduler="threads", workers=2, oversample=1,
                             sobol_base=0, one_at_a_time=False)
    return {"spec": rep["spec"]["source"], "samples": rep["run"]["samples"], "sampling": rep["sampling"]["description"],
            "primary_metric": rep["primary_metric"], "metrics": rep["metrics"], "yield": rep["yield"],
            "seconds_per_sample": rep["timing"]["seconds_per_sample"]}


def run_demo(out_dir: str | Path, cfg: DemoConfig | None = None) -> dict:
    """Run the whole chain into ``out_dir`` and return the report dictionary."""
    cfg = cfg or DemoConfig()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    timings = Timings()
    camera = demo_camera(cfg)
    run = timings.run("design (nlopt, Bayer target)", design_step, cfg, camera, out)
    design = Design.load(out / "design.npz")  # the file a user would hand on
    psf = timings.run("PSFs of the design", psf_step, design, camera, out)
    design_path = out / "design.npz"
    masks_report = timings.run("masks and GDSII (export + verification)", masks_step, design, design_path, out)
    meas_path, hidden = timings.run("fabrication and Zygo measurement (simulated)", fabricate_and_measure,
                                    design, cfg, out)
    comparison, comp = timings.run("compare measurement with design", compare_step, meas_path, design, design_path,
                                   out)
    diagnosis = timings.run("diagnose (camera frame)", diagnose_step, meas_path, design, design_path, out, cfg, comp)
    tolerance = timings.run("tolerance (process Monte Carlo)", tolerance_step, design, design_path, out, cfg)
    loop = _fab_loop(timings, design, design_path, out, cfg)
    report = {
        "config": cfg.__dict__,
        "timings": timings.steps,
        "design": {k: run.report.get(k) for k in ("continuous", "quantized", "run_time_s")},
        "psf_energy_in_window": psf.energy_in_window.tolist(),
        "masks": masks_report,
        "comparison": comparison,
        "diagnosis": diagnosis,
        "hidden_error": hidden,
        "tolerance": tolerance,
        "fab_loop": loop,
    }
    write_json(out / "report.json", report)
    with atomic_path(out / "report.md") as tmp:
        tmp.write_text(markdown_report(json_ready(report), out))
    return report


def _fab_loop(timings: Timings, design: Design, design_path: Path, out: Path, cfg: DemoConfig) -> dict:
    """The closing loop (:mod:`metrology.demo_loop`): correct, then the next wafer made with the job sheet."""
    from metrology.demo_loop import correct_step, loop_summary, next_wafer_params

    sheet = timings.run("fab loop: doe correct (masks, job sheet, merit)", correct_step, design, design_path, out,
                        seed=cfg.seed)
    if not cfg.next_wafer:
        return loop_summary(sheet, None)
    nxt = out / "next_wafer"
    params = next_wafer_params(hidden_process(cfg), sheet)
    meas, _ = timings.run("fab loop: next wafer made and measured", fabricate_and_measure, design, cfg, nxt, params,
                          seed=cfg.seed + 1)
    _, comp = timings.run("fab loop: next wafer compared", compare_step, meas, design, design_path, nxt, full=False)
    diag = timings.run("fab loop: next wafer diagnosed", diagnose_step, meas, design, design_path, nxt, cfg, comp,
                       cfg.next_wafer_window_px)
    return loop_summary(sheet, diag)


def markdown_report(report: dict, out: Path) -> str:
    """The demo report as Markdown: a summary to read in two minutes, tables with units, the
    figures inline (paths relative to the report) and a link to report.json beside it."""
    from doedesign import report_md as md
    from metrology import report_pages as pages

    cfg, d = report["config"], report["design"]
    cont, quant = d.get("continuous") or {}, d.get("quantized") or {}
    comp, diag, masks = report.get("comparison") or {}, report.get("diagnosis") or {}, report.get("masks") or {}
    on_c, on_q = _per_colour(cont), _per_colour(quant)
    bound = _per_colour(quant.get("bound") or cont.get("bound") or {}, "bound")
    findings = pages.compare_findings(comp)
    named = [e for e in diag.get("effects_found") or [] if e not in (diag.get("measurement_artefacts") or [])]
    depths = [layer.get("etch_depth_nm") for layer in masks.get("layers") or []]
    verified = (masks.get("verification") or {}).get("passed")
    colours = "/".join(md.fmt(v, 2) for v in on_q)
    parts = [
        "# DOE toolkit demo: Bayer colour-sorting element, design to diagnosis", "",
        "## Summary",
        f"- **Designed**: a {cfg['doe_px']} x {cfg['doe_px']}-pixel (5.4 um pitch) 16-level Bayer colour-sorting "
        f"element for the left half of the 2-in-1 camera, focused at infinity; light on the R/G/B target pixels "
        f"{colours} after quantization ({'/'.join(md.fmt(v, 2) for v in on_c)} continuous), "
        f"{'/'.join(md.fmt(_fraction(q, b), 2) for q, b in zip(on_q, bound))} of each colour's "
        "single-colour bound.",
        f"- **Made**: four masks ({', '.join(md.fmt(v, 3) for v in depths)} nm) written as GDSII and "
        + ("verified pixel-exact" if verified else "**not** verified")
        + f"; the wafer was simulated with a hidden process error and measured at "
        f"{md.fmt(cfg['measurement_pixel_m'] * 1e6, 3)} um pixels.",
        "- **What went wrong**: the comparison finds "
        + ("; ".join(f[2] for f in findings) if findings else "every mask within tolerance")
        + "; the diagnosis names " + (", ".join(named) if named else "no fabrication effect") + ".",
        f"- **How sure**: {pages.match_sentence(comp)}; "
        + ("the named effects explain the residual down to the noise floor"
           if not diag.get("unexplained") else "a structured residual remains unexplained") + ".",
        *([f"- **Fab loop**: {_loop_verdict(report['fab_loop'])}."] if report.get("fab_loop") else []),
        "",
        "## Light on target per colour",
        "Energies are fractions of the coded half-aperture's light on each colour's target pixel (the "
        "design's figure of merit). The bound is what a diffraction-limited spot of that half aperture puts "
        "on one pixel (`doedesign.bounds`): no phase element beats it for one colour, and a router serving "
        "three colours at once gets less. The fabricated element's PSF is compared with the design's below, "
        "under the measurement.", "",
        md.table([(name, md.fmt(nm, 3), md.fmt(b, 3), md.fmt(c, 3), md.fmt(_fraction(c, b), 3), md.fmt(q, 3),
                   md.fmt(_fraction(q, b), 3), md.fmt(100 * (q - c) / c if c else None, 2))
                  for name, nm, c, q, b in zip("RGB", RGB_NM, on_c, on_q, bound)],
                 ("colour", "wavelength (nm)", "bound (fraction of light)", "continuous (fraction of light)",
                  "continuous / bound", "16 levels (fraction of light)", "16 levels / bound",
                  "quantization change (%)")),
        md.figure(out, "psf.png", "coded and uncoded PSFs of the quantized design (log scale)"),
        "## Masks",
        md.table([(f"mask {layer.get('mask')}", layer.get("layer"), md.fmt(layer.get("etch_depth_nm"), 4),
                   layer.get("polygons"), layer.get("vertices"))
                  for layer in masks.get("layers") or []],
                 ("mask", "GDS layer", "etch depth (nm)", "polygons", "vertices")),
        f"Verification by an independent rasterization: "
        f"{md.verdict(verified, 'every pixel of every mask matches the design', 'mismatched pixels, see masks/report.json')}.",
        "",
        md.figure(out, "masks/masks.png", "the four binary masks and the level map"),
        "## Measurement compared with the design",
        *pages.compare_sections(comp, out, prefix="compare/", level=3),
        "## Diagnosis",
        *pages.diagnose_sections(diag, out, prefix="diagnose/", level=3),
        "## The hidden error (revealed after the diagnosis)",
        _hidden_table(report.get("hidden_error") or {}, comp, diag),
        "## Timings",
        md.table([(s["step"], md.fmt(s["seconds"], 3), md.fmt(s.get("cpu_seconds"), 3)) for s in report["timings"]],
                 ("step", "wall time (s)", "CPU time (s, all threads)")),
        md.json_link(),
    ]
    tol = report.get("tolerance")
    if tol:
        from masks.tolerance.metrics import metric_unit
        from masks.tolerance.report import yield_verdict

        name = tol["primary_metric"]
        m, y = tol["metrics"][name], tol["yield"]
        parts[-1:-1] = [
            "## Tolerance", f"{tol['samples']} process samples, {tol['spec']}. {tol['sampling']}.", "",
            f"Yield: {yield_verdict(y)}.", "",
            md.table([(f"{name} ({metric_unit(name)})", md.fmt(m["nominal"], 4), md.fmt(m["mean"], 4),
                       md.fmt(m["worst_decile_mean"], 4), f"{y['passed']}/{y['samples']}",
                       f"{md.fmt(y['ci95'][0], 2)}-{md.fmt(y['ci95'][1], 2)}")],
                     ("metric", "nominal", "mean", "worst decile", "yield", "95 % interval")),
            md.figure(out, "tolerance/distributions.png", "metric distributions against the nominal element")]
    if report.get("fab_loop"):
        from metrology.demo_loop import loop_sections

        parts[-1:-1] = loop_sections(report["fab_loop"])
    return md.join(parts)


def _loop_verdict(loop):
    from metrology.demo_loop import loop_verdict

    return loop_verdict(loop)


def _per_colour(result, key="energy_on_target"):
    """R/G/B values of ``key`` in a design report stage (first source distance): the light on the
    target pixels, or with ``key="bound"`` in the stage's bound report, the single-colour bounds."""
    values = np.asarray(result.get(key) or [[np.nan] * 3], dtype=float)
    return [float(v) for v in values.reshape(-1, values.shape[-1])[0]]


def _fraction(value, bound):
    """``value / bound``, or None when either is missing."""
    ok = value is not None and bound is not None and np.isfinite(value) and np.isfinite(bound) and bound > 0
    return value / bound if ok else None


def _hidden_table(hidden, comp, diag):
    from doedesign import report_md as md

    ov = hidden.get("mask_overlay")
    if not ov:
        return "No error was hidden.\n"
    j = ov["mask"]
    found = comp.get("overlay_um") or []
    err = comp.get("overlay_err_um") or []
    measured = found[j] if j < len(found) else [None, None]
    sigma = err[j] if j < len(err) else [None, None]
    params = next((s.get("params") or {} for s in diag.get("steps") or [] if s.get("effect") == "mask_overlay"), {})
    diag_dx = params.get(f"dx_mask{j}_m")
    return md.table([(f"overlay dx of mask {j} (um)", md.fmt(ov["dx_um"], 3), md.fmt_pm(measured[0], sigma[0], 3),
                      md.fmt(None if diag_dx is None else diag_dx * 1e6, 3)),
                     (f"overlay dy of mask {j} (um)", md.fmt(ov["dy_um"], 3), md.fmt_pm(measured[1], sigma[1], 3),
                      md.fmt(params.get(f"dy_mask{j}_m", None) and params[f"dy_mask{j}_m"] * 1e6, 3))],
                    ("quantity", "hidden", "doe compare", "doe diagnose"))
