"""`doe import` of a 4500 x 4500 phase map (.npy): CPU time and peak traced memory against the
limits of issue 53 (5 s, twice the array's memory)."""

from __future__ import annotations

import tempfile
import time
import tracemalloc
from pathlib import Path

import numpy as np


def run(quick: bool = False) -> list[dict]:
    from doedesign.importer import import_design

    n = 1500 if quick else 4500
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        src = Path(tmp) / "phase.npy"
        x = (np.arange(n) - n / 2) * 5.4e-6
        np.save(src, (-np.pi * (x[:, None] ** 2 + x[None, :] ** 2) / (550e-9 * 0.05)).astype(np.float64))
        array_bytes = n * n * 8
        tracemalloc.start()
        t0 = time.process_time()
        import_design(src, pitch_m=5.4e-6, phase_at_m=550e-9, n_levels=16)
        cpu = time.process_time() - t0
        peak = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
    note = f"{n} x {n} float64 phase map, 16 levels; CPU seconds (time.process_time), tracemalloc peak"
    rows.append({"benchmark": "doe import", "figure": f"CPU time, {n} x {n} map", "value": round(cpu, 2), "unit": "s",
                 "peer": None, "peer_value": None, "ratio": None, "limit": 5.0, "notes": note})
    rows.append({"benchmark": "doe import", "figure": f"peak memory / array memory, {n} x {n} map",
                 "value": round(peak / array_bytes, 2), "unit": "x", "peer": None, "peer_value": None, "ratio": None,
                 "limit": 2.0, "notes": note})
    return rows


if __name__ == "__main__":
    import json

    print(json.dumps(run(), indent=1))
