"""A whole tolerance study: nominal element, Monte Carlo samples, sensitivity, report.

:func:`tolerance_analysis` is what ``doe tolerance`` and ``doe demo`` call.
"""

from __future__ import annotations

import hashlib
import itertools
import logging
import time
from pathlib import Path

import numpy as np

from doedesign.budget import check_memory, format_bytes, psf_bytes
from doedesign.camera import describe_surround, resolve_surround
from doedesign.design import Design
from doedesign.errors import DoeError
from doedesign.fileio import output_run, write_json
from doedesign.levels import design_levels

from .evaluate import Evaluator
from .metrics import DIRECTIONS, design_wavelengths_depths, metric_set
from .report import (default_thresholds, metric_summary, plot_distributions, plot_tornado, tolerance_page,
                     yield_summary)
from .runner import local_workers, make_client, n_workers, open_store, run_jobs, run_key
from .sensitivity import oat_jobs, oat_table, sobol_indices, sobol_jobs
from .spec import ToleranceSpec, check_yield_goal, nominal_process

__all__ = ["build_evaluator", "design_wavelengths_depths", "evaluation_bytes", "nominal_depths",
           "sampling_description",
           "tolerance_analysis"]

log = logging.getLogger(__name__)


def nominal_depths(design: Design) -> np.ndarray:
    """Mask etch depths (m) of the design's process (:meth:`doedesign.design.Design.etch_depths_m`:
    its own, else binary multiples of its level step)."""
    return np.asarray(design.etch_depths_m(), dtype=float)


def build_evaluator(design: Design, spec: ToleranceSpec, source: str = "design", oversample: int = 2,
                    process_upsample: int | None = None, wavelengths_m: np.ndarray | None = None,
                    metric_script: str | None = None, device: str = "cpu") -> tuple[Evaluator, dict, float]:
    """The evaluator of ``design`` under ``spec`` and the nominal (ideal element) metrics."""
    camera = design.camera()
    wls, depths = design_wavelengths_depths(design, camera)
    if wavelengths_m is not None:
        wls = np.asarray(wavelengths_m, float)
    levels = design_levels(design, None, source)
    base = nominal_process(nominal_depths(design))
    ev = Evaluator(levels=levels.astype(np.int16), pitch_m=design.pitch_m, material=design.material, camera=camera,
                   wavelengths_m=wls, depths_m=depths, spec=spec, base=base, metrics=None, oversample=int(oversample),
                   process_upsample=process_upsample, device=device,
                   surround=resolve_surround(None, design.metadata, source)[0])
    check_memory(evaluation_bytes(ev), f"{source}: one tolerance sample of this {design.shape[0]} x "
                 f"{design.shape[1]} px design ({ev.wavelengths_m.size} wavelengths, {ev.depths_m.size} depths)")
    t0 = time.perf_counter()
    ideal = {p.name: 0.0 for p in spec.params}
    psf = ev.coded_psf(ev.height(ideal))
    ev.metrics = metric_set(design, camera, psf, wls, depths, metric_script)
    nominal = ev.metrics(psf)
    return ev, nominal, time.perf_counter() - t0


def evaluation_bytes(ev: Evaluator) -> int:
    """Peak bytes of one sample: the process model (about 64 bytes per process-grid sample,
    measured) and the coded-view PSF engine on the oversampled grid."""
    rows, cols = ev.levels.shape
    q, u = ev.oversample, ev.process_upsample or ev.oversample
    return 64 * rows * cols * u * u + psf_bytes(ev.camera, ev.pitch_m / q, (rows * q, cols * q),
                                                ev.wavelengths_m.size, ev.depths_m.size, n_views=1)


def sampling_description(ev: Evaluator) -> dict:
    """How the evaluator ``ev`` samples the element (grids, wavelengths, depths, surround), for the report."""
    u = ev.process_upsample or ev.oversample
    return {"oversample": ev.oversample, "process_upsample": u,
            "psf_grid_m": ev.pitch_m / ev.oversample, "process_grid_m": ev.pitch_m / u,
            "wavelengths_nm": (ev.wavelengths_m * 1e9).tolist(),
            "depths_m": [float(d) if np.isfinite(d) else "inf" for d in ev.depths_m], "views": ["coded"],
            "surround": ev.surround, "surround_means": describe_surround(ev.surround),
            "description": (f"process model on the whole element at {u} samples per design pixel "
                            f"({ev.pitch_m / u * 1e6:.3g} um), area-averaged to {ev.oversample} per pixel for the "
                            f"PSF engine; coded view, {ev.wavelengths_m.size} wavelengths, {ev.depths_m.size} "
                            "depth(s); sub-sample mask slivers are height-averaged (see masks/fabricated.py)")}


def tolerance_analysis(design: Design, spec: ToleranceSpec, n_samples: int, out_dir: str | Path,
                       design_name: str = "design", seed: int = 0, scheduler: str = "processes",
                       workers: int | None = None, oversample: int = 2, process_upsample: int | None = None,
                       wavelengths_m: np.ndarray | None = None, sobol_base: int = 8,
                       one_at_a_time: bool = True, thresholds: dict | None = None,
                       metric_script: str | None = None, yield_goal: float | None = None, device: str = "cpu") -> dict:
    """Run the study and write ``report.json``, ``report.md``, ``distributions.png``, ``tornado.png``.

    Parameters
    ----------
    yield_goal : float, optional
        Share of elements that must meet every threshold, in (0, 1); default the spec's
        (``[yield] goal``, else 0.9).
    device : {"cpu", "gpu", "auto"}
        Where each sample is computed (:mod:`doedesign.engine.backend`): process render, PSFs
        and metrics. On GPUs the local ``processes`` cluster has one single-threaded worker per
        visible GPU, pinned to it (:func:`masks.tolerance.runner.make_client`).

    Returns
    -------
    dict
        The report (see ``doe tolerance --help``).
    """
    if n_samples < 1:
        raise DoeError(f"--samples {n_samples}: need at least one sample")
    if sobol_base < 0:
        raise DoeError(f"--sobol-base {sobol_base}: must be >= 0")
    goal = spec.yield_goal if yield_goal is None else check_yield_goal(yield_goal, "yield goal")
    t_start = time.perf_counter()
    ev, nominal, t_nominal = build_evaluator(design, spec, design_name, oversample, process_upsample,
                                             wavelengths_m, metric_script, device)
    assert ev.metrics is not None  # build_evaluator sets it up
    directions = {**DIRECTIONS, **ev.metrics.directions()}
    primary = ev.metrics.primary
    thresholds = dict(spec.thresholds, **(thresholds or {}))
    for m in thresholds:
        if m not in nominal:
            raise DoeError(f"threshold on unknown metric {m!r}; this design's metrics: {', '.join(nominal)}")
    if not thresholds:
        thresholds = default_thresholds(primary, nominal, directions.get(primary, "higher"))
    def mc_job(k):
        values, s = spec.draw(seed, k)
        return {"id": f"mc-{k:05d}", "kind": "mc", "index": k, "seed": s, "values": values}

    # Monte Carlo samples are drawn as they are handed out (sample k from its own seed, so
    # the same values whenever it is drawn); the sensitivity runs are few and listed.
    extra = oat_jobs(spec) if one_at_a_time and spec.random_params else []
    extra += sobol_jobs(spec, sobol_base, seed)
    sampling = sampling_description(ev)
    key = run_key({"design": hashlib.sha256(np.ascontiguousarray(ev.levels).tobytes()).hexdigest(),
                   "shape": ev.levels.shape, "pitch": ev.pitch_m, "spec": spec.describe()["parameters"],
                   "seed": seed, "sampling": sampling, "script": ev.metrics.script_source})
    t_run = time.perf_counter()
    # Connect first: a run that cannot reach its scheduler writes nothing. The folder says
    # INCOMPLETE until the report is written; finished samples are kept for a rerun to resume.
    gpu = ev.backend.device == "gpu"
    if scheduler in ("processes", "threads") and not gpu:  # GPU workers hold a sample in device memory
        local = local_workers(scheduler, workers)
        check_memory((local + 1) * evaluation_bytes(ev),
                     f"{design_name}: {local} local tolerance worker(s) of {format_bytes(evaluation_bytes(ev))} each")
    with make_client(scheduler, workers, gpu=gpu) as client:
        n_threads = n_workers(client)
        with output_run(out_dir, f"doe tolerance {design_name}", keep_partial=True):
            samples_dir = open_store(out_dir, key, {"design": design_name, "seed": seed})
            results = run_jobs(ev, itertools.chain(map(mc_job, range(n_samples)), extra), samples_dir, client,
                               seconds_per_job=t_nominal, total=n_samples + len(extra))
            t_run = time.perf_counter() - t_run
            report = _write_report(spec, ev, nominal, results, n_samples, extra, out_dir, design_name,
                                   seed, scheduler, n_threads, sampling, thresholds, goal, directions, primary,
                                   one_at_a_time, t_nominal, t_run, t_start)
    return report


def _write_report(spec, ev, nominal, results, n_samples, extra, out_dir, design_name, seed, scheduler,
                  n_threads, sampling, thresholds, goal, directions, primary, one_at_a_time, t_nominal, t_run,
                  t_start):
    mc = [results[f"mc-{k:05d}"] for k in range(n_samples)]
    by_name = {p.name: p for p in spec.params}
    samples = [{"index": r["index"], "seed": r["seed"],
                "effects": {n: by_name[n].to_report(v) for n, v in r["values"].items()},
                "metrics": r["metrics"]} for r in mc]
    sensitivity = {"metric": primary}
    if one_at_a_time and spec.random_params:
        sensitivity["one_at_a_time"] = oat_table(spec, results, primary)
    sensitivity["sobol"] = sobol_indices(spec, results, primary, seed)
    out = Path(out_dir)
    report = {
        "design": design_name,
        "spec": spec.describe(),
        "run": {"samples": n_samples, "seed": seed, "scheduler": scheduler, "workers": n_threads,
                "jobs": n_samples + len(extra),
                "seed_rule": "sample k uses numpy SeedSequence([seed, k])"},
        "sampling": sampling,
        "primary_metric": primary,
        "metric_note": ev.metrics.note,
        "nominal": nominal,
        "metrics": metric_summary(samples, nominal, directions),
        "yield": yield_summary(samples, thresholds, goal),
        "sensitivity": sensitivity,
        "samples": samples,
        "timing": {"seconds_per_sample": float(np.median([r["seconds"] for r in results.values()])),
                   "nominal_s": t_nominal, "run_s": t_run, "total_s": time.perf_counter() - t_start},
        "units": "effects in the unit named in each key (nm, um, urad); metrics are fractions of the light "
                 "through the coded half-aperture unless named _px",
    }
    write_json(out / "report.json", report)
    plot_distributions(samples, nominal, out / "distributions.png")
    if sensitivity.get("one_at_a_time") and sensitivity["one_at_a_time"]["rows"]:
        plot_tornado(sensitivity["one_at_a_time"], out / "tornado.png")
    tolerance_page(report, out)
    return report
