"""GDS export of a full 10 mm die (1852 x 1852 px): ours vs per-pixel boxes merged by KLayout.

The time row is the whole ``doe masks DESIGN.npz --out DIR`` command (start-up, loading,
export, independent read-back and pixel comparison, preview, report) against the peer as a
whole process too: a script that loads the same levels, builds one box per open pixel in a
KLayout Region, merges it and writes GDSII with the same 199-vertex limit (no verification).
The two run in turn, ``PAIRS`` times; the ratio is the median of the per-pair ratios, so a
machine whose speed drifts (shared, loaded) still compares like with like.

Memory and polygon counts come from our export alone in a child process (its peak resident
memory is its own). Our file is also read by KLayout, whose polygon area per mask layer must
equal the open pixel count times the pixel area.
"""

from __future__ import annotations

import importlib.util
import json
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from doedesign.design import Design
from masks.decompose import levels_to_masks

PITCH_M = 5.4e-6
MAX_VERTICES = 199
PAIRS = 3  # ours/peer runs in turn
STEP_M = 74.74e-9  # any level step: the masks depend on the levels only

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


_PEER = r"""
import sys
import numpy as np
import klayout.db as db
levels = np.load(sys.argv[1])["levels"]
masks = np.stack([(levels >> j) & 1 for j in range(4)]).astype(bool)
p, max_vertices = int(sys.argv[3]), int(sys.argv[4])
ly = db.Layout()
ly.dbu = 0.001
top = ly.create_cell("TOP")
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
opts.gds2_max_vertex_count = max_vertices
ly.write(sys.argv[2], opts)
"""

_DOE = "import sys; from doedesign.cli import main; sys.exit(main())"  # what the `doe` script runs


def _child(cmd, cwd):
    """Run ``cmd`` to completion; (wall s, CPU s of the child: user + system)."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t = time.perf_counter()
    subprocess.run(cmd, cwd=cwd, check=True, capture_output=True)
    wall = time.perf_counter() - t
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    return wall, (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)


def _whole_commands(levels, tmp, name, pairs):
    """``doe masks`` and the KLayout peer, each as a whole process, in turn ``pairs`` times."""
    tmp = Path(tmp)
    design = tmp / f"{name}_design.npz"
    Design(-levels * STEP_M, PITCH_M, levels=levels, metadata={"name": name}).save(design)
    root = Path(__file__).resolve().parents[1]
    peer_cmd = [sys.executable, "-c", _PEER, str(design), str(tmp / f"{name}_klayout.gds"),
                str(int(round(PITCH_M * 1e9))), str(MAX_VERTICES)]
    have_peer = importlib.util.find_spec("klayout") is not None
    ours, peer = [], []
    for k in range(pairs):
        ours.append(_child([sys.executable, "-c", _DOE, "masks", str(design), "--out", str(tmp / f"{name}_cmd{k}")],
                           root))
        if have_peer:
            peer.append(_child(peer_cmd, root))
    return ours, peer, tmp / f"{name}_klayout.gds"


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


def run(quick=False, pairs=PAIRS, only=None):
    """Rows for every design of :func:`_designs` (or those named in ``only``)."""
    n = 400 if quick else 1852
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for name, levels in _designs(n).items():
            if only is not None and name not in only:
                continue
            masks = levels_to_masks(levels)
            ours, gds = _ours(masks, tmp, name, trace=False)
            traced = _ours(masks, tmp, name + "_traced", trace=True)[0]["traced_mb"]
            cmd, peer_runs, peer_gds = _whole_commands(levels, tmp, name, 1 if quick else pairs)
            try:
                area_err = _klayout_area_mismatch(gds, masks)
            except ImportError:
                area_err = None
            wall = float(np.median([w for w, _ in cmd]))
            peer_s = float(np.median([w for w, _ in peer_runs])) if peer_runs else None
            ratio = float(np.median([a[0] / b[0] for a, b in zip(cmd, peer_runs)])) if peer_runs else None
            cpu_ratio = float(np.median([a[1] / b[1] for a, b in zip(cmd, peer_runs)])) if peer_runs else None
            peer_size = peer_gds.stat().st_size if peer_runs else None
            polys = sum(layer["polygons"] for layer in ours["layers"])
            verts = sum(layer["vertices"] for layer in ours["layers"])
            size = ours["file_size_bytes"]
            common = f"{n}x{n} px, {name} levels, 4 masks, 2 threads"
            peer = "KLayout Region merge of per-pixel boxes, GDS2 max 199 vertices (no verification)"
            speed = (f"{1 / ratio:.1f}x faster than the peer (wall), {1 / cpu_ratio:.1f}x in CPU time; "
                     if ratio else "")
            rows += [
                dict(benchmark=f"gds_{name}", figure="doe masks, whole command", value=wall, unit="s",
                     peer=f"{peer}, whole process" if peer_runs else None, peer_value=peer_s, ratio=ratio,
                     limit=0.1,
                     notes=f"{common}; {speed}start-up, export, verification, preview and report included; "
                           f"median of {len(cmd)} runs in turn with the peer, ratio = median of the per-pair "
                           f"ratios; export and verification alone {ours['seconds']:.2f} s; "
                           f"goal: ratio <= 0.1 (>= 10x faster)"),
                dict(benchmark=f"gds_{name}", figure="peak resident memory", value=ours["rss_mb"],
                     unit="MB", peer=None, peer_value=None, ratio=None, limit=1000.0,
                     notes=f"{common}; export child process ru_maxrss incl. interpreter and imports; "
                           f"tracemalloc peak {traced:.0f} MB"),
                dict(benchmark=f"gds_{name}", figure="file size", value=size / 1e6, unit="MB",
                     peer=peer if peer_size else None,
                     peer_value=peer_size / 1e6 if peer_size else None,
                     ratio=size / peer_size if peer_size else None, limit=None,
                     notes=f"{common}; ours includes die outline, labels, marks and test structures; "
                           "goal: within 5 % of the peer's"),
                dict(benchmark=f"gds_{name}", figure="polygons", value=polys, unit="polygons",
                     peer=None, peer_value=None, ratio=None, limit=None,
                     notes=f"{verts} vertices, max {max(x['max_vertices'] for x in ours['layers'])} "
                           f"per polygon; verification mismatches {ours['mismatched_pixels']}"),
                dict(benchmark=f"gds_{name}", figure="KLayout read-back area error", value=area_err,
                     unit="px", peer=None, peer_value=None, ratio=None, limit=0.0,
                     notes="max over mask layers of |KLayout polygon area / pixel area - open pixels|"),
            ]
    return rows
