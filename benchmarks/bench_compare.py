"""``doe compare`` end to end on a synthetic 2000 x 2000 Zygo .datx field: time, peak memory, accuracy.

The measurement is made by the process model (one etch 6 % deep, 0.4 um overlay on the
600 nm mask, linewidth bias, 0.5 um instrument blur, 1 nm noise, tilt, 1 deg rotation,
1.1 um pixels) from a random 16-level design of 4 x 4-pixel features. The run includes
reading, levelling, registration, level heights, the edge fit, the process-model error map,
figures, the PSF comparison (3 wavelengths, seed camera; default PSF oversample 1, and 2 for
comparison in the full run) and the 3-D rendering. No peer
tool does this chain (see the reference notes), so the goal is the one of the issue:
under 30 s on 2 cores. ``quick=True``: a 500 x 500 field and a small PSF.
"""

from __future__ import annotations

import json
import logging
import tempfile
import time
import tracemalloc
from pathlib import Path

import numpy as np

from doedesign.camera import Camera
from doedesign.cli import main
from doedesign.design import Design
from masks.process import ProcessParams
from metrology.matching import compare, level, register
from metrology.formats.writers import write_measurement

log = logging.getLogger(__name__)
PITCH = 5.4e-6
PIXEL = 1.1e-6
GOAL_S = 30.0


def _case(n_meas, n_design, camera):
    rng = np.random.default_rng(1)
    levels = np.kron(rng.integers(0, 16, (n_design // 4, n_design // 4)), np.ones((4, 4), int))
    step = Design(height_m=np.zeros((1, 1)), pitch_m=PITCH).height_2pi_m() / 16
    design = Design(height_m=-levels * step, pitch_m=PITCH, levels=levels, metadata={"camera": camera.to_dict()})
    depths = step * np.array([1.0, 2.0, 4.0 * 1.06, 8.0])
    overlay = np.zeros((4, 3))
    overlay[3, 0] = 0.4e-6
    params = ProcessParams(etch_depth=depths, mask_overlay=overlay,
                           linewidth_bias=np.array([0.05, 0.1, -0.1, 0.05]) * 1e-6)
    centre = ((n_design - 1) / 2 + 0.3, (n_design - 1) / 2 - 0.4)
    truth = register.Registration.from_parameters(PIXEL / PITCH, 1.0, (False, True, False), centre, PITCH,
                                                  levels.shape, (n_meas, n_meas))
    h = compare.process_on_measurement(levels, PITCH, params, truth, blur_m=0.5e-6, step_m=0.5e-6)
    h += level.plane_image(np.array([1e-6, 0.4e-9, -0.2e-9]), h.shape) + rng.normal(0, 1e-9, h.shape)
    return design, params, h


def run(quick=False):
    n_meas = 500 if quick else 2000
    if quick:
        camera = Camera(aperture_diameter_m=None, doe_side="full", window_shape=(128, 128), axis_pixel=(64, 64))
        n_design = 160
    else:
        camera = Camera()
        n_design = 480
    t0 = time.perf_counter()
    design, params, h = _case(n_meas, n_design, camera)
    t_make = time.perf_counter() - t0
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        design.save(tmp / "design.npz")
        write_measurement(tmp / "field.datx", h, pixel_size_m=PIXEL)
        runs = {}
        for q in ((1,) if quick else (1, 2)):
            tracemalloc.start()
            t0 = time.perf_counter()
            code = main(["compare", str(tmp / "field.datx"), "--design", str(tmp / "design.npz"),
                         "--out", str(tmp / f"out{q}"), "--psf-oversample", str(q)])
            elapsed = time.perf_counter() - t0
            _, peak = tracemalloc.get_traced_memory()
            tracemalloc.stop()
            if code != 0:
                raise RuntimeError(f"doe compare exited with {code}")
            runs[q] = (elapsed, peak)
        rep = json.loads((tmp / "out1" / "report.json").read_text())
    depth_err = float(np.max(np.abs(np.asarray(rep["etch_depths_nm"]) - params.etch_depth * 1e9)))
    overlay_err = float(np.max(np.abs(np.asarray(rep["overlay_um"]) - params.mask_overlay[:, :2] * 1e6)))
    size = f"{n_meas} x {n_meas}"
    notes = f"field {size} px of 1.1 um on a {n_design}^2-pixel design; synthetic data made in {t_make:.1f} s"
    rows = []
    for q, (elapsed, peak) in runs.items():
        rows += [
            dict(benchmark="compare", figure=f"doe compare wall time ({size}, PSF oversample {q})", value=elapsed,
                 unit="s", peer=None, peer_value=None, ratio=None, limit=GOAL_S,
                 notes=notes + "; 2 cores; includes reading, PSF (3 wavelengths) and 3-D render"),
            dict(benchmark="compare", figure=f"doe compare peak traced memory ({size}, PSF oversample {q})",
                 value=peak / 2 ** 20, unit="MiB", peer=None, peer_value=None, ratio=None, limit=None,
                 notes="tracemalloc peak (numpy buffers included; VTK's own memory not traced)"),
        ]
    rows += [
        dict(benchmark="compare", figure="etch depth max error", value=depth_err, unit="nm", peer=None,
             peer_value=None, ratio=None, limit=2.0, notes="goal from the issue: within 2 nm"),
        dict(benchmark="compare", figure="overlay max error", value=overlay_err, unit="um", peer=None,
             peer_value=None, ratio=None, limit=0.15, notes="goal from the issue: within 0.15 um"),
    ]
    for r in rows:
        log.info("%s: %.3g %s", r["figure"], r["value"], r["unit"])
    return rows


if __name__ == "__main__":
    logging.basicConfig(level=logging.INFO)
    for row in run(quick=True):
        print(row)  # noqa: T201 - benchmark script output
