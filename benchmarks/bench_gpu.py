"""The engine on a GPU beside the same engine on the CPU of the same machine.

Rows (each the GPU figure with the CPU run beside it, host memory in and out: heights go in and
PSFs and gradients come out as NumPy arrays):

- the full PSF stack: 1600 x 1600 DOE, 31 wavelengths 400-700 nm, both views, 512 x 512 window
  (bench_psf's case), in double and single precision, with the largest difference from the CPU
  stack relative to its peak;
- ``value_and_grad`` of the demo's Bayer loss (the few target pixels and the window energy) at
  1600 px;
- the demo's Bayer design at 1600 px (its settings, as bench_design's ``bayer_design_time``);
- ``doe tolerance``: N Monte Carlo samples (default 1,000) of the full-size Bayer element
  (1600 px, the demo's camera and 512 x 512 window) at 31 wavelengths, process render, PSFs
  and metrics on the GPU, timed whole (nominal, samples, report) with the issue's limit of
  5 minutes per 1,000 samples; beside it a few samples of the same run on the CPU, whose
  per-sample time is extrapolated to N (labelled so in the row).

Run where CuPy finds a GPU: ``python -m benchmarks.bench_gpu --out rows.json`` (what
``benchmarks/gpu_check.sh`` does; ``--rows tolerance --tolerance-samples 200`` for a shorter
check). Times are medians of repeated runs after a warm-up. ``--device cpu`` runs the
tolerance rows on the CPU alone, at any size, to check the code where there is no GPU.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import statistics
import tempfile
import time

import numpy as np

from doedesign import targets
from doedesign.camera import Camera
from doedesign.engine.backend import select_backend
from doedesign.engine.psf import PSFEngine
from doedesign.optimizer.losses import LossSpec, make_loss

PITCH = 5.4e-6
CPU_THREADS = min(16, os.cpu_count() or 1)


def _median_time(fn, repeats):
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times), out


def _device_memory_gib():
    import cupy

    return cupy.get_default_memory_pool().total_bytes() / 2 ** 30


def psf_stack_rows(n=1600, n_wl=31, repeats=5):
    wavelengths = np.linspace(400e-9, 700e-9, n_wl)
    cam = Camera(aperture_diameter_m=n * PITCH)
    h = -np.random.default_rng(0).uniform(0, 1.2e-6, (n, n))
    label = f"{n}x{n} DOE, {n_wl} wavelengths, 2 views, 512x512"
    cpu = PSFEngine(cam, PITCH, h.shape, wavelengths_m=wavelengths, device="cpu")
    t_cpu, ref = _median_time(lambda: cpu.psf(h, threads=CPU_THREADS).psf, 1)
    rows = []
    for precision, limit in (("double", 1e-10), ("single", 1e-6)):
        gpu = PSFEngine(cam, PITCH, h.shape, wavelengths_m=wavelengths, device="gpu", precision=precision)
        gpu.psf(h)  # warm-up: cuFFT plans, kernels
        t_gpu, stack = _median_time(lambda: gpu.psf(h).psf, repeats)
        err = float(np.abs(stack - ref).max() / ref.max())
        rows.append(dict(benchmark="gpu_psf", figure=f"time, {precision} precision ({label})", value=t_gpu,
                         unit="s", peer=f"same engine on {CPU_THREADS} CPU threads", peer_value=t_cpu,
                         ratio=t_gpu / t_cpu, limit=0.15,
                         notes=f"host heights in, host PSF stack out; max difference from the CPU stack "
                               f"{err:.2e} of its peak (limit {limit:g}); device pool {_device_memory_gib():.2f} GiB"))
    return rows


def value_and_grad_rows(n=1600, repeats=20):
    cam = Camera(aperture_diameter_m=n * PITCH, focus_distance_m=np.inf)
    target = targets.bayer(cam)
    loss = make_loss(target, LossSpec.parse(targets.DEFAULT_LOSS["bayer"]))
    h = -np.random.default_rng(1).uniform(0, 1.2e-6, (n, n))
    out = {}
    for device in ("cpu", "gpu"):
        engine = PSFEngine(cam, PITCH, h.shape, wavelengths_m=target.wavelengths_m, depths_m=target.depths_m,
                           device=device)
        engine.value_and_grad(h, loss)
        out[device] = _median_time(lambda: engine.value_and_grad(h, loss), repeats if device == "gpu" else 3)
    (t_cpu, (v_cpu, g_cpu)), (t_gpu, (v_gpu, g_gpu)) = out["cpu"], out["gpu"]
    err = float(np.abs(g_gpu - g_cpu).max() / np.abs(g_cpu).max())
    return [dict(benchmark="gpu_value_and_grad", figure=f"value_and_grad, demo's Bayer loss, {n} px", value=t_gpu,
                 unit="s", peer="same engine on the CPU", peer_value=t_cpu, ratio=t_gpu / t_cpu, limit=0.020,
                 notes=f"loss reads the target pixels and the window energy; loss differs by "
                       f"{abs(v_gpu - v_cpu) / abs(v_cpu):.1e}, gradient by {err:.1e} of its largest value")]


def design_rows(n=1600):
    from benchmarks.bench_design import bayer_design_time

    rows = {}
    # A small design first compiles CuPy's kernels, so the timed GPU design is a warm one.
    bayer_design_time(size_px=256, max_iter=2, anneal_iter=1, full_window=False, device="gpu")
    for device in ("cpu", "gpu"):
        rows[device] = [r for r in bayer_design_time(size_px=n, full_window=False, device=device)
                        if r["benchmark"] == "bayer_design_time"][0]
    cpu, gpu = rows["cpu"], rows["gpu"]
    return [dict(benchmark="gpu_bayer_design", figure=gpu["figure"], value=gpu["value"], unit="s",
                 peer="same design on the CPU", peer_value=cpu["value"], ratio=gpu["value"] / cpu["value"], limit=10,
                 notes=f"warm (after a 256 px design in the same process); {gpu['notes']}")]


def paper_setting_rows():
    """``doe design bayer --paper-setting --device gpu`` timed whole, in this process (the command's
    parser built here: a checkout on PYTHONPATH has no entry points; the CPU run takes hours on 2
    cores and is not run beside it)."""
    import cupy

    from doedesign.cli.design import register

    parser = argparse.ArgumentParser()
    register(parser.add_subparsers())
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        args = parser.parse_args(["design", "bayer", "--paper-setting", "--device", "gpu", "--out", f"{tmp}/paper.npz"])
        rc = args.func(args) or 0
        wall = time.perf_counter() - t0
        report = json.load(open(f"{tmp}/report.json"))
    if rc != 0:
        raise RuntimeError(f"doe design --paper-setting exited with {rc}")
    history = report["loss_history"]
    pool_gib = cupy.get_default_memory_pool().total_bytes() / 2 ** 30
    return [dict(benchmark="gpu_paper_setting", figure="doe design bayer --paper-setting --device gpu (4500 px of 1.8 um)",
                 value=wall, unit="s", peer=None, peer_value=None, ratio=None, limit=60,
                 notes=f"{len(history['continuous'])} + {len(history.get('anneal', []))} evaluations, "
                       f"quantized efficiency {report['quantized']['efficiency']:.4f}, final loss "
                       f"{min(history.get('anneal') or history['continuous']):.6f}; device pool after the run "
                       f"{pool_gib:.2f} GiB (limit 16 GB)")]


def _bayer_element(n, n_wl, window=512):
    """The full-size Bayer element's geometry: the demo's camera (focused at infinity, ``window``
    pixels) over an n px aperture of 16 random levels (a sample's cost does not depend on the
    level map). Scored by the generic figure (light on the nominal PSF's brightest pixels), as
    the Bayer figure is defined at its three colours only."""
    from doedesign.design import Design
    from doedesign.levels import level_step_m

    levels = np.random.default_rng(0).integers(0, 16, (n, n)).astype(np.int16)
    cam = Camera(aperture_diameter_m=n * PITCH, focus_distance_m=math.inf, window_shape=(window, window),
                 axis_pixel=(window // 2, window // 2))
    wavelengths_nm = np.linspace(400.0, 700.0, n_wl) if n_wl > 1 else np.array([550.0])
    meta = {"camera": cam.to_dict(), "n_levels": 16,
            "target": {"kind": "image", "wavelengths_nm": [float(w) for w in wavelengths_nm], "depths_m": ["inf"]}}
    return Design(height_m=-levels * level_step_m("fused_silica", 550e-9, 16), pitch_m=PITCH, levels=levels,
                  metadata=meta)


def _tolerance_run(design, n_samples, device, scheduler):
    from masks.tolerance.analysis import nominal_depths, tolerance_analysis
    from masks.tolerance.spec import default_spec

    spec = default_spec(nominal_depths(design))
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        report = tolerance_analysis(design, spec, n_samples, tmp, design_name="bayer element", seed=0,
                                    scheduler=scheduler, sobol_base=0, one_at_a_time=False, device=device)
        return time.perf_counter() - t0, report


def tolerance_rows(n=1600, n_wl=31, samples=1000, cpu_samples=2, device="gpu", scheduler="inline", window=512):
    """``doe tolerance``'s Monte Carlo run on ``device`` beside a few samples of it on the CPU.

    Both run :func:`masks.tolerance.analysis.tolerance_analysis` whole (nominal element,
    samples, report; the default spec, no Sobol or one-at-a-time runs), oversample 2. The CPU
    run is ``cpu_samples`` samples in process (its FFTs on every core); its N-sample time is
    its nominal and report time plus N times its median per-sample time: an extrapolation.
    """
    design = _bayer_element(n, n_wl, window)
    t_dev, rep_dev = _tolerance_run(design, samples, device, scheduler)
    per_dev = rep_dev["timing"]["seconds_per_sample"]
    limit = 300.0 * samples / 1000
    primary = rep_dev["primary_metric"]
    case = (f"{n} px Bayer element (demo camera, {window}x{window} window, random 16-level map), {n_wl} wavelengths "
            f"400-700 nm, oversample 2, default spec, sobol and one-at-a-time off, scheduler {scheduler}")
    figure = f"doe tolerance, {samples} samples on the {device.upper()} ({case})"
    dev_notes = (f"limit: 5 min per 1,000 samples; {device}: {per_dev:.3f} s per sample (median), projected "
                 f"1,000 samples {t_dev + (1000 - samples) * per_dev:.0f} s")
    if cpu_samples < 1:  # the device run alone (a short lease): no peer in this run
        return [dict(benchmark="gpu_tolerance", figure=figure, value=t_dev, unit="s", peer=None, peer_value=None,
                     ratio=None, limit=limit, notes=f"{dev_notes}; no CPU run beside it")]
    t_cpu, rep_cpu = _tolerance_run(design, cpu_samples, "cpu", "inline")
    per_cpu = rep_cpu["timing"]["seconds_per_sample"]
    cpu_extrapolated = t_cpu + (samples - cpu_samples) * per_cpu
    same = [abs(a["metrics"][primary] - b["metrics"][primary]) for a, b in zip(rep_dev["samples"], rep_cpu["samples"])]
    return [dict(benchmark="gpu_tolerance", figure=figure,
                 value=t_dev, unit="s", peer=f"{cpu_samples} CPU samples extrapolated to {samples} "
                 f"({CPU_THREADS} CPU threads, in process)", peer_value=cpu_extrapolated,
                 ratio=t_dev / cpu_extrapolated, limit=limit,
                 notes=f"{dev_notes}; CPU: {t_cpu:.1f} s for "
                       f"{cpu_samples} sample(s) incl. nominal and report, {per_cpu:.2f} s per sample; the first "
                       f"{len(same)} samples' {primary} differ by at most {max(same, default=0.0):.1e} "
                       "between the two runs")]


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", required=True, help="rows (JSON list)")
    parser.add_argument("--skip-design", action="store_true")
    parser.add_argument("--rows", default="psf,grad,design,tolerance",
                        help="comma-separated rows to run: psf, grad, design, tolerance, paper (default all "
                             "but paper, the --paper-setting design: about 80 s)")
    parser.add_argument("--device", choices=("gpu", "cpu"), default="gpu",
                        help="cpu: the tolerance rows alone, on the CPU (a check where there is no GPU)")
    parser.add_argument("--tolerance-samples", type=int, default=1000, help="device samples (default 1000)")
    parser.add_argument("--tolerance-cpu-samples", type=int, default=2,
                        help="CPU samples beside them (default 2; 0: the device run alone)")
    parser.add_argument("--tolerance-size", type=int, default=1600, help="element size, px (default 1600)")
    parser.add_argument("--tolerance-wavelengths", type=int, default=31, help="wavelengths (default 31)")
    parser.add_argument("--tolerance-window", type=int, default=512, help="sensor window, px (default 512)")
    parser.add_argument("--tolerance-scheduler", default="inline",
                        help="inline (default) or processes (one dask worker per GPU)")
    args = parser.parse_args(argv)
    wanted = {r.strip() for r in args.rows.split(",") if r.strip()}
    if args.device == "cpu":
        machine, wanted = f"no GPU: both runs on {CPU_THREADS} CPU threads", {"tolerance"}
    else:
        backend = select_backend("gpu")
        import cupy

        props = cupy.cuda.runtime.getDeviceProperties(0)
        machine = f"{props['name'].decode()}, {CPU_THREADS} CPU threads for the CPU rows ({backend.name})"
    groups = {"psf": psf_stack_rows, "grad": value_and_grad_rows, "design": design_rows, "paper": paper_setting_rows,
              "tolerance": lambda: tolerance_rows(args.tolerance_size, args.tolerance_wavelengths,
                                                  args.tolerance_samples, args.tolerance_cpu_samples, args.device,
                                                  args.tolerance_scheduler, args.tolerance_window)}
    if args.skip_design:
        wanted.discard("design")
    rows = []
    # Each group's rows are printed and written as they come, so a later failure keeps them.
    for name in (g for g in groups if g in wanted):
        for r in groups[name]():
            r["notes"] = f"{machine}; {r['notes']}"
            beside = "no CPU run" if r["peer_value"] is None else f"CPU {r['peer_value']:.4g}, ratio {r['ratio']:.3g}"
            print(f"{r['figure']}: {r['value']:.4g} {r['unit']} ({beside}, limit {r['limit']})", flush=True)
            rows.append(r)
        with open(args.out, "w") as f:
            json.dump(rows, f, indent=1)


if __name__ == "__main__":
    main()
