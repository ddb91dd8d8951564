"""What the camera model's fine grid costs and buys: render time and discretization per step.

Every evaluation of a camera-frame diagnosis renders each mask's etch on a fine grid in the
design frame (:data:`metrology.matching.instrument.FINE_STEP_M`), transforms it and samples it at
the camera pixels, so its cost goes as the fine cells. A coarser grid is faster and less exact.
For each step this measures, on a random 16-level element (40 x 40 design pixels of 5.4 um; a
96 x 96 field of 1 um camera pixels, rotated 0.5 degrees):

- the rms difference (nm) of the camera render to one on a grid of :data:`REFERENCE_STEP_M`,
  the largest over three lateral transfers (point sampling with a 0.25 um blur, full pixels with
  0.4 um, a CSI objective of NA 0.55 with a 0.5 fill factor), for the ideal element, an 80 nm
  linewidth bias, overlays, the two together, a trench, a 0.3 um sidewall ramp and a 10 % batwing
  0.3 um wide; with the fine cells' first moments (the default,
  :func:`masks.moments.moment_corrected`) and without them;
- the time of one render of the biased element from nothing cached (best of 3), as a ratio to
  the former default's (0.125 um, no moments) in the same run.

The noise floor of the files the diagnosis closes on is about 1.2 nm.

    python -m benchmarks.bench_fine_step
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

from masks.process_params import ProcessParams
from metrology.diagnosis.effects import get_effect
from metrology.matching.instrument import InstrumentModel, Placement
from metrology.matching.transfer import LateralTransfer

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests" / "metrology"))
import filegen  # noqa: E402  (the tests' wafer generator: its random 16-level designs)

STEPS_M = (0.125e-6, 0.16e-6, 0.2e-6, 0.25e-6)
REFERENCE_STEP_M = 0.03125e-6
FORMER_STEP_M = 0.125e-6  # the default before the moments
TRANSFERS = {"point sampling": LateralTransfer(0.25e-6, 0.0),
             "full pixels": LateralTransfer(0.4e-6, 1.0),
             "CSI": LateralTransfer(0.05e-6, 0.5, na=0.55, wavelength_m=0.55e-6)}


def cases() -> dict:
    """Name -> (process parameters, surface effect or None) of the element's models (the step's
    accuracy test in ``tests/metrology/test_instrument.py`` renders the same ones)."""
    ideal = ProcessParams.ideal()
    batwing = get_effect("batwing")
    bias = [80e-9, -60e-9, 40e-9, 100e-9]
    overlay = [[0.13e-6, -0.27e-6, 0], [0, 0, 0], [0.41e-6, 0.05e-6, 0], [-0.33e-6, 0.21e-6, 0]]
    return {"ideal": (ideal, None),
            "80 nm bias": (ideal.copy(linewidth_bias=bias), None),
            "overlay": (ideal.copy(mask_overlay=overlay), None),
            "bias + overlay": (ideal.copy(linewidth_bias=bias, mask_overlay=overlay), None),
            "trench": (ideal.copy(microtrenching=[[0, 4e-7], [0, 4e-7], [30e-9, 3e-7], [0, 4e-7]]), None),
            "sidewall ramp": (ideal.copy(sidewall_slope=0.3e-6), None),
            "batwing": (ideal, lambda h, s: batwing.apply(h, np.array([0.1, 0.3e-6]), s))}


def rotated_field(design_px: int = 40, field_px: int = 96, offset_px: float = 8.0):
    """(levels, placement, field shape): a random 16-level design of ``design_px`` pixels and a
    field of 1 um camera pixels rotated 0.5 degrees, its first pixel at design pixel ``offset_px``."""
    levels = filegen.random_levels((design_px, design_px), np.random.default_rng(5))
    turn = np.deg2rad(0.5)
    matrix = np.array([[np.cos(turn), -np.sin(turn)], [np.sin(turn), np.cos(turn)]]) * 1e-6 / filegen.PITCH_M
    return levels, Placement(matrix, np.array([offset_px, offset_px])), (field_px, field_px)


def run(quick: bool = False) -> list[dict]:
    """The rows: per step and case the largest rms difference (nm), with the cells' moments and
    without, and the render time ratio."""
    levels, placement, shape = rotated_field(24, 48) if quick else rotated_field()
    steps = STEPS_M[::3] if quick else STEPS_M
    reference = InstrumentModel(levels, filegen.PITCH_M, shape, placement, step_m=REFERENCE_STEP_M, moments=True)
    model = {(s, m): InstrumentModel(levels, filegen.PITCH_M, shape, placement, step_m=s, moments=m)
             for s in steps for m in (True, False)}
    rows = []
    models = cases()
    for name, (params, surface) in models.items():
        worst = dict.fromkeys(model, 0.0)
        for transfer in TRANSFERS.values():
            ref = reference.render(params, placement, transfer, surface)
            for key, m in model.items():
                d = m.render(params, placement, transfer, surface) - ref
                worst[key] = max(worst[key], float(np.std(d)) * 1e9)
        for (s, moments), value in worst.items():
            rows.append(dict(benchmark="fine_step",
                             figure=f"render difference, {name}, step {s * 1e6:.3g} um"
                                    + ("" if moments else ", without moments"),
                             value=value, unit="nm rms", peer=None, peer_value=None, ratio=None, limit=None,
                             notes=f"largest of {len(TRANSFERS)} transfers; against a "
                                   f"{REFERENCE_STEP_M * 1e6:.3g} um grid"))
    # Render times, against the former default (0.125 um, no moments) in the same run.
    timing, cells = {}, {}
    biased = models["80 nm bias"][0]
    for key in [(FORMER_STEP_M, False)] + [(s, True) for s in steps]:
        best = np.inf
        for _ in range(3):
            fresh = InstrumentModel(levels, filegen.PITCH_M, shape, placement, step_m=key[0], moments=key[1])
            start = time.perf_counter()  # nothing cached
            fresh.render(biased, placement, TRANSFERS["CSI"])
            best = min(best, time.perf_counter() - start)
        timing[key], cells[key] = best, fresh.upsample
    base = (FORMER_STEP_M, False)
    for s in steps:
        rows.append(dict(benchmark="fine_step", figure=f"render time, step {s * 1e6:.3g} um", value=timing[(s, True)],
                         unit="s", peer=f"step {FORMER_STEP_M * 1e6:.3g} um without moments (the former default)",
                         peer_value=timing[base], ratio=timing[(s, True)] / timing[base], limit=None,
                         notes=f"{cells[(s, True)]} fine cells per design pixel, with moments; best of 3 renders "
                               f"from nothing cached"))
    return rows


if __name__ == "__main__":
    for row in run(quick="--quick" in sys.argv):
        print(f"{row['figure']:55s} {row['value']:8.3f} {row['unit']}" +
              (f"  ({row['ratio']:.2f}x the former default's)" if row["ratio"] is not None else ""))
