"""The process as measured, written as a ``doe tolerance`` spec (:mod:`masks.tolerance.spec`).

Every sigma is the measured spread between fields; a mean is kept only where the next run
still carries it (a systematic effect that no knob removes, the etch error left after the new
target). Corrected effects and those not significant are centred on zero: what the fab did
becomes the tolerance run's input instead of a guess.

The TOML is written here by hand (a few flat tables of numbers; the standard library reads
TOML but does not write it) and read back through :func:`masks.tolerance.spec.build_spec`
before it is kept, so a spec that ``doe tolerance`` would refuse is never written.
"""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from typing import Any

from .systematic import Estimate, find_estimate

__all__ = ["spec_table", "toml_text"]


def _mask_entry(table, effect, mask, key, value):
    table.setdefault(effect, {}).setdefault("mask", {}).setdefault(str(mask), {})[key] = value


def spec_table(estimates: Sequence[Estimate], jobs: Sequence[dict]) -> tuple[dict, list[str]]:
    """The spec as a dict of the TOML schema, and notes on what it cannot say."""
    table: dict[str, Any] = {}
    notes: list[str] = []
    by: dict[tuple[str, int | None], list[Estimate]] = {}
    for e in estimates:
        by.setdefault((e.effect, e.mask), []).append(e)
    for (effect, mask), group in by.items():
        if effect == "etch_depth":
            e = group[0]
            assert mask is not None  # a depth is per mask
            job = jobs[mask]
            left = (1.0 + e.mean) * job["etch_depth_target_nm"] / job["etch_depth_nm"] - 1.0 if (
                e.corrected or job["etch_loading_mean_loss_fraction"]) else (e.mean if e.systematic else 0.0)
            _mask_entry(table, effect, mask, "mean_rel", left)
            _mask_entry(table, effect, mask, "sigma_rel", e.spread)
        elif effect in ("mask_overlay", "linewidth_bias"):
            sigma = max(e.spread for e in group)
            _mask_entry(table, effect, mask, "sigma_um", sigma * 1e6)
            if effect == "mask_overlay" and len(group) > 1 and abs(group[0].spread - group[1].spread) > 0.2 * sigma:
                notes.append(f"mask_overlay mask {mask}: x and y spreads differ "
                             f"({group[0].spread * 1e6:.3g}, {group[1].spread * 1e6:.3g} um); the spec takes the larger")
        elif effect == "mask_rotation":
            _mask_entry(table, effect, mask, "sigma_urad", group[0].spread * math.pi / 180 * 1e6)
        elif effect == "etch_loading":
            e = group[0]
            table[effect] = {"mean": e.mean if e.systematic else 0.0, "sigma": e.spread}
        elif effect in ("proximity_blur", "sidewall_slope"):
            e = group[0]
            table[effect] = {"mean_um": e.mean * 1e6 if e.systematic else 0.0, "sigma_um": e.spread * 1e6}
        elif effect == "proximity_print":
            gap = find_estimate(group, effect, None, "gap", corrected_only=False)
            assert gap is not None  # a named print has both parameters
            if gap.corrected:
                notes.append(f"proximity_print: the corrected masks are pre-distorted for the {gap.mean * 1e6:.1f} um "
                             "gap; the spec cannot hold those masks and leaves the print out (a tolerance run of the "
                             "design's masks at that gap would count the error the correction takes out)")
                continue
            for e in group:
                if e.param == "gap_m":
                    table["proximity_gap"] = {"mean_um": e.mean * 1e6 if e.systematic else 0.0,
                                              "sigma_um": e.spread * 1e6}
                else:
                    table["resist_threshold"] = {"mean": e.mean - e.null if gap.systematic else 0.0,
                                                 "sigma": e.spread}
        elif effect == "etch_gradient":
            table[effect] = {"sigma_percent_per_mm": max(e.spread for e in group) * 0.1}
            if any(e.systematic for e in group):
                notes.append("etch_gradient: a systematic gradient is left out of the spec's mean "
                             "(one mean serves both axes in the schema)")
        else:
            notes.append(f"{effect}: not expressible in a tolerance spec here; left out")
    return table, notes


def _value(v):
    if isinstance(v, str):
        return json.dumps(v)
    return repr(float(v))


def toml_text(table: dict, header: Sequence[str] = ()) -> str:
    """TOML for a nested dict of numbers and strings (tables of tables, no arrays)."""
    lines = [f"# {h}" for h in header]

    def emit(prefix, tab):
        scalars = {k: v for k, v in tab.items() if not isinstance(v, dict)}
        subs = {k: v for k, v in tab.items() if isinstance(v, dict)}
        if prefix and scalars:
            lines.append(f"[{'.'.join(prefix)}]")
        lines.extend(f"{k} = {_value(v)}" for k, v in scalars.items())
        for k, v in subs.items():
            emit(prefix + [str(k)], v)

    emit([], table)
    return "\n".join(lines) + "\n"
