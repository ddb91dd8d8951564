"""Tolerance analysis on Dask: samples per second at 1 and 2 workers, memory per worker, and
the per-sample cost of the full element, from which the notes project 1,000 samples x 31
wavelengths on 100 workers.

Scaling: a 256 x 256 px Bayer-metadata element (128 x 128 window, 3 wavelengths, PSF
oversample 2, default spec), the same jobs in process (the peer: no Dask) and on a
LocalCluster of 1 and 2 process workers; cluster start-up is timed apart. Every run is
pinned to one core per worker (the in-process one too), so the rates compare one core with
two; CPU time per sample, which other jobs on the machine do not inflate, is reported beside. Full element:
one sample of a 1600 x 1600 px element at oversample 2 (3200^2 PSF grid), process model
timed apart from the PSF engine per wavelength. Robust design: the Bayer element designed plainly
and robustly (:func:`masks.tolerance.robust.nominal_vs_robust`), both run through the same
tolerance study; the robust design is the value, the plain one the peer.
"""

from __future__ import annotations

import math
import os
import tempfile
import time

import numpy as np

from doedesign.camera import Camera
from doedesign.design import Design
from doedesign.levels import level_step_m
from masks.tolerance.analysis import build_evaluator, nominal_depths
from masks.tolerance.robust import nominal_vs_robust
from masks.tolerance.runner import make_client, run_jobs
from masks.tolerance.spec import default_spec

PITCH = 5.4e-6
# The robust-design study: a fab with poorer control than the built-in default spec.
ROBUST_SPEC = {"etch_depth": {"sigma_rel": 0.06}, "mask_overlay": {"sigma_um": 1.0}, "linewidth_bias": {"sigma_um": 0.3}}


def _design(n, window, wavelengths_nm=(656.0, 589.0, 486.0), kind="bayer"):
    rng = np.random.default_rng(0)
    levels = rng.integers(0, 16, (n, n)).astype(np.int16)
    cam = Camera(aperture_diameter_m=n * PITCH, focus_distance_m=math.inf, window_shape=(window, window),
                 axis_pixel=(window // 2, window // 2))
    meta = {"camera": cam.to_dict(), "n_levels": 16,
            "target": {"kind": kind, "wavelengths_nm": [float(w) for w in wavelengths_nm], "depths_m": ["inf"]}}
    return Design(height_m=-levels * level_step_m("fused_silica", 550e-9, 16), pitch_m=PITCH, levels=levels,
                  metadata=meta)


def _jobs(spec, n):
    out = []
    for k in range(n):
        values, seed = spec.draw(0, k)
        out.append({"id": f"mc-{k:05d}", "kind": "mc", "index": k, "seed": seed, "values": values})
    return out


def _worker_rss_mib(client):
    import psutil

    return max(client.run(lambda: psutil.Process().memory_info().rss).values()) / 2 ** 20


def _worker_cpu_s(client):
    import psutil

    def cpu():
        t = psutil.Process().cpu_times()
        return t.user + t.system

    return sum(client.run(cpu).values())


def _pin_workers(client):
    """One core per worker: the PSF engine's FFTs ask for every core, which would oversubscribe."""
    cores = sorted(os.sched_getaffinity(0))
    for i, address in enumerate(sorted(client.scheduler_info()["workers"])):
        client.run(os.sched_setaffinity, 0, {cores[i % len(cores)]}, workers=[address])


def _scaling(n_px, window, n_samples):
    design = _design(n_px, window)
    spec = default_spec(nominal_depths(design))
    ev, _, t_nominal = build_evaluator(design, spec)
    jobs = _jobs(spec, n_samples)
    out = {}
    with tempfile.TemporaryDirectory() as tmp:
        cores = os.sched_getaffinity(0)
        os.sched_setaffinity(0, {min(cores)})
        try:
            t0, c0 = time.perf_counter(), time.process_time()
            run_jobs(ev, jobs, f"{tmp}/inline")
            out["inline"] = n_samples / (time.perf_counter() - t0)
            out["cpu_inline"] = (time.process_time() - c0) / n_samples
        finally:
            os.sched_setaffinity(0, cores)
        for workers in (1, 2):
            t0 = time.perf_counter()
            with make_client("processes", workers) as client:
                out[f"start_{workers}"] = time.perf_counter() - t0
                _pin_workers(client)
                c1 = _worker_cpu_s(client)
                t1 = time.perf_counter()
                run_jobs(ev, jobs, f"{tmp}/w{workers}", client, seconds_per_job=t_nominal)
                out[f"rate_{workers}"] = n_samples / (time.perf_counter() - t1)
                out[f"cpu_{workers}"] = (_worker_cpu_s(client) - c1) / n_samples
                out[f"rss_{workers}"] = _worker_rss_mib(client)
    return out


def _full_element_cost(n_px, n_wl):
    # Generic metadata: the Bayer figure needs exactly three wavelengths.
    design = _design(n_px, 512, wavelengths_nm=np.linspace(486, 656, n_wl), kind="image")
    spec = default_spec(nominal_depths(design))
    ev, _, _ = build_evaluator(design, spec)
    values, seed = spec.draw(0, 0)
    t0, c0 = time.perf_counter(), time.process_time()
    h = ev.height(values, seed)
    t_process, c_process = time.perf_counter() - t0, time.process_time() - c0
    t0, c0 = time.perf_counter(), time.process_time()
    ev.coded_psf(h)
    t_psf, c_psf = time.perf_counter() - t0, time.process_time() - c0
    return t_process, t_psf / n_wl, c_process, c_psf / n_wl


def _load():
    return "load average {:.1f} / {:.1f} / {:.1f} (1/5/15 min)".format(*os.getloadavg())


def run(quick=False):
    n_px, window, n_samples = (64, 64, 8) if quick else (256, 128, 48)
    load_before = _load()
    s = _scaling(n_px, window, n_samples)
    load = f"{load_before} before, {_load()} after"
    eff = s["rate_2"] / (2 * s["rate_1"])
    case = f"{n_px}x{n_px} px, {window}^2 window, 3 wavelengths, oversample 2, default spec, {n_samples} samples"
    rows = [
        {"benchmark": "tolerance", "figure": "samples/s, 1 process worker", "value": s["rate_1"], "unit": "1/s",
         "peer": "in process, no Dask", "peer_value": s["inline"], "ratio": s["rate_1"] / s["inline"],
         "notes": f"{case}; cluster start {s['start_1']:.1f} s not included; {load}"},
        {"benchmark": "tolerance", "figure": "samples/s, 2 process workers", "value": s["rate_2"], "unit": "1/s",
         "peer": "in process, no Dask", "peer_value": s["inline"], "ratio": s["rate_2"] / s["inline"],
         "limit": 2 * s["rate_1"], "notes": f"{case}; scaling efficiency {eff:.2f} (limit = 2 x one worker); "
                                           f"cluster start {s['start_2']:.1f} s not included; 2 cores shared; {load}"},
        {"benchmark": "tolerance", "figure": "RSS per worker after the run (2 workers)", "value": s["rss_2"], "unit": "MiB",
         "notes": f"{case}; 1 worker: {s['rss_1']:.0f} MiB"},
        {"benchmark": "tolerance", "figure": "CPU time per sample, 2 process workers", "value": s["cpu_2"], "unit": "s",
         "peer": "in process, no Dask", "peer_value": s["cpu_inline"], "ratio": s["cpu_2"] / s["cpu_inline"],
         "notes": f"{case}; 1 worker: {s['cpu_1']:.2f} s; CPU time is what load does not inflate; {load}"},
    ]
    n_full, n_wl = (400, 1) if quick else (1600, 2)
    load_before = _load()
    t_process, t_wl, c_process, c_wl = _full_element_cost(n_full, n_wl)
    load = f"{load_before} before, {_load()} after"
    per_sample_31 = t_process + 31 * t_wl
    hours = 1000 * per_sample_31 / 100 / 3600
    rows += [
        {"benchmark": "tolerance", "figure": f"process model, {n_full} px element at oversample 2", "value": t_process,
         "unit": "s", "notes": f"whole element, default-spec sample (overlay + bias + depth); CPU {c_process:.1f} s; {load}"},
        {"benchmark": "tolerance", "figure": f"coded PSF per wavelength, {n_full} px element at oversample 2",
         "value": t_wl, "unit": "s", "notes": f"512 x 512 window; mean of {n_wl} wavelengths; CPU {c_wl:.1f} s; {load}"},
        {"benchmark": "tolerance", "figure": "projected 1,000 samples x 31 wavelengths on 100 workers",
         "value": hours, "unit": "h",
         "notes": f"per sample {per_sample_31:.0f} s = process {t_process:.1f} s + 31 x {t_wl:.2f} s on this "
                  f"machine's core(s); x 1000 / 100 workers, assuming each worker is as fast as this machine and "
                  "perfect scaling (measured efficiency above); Sobol/OAT runs add N(G+2) + 2P samples; from CPU "
                  f"time ({c_process + 31 * c_wl:.0f} s per sample on one core): "
                  f"{1000 * (c_process + 31 * c_wl) / 100 / 3600:.2f} h"},
    ]
    return rows + _robust_rows(quick)


def _robust_rows(quick):
    size, k, n_eval, iterations = (64, 2, 8, 10) if quick else (128, 8, 64, 30)
    load_before = _load()
    with tempfile.TemporaryDirectory() as tmp:
        r = nominal_vs_robust(size, 32, ROBUST_SPEC, tmp, robust_samples=k, eval_samples=n_eval,
                              iterations=iterations, anneal_iterations=max(iterations // 6, 3), keep=0.95)
    plain, robust = r["nominal"], r["robust"]
    spec = ", ".join(f"{e} {next(iter(v.items()))[0]} {next(iter(v.items()))[1]:g}" for e, v in ROBUST_SPEC.items())
    case = (f"Bayer element {size} px, camera scaled to the paper's f-number, {iterations} it. + annealing, "
            f"soft-min objective; robust: mean loss over K = {k} process samples; both through doe tolerance with "
            f"{n_eval} fresh samples (full process model, oversample 2); spec {spec}; {load_before}")
    rows = []
    for key, figure in (("nominal", "on-target light, nominal (mean of R, G, B)"),
                        ("worst_decile_mean", "on-target light, worst-decile mean"), ("mean", "on-target light, mean"),
                        ("yield", "yield (on-target >= 95 % of the plain design's nominal)")):
        note = case
        if key == "yield":
            note += (f"; 95 % intervals: robust {robust['yield_ci95'][0]:.2f}-{robust['yield_ci95'][1]:.2f}, "
                     f"plain {plain['yield_ci95'][0]:.2f}-{plain['yield_ci95'][1]:.2f}")
        rows.append({"benchmark": "robust_design", "figure": figure, "value": robust[key], "unit": "fraction",
                     "peer": "plain design", "peer_value": plain[key],
                     "ratio": robust[key] / plain[key] if plain[key] else None, "notes": note})
    paired = r["paired"]
    rows.append({"benchmark": "robust_design", "figure": "share of evaluation samples where the robust design is better",
                 "value": paired["robust_better_fraction"], "unit": "fraction", "limit": 0.5,
                 "notes": f"{case}; paired (same samples for both): mean difference {paired['mean_difference']:.5f} "
                          f"+- {paired['difference_se']:.5f} (standard error)"})
    rows.append({"benchmark": "robust_design", "figure": "design time", "value": robust["design_s"], "unit": "s",
                 "peer": "plain design", "peer_value": plain["design_s"],
                 "ratio": robust["design_s"] / plain["design_s"], "notes": case})
    return rows
