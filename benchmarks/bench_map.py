"""``doe map``: CPU per tile, scaling with Dask workers, memory per worker, and the 16000 x 16000 estimate.

An element from the tests' generator (:mod:`elementgen`) on a 1024 px design (the 2048 x 2048
map at 2 map pixels per design pixel; a tile's model evaluations read the design, so its size
is part of the cost), 40 design-pixel tiles:

- CPU seconds of one tile (on one BLAS thread, as every tile runs) at 2, 4 and 10 map pixels per
  design pixel (the 0.55 um map of a 5.4 um design is 10), and the peak memory its diagnosis
  allocates (tracemalloc, a separate call: it slows the one it watches);
- the same measured tiles on a LocalCluster of 1 and 2 workers started here: the cluster's start,
  the run's wall time, each worker's CPU (so the load's balance) and its peak RSS
  (``ru_maxrss``); scaling efficiency ``t1 / (n t_n)`` with and without the start;
- the rate in tiles per CPU second, and from it the 16000 x 16000 map (1600 px design at u=10,
  the tiles of ``doe map``'s defaults) in core-hours and on a 64-worker cluster, and the 2048 x
  2048 map on 2 workers.

The machine is shared: every timed row's notes carry the load average, and wall figures on a
loaded machine are upper bounds (the CPU figures are not). ``python -m benchmarks.bench_map
--map2048 OUT`` runs the 2048 x 2048 map through ``doe map`` itself (progress bar on stderr)
and prints its rows (merge them with ``benchmarks/run.py --rows``).
"""

from __future__ import annotations

import os
import resource
import subprocess
import sys
import tempfile
import time
import tracemalloc
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests" / "metrology"))
import elementgen  # noqa: E402  (the tests' independent generator)

EFFECTS = ["etch_depth", "mask_overlay", "linewidth_bias", "etch_loading", "mask_rotation"]
T = 40
N_DESIGN = 1024
# The element: 3 % radial depth, 10 ppm magnification of mask 2, mask 3 shifted and turned.
TRUTH = {"radial": 0.03, "magnification": {2: 10e-6}, "shift_m": {3: (50e-9, -30e-9)}, "rotation_rad": {3: 10e-6}}
CLUSTER_WORKERS = 64


def _row(figure, value, unit, notes="", limit=None):
    return {"benchmark": "map", "figure": figure, "value": value, "unit": unit, "peer": None, "peer_value": None,
            "ratio": None, "limit": limit, "notes": notes}


def _load():
    return "load %.1f" % os.getloadavg()[0]


def _tile_cost(levels, tmp, u, memory=True):
    """CPU s of one tile at ``u`` map pixels per design pixel (after a warm call), and its peak MiB."""
    from metrology.diagnosis.tiles_map import diagnose_tile

    r0 = 80
    region = [r0, r0 + T, r0, r0 + T]
    path = Path(tmp) / f"tile{u}.npy"
    # The map ends with the tile (a tile reads only its own pixels); the generator renders the
    # design's first rows and columns only, so the truth's centre is theirs.
    np.save(path, elementgen.measure(levels[:r0 + T, :r0 + T], u, [tuple(region)], TRUTH))
    args = (levels, elementgen.PITCH_M, str(path), u, {"id": "t", "region": region}, list(elementgen.DEPTHS_M),
            EFFECTS, 10.0)
    diagnose_tile(*args)  # imports and caches warm
    t0 = time.process_time()
    diagnose_tile(*args)
    cpu = time.process_time() - t0
    peak = None
    if memory:
        tracemalloc.start()
        diagnose_tile(*args)
        peak = tracemalloc.get_traced_memory()[1] / 2 ** 20
        tracemalloc.stop()
    return cpu, peak


def _worker_cpu():
    return time.process_time()


def _worker_peak_mib():
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def _scaling(levels, tmp, n_tiles):
    """Per worker count: cluster start, run wall, per-worker CPU and peak RSS for ``n_tiles`` tiles."""
    from distributed import Client, LocalCluster

    from metrology.diagnosis.tiles_map import run_map

    per_side = int(np.ceil(np.sqrt(n_tiles)))
    starts = [i * T for i in range(per_side)]
    patches = [(r, r + T, c, c + T) for r in starts for c in starts][:n_tiles]
    # The design's first rows and columns, every tile measured (a tile's cost hardly depends on
    # the design's size once its levels are checked; the scatter of the whole design is timed apart).
    sub = levels[:per_side * T, :per_side * T]
    np.save(Path(tmp) / "many_sub.npy", elementgen.measure(sub, 2, patches, TRUTH))
    out = {}
    for workers in (1, 2):
        t0 = time.perf_counter()
        cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True, dashboard_address=None)
        client = Client(cluster)
        start_s = time.perf_counter() - t0
        try:
            cpu0 = client.run(_worker_cpu)
            load0 = os.getloadavg()[0]
            t0 = time.perf_counter()
            run_map(sub, elementgen.PITCH_M, Path(tmp) / "many_sub.npy", 2, Path(tmp) / f"w{workers}", tile_px=T,
                    overlap_px=0, candidates=EFFECTS, scheduler=cluster.scheduler_address)
            wall = time.perf_counter() - t0
            cpu1 = client.run(_worker_cpu)
            peaks = client.run(_worker_peak_mib)
            t0 = time.perf_counter()
            client.scatter(levels, broadcast=True)  # the one payload every task shares (1024 px design)
            scatter_s = time.perf_counter() - t0
        finally:
            client.close()
            cluster.close()
        cpus = [cpu1[k] - cpu0[k] for k in cpu0]
        out[workers] = {"start_s": start_s, "wall_s": wall, "cpu_s": cpus, "peak_mib": list(peaks.values()),
                        "scatter_s": scatter_s, "load": (load0 + os.getloadavg()[0]) / 2}
    return out


def run(quick: bool = False) -> list[dict]:
    from metrology.diagnosis.tiles_map import map_tiles

    rows = []
    levels = elementgen.element_levels(N_DESIGN)
    per_tile = {}
    with tempfile.TemporaryDirectory() as tmp:
        for u in ((2, 4) if quick else (2, 4, 10)):
            cpu, peak = _tile_cost(levels, tmp, u)
            per_tile[u] = cpu
            rows.append(_row(f"CPU per 40 px tile, u={u}", round(cpu, 2), "s",
                             f"1024 px design, one BLAS thread; {_load()}"))
            rows.append(_row(f"tiles per CPU second, u={u}", round(1 / cpu, 2), "1/s", "the rate the estimates use"))
            rows.append(_row(f"peak memory per tile, u={u}", round(peak, 1), "MiB", "tracemalloc: the tile's own"))
        n_tiles = 8 if quick else 16
        sc = _scaling(levels, tmp, n_tiles)
    one, two = sc[1], sc[2]
    for w, s in sc.items():
        rows.append(_row(f"cluster start, {w} worker(s)", round(s["start_s"], 1), "s", f"LocalCluster + Client; load {s['load']:.1f}"))
        rows.append(_row(f"wall, {n_tiles} tiles, {w} worker(s)", round(s["wall_s"], 1), "s",
                         f"run_map on a running cluster; worker CPU {', '.join(f'{c:.1f}' for c in s['cpu_s'])} s; "
                         f"load {s['load']:.1f}"))
        rows.append(_row(f"peak RSS per worker, {w} worker(s)", round(max(s["peak_mib"]), 0), "MiB",
                         "ru_maxrss of each worker after the run (imports, the design, one tile at a time)"))
    eff = one["wall_s"] / (2 * two["wall_s"])
    eff_start = (one["wall_s"] + one["start_s"]) / (2 * (two["wall_s"] + two["start_s"]))
    cpu2 = two["cpu_s"]
    rows.append(_row("scaling efficiency 2 workers", round(eff, 2), "1",
                     f"t1 / (2 t2) on a running cluster; {round(eff_start, 2)} with the cluster's start; "
                     f"2 cores shared, load {two['load']:.1f}"))
    eff_cpu = sum(one["cpu_s"]) / (2 * max(cpu2))
    rows.append(_row("scaling efficiency 2 workers, from CPU", round(eff_cpu, 2), "1",
                     "t1 CPU / (2 x the busier worker's CPU): the wall an idle machine would give, the "
                     "cluster's start and the scheduler's latency aside"))
    rows.append(_row("load balance 2 workers", round(max(cpu2) / (sum(cpu2) / 2), 2), "1",
                     "max / mean worker CPU over the run (1 = even); tiles_per_task 4"))
    rows.append(_row("scatter of the 1024 px design", round(two["scatter_s"], 2), "s", "broadcast to 2 workers, once a run"))
    u16 = 10 if 10 in per_tile else 4
    cost16 = per_tile[u16] * (1.0 if u16 == 10 else (10 / 4) ** 2)
    tiles_16k = len(map_tiles((1600, 1600), T, 8))
    cpu_16k = tiles_16k * cost16
    rows.append(_row("16000 x 16000 map, CPU estimate", round(cpu_16k / 3600, 1), "core-hours",
                     f"{tiles_16k} tiles (1600 px design, 40/8 px) x {cost16:.2f} s (u=10"
                     f"{'' if u16 == 10 else ' from u=4 x (10/4)^2'}); on {CLUSTER_WORKERS} workers at the measured "
                     f"efficiency {cpu_16k / CLUSTER_WORKERS / max(eff, 0.1) / 60:.0f} min"))
    tiles_2k = len(map_tiles((N_DESIGN, N_DESIGN), T, 8))
    rows.append(_row("2048 x 2048 map (u=2), CPU estimate", round(tiles_2k * per_tile[2] / 60, 1), "CPU min",
                     f"{tiles_2k} tiles x the u=2 tile cost; / 2 workers at efficiency {eff:.2f}: "
                     f"{tiles_2k * per_tile[2] / 2 / max(eff, 0.1) / 60:.1f} min wall", limit=None))
    return rows


def _tree_sample(proc, seen):
    """CPU seconds and RSS of ``proc`` and its descendants, latest per pid, into ``seen``."""
    import psutil

    try:
        procs = [proc] + proc.children(recursive=True)
    except psutil.NoSuchProcess:
        return
    for p in procs:
        try:
            t = p.cpu_times()
            rss = p.memory_info().rss
            name = " ".join(p.cmdline()[:3])
        except (psutil.NoSuchProcess, psutil.AccessDenied):
            continue
        old = seen.get(p.pid, {"peak_rss": 0})
        seen[p.pid] = {"cpu": t.user + t.system, "peak_rss": max(old["peak_rss"], rss), "name": name}


def map2048(out: str, limit_s: float = 1800.0) -> list[dict]:
    """The 2048 x 2048 map through ``doe map`` (2 workers, progress bar on stderr): wall, CPU
    (the process tree's, sampled every 2 s), each process's peak RSS, and the load. A run past
    ``limit_s`` is interrupted (resumable) and reported with the tiles it finished."""
    import signal

    import psutil

    out_dir = Path(out)
    out_dir.mkdir(parents=True, exist_ok=True)
    levels = elementgen.element_levels(N_DESIGN)
    if not (out_dir / "map.npy").is_file():
        from doedesign.design import Design

        masks = np.stack([(levels >> j) & 1 for j in range(4)])
        Design(height_m=-np.tensordot(np.array(elementgen.DEPTHS_M), masks, 1), pitch_m=elementgen.PITCH_M,
               levels=levels.astype(np.int16)).save(out_dir / "design.npz")
        np.save(out_dir / "map.npy", elementgen.measure(levels, 2, [(0, N_DESIGN, 0, N_DESIGN)], TRUTH))
    cmd = [str(Path(sys.executable).with_name("doe")), "map", "--design", str(out_dir / "design.npz"), "--measured",
           str(out_dir / "map.npy"), "--upsample", "2", "--out", str(out_dir / "run"), "--workers", "2",
           "--effects", ",".join(EFFECTS)]
    load0 = os.getloadavg()
    seen = {}
    t0 = time.perf_counter()
    child = subprocess.Popen(cmd, env={**os.environ, "DOE_PROGRESS": "1"})  # the bar on a non-terminal stderr too
    proc = psutil.Process(child.pid)
    finished = True
    while child.poll() is None:
        _tree_sample(proc, seen)
        if time.perf_counter() - t0 > limit_s:
            finished = False
            child.send_signal(signal.SIGINT)
            try:
                child.wait(60)
            except subprocess.TimeoutExpired:
                child.kill()
            break
        time.sleep(2)
    wall = time.perf_counter() - t0
    load1 = os.getloadavg()
    cpu = sum(v["cpu"] for v in seen.values())
    # The driver's descendants (the workers, the resource tracker); their command lines vary.
    workers = [v["peak_rss"] / 2 ** 20 for pid, v in seen.items() if pid != child.pid and v["peak_rss"] > 2 ** 27]
    done = (out_dir / "run" / "tiles.jsonl").read_text().count("\n") if (out_dir / "run" / "tiles.jsonl").is_file() else 0
    load = f"load at start {load0[0]:.1f} (15 min {load0[2]:.1f}), at end {load1[0]:.1f} (15 min {load1[2]:.1f})"
    what = "1024 tiles of 40/8 px" if finished else f"interrupted at {limit_s / 60:.0f} min: {done} of 1024 tiles"
    return [_row("2048 x 2048 map, doe map on 2 workers, wall", round(wall / 60, 1), "min",
                 f"{what}, progress bar; {load}", limit=10),
            _row("2048 x 2048 map, CPU", round(cpu / 60, 1), "CPU min",
                 f"doe map, its nanny and workers (sampled every 2 s); CPU / 2 = {cpu / 2 / 60:.1f} min, the wall "
                 f"an idle 2-core machine would take; {cpu / max(done, 1):.2f} CPU s per tile"),
            _row("2048 x 2048 map, peak RSS per worker", round(max(workers, default=0.0)), "MiB",
                 f"psutil, sampled every 2 s; workers {', '.join(f'{w:.0f}' for w in workers)} MiB")]


if __name__ == "__main__":
    import json

    if "--map2048" in sys.argv:
        i = sys.argv.index("--map2048")
        limit = float(sys.argv[i + 2]) if len(sys.argv) > i + 2 else 1800.0
        print(json.dumps(map2048(sys.argv[i + 1], limit), indent=1))
    else:
        print(json.dumps(run(quick="--quick" in sys.argv), indent=1))
