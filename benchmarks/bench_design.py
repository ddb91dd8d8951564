"""Design benchmarks: spot arrays against slmsuite's weighted Gerchberg-Saxton; Bayer design time.

Spot array: a 4 x 4 grid (+-3, +-9 DFT bins about the axis, point- and transpose-symmetric so
no sign or axis convention of either code matters) on a square N x N DOE filling the pupil.
The camera's sensor pixel is set to one DFT bin of the DOE, lambda z / (N p), so slmsuite's
``SpotHologram`` (basis "knm") and our target address the same points. Both phase maps are
then scored with the same physical model, :class:`doedesign.engine.psf.PSFEngine` (pixelated DOE,
pixel-integrated sensor, light normalized to all that passes the pupil): efficiency = light on
the 16 spot pixels, uniformity = 1 - (max - min) / (max + min) of the spot powers.
Our loss is energy + L2 toward the reachable energy, with WGS-like reweighting rounds of the
spot weights (``OptimizerSettings.reweight_rounds``); the plain loss without them is reported
too, and the WGS phase rounded to 16 levels is the peer of our quantized figures.

Bayer: the demo's element (its settings: RGGB geometry, soft minimum from the router start)
at the full 8.64 mm aperture (1600 px) with the camera focused at infinity, as the target's
plane is; the few-pixel path beside the full-window path.
"""

from __future__ import annotations

import logging
import time
import warnings

import numpy as np
from scipy.integrate import quad

from doedesign import targets
from doedesign.camera import Camera
from doedesign.engine.psf import PSFEngine
from doedesign.levels import level_step_m, quantize
from doedesign.materials import get_material
from doedesign.optimizer.losses import LossSpec
from doedesign.optimizer.optimize import ANNEAL_SCHEDULE, OptimizerSettings, design_doe

log = logging.getLogger(__name__)
PITCH = 5.4e-6
WL = 550e-9
OFFSETS = (-9, -3, 3, 9)


def _spot_setup(n):
    z = 50e-3
    cam = Camera(aperture_diameter_m=None, doe_side="full", pixel_pitch_m=WL * z / (n * PITCH),
                 sensor_distance_m=z, window_shape=(n, n), axis_pixel=(n // 2, n // 2))
    rows, cols = np.meshgrid(OFFSETS, OFFSETS, indexing="ij")
    pos = np.stack([rows.ravel() + n // 2, cols.ravel() + n // 2], axis=1)
    return cam, pos


def _score(engine, height_m, pos):
    psf = engine.psf(height_m, views=("coded",)).psf[0, 0, 0]
    p = psf[pos[:, 0], pos[:, 1]]
    return float(p.sum()), float(1 - (p.max() - p.min()) / (p.max() + p.min()))


def _slmsuite_phase(n, pos, maxiter):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        logging.getLogger("slmsuite").setLevel(logging.WARNING)
        from slmsuite.holography.algorithms import SpotHologram

        vec = np.stack([pos[:, 1], pos[:, 0]]).astype(float)  # (x = col, y = row) in knm pixels
        holo = SpotHologram(shape=(n, n), spot_vectors=vec, basis="knm", slm_shape=(n, n))
        holo.optimize(method="WGS-Kim", maxiter=maxiter, verbose=False)
        return np.asarray(holo.get_phase(), dtype=float)


def spot_array(n=64, maxiter=100):
    """Rows comparing slmsuite WGS-Kim with our nlopt design on the same spot array."""
    cam, pos = _spot_setup(n)
    engine = PSFEngine(cam, PITCH, (n, n), wavelengths_m=[WL])
    mat = get_material("fused_silica")
    t0 = time.perf_counter()
    phase = _slmsuite_phase(n, pos, maxiter)
    t_wgs = time.perf_counter() - t0
    h_wgs = -np.mod(-phase, 2 * np.pi) * WL / (2 * np.pi * (mat.n(WL) - 1))
    eff_wgs, uni_wgs = _score(engine, h_wgs, pos)
    step = level_step_m("fused_silica", WL)
    eff_wgs_q, uni_wgs_q = _score(engine, quantize(h_wgs, step).height_m, pos)
    # Upper bound: every spot carries the pixel envelope sinc^2(u) sinc^2(v) (u, v in cycles/pixel)
    # and a single bin-wide sensor pixel holds (integral of sinc^2 over one bin)^2 = 0.7737^2 of it.
    bin_frac = quad(lambda u: np.sinc(u) ** 2, -0.5, 0.5)[0] ** 2
    env = np.mean([np.sinc(r / n) ** 2 * np.sinc(c / n) ** 2 for r in OFFSETS for c in OFFSETS])
    limit = float(bin_frac * env)
    # Asking for the reachable energy makes the L2 term a pure uniformity term.
    target = targets.spots(pos, camera=cam, wavelengths_m=[WL], energy=limit)
    loss = LossSpec(l1=0, energy=1, l2=1)
    base = dict(max_iter=maxiter, height_range="wrap", init="random", seed=0, anneal_iter=maxiter // 5)
    plain = design_doe(target, cam, PITCH, (n, n), loss=loss, settings=OptimizerSettings(**base))
    eff_p, uni_p = _score(engine, plain.continuous_height_m, pos)
    t0 = time.perf_counter()
    run = design_doe(target, cam, PITCH, (n, n), loss=loss,
                     settings=OptimizerSettings(**base, reweight_rounds=3, reweight_iter=max(maxiter // 3, 5)))
    t_ours = time.perf_counter() - t0
    eff_c, uni_c = _score(engine, run.continuous_height_m, pos)
    eff_q, uni_q = _score(engine, run.design.height_m, pos)
    note = (f"{n}x{n} DOE, 4x4 spots, scored by PSFEngine (pixel-integrated, 1 sensor px = 1 DFT bin); "
            f"slmsuite WGS-Kim {maxiter} it. on numpy; ours nlopt LD_LBFGS energy+L2, {maxiter} it. + 3 WGS-like "
            f"reweighting rounds of {max(maxiter // 3, 5)} it.; {run.report['evaluations']} evaluations in all")
    note_q = note + "; both phases rounded to the nearest of 16 levels (ours after the quantization-aware finish)"
    return [
        dict(benchmark="spot_array_efficiency", figure="efficiency continuous (ours)", value=eff_c, unit="fraction",
             peer="slmsuite WGS-Kim", peer_value=eff_wgs, ratio=eff_c / eff_wgs, limit=limit, notes=note),
        dict(benchmark="spot_array_uniformity", figure="uniformity continuous (ours)", value=uni_c, unit="fraction",
             peer="slmsuite WGS-Kim", peer_value=uni_wgs, ratio=uni_c / uni_wgs, limit=1.0, notes=note),
        dict(benchmark="spot_array_uniformity_plain", figure="uniformity continuous, plain loss (no reweighting)",
             value=uni_p, unit="fraction", peer="slmsuite WGS-Kim", peer_value=uni_wgs, ratio=uni_p / uni_wgs,
             limit=1.0, notes=f"same loss and seed without reweight_rounds; efficiency {eff_p:.4f}"),
        dict(benchmark="spot_array_efficiency_16lvl", figure="efficiency 16-level quantized (ours)", value=eff_q,
             unit="fraction", peer="slmsuite WGS-Kim rounded to 16 levels", peer_value=eff_wgs_q,
             ratio=eff_q / eff_wgs_q, limit=limit, notes=note_q),
        dict(benchmark="spot_array_uniformity_16lvl", figure="uniformity 16-level quantized (ours)", value=uni_q,
             unit="fraction", peer="slmsuite WGS-Kim rounded to 16 levels", peer_value=uni_wgs_q,
             ratio=uni_q / uni_wgs_q, limit=1.0, notes=note_q),
        dict(benchmark="spot_array_time", figure="design time (ours, incl. quantization)", value=t_ours, unit="s",
             peer="slmsuite WGS-Kim", peer_value=t_wgs, ratio=t_ours / t_wgs, limit=None, notes=note),
    ]


def bayer_design_time(size_px=1600, max_iter=None, anneal_iter=None, full_window=True, device="cpu"):
    """Time to design the demo's Bayer element (its settings, ``metrology.pipeline.DemoConfig``) at ``size_px``.

    The demo's element: RGGB geometry, soft minimum of the three colours' on-target light,
    L-BFGS from the router start, ``max_iter`` continuous evaluations (default the demo's 25)
    and ``anneal_iter`` per annealing stage (default 5), camera focused at infinity. The loss
    reads the target pixels and the window energy, so the engine computes only those; with
    ``full_window`` the same design is run again through the whole 512 x 512 window (the peer
    row) and the two height maps are compared. ``device``: where the engine computes
    (:mod:`doedesign.engine.backend`).
    """
    from metrology.pipeline import DemoConfig

    demo = DemoConfig()
    cam = Camera(aperture_diameter_m=size_px * PITCH, focus_distance_m=np.inf)
    target = targets.bayer(cam, rggb=demo.rggb)
    settings = OptimizerSettings(max_iter=max_iter or demo.iterations, seed=demo.seed, objective=demo.objective,
                                 init=targets.DEFAULT_INIT["bayer"], anneal_iter=anneal_iter or demo.anneal_iterations,
                                 device=device)
    loss = LossSpec.parse(targets.DEFAULT_LOSS["bayer"])

    def design(full):
        t0, c0 = time.perf_counter(), time.process_time()
        run = design_doe(target, cam, PITCH, (size_px, size_px), loss=loss, settings=settings, full_window=full)
        return run, time.perf_counter() - t0, time.process_time() - c0

    run, elapsed, cpu = design(False)
    rep = run.report
    colours = [f"{c} {1e9 * wl:.0f} nm" for c, wl in zip("RGB", target.wavelengths_m)]
    label = (f"{target.name}, {settings.objective} from the {settings.init} start, {settings.max_iter} it. + "
             f"annealing {settings.anneal_iter} it. x {len(ANNEAL_SCHEDULE)}")
    bound = rep["quantized"]["bound"]
    per_colour = [dict(benchmark="bayer_energy_on_target", figure=f"energy on the {name} target pixels (quantized)",
                       value=q, unit="fraction", peer="our continuous design", peer_value=c, ratio=q / c, limit=b,
                       notes=f"{size_px} px aperture, {label}; fraction of the coded half's light; "
                             f"limit = single-colour bound, {q / b:.2f} of it")
                  for name, q, c, b in zip(colours, rep["quantized"]["energy_on_target"][0],
                                           rep["continuous"]["energy_on_target"][0], bound["bound"][0])]
    time_row = dict(benchmark="bayer_design_time", figure=f"Bayer design, {size_px} px aperture, {rep['evaluations']} evals",
                    value=elapsed, unit="s", peer=None, peer_value=None, ratio=None, limit=30,
                    notes=f"{label}; CPU {cpu:.1f} s; the loss reads the target pixels and the window energy; "
                          f"energy on target pixels R/G/B quantized {np.round(rep['quantized']['energy_on_target'][0], 4)}, "
                          f"continuous {np.round(rep['continuous']['energy_on_target'][0], 4)}")
    rows = per_colour + [time_row]
    if full_window:
        ref, t_full, cpu_full = design(True)
        diff = np.abs(ref.continuous_height_m - run.continuous_height_m).max()
        time_row.update(peer="same design through the full 512 x 512 window", peer_value=t_full,
                        ratio=elapsed / t_full)
        time_row["notes"] += f"; full window CPU {cpu_full:.1f} s (CPU ratio {cpu / cpu_full:.3f})"
        rows.append(dict(benchmark="bayer_design_time", figure="max height difference, few-pixel vs full-window path",
                         value=float(diff / np.abs(ref.continuous_height_m).max()), unit="relative", peer=None,
                         peer_value=None, ratio=None, limit=1e-9,
                         notes=f"continuous heights; quantized levels identical: "
                               f"{bool(np.array_equal(ref.design.levels, run.design.levels))}"))
    return rows + [
        dict(benchmark="bayer_design_efficiency", figure="weakest colour's energy on its target pixels (quantized)",
             value=float(min(rep["quantized"]["energy_on_target"][0])), unit="fraction", peer=None, peer_value=None,
             ratio=None, limit=0.25,
             notes=f"{size_px} px aperture, coded (left) half; fraction of the light through that half; "
                   f"goal (issue 12): at least 0.25 after 16-level quantization; mean {rep['quantized']['efficiency']:.4f}"),
    ]


def run(quick=False):
    """Benchmark rows (see benchmarks/run.py); quick=True finishes in well under 30 s."""
    rows = spot_array(n=32 if quick else 64, maxiter=30 if quick else 150)
    rows += bayer_design_time(size_px=64, max_iter=4, anneal_iter=2) if quick else bayer_design_time()
    return rows
