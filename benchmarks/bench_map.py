"""``doe map``: CPU per tile, scaling with Dask workers, memory per worker, and the 16000 x 16000 estimate.

A null element from the tests' generator (:mod:`elementgen`), 40 design-pixel tiles: the CPU
seconds of one tile at 2 and 4 map pixels per design pixel (the 0.55 um map of a 5.4 um design is 10),
the peak memory one tile's diagnosis allocates (tracemalloc: the worker's own, the map never read
whole), and wall time for the same tiles with 1 and 2 local workers (scaling efficiency
``t1 / (n t_n)``; on 2 shared cores a third is the machine's). The 16000 x 16000 estimate scales the
measured u=4 cost by ``(10 / 4)^2`` (pixels per tile) over (16000 / 10 / 40)^2 tiles.
"""

from __future__ import annotations

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
TRUTH = {"depth_error": [0.02, 0.02, 0.02, 0.02], "shift_m": {2: (40e-9, 0.0)}}


def _row(figure, value, unit, notes="", limit=None):
    return {"benchmark": "map", "figure": figure, "value": value, "unit": unit, "peer": None, "peer_value": None,
            "ratio": None, "limit": limit, "notes": notes}


def run(quick: bool = False) -> list[dict]:
    from metrology.diagnosis.tiles_map import diagnose_tile, run_map

    rows = []
    n = 200
    levels = elementgen.element_levels(n)
    per_tile = {}
    with tempfile.TemporaryDirectory() as tmp:
        for u in (2, 4):
            path = Path(tmp) / f"map{u}.npy"
            np.save(path, elementgen.measure(levels, u, [(80, 80 + T, 80, 80 + T)], TRUTH))
            tile = {"id": "t", "region": [80, 80 + T, 80, 80 + T]}
            args = (levels, elementgen.PITCH_M, str(path), u, tile, list(elementgen.DEPTHS_M), EFFECTS, 10.0)
            diagnose_tile(*args)  # imports and caches warm
            t0 = time.process_time()
            diagnose_tile(*args)
            per_tile[u] = time.process_time() - t0
            tracemalloc.start()  # a separate call: tracemalloc slows the one it watches
            diagnose_tile(*args)
            peak = tracemalloc.get_traced_memory()[1]
            tracemalloc.stop()
            rows.append(_row(f"CPU per 40 px tile, u={u}", round(per_tile[u], 2), "s",
                             "depth 2 %, mask-2 overlay 40 nm; one process"))
            rows.append(_row(f"peak memory per tile, u={u}", round(peak / 2 ** 20, 1), "MiB", "tracemalloc"))
        k = 4 if quick else 8
        starts = [0, 40, 80, 120][: k // 2]
        patches = [(r, r + T, c, c + T) for r in starts for c in (0, 160)]
        path = Path(tmp) / "many.npy"
        np.save(path, elementgen.measure(levels, 2, patches, TRUTH))
        walls = {}
        for workers in (1, 2):
            t0 = time.perf_counter()
            run_map(levels, elementgen.PITCH_M, path, 2, Path(tmp) / f"w{workers}", tile_px=T, overlap_px=0,
                    candidates=EFFECTS, scheduler="processes", workers=workers, tiles_per_task=1)
            walls[workers] = time.perf_counter() - t0
            rows.append(_row(f"wall, {len(patches)} measured tiles, {workers} worker(s)", round(walls[workers], 1), "s",
                             "includes the cluster's start and the empty tiles"))
        rows.append(_row("scaling efficiency 2 workers", round(walls[1] / (2 * walls[2]), 2), "1",
                         "t1 / (2 t2), on 2 cores shared with other jobs"))
    tiles_16k = (16000 // 10 // T) ** 2
    cpu_16k = tiles_16k * per_tile[4] * (10 / 4) ** 2
    rows.append(_row("16000 x 16000 map, CPU estimate", round(cpu_16k / 3600, 1), "core-hours",
                     f"{tiles_16k} tiles x u=4 tile cost x (10/4)^2; on 64 workers {cpu_16k / 64 / 60:.0f} min"))
    tiles_2k = (1024 // T + 1) ** 2
    rows.append(_row("2048 x 2048 map (u=2), wall estimate on 2 workers", round(tiles_2k * per_tile[2] / 2 / 60, 1),
                     "min", f"{tiles_2k} tiles x the u=2 tile cost / 2", limit=10))
    return rows


if __name__ == "__main__":
    import json

    print(json.dumps(run(quick="--quick" in sys.argv), indent=1))
