"""Which mask and effect matter: one-at-a-time swings and Sobol indices (SALib).

One-at-a-time: each random parameter at its 15.9 % and 84.1 % quantiles (minus and plus one
sigma for a normal), every other at its centre. Sobol: SALib's Saltelli design (scrambled
Sobol sequence, ``N (G + 2)`` runs for ``G`` groups, no second order) over the parameters'
quantiles, one group per effect and mask (overlay x and y together), analysed with
``SALib.analyze.sobol`` (first-order ``S1`` and total ``ST`` with 95 % bootstrap intervals).
"""

from __future__ import annotations

import numpy as np

from .spec import ToleranceSpec

__all__ = ["oat_jobs", "oat_table", "sobol_indices", "sobol_jobs"]

ONE_SIGMA_QUANTILES = (0.15865525393145707, 0.8413447460685429)
# Sobol quantiles stay off 0 and 1, where a normal's ppf is infinite.
_U_EPS = 1e-6


def oat_jobs(spec: ToleranceSpec) -> list[dict]:
    """Jobs with one parameter at -1 / +1 sigma-equivalent quantiles, the others at their centres."""
    centre = spec.nominal_values()
    jobs = [{"id": "oat-centre", "kind": "oat", "param": None, "side": None, "seed": 0, "values": centre}]
    for i, p in enumerate(spec.random_params):
        for side, u in zip(("low", "high"), ONE_SIGMA_QUANTILES):
            jobs.append({"id": f"oat-{i:03d}-{side}", "kind": "oat", "param": p.name, "side": side, "seed": 0,
                         "values": {**centre, p.name: float(p.ppf(u))}})
    return jobs


def oat_table(spec: ToleranceSpec, results: dict, metric: str) -> dict:
    """Rows ``{param, label, low_delta, high_delta, swing}`` of ``metric`` changes, largest ``|change|`` first."""
    base = results["oat-centre"]["metrics"][metric]
    rows = []
    for i, p in enumerate(spec.random_params):
        lo = results[f"oat-{i:03d}-low"]["metrics"][metric] - base
        hi = results[f"oat-{i:03d}-high"]["metrics"][metric] - base
        rows.append({"param": p.name, "label": p.label, "low_delta": lo, "high_delta": hi,
                     "swing": max(abs(lo), abs(hi)), "low_value": p.to_report(p.ppf(ONE_SIGMA_QUANTILES[0])),
                     "high_value": p.to_report(p.ppf(ONE_SIGMA_QUANTILES[1]))})
    rows.sort(key=lambda r: -r["swing"])
    return {"metric": metric, "centre_value": base, "rows": rows}


def _problem(spec):
    params = spec.random_params
    return {"num_vars": len(params), "names": [p.name for p in params], "bounds": [[0.0, 1.0]] * len(params),
            "groups": [p.group for p in params]}


def sobol_jobs(spec: ToleranceSpec, base_n: int, seed: int) -> list[dict]:
    """Saltelli jobs (``base_n`` rounded up to a power of two), or [] when nothing varies."""
    params = spec.random_params
    if base_n <= 0 or not params:
        return []
    from SALib.sample import sobol as sobol_sample

    n = 1 << int(np.ceil(np.log2(base_n)))
    u = sobol_sample.sample(_problem(spec), n, calc_second_order=False, seed=seed)
    u = np.clip(u, _U_EPS, 1 - _U_EPS)
    centre = spec.nominal_values()
    jobs = []
    for k, row in enumerate(u):
        values = dict(centre)
        values.update({p.name: float(p.ppf(ui)) for p, ui in zip(params, row)})
        jobs.append({"id": f"sobol-{k:05d}", "kind": "sobol", "index": k, "seed": 0, "values": values})
    return jobs


def sobol_indices(spec: ToleranceSpec, results: dict, metric: str, seed: int) -> dict | None:
    """First-order and total Sobol indices of ``metric`` per group (effect on one mask); None
    without Sobol results."""
    ids = sorted(k for k in results if k.startswith("sobol-"))
    if not ids:
        return None
    from SALib.analyze import sobol as sobol_analyze

    y = np.array([results[k]["metrics"][metric] for k in ids])
    problem = _problem(spec)
    if np.ptp(y) == 0:
        groups = list(dict.fromkeys(problem["groups"]))
        return {"metric": metric, "runs": len(ids), "groups": groups, "S1": [0.0] * len(groups),
                "ST": [0.0] * len(groups), "S1_conf": [0.0] * len(groups), "ST_conf": [0.0] * len(groups),
                "note": "the metric did not vary"}
    res = sobol_analyze.analyze(problem, y, calc_second_order=False, seed=seed)
    groups = list(dict.fromkeys(problem["groups"]))

    def clean(a):
        return [float(v) if np.isfinite(v) else 0.0 for v in np.asarray(a, float)]

    return {"metric": metric, "runs": len(ids), "groups": groups, "S1": clean(res["S1"]), "ST": clean(res["ST"]),
            "S1_conf": clean(res["S1_conf"]), "ST_conf": clean(res["ST_conf"]),
            "method": "SALib Saltelli/Sobol, no second order, 95 % bootstrap intervals"}
