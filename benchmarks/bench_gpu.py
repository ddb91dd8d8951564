"""The engine on a GPU beside the same engine on the CPU of the same machine.

Rows (each the GPU figure with the CPU run beside it, host memory in and out: heights go in and
PSFs and gradients come out as NumPy arrays):

- the full PSF stack: 1600 x 1600 DOE, 31 wavelengths 400-700 nm, both views, 512 x 512 window
  (bench_psf's case), in double and single precision, with the largest difference from the CPU
  stack relative to its peak;
- ``value_and_grad`` of the demo's Bayer loss (the few target pixels and the window energy) at
  1600 px;
- the demo's Bayer design at 1600 px (its settings, as bench_design's ``bayer_design_time``).

Run where CuPy finds a GPU: ``python -m benchmarks.bench_gpu --out rows.json`` (what
``benchmarks/gpu_check.sh`` does). Times are medians of repeated runs after a warm-up.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
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
    for device in ("cpu", "gpu"):
        rows[device] = [r for r in bayer_design_time(size_px=n, full_window=False, device=device)
                        if r["benchmark"] == "bayer_design_time"][0]
    cpu, gpu = rows["cpu"], rows["gpu"]
    return [dict(benchmark="gpu_bayer_design", figure=gpu["figure"], value=gpu["value"], unit="s",
                 peer="same design on the CPU", peer_value=cpu["value"], ratio=gpu["value"] / cpu["value"], limit=10,
                 notes=gpu["notes"])]


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", required=True, help="rows (JSON list)")
    parser.add_argument("--skip-design", action="store_true")
    args = parser.parse_args(argv)
    backend = select_backend("gpu")
    import cupy

    props = cupy.cuda.runtime.getDeviceProperties(0)
    machine = f"{props['name'].decode()}, {CPU_THREADS} CPU threads for the CPU rows ({backend.name})"
    rows = psf_stack_rows() + value_and_grad_rows()
    if not args.skip_design:
        rows += design_rows()
    for r in rows:
        r["notes"] = f"{machine}; {r['notes']}"
        print(f"{r['figure']}: {r['value']:.4g} {r['unit']} (CPU {r['peer_value']:.4g}, ratio {r['ratio']:.3g}, "
              f"limit {r['limit']})", flush=True)
    with open(args.out, "w") as f:
        json.dump(rows, f, indent=1)


if __name__ == "__main__":
    main()
