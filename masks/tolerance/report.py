"""Summaries, yield, plots and report.md of a tolerance run.

Yield is the fraction of Monte Carlo samples meeting every threshold, with an exact
(Clopper-Pearson) 95 % binomial interval. The Markdown is written with a small local table
helper (no shared Markdown module was on main when this was written).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from scipy import stats

from doedesign.fileio import save_figure

from .spec import meets

__all__ = ["clopper_pearson", "default_thresholds", "markdown", "md_table", "metric_summary",
           "plot_distributions", "plot_tornado", "yield_summary"]

CONFIDENCE = 0.95
# Without user thresholds, the primary metric must keep this share of its nominal value
# (or, for a lower-is-better metric, stay below nominal / this).
DEFAULT_KEEP = 0.9


def clopper_pearson(k: int, n: int, confidence: float = CONFIDENCE) -> list[float]:
    """Exact binomial interval of ``k`` successes in ``n`` trials."""
    if n == 0:
        return [0.0, 1.0]
    a = (1 - confidence) / 2
    lo = 0.0 if k == 0 else float(stats.beta.ppf(a, k, n - k + 1))
    hi = 1.0 if k == n else float(stats.beta.ppf(1 - a, k + 1, n - k))
    return [lo, hi]


def default_thresholds(primary: str, nominal: dict, direction: str) -> dict:
    """The primary metric keeps :data:`DEFAULT_KEEP` of its nominal value."""
    value = nominal[primary]
    if direction == "lower":
        return {primary: ("<=", value / DEFAULT_KEEP)}
    return {primary: (">=", value * DEFAULT_KEEP)}


def yield_summary(samples: list[dict], thresholds: dict) -> dict:
    """Fraction of samples meeting every threshold, with its interval and per-threshold pass rates."""
    n = len(samples)
    passed = [all(meets(s["metrics"][m], t) for m, t in thresholds.items()) for s in samples]
    k = int(sum(passed))
    per = {m: float(np.mean([meets(s["metrics"][m], t) for s in samples])) if n else 0.0
           for m, t in thresholds.items()}
    return {"thresholds": {m: f"{op} {v:.6g}" for m, (op, v) in thresholds.items()}, "samples": n, "passed": k,
            "fraction": k / n if n else 0.0, "ci95": clopper_pearson(k, n), "per_threshold": per,
            "interval": "Clopper-Pearson exact binomial, 95 %"}


def metric_summary(samples: list[dict], nominal: dict, directions: dict) -> dict:
    """Per metric: nominal, mean, std, percentiles and the worst-decile mean."""
    out = {}
    for name in nominal:
        v = np.array([s["metrics"][name] for s in samples], float)
        d = directions.get(name, "higher")
        worst = np.sort(v)[::-1] if d == "lower" else np.sort(v)
        k = max(1, int(np.ceil(0.1 * v.size)))
        out[name] = {"direction": f"{d} is better", "nominal": nominal[name], "mean": float(v.mean()),
                     "std": float(v.std(ddof=1)) if v.size > 1 else 0.0,
                     "p10": float(np.percentile(v, 10)), "p50": float(np.percentile(v, 50)),
                     "p90": float(np.percentile(v, 90)), "worst_decile_mean": float(worst[:k].mean()),
                     "min": float(v.min()), "max": float(v.max())}
    return out


def plot_distributions(samples: list[dict], nominal: dict, path: str | Path) -> None:
    """Histogram of each metric with its nominal value."""
    import matplotlib.pyplot as plt

    names = list(nominal)
    cols = min(3, len(names))
    rows = int(np.ceil(len(names) / cols))
    fig, axes = plt.subplots(rows, cols, figsize=(4.2 * cols, 3.0 * rows), squeeze=False)
    for ax, name in zip(axes.ravel(), names):
        v = [s["metrics"][name] for s in samples]
        ax.hist(v, bins=max(5, min(30, len(v) // 4)), color="tab:blue", alpha=0.75)
        ax.axvline(nominal[name], color="k", ls="--", label="nominal")
        ax.set_title(name, fontsize=9)
        ax.legend(fontsize=7)
    for ax in axes.ravel()[len(names):]:
        ax.set_visible(False)
    fig.suptitle(f"{len(samples)} process samples", fontsize=10)
    fig.tight_layout()
    save_figure(fig, path)
    plt.close(fig)


def plot_tornado(oat: dict, path: str | Path, top: int = 12) -> None:
    """Tornado chart: change of the metric at -1 / +1 sigma of each mask and effect."""
    import matplotlib.pyplot as plt

    rows = oat["rows"][:top][::-1]
    fig, ax = plt.subplots(figsize=(7, 0.4 * len(rows) + 1.4))
    y = np.arange(len(rows))
    ax.barh(y, [r["low_delta"] for r in rows], color="tab:red", label="-1 sigma")
    ax.barh(y, [r["high_delta"] for r in rows], color="tab:blue", alpha=0.7, label="+1 sigma")
    ax.set_yticks(y, [r["label"] for r in rows], fontsize=8)
    ax.axvline(0, color="k", lw=0.8)
    ax.set_xlabel(f"change of {oat['metric']} from {oat['centre_value']:.4g}")
    ax.legend(fontsize=8)
    fig.tight_layout()
    save_figure(fig, path)
    plt.close(fig)


def md_table(header: list, rows: list) -> str:
    """A Markdown table from a header and rows of cells."""
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(_cell(c) for c in row) + " |" for row in rows]
    return "\n".join(lines)


def _cell(value):
    if isinstance(value, float):
        return f"{value:.4g}"
    return str(value)


def markdown(report: dict) -> str:
    """report.md text of a tolerance report."""
    y = report["yield"]
    lines = [f"# Tolerance analysis of {report['design']}", "",
             f"{report['run']['samples']} Monte Carlo samples (seed {report['run']['seed']}), "
             f"scheduler {report['run']['scheduler']} with {report['run']['workers']} worker threads, "
             f"{report['timing']['seconds_per_sample']:.3g} s per sample.", "",
             f"Spec: {report['spec']['source']}.", "",
             md_table(["parameter", "dist", "values"],
                      [[p["name"], p["dist"], ", ".join(f"{k} {v:.4g}" for k, v in p.items()
                                                        if k not in ("name", "effect", "mask", "dist"))]
                       for p in report["spec"]["parameters"]]), "",
             f"Sampling: {report['sampling']['description']}", "",
             "## Metrics", "",
             md_table(["metric", "better", "nominal", "mean", "p10", "p90", "worst decile"],
                      [[k, v["direction"].split()[0], v["nominal"], v["mean"], v["p10"], v["p90"],
                        v["worst_decile_mean"]] for k, v in report["metrics"].items()]), "",
             "## Yield", "",
             f"{y['passed']} of {y['samples']} samples meet {', '.join(f'{m} {t}' for m, t in y['thresholds'].items())}"
             f": yield {y['fraction']:.3f} (95 % interval {y['ci95'][0]:.3f} - {y['ci95'][1]:.3f}).", "",
             "![distributions](distributions.png)", ""]
    oat = report["sensitivity"].get("one_at_a_time")
    if oat and oat["rows"]:
        lines += ["## Sensitivity", "",
                  f"One at a time ({oat['metric']}, centre {oat['centre_value']:.4g}):", "",
                  md_table(["mask and effect", "-1 sigma", "+1 sigma", "change at -1", "change at +1"],
                           [[r["label"], r["low_value"], r["high_value"], r["low_delta"], r["high_delta"]]
                            for r in oat["rows"]]), "", "![tornado](tornado.png)", ""]
    sob = report["sensitivity"].get("sobol")
    if sob:
        lines += [f"Sobol indices of {sob['metric']} ({sob['runs']} runs):", "",
                  md_table(["mask and effect", "S1", "S1 +-", "ST", "ST +-"],
                           [[g, a, b, c, d] for g, a, b, c, d in zip(sob["groups"], sob["S1"], sob["S1_conf"],
                                                                     sob["ST"], sob["ST_conf"])]), ""]
    return "\n".join(lines) + "\n"
