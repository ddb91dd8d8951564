"""Registration from a wrong starting pixel size (issue 51): CPU time of
:func:`metrology.matching.register.register` with the starting pixel size at 0.5x, 0.8x, 1.25x
and 2x the true one, against the right start (the scale scan runs only when the +-15 % band
finds no good match, so the right start takes the same path as before the scan existed).

Fields from the tests' independent profilometer-file generator (tests/metrology/filegen.py),
levelled on level 0 as ``doe compare`` does before it registers.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

from doedesign.levels import printed_height_m
from metrology.matching.level import level_on_top, remove_spikes
from metrology.matching.register import register

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests" / "metrology"))
import filegen  # noqa: E402  (the tests' wafer and camera generator)

FACTORS = (0.5, 0.8, 1.25, 2.0)


def _cpu(fn, repeat):
    t = time.process_time()
    for _ in range(repeat):
        out = fn()
    return (time.process_time() - t) / repeat, out


def run(quick: bool = False) -> list[dict]:
    """Rows: per field size and starting factor the CPU seconds of one registration, the ratio to
    the right start, and whether the pixel size came out within 0.1 % of the true one."""
    from doedesign.design import Design

    sizes = ((36, 120),) if quick else ((36, 120), (64, 240))
    repeat = 2 if quick else 3
    rows = []
    for design_px, field_px in sizes:
        case = filegen.make_case([], 2, design_px=design_px, field_px=field_px, fine=40)
        pitch = filegen.PITCH_M
        printed = printed_height_m(Design(-case.levels * Design(np.zeros((2, 2)), pitch).level_step_m(), pitch))
        h, _ = remove_spikes(case.height_m)
        first = level_on_top(h).height_m
        true_m = case.instrument["pixel_m"]
        base, _ = _cpu(lambda: register(first, printed, pitch, pixel_size_m=true_m), repeat)
        rows.append({"benchmark": "registration_scale", "figure": f"register CPU, right start, {field_px} px field",
                     "value": base, "unit": "s", "peer": None, "peer_value": None, "ratio": None, "limit": None,
                     "notes": f"{design_px} px design, generator seed 2"})
        for f in FACTORS:
            t, reg = _cpu(lambda: register(first, printed, pitch, pixel_size_m=true_m * f), repeat)
            ok = abs(reg.pixel_size_m / true_m - 1) < 1e-3
            rows.append({"benchmark": "registration_scale",
                         "figure": f"register CPU, start {f:g}x the true pixel, {field_px} px field",
                         "value": t, "unit": "s", "peer": "right start", "peer_value": base, "ratio": t / base,
                         "limit": "registers (pixel size within 0.1 %)",
                         "notes": f"registered: {ok}; measured {reg.pixel_size_m / true_m:.5f}x the true pixel"})
    return rows


if __name__ == "__main__":
    import json

    print(json.dumps(run(quick="--quick" in sys.argv), indent=1))
