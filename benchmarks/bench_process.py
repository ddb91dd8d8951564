"""Process model: speed of simulate_surface and accuracy of the printed geometry.

Speed: a 100 x 100 design-pixel region (5.4 um pitch) of a random 16-level design on a
0.25 um grid (22 x 22 fine pixels per design pixel, 2200 x 2200 output), ideal and with
every effect on. Goal: well under 2 s for all effects (the fitters call it many times).

Accuracy: printed area of a blurred, thresholded 4 x 4-pixel square against the area of
the analytic (erf) aerial image thresholded on a 20 nm grid, and the etched volume of a
biased square against (L + 2 b)**2 d.
"""

from __future__ import annotations

import time

import numpy as np
from scipy.special import erf

from masks.process import ProcessParams, simulate_surface

PITCH = 5.4e-6
STEP = 0.25e-6


def _timed(levels, params, repeats):
    best = np.inf
    for _ in range(repeats):
        t0 = time.perf_counter()
        simulate_surface(levels, PITCH, params, STEP, region=(100, 200, 100, 200))
        best = min(best, time.perf_counter() - t0)
    return best


def _all_effects(rotation_rad):
    overlay = np.array([[0, 0, 0], [0.1e-6, 0.2e-6, rotation_rad], [0.3e-6, -0.1e-6, 0],
                        [0.5e-6, 0.0, 0]])
    return ProcessParams.ideal().copy(
        mask_overlay=overlay, linewidth_bias=np.full(4, 0.1e-6), proximity_blur=1.0e-6,
        resist_threshold=0.45, sidewall_slope=0.3e-6, etch_loading=0.05, roughness=1e-9, seed=1)


def _blur_area_error(sigma_m):
    pitch, step, n = 4e-6, 0.25e-6, 12
    levels = np.zeros((n, n), int)
    levels[4:8, 4:8] = 8
    params = ProcessParams.ideal().copy(proximity_blur=sigma_m, resist_threshold=0.5)
    area = simulate_surface(levels, pitch, params, step).masks_printed[3].sum() * step ** 2
    side = 4 * pitch
    x = np.arange(-side, side, 20e-9) + 10e-9
    f = 0.5 * (erf((side / 2 - x) / (np.sqrt(2) * sigma_m)) + erf((side / 2 + x) / (np.sqrt(2) * sigma_m)))
    ref = np.count_nonzero(np.outer(f, f) > 0.5) * (20e-9) ** 2
    return area / ref - 1


def run(quick=False):
    """Rows for benchmarks/run.py (see CONTRIBUTING / team rules for the keys)."""
    repeats = 1 if quick else 3
    rng = np.random.default_rng(0)
    levels = rng.integers(0, 16, (300, 300))
    rows = []
    for name, params in (("ideal", ProcessParams.ideal()),
                         ("all effects, no rotation", _all_effects(0.0)),
                         ("all effects, one mask rotated", _all_effects(1e-4))):
        rows.append(dict(benchmark="process", figure=f"simulate_surface 100x100 px at 0.25 um, {name}",
                         value=_timed(levels, params, repeats), unit="s", peer=None, peer_value=None,
                         ratio=None, limit=2.0,
                         notes="best of %d; 2200 x 2200 output, 5.4 um pitch" % repeats))
    for sigma in (0.5e-6, 1.0e-6, 2.0e-6):
        rows.append(dict(benchmark="process", figure=f"blurred square area error, sigma {sigma * 1e6:.1f} um",
                         value=_blur_area_error(sigma), unit="relative", peer="analytic erf aerial image",
                         peer_value=0.0, ratio=None, limit=0.005,
                         notes="16 um square, 0.25 um grid, threshold 0.5"))
    return rows
