"""Diagnosis accuracy on random hidden effects, and the time of one diagnosis.

Accuracy table: every built-in effect hidden alone (several random seeds each: size, direction,
affected mask, noise level and noise correlation all drawn from the seed), random pairs of
height effects, and null cases with noise only. Reported: the fraction of hidden effects named,
false names (effects named that were not hidden), the largest relative parameter error, and the
largest final residual over the noise floor. Timing: one full diagnosis of a 512 x 512 height
map (all candidates), of a 31-wavelength, two-view PSF stack, and of a full-size PSF stack
(1600 x 1600 DOE, 5 wavelengths, two views, 512 x 512 window; time and peak memory).

No public tool names fabrication effects from metrology data (see the reference notes), so
``peer`` is None; the limits are the issue's goals: all effects found, no false names,
parameters within 20 %, final residual within 1.3x the noise floor, under 60 s per diagnosis.
"""

from __future__ import annotations

import logging
import os
import resource
import time
import tracemalloc

import numpy as np

from metrology.diagnosis import PsfProblem, diagnose_heights, run_diagnosis
from metrology.diagnosis.effects import effects_for
from metrology.diagnosis.synthetic import (HEIGHT_EFFECTS, PSF_EFFECTS, make_height_case, make_psf_case, parameter_errors,
                                 psf_test_setup)

log = logging.getLogger(__name__)


def _height(effects, seed, **kw):
    case = make_height_case(effects, seed, **kw)
    d = case.data
    t = time.perf_counter()
    diag = diagnose_heights(d["levels"], d["pitch_m"], d["measured_height_m"], d["step_m"],
                            stop_at_floor=not effects)
    return case, diag, time.perf_counter() - t


def _psf(effects, seed, n_wavelengths=3, setup=None):
    case = make_psf_case(effects, seed, n_wavelengths=n_wavelengths, setup=setup)
    d = case.data
    t = time.perf_counter()
    problem = PsfProblem(d["design"].height_m, d["design"].pitch_m, d["camera"], d["measured_psf"], d["views"],
                         d["wavelengths_m"], d["camera"].focus_distance_m, effects_for("psf"))
    diag = run_diagnosis(problem, domain="psf", stop_at_floor=bool(effects))
    return case, diag, time.perf_counter() - t


def _cases(quick):
    rng = np.random.default_rng(2024)
    seeds = 1 if quick else 3
    out = []
    for s in range(seeds):
        heights = HEIGHT_EFFECTS if not quick else ("batwing",)
        out += [("height", [e], 5000 + 100 * s + i) for i, e in enumerate(heights)]
        psfs = PSF_EFFECTS if not quick else ("dual_pixel_crosstalk",)
        out += [("psf", [e], 6000 + 100 * s + i) for i, e in enumerate(psfs)]
    n_pairs = 1 if quick else 6
    for p in range(n_pairs):
        out.append(("height", [str(e) for e in rng.choice(HEIGHT_EFFECTS, 2, replace=False)], 7000 + p))
    n_null = 1 if quick else 4
    out += [("height", [], 8000 + k) for k in range(n_null)]
    out += [("psf", [], 8500 + k) for k in range(0 if quick else 2)]
    return out


def run(quick=False):
    rows = []
    hidden = found = false_null = false_other = 0
    worst_param, worst_resid = 0.0, 0.0
    failures = []
    for domain, effects, seed in _cases(quick):
        case, diag, _ = (_height if domain == "height" else _psf)(effects, seed)
        named = set(diag.named)
        hidden += len(effects)
        found += len(named & set(effects))
        extra = named - set(effects)
        if effects:
            false_other += len(extra)
        else:
            false_null += len(extra)
        errs = parameter_errors(case, diag)
        finite = [e for e in errs.values() if np.isfinite(e)]
        worst_param = max([worst_param] + finite)
        worst_resid = max(worst_resid, diag.final_residual_rms / diag.noise_floor)
        if extra or set(effects) - named:
            failures.append(f"{domain} {effects} seed {seed} -> {diag.named}")
    n_cases = len(_cases(quick))
    notes = f"{n_cases} random cases; misses/false names: {'; '.join(failures) or 'none'}"
    rows.append(dict(benchmark="diagnose", figure="hidden effects named", value=found / max(hidden, 1),
                     unit="fraction", peer=None, peer_value=None, ratio=None, limit=1.0, notes=notes))
    rows.append(dict(benchmark="diagnose", figure="false names in null cases", value=false_null, unit="count",
                     peer=None, peer_value=None, ratio=None, limit=0, notes="noise-only height maps and PSF stacks"))
    rows.append(dict(benchmark="diagnose", figure="false names with hidden effects", value=false_other, unit="count",
                     peer=None, peer_value=None, ratio=None, limit=0, notes="extra effects named beside the hidden ones"))
    rows.append(dict(benchmark="diagnose", figure="largest parameter error", value=worst_param, unit="fraction",
                     peer=None, peer_value=None, ratio=None, limit=0.2,
                     notes="|fit - truth| / |truth| over the hidden parameters of named effects"))
    rows.append(dict(benchmark="diagnose", figure="largest final residual / noise floor", value=worst_resid,
                     unit="ratio", peer=None, peer_value=None, ratio=None, limit=1.3, notes=""))

    # Time of one diagnosis: a 512 x 512 height map (128 x 128 design pixels at 4 samples each;
    # the diagnosed window is the central 40 x 40 design pixels) with a hidden overlay + blur.
    if not quick:
        case, diag, dt = _height(["mask_overlay", "instrument_blur"], 9001, shape=(128, 128), upsample=4)
        rows.append(dict(benchmark="diagnose", figure="time, 512 x 512 height map", value=dt, unit="s", peer=None,
                         peer_value=None, ratio=None, limit=60.0,
                         notes=f"all 8 height candidates; named {diag.named}"))
        case, diag, dt = _psf(["dual_pixel_crosstalk"], 9002, n_wavelengths=31)
        design, camera, _ = psf_test_setup(31)
        rows.append(dict(benchmark="diagnose", figure="time, 31-wavelength PSF stack", value=dt, unit="s", peer=None,
                         peer_value=None, ratio=None, limit=60.0,
                         notes=f"2 views, {camera.window_shape} window, {design.shape} DOE pixels; named {diag.named}"))
        rows += [row for e, seed in FULL_SIZE_CASES for row in full_size_psf_rows(effect=e, seed=seed)]
    return rows


FULL_SIZE_CASES = (("dual_pixel_crosstalk", 9003), ("source_bandwidth", 9004))


def full_size_psf_rows(size_px=1600, n_wavelengths=5, window=(512, 512), effect="dual_pixel_crosstalk", seed=9003):
    """Time and peak traced memory of one PSF-stack diagnosis at full size (all candidates)."""
    setup = psf_test_setup(n_wavelengths, size_px=size_px, pitch_m=5.4e-6, window=window,
                           axis=(window[0] // 2, window[1] // 2))
    tracemalloc.start()
    cpu0 = time.process_time()
    case, diag, dt = _psf([effect], seed, n_wavelengths=n_wavelengths, setup=setup)
    cpu = time.process_time() - cpu0
    peak = tracemalloc.get_traced_memory()[1] / 2 ** 30
    tracemalloc.stop()
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2 ** 20
    shape = f"{size_px} x {size_px} DOE, {n_wavelengths} wavelengths, 2 views, {window[0]} x {window[1]}"
    label = f"{shape}; hidden {effect}, seed {seed}"
    load = ", ".join(f"{v:.1f}" for v in os.getloadavg())
    fitted, truth = ({k: [float(f"{x:.6g}") for x in np.ravel(v)] for k, v in m.items()} for m in (diag.model, case.truth))
    notes = (f"named {diag.named} (hidden {truth}; fitted {fitted}); final/floor "
             f"{diag.final_residual_rms / diag.noise_floor:.3f}; candidates screened on a 128 x 128 crop; "
             f"process CPU time {cpu:.1f} s (case included); load average {load} on {os.cpu_count()} cores")
    return [dict(benchmark="diagnose", figure=f"time, PSF stack ({label})", value=dt, unit="s", peer=None,
                 peer_value=None, ratio=None, limit=60.0, notes=notes),
            dict(benchmark="diagnose", figure=f"peak memory, PSF stack ({label})", value=peak, unit="GB", peer=None,
                 peer_value=None, ratio=None, limit=4.0,
                 notes=f"tracemalloc peak over the case and the diagnosis; peak RSS of the process {rss:.2f} GB")]


if __name__ == "__main__":
    import argparse
    import json

    from doedesign.fileio import json_ready, write_json

    parser = argparse.ArgumentParser(description="time the full-size PSF-stack diagnoses alone")
    parser.add_argument("--case", choices=[e for e, _ in FULL_SIZE_CASES], action="append",
                        help="the hidden effect of a full-size case (default: every case)")
    parser.add_argument("--out", help="write the rows to this JSON file (else print them)")
    args = parser.parse_args()
    logging.basicConfig(level=logging.WARNING)
    chosen = [(e, s) for e, s in FULL_SIZE_CASES if not args.case or e in args.case]
    got = [row for e, s in chosen for row in full_size_psf_rows(effect=e, seed=s)]
    if args.out:
        write_json(args.out, {"rows": got})
    else:
        print(json.dumps(json_ready(got), indent=1))  # noqa: T201 - the rows are the output
