"""Tolerance analysis on Dask: samples per second at 1 and 2 workers, memory per worker, and
the per-sample cost of the full element, from which the notes project 1,000 samples x 31
wavelengths on 100 workers.

Scaling: a 128 x 128 px Bayer-metadata element (128 x 128 window, 3 wavelengths, PSF
oversample 2, default spec), the same jobs in process (the peer: no Dask) and on a
LocalCluster of 1 and 2 process workers; cluster start-up is timed apart. Full element:
one sample of a 1600 x 1600 px element at oversample 2 (3200^2 PSF grid), process model
timed apart from the PSF engine per wavelength.
"""

from __future__ import annotations

import math
import tempfile
import time

import numpy as np

from doedesign.camera import Camera
from doedesign.design import Design
from doedesign.levels import level_step_m
from masks.tolerance.analysis import build_evaluator, nominal_depths
from masks.tolerance.runner import make_client, run_jobs
from masks.tolerance.spec import default_spec

PITCH = 5.4e-6


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


def _scaling(n_px, window, n_samples):
    design = _design(n_px, window)
    spec = default_spec(nominal_depths(design))
    ev, _, t_nominal = build_evaluator(design, spec)
    jobs = _jobs(spec, n_samples)
    out = {}
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        run_jobs(ev, jobs, f"{tmp}/inline")
        out["inline"] = n_samples / (time.perf_counter() - t0)
        for workers in (1, 2):
            t0 = time.perf_counter()
            with make_client("processes", workers) as client:
                out[f"start_{workers}"] = time.perf_counter() - t0
                t1 = time.perf_counter()
                run_jobs(ev, jobs, f"{tmp}/w{workers}", client, seconds_per_job=t_nominal)
                out[f"rate_{workers}"] = n_samples / (time.perf_counter() - t1)
                out[f"rss_{workers}"] = _worker_rss_mib(client)
    return out


def _full_element_cost(n_px, n_wl):
    # Generic metadata: the Bayer figure needs exactly three wavelengths.
    design = _design(n_px, 512, wavelengths_nm=np.linspace(486, 656, n_wl), kind="image")
    spec = default_spec(nominal_depths(design))
    ev, _, _ = build_evaluator(design, spec)
    values, seed = spec.draw(0, 0)
    t0 = time.perf_counter()
    h = ev.height(values, seed)
    t_process = time.perf_counter() - t0
    t0 = time.perf_counter()
    ev.coded_psf(h)
    t_psf = time.perf_counter() - t0
    return t_process, t_psf / n_wl


def run(quick=False):
    n_px, window, n_samples = (64, 64, 8) if quick else (128, 128, 24)
    s = _scaling(n_px, window, n_samples)
    eff = s["rate_2"] / (2 * s["rate_1"])
    case = f"{n_px}x{n_px} px, {window}^2 window, 3 wavelengths, oversample 2, default spec, {n_samples} samples"
    rows = [
        {"benchmark": "tolerance", "figure": "samples/s, 1 process worker", "value": s["rate_1"], "unit": "1/s",
         "peer": "in process, no Dask", "peer_value": s["inline"], "ratio": s["rate_1"] / s["inline"],
         "notes": f"{case}; cluster start {s['start_1']:.1f} s not included"},
        {"benchmark": "tolerance", "figure": "samples/s, 2 process workers", "value": s["rate_2"], "unit": "1/s",
         "peer": "in process, no Dask", "peer_value": s["inline"], "ratio": s["rate_2"] / s["inline"],
         "limit": 2 * s["rate_1"], "notes": f"{case}; scaling efficiency {eff:.2f} (limit = 2 x one worker); "
                                           f"cluster start {s['start_2']:.1f} s not included; 2 cores shared"},
        {"benchmark": "tolerance", "figure": "RSS per worker after the run (2 workers)", "value": s["rss_2"], "unit": "MiB",
         "notes": case},
    ]
    n_full, n_wl = (400, 1) if quick else (1600, 2)
    t_process, t_wl = _full_element_cost(n_full, n_wl)
    per_sample_31 = t_process + 31 * t_wl
    hours = 1000 * per_sample_31 / 100 / 3600
    rows += [
        {"benchmark": "tolerance", "figure": f"process model, {n_full} px element at oversample 2", "value": t_process,
         "unit": "s", "notes": "whole element, default-spec sample (overlay + bias + depth)"},
        {"benchmark": "tolerance", "figure": f"coded PSF per wavelength, {n_full} px element at oversample 2",
         "value": t_wl, "unit": "s", "notes": f"512 x 512 window; mean of {n_wl} wavelengths"},
        {"benchmark": "tolerance", "figure": "projected 1,000 samples x 31 wavelengths on 100 workers",
         "value": hours, "unit": "h",
         "notes": f"per sample {per_sample_31:.0f} s = process {t_process:.1f} s + 31 x {t_wl:.2f} s on this "
                  f"machine's core(s); x 1000 / 100 workers, assuming each worker is as fast as this machine and "
                  "perfect scaling (measured efficiency above); Sobol/OAT runs add N(G+2) + 2P samples"},
    ]
    return rows
