"""Masks corrected for a 30 um gap (``doe masks --gap-um 30 --opc``): the field overlap at 550 nm of
what prints of a fine-featured element, against the masks as drawn and the contact print (1.0).

The element is the tests' feature-rich 16-level map (``tests/metrology/filegen.random_levels``,
seed 0): 32 px of 5.4 um, 0.86-0.89 mask edges per pixel on the two shallow masks. One row per
minimum feature the corrected masks may hold, and one for the level set alone (40 steps). CPU
time of the command (one thread). ``quick``: the 0.45 um row only.
"""

from __future__ import annotations

import json
import os
import sys
import tempfile
import time
from contextlib import redirect_stdout
from pathlib import Path

import numpy as np

from doedesign.cli import main
from doedesign.design import Design

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests" / "metrology"))
import filegen  # noqa: E402  (the tests' independent generator)

PITCH_M = 5.4e-6
# (minimum feature um, extra options, label)
CASES = ((0.45, [], "density + polish"), (0.9, [], "density + polish"), (1.0, [], "density + polish (default feature)"),
         (0.9, ["--opc-method", "level-set", "--opc-iterations", "40"], "level set alone, 40 steps"))


def run(quick: bool = False) -> list[dict]:
    levels = filegen.random_levels((32, 32), np.random.default_rng(0))
    probe = Design(height_m=np.zeros(levels.shape), pitch_m=PITCH_M)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        design = Path(tmp) / "fine.npz"
        Design(height_m=-levels * probe.level_step_m(), pitch_m=PITCH_M).save(design)
        for i, (feature_um, extra, label) in enumerate(CASES[:1] if quick else CASES):
            out = Path(tmp) / f"opc{i}"
            start = time.process_time()
            with open(os.devnull, "w") as sink, redirect_stdout(sink):
                main(["masks", str(design), "--out", str(out), "--gap-um", "30", "--opc",
                      "--opc-min-feature-um", str(feature_um), *extra])
            cpu = time.process_time() - start
            check = json.loads((out / "print_check.json").read_text())
            drawn = check["uncorrected"]["field_overlap"]
            rows.append({"benchmark": "opc_fine_element",
                         "figure": f"field overlap through 30 um, {label}, {feature_um:g} um features",
                         "value": check["field_overlap"], "unit": "fraction", "peer": "masks as drawn",
                         "peer_value": drawn, "ratio": check["field_overlap"] / drawn,
                         "limit": ">= 0.98 (contact print 1.0)",
                         "notes": f"32 px element, 0.225 um mask grid ({check['opc']['min_feature_um']:.3g} um drawn "
                                  f"minimum); {cpu:.0f} s CPU of the whole command; load average "
                                  f"{os.getloadavg()[0]:.1f} on {os.cpu_count()} cores"})
    return rows


if __name__ == "__main__":
    print(json.dumps(run(quick="--quick" in sys.argv), indent=1))
