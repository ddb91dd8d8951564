"""GDS export of a full 10 mm die (1852 x 1852 px): ours vs per-pixel boxes merged by KLayout.

Our export (merge, write, independent read-back and pixel comparison) runs in a child
process so its peak resident memory is its own. The peer builds one box per open pixel in a
KLayout Region, merges it and writes GDSII with the same 199-vertex limit (no verification).
Our file is also read by KLayout, whose polygon area per mask layer must equal the open
pixel count times the pixel area.
"""

from __future__ import annotations

import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from masks.decompose import levels_to_masks

PITCH_M = 5.4e-6
MAX_VERTICES = 199

_CHILD = r"""
import json, resource, sys, time, tracemalloc
import numpy as np
from masks.gds import export_masks
masks = np.load(sys.argv[1])
trace = sys.argv[3] == "trace"
if trace:
    tracemalloc.start()
t = time.perf_counter()
rep = export_masks(sys.argv[2], masks, float(sys.argv[4]), clear_aperture_m=None)
out = {"seconds": time.perf_counter() - t,
       "rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e3,
       "traced_mb": tracemalloc.get_traced_memory()[1] / 1e6 if trace else None,
       "file_size_bytes": rep["file_size_bytes"], "layers": rep["layers"],
       "mismatched_pixels": rep["verification"]["mismatched_pixels"]}
print(json.dumps(out))
"""


def _designs(n):
    yy, xx = np.mgrid[:n, :n] - n / 2
    # Fresnel-lens-like rings: f chosen so the outermost zones are ~6 px wide at n = 1852
    fresnel = np.floor(((xx ** 2 + yy ** 2) / (40.0 * n)) % 1 * 16).astype(np.int16)
    rnd = np.random.default_rng(0).integers(0, 16, (n, n)).astype(np.int16)
    return {"fresnel": fresnel, "random": rnd}


def _ours(masks, tmp, name, trace):
    npy = Path(tmp) / f"{name}_masks.npy"
    np.save(npy, masks)
    gds = Path(tmp) / f"{name}.gds"
    root = Path(__file__).resolve().parents[1]
    proc = subprocess.run([sys.executable, "-c", _CHILD, str(npy), str(gds),
                           "trace" if trace else "plain", repr(PITCH_M)],
                          capture_output=True, text=True, cwd=root, check=True)
    return json.loads(proc.stdout.strip().splitlines()[-1]), gds


def _klayout_boxes(masks, path):
    import klayout.db as db

    t = time.perf_counter()
    ly = db.Layout()
    ly.dbu = 0.001
    top = ly.create_cell("TOP")
    p = int(round(PITCH_M * 1e9))
    rows, cols = masks.shape[1:]
    for j, m in enumerate(masks):
        reg = db.Region()
        for r, c in zip(*np.nonzero(m)):
            x = int(c) * p - cols * p // 2
            y = rows * p // 2 - (int(r) + 1) * p
            reg.insert(db.Box(x, y, x + p, y + p))
        reg.merge()
        top.shapes(ly.layer(j + 1, 0)).insert(reg)
    opts = db.SaveLayoutOptions()
    opts.format = "GDS2"
    opts.gds2_max_vertex_count = MAX_VERTICES
    ly.write(str(path), opts)
    return time.perf_counter() - t, path.stat().st_size


def _klayout_area_mismatch(path, masks):
    """Largest |KLayout polygon area - open pixels x pixel area| over the mask layers, in px."""
    import klayout.db as db

    ly = db.Layout()
    ly.read(str(path))
    cell = ly.cell("ELEMENT")
    p = int(round(PITCH_M * 1e9))
    worst = 0.0
    for j, m in enumerate(masks):
        area = db.Region(cell.begin_shapes_rec(ly.layer(j + 1, 0))).area()
        worst = max(worst, abs(area / p ** 2 - int(m.sum())))
    return worst


def run(quick=False):
    n = 400 if quick else 1852
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for name, levels in _designs(n).items():
            masks = levels_to_masks(levels)
            ours, gds = _ours(masks, tmp, name, trace=False)
            traced = _ours(masks, tmp, name + "_traced", trace=True)[0]["traced_mb"]
            try:
                area_err = _klayout_area_mismatch(gds, masks)
                peer_s, peer_size = _klayout_boxes(masks, Path(tmp) / f"{name}_klayout.gds")
            except ImportError:
                area_err = peer_s = peer_size = None
            polys = sum(layer["polygons"] for layer in ours["layers"])
            verts = sum(layer["vertices"] for layer in ours["layers"])
            secs, size = ours["seconds"], ours["file_size_bytes"]
            common = f"{n}x{n} px, {name} levels, 4 masks, 2 threads"
            peer = "KLayout Region merge of per-pixel boxes, GDS2 max 199 vertices (no verification)"
            rows += [
                dict(benchmark=f"gds_{name}", figure="export+verify time", value=secs, unit="s",
                     peer=peer if peer_s else None, peer_value=peer_s,
                     ratio=secs / peer_s if peer_s else None, limit=5.0,
                     notes=f"{common}; goal < 5 s and <= 0.1 x the peer's time"),
                dict(benchmark=f"gds_{name}", figure="peak resident memory", value=ours["rss_mb"],
                     unit="MB", peer=None, peer_value=None, ratio=None, limit=1000.0,
                     notes=f"{common}; child process ru_maxrss incl. interpreter and imports; "
                           f"tracemalloc peak {traced:.0f} MB"),
                dict(benchmark=f"gds_{name}", figure="file size", value=size / 1e6, unit="MB",
                     peer=peer if peer_size else None,
                     peer_value=peer_size / 1e6 if peer_size else None,
                     ratio=size / peer_size if peer_size else None, limit=None,
                     notes=f"{common}; ours includes die outline, labels, marks and test structures"),
                dict(benchmark=f"gds_{name}", figure="polygons", value=polys, unit="polygons",
                     peer=None, peer_value=None, ratio=None, limit=None,
                     notes=f"{verts} vertices, max {max(x['max_vertices'] for x in ours['layers'])} "
                           f"per polygon; verification mismatches {ours['mismatched_pixels']}"),
                dict(benchmark=f"gds_{name}", figure="KLayout read-back area error", value=area_err,
                     unit="px", peer=None, peer_value=None, ratio=None, limit=0.0,
                     notes="max over mask layers of |KLayout polygon area / pixel area - open pixels|"),
            ]
    return rows
