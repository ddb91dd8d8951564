"""Reader speed, memory and fidelity on 1000 x 1000 Zygo files written to a temp dir.

Each format gets: read time (best of a few runs), peak Python/numpy memory during the
read (tracemalloc; HDF5's own C buffers are not counted), and the round-trip error
as a fraction of the format's resolution (half a phase count for .dat / .asc).
No peer is installed (prysm reads .dat / .datx but is not a dependency).
"""

from __future__ import annotations

import tempfile
import time
import tracemalloc
from pathlib import Path

import numpy as np

from metrology.formats.readers import read_measurement
from metrology.formats.writers import write_asc, write_dat, write_datx, write_xyz

WAVELENGTH_M = 632.8e-9


def _surface(n):
    """A 16-level staircase (75 nm steps, period 16 px) with 1 nm noise and 1 % invalid pixels."""
    rng = np.random.default_rng(0)
    h = -(np.arange(n)[np.newaxis, :] % 16) * 75e-9 + rng.normal(0, 1e-9, (n, n))
    h[rng.random((n, n)) < 0.01] = np.nan
    return h


def _measure(path, repeats):
    best = np.inf
    for _ in range(repeats):
        t0 = time.perf_counter()
        read_measurement(path)
        best = min(best, time.perf_counter() - t0)
    tracemalloc.start()
    meas = read_measurement(path)
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    return best, peak, meas


def run(quick=False):
    """Benchmark rows (see benchmarks/run.py for the keys)."""
    n = 1000
    surface = _surface(n)
    half_count_m = 0.5 * 0.5 * float(np.float32(WAVELENGTH_M)) / 32768
    cases = [("dat", lambda p: write_dat(p, surface, 1e-6, phase_res=1), half_count_m),
             ("datx", lambda p: write_datx(p, surface, 1e-6, unit="Fringes"), 1e-15)]
    if not quick:
        cases += [("asc", lambda p: write_asc(p, surface, 1e-6, phase_res=1), 0.5 * 0.5 * WAVELENGTH_M / 32768),
                  ("xyz", lambda p: write_xyz(p, surface, 1e-6), 0.5e-13)]
    rows = []
    array_mb = surface.nbytes / 1e6
    with tempfile.TemporaryDirectory() as tmp:
        for fmt, write, resolution in cases:
            path = Path(tmp) / f"s.{fmt}"
            write(path)
            seconds, peak, meas = _measure(path, 1 if quick or fmt in ("asc", "xyz") else 3)
            err = float(np.nanmax(np.abs(meas.height_m - surface)))
            same_mask = bool(np.array_equal(np.isnan(meas.height_m), np.isnan(surface)))
            base = dict(peer=None, peer_value=None, ratio=None)
            rows.append(dict(benchmark=f"read_{fmt}_{n}x{n}", figure="read time", value=seconds, unit="s",
                             limit=None, notes=f"file {path.stat().st_size / 1e6:.1f} MB", **base))
            rows.append(dict(benchmark=f"read_{fmt}_{n}x{n}", figure="peak traced memory", value=peak / 1e6,
                             unit="MB", limit=array_mb,
                             notes="limit = the float64 result itself; HDF5 C buffers not traced", **base))
            rows.append(dict(benchmark=f"read_{fmt}_{n}x{n}", figure="max round-trip error",
                             value=err, unit="m", limit=resolution,
                             notes=f"limit = half the format's resolution; invalid mask preserved: {same_mask}",
                             **base))
    return rows

