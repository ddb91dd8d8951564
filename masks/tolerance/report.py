"""Summaries, yield, plots and report.md of a tolerance run.

Yield is the fraction of Monte Carlo samples meeting every threshold, with an exact
(Clopper-Pearson) 95 % binomial interval, judged against a goal (the spec's ``[yield] goal``,
``doe tolerance --yield-goal``, default :data:`~masks.tolerance.spec.YIELD_GOAL`): met when the
interval lies above it, missed when it lies below, undecided (more samples needed) when it
straddles it. ``report.md`` is built from the shared blocks of :mod:`doedesign.report_md`
like every other page: a summary first, tables with units, verdicts in words, figures
inline and a link to ``report.json``.
"""

from __future__ import annotations

from pathlib import Path

import math

import numpy as np
from scipy import stats

from doedesign import report_md as md
from doedesign.fileio import save_figure

from .metrics import metric_unit
from .spec import YIELD_GOAL, meets

__all__ = ["YIELD_GOAL", "clopper_pearson", "default_thresholds", "meets_goal", "metric_summary", "most_important",
           "plot_distributions", "plot_tornado", "samples_to_show", "tolerance_page", "tolerance_sections",
           "yield_summary", "yield_verdict"]

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


def meets_goal(ci95: list[float], goal: float = YIELD_GOAL) -> bool | None:
    """True when the whole yield interval lies at or above ``goal``, False when below, None when it straddles."""
    if ci95[0] >= goal:
        return True
    if ci95[1] < goal:
        return False
    return None


def samples_to_show(goal: float = YIELD_GOAL, confidence: float = CONFIDENCE) -> int:
    """Fewest samples, all passing, whose Clopper-Pearson lower bound reaches ``goal``.

    With k = n the lower bound is ``((1 - confidence) / 2) ** (1 / n)`` in closed form.
    """
    return max(1, math.ceil(math.log((1 - confidence) / 2) / math.log(goal)))


def default_thresholds(primary: str, nominal: dict, direction: str) -> dict:
    """The primary metric keeps ``DEFAULT_KEEP`` of its nominal value."""
    value = nominal[primary]
    if direction == "lower":
        return {primary: ("<=", value / DEFAULT_KEEP)}
    return {primary: (">=", value * DEFAULT_KEEP)}


def yield_summary(samples: list[dict], thresholds: dict, goal: float = YIELD_GOAL) -> dict:
    """Fraction of samples meeting every threshold, with its interval, per-threshold pass rates and the goal."""
    n = len(samples)
    passed = [all(meets(s["metrics"][m], t) for m, t in thresholds.items()) for s in samples]
    k = int(sum(passed))
    per = {m: float(np.mean([meets(s["metrics"][m], t) for s in samples])) if n else 0.0
           for m, t in thresholds.items()}
    ci95 = clopper_pearson(k, n)
    return {"thresholds": {m: f"{op} {v:.6g}" for m, (op, v) in thresholds.items()}, "samples": n, "passed": k,
            "fraction": k / n if n else 0.0, "ci95": ci95, "per_threshold": per,
            "interval": "Clopper-Pearson exact binomial, 95 %", "goal": goal,
            "meets_goal": meets_goal(ci95, goal)}


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


def _unit_label(name: str, unit: str) -> str:
    return f"{name} ({unit or 'plain number'})"


_NOT_VALUES = ("name", "effect", "mask", "dist")


def _param_unit(row: dict) -> str:
    """A spec row's unit, from its value keys (``sigma_nm`` -> ``nm``; none for a plain number)."""
    return next((k.partition("_")[2] for k in row if k not in _NOT_VALUES), "")


def _param_values(row: dict) -> str:
    """``mean 0, sigma 2.24`` (the unit is in the parameter's name)."""
    return ", ".join(f"{k.partition('_')[0]} {md.fmt(v, 4)}" for k, v in row.items() if k not in _NOT_VALUES)


def _param_label(row: dict) -> str:
    """``mask 3 mask_overlay dx`` from a spec row (the label of :attr:`masks.tolerance.spec.Param.label`)."""
    base, unit = row["name"].split("[")[0], _param_unit(row)
    base = base.removesuffix(f"_{unit}") if unit else base
    return ("" if row["mask"] is None else f"mask {row['mask']} ") + base.replace(".", " ")


def _varied(parameters: list[dict]) -> str:
    """``etch_depth on masks 0, 1, 2, 3; mask_overlay on mask 3``: what the spec varies."""
    masks: dict[str, set[int]] = {}
    for p in parameters:
        if p["dist"] != "fixed":
            masks.setdefault(p["effect"], set())
            if p["mask"] is not None:
                masks[p["effect"]].add(p["mask"])
    words = []
    for effect, on in masks.items():
        where = "" if not on else f" on mask{'s' if len(on) > 1 else ''} {', '.join(str(m) for m in sorted(on))}"
        words.append(effect + where)
    return "; ".join(words) or "nothing (every parameter fixed)"


def most_important(sensitivity: dict) -> tuple[str, str] | None:
    """The mask and effect that moves the primary metric most: (its label, a sentence saying by how much);
    None without a sensitivity run.

    The one-at-a-time swing is used when it was run (deterministic, one sigma each way), else
    the largest total Sobol index.
    """
    oat = sensitivity.get("one_at_a_time")
    if oat and oat["rows"]:
        top = oat["rows"][0]
        if top["swing"] == 0:
            return None
        unit = metric_unit(oat["metric"])
        centre = oat["centre_value"]
        rel = f", {100 * top['swing'] / abs(centre):.2g} % of its nominal value" if centre else ""
        return top["label"], (f"one sigma of it moves {oat['metric']} by up to {md.fmt(top['swing'], 3, unit)}{rel} "
                              "(one at a time)")
    sob = sensitivity.get("sobol")
    if sob and sob["groups"] and max(sob["ST"]) > 0:
        i = int(np.argmax(sob["ST"]))
        return sob["groups"][i], (f"total Sobol index {md.fmt_pm(sob['ST'][i], sob['ST_conf'][i], 2)} of "
                                  f"{sob['metric']}'s variance ({sob['runs']} runs)")
    return None


def _no_ranking(sensitivity: dict) -> str:
    ran = (sensitivity.get("one_at_a_time") or {}).get("rows") or sensitivity.get("sobol")
    return f"no parameter moved {sensitivity['metric']}" if ran else "not computed (no sensitivity run)"


def _percent(fraction: float) -> str:
    return md.fmt(100 * fraction, 3, "%")


def yield_verdict(y: dict, most: tuple[str, str] | None = None) -> str:
    """The yield judged against its goal, in words (see :func:`meets_goal`); ``most`` names what to tighten."""
    goal, (lo, hi) = y.get("goal", YIELD_GOAL), y["ci95"]
    interval = f"95 % interval {_percent(lo)} to {_percent(hi)}"
    ok = meets_goal([lo, hi], goal)
    if ok is None:
        return md.verdict(None, "", f"{y['samples']} samples cannot tell whether the yield reaches "
                                    f"{100 * goal:g} % ({interval}); at least {samples_to_show(goal)} samples, all "
                                    "passing, are needed to show it")
    fix = f"; tighten the process on {most[0]} first, or relax the thresholds" if most else ""
    return md.verdict(ok, f"at least {100 * goal:g} % of elements meet the thresholds ({interval})",
                      f"the yield is below {100 * goal:g} % ({interval}){fix}")


def tolerance_sections(report: dict, folder: str | Path, prefix: str = "", level: int = 2) -> list[str]:
    """Markdown parts of a tolerance report: summary, parameters, metrics, yield, sensitivity, figures."""
    h = "#" * level
    y, run, spec, sens = report["yield"], report["run"], report["spec"], report["sensitivity"]
    most = most_important(sens)
    thresholds = ", ".join(f"{m} {t}" for m, t in y["thresholds"].items())
    parts = [f"{h} Summary",
             f"- **Toleranced**: `{report['design']}` under the process spec {spec['source']}, varying "
             f"{_varied(spec['parameters'])}.",
             f"- **Samples**: {run['samples']} Monte Carlo process samples (seed {run['seed']}), each judged on "
             f"{thresholds}.",
             f"- **Yield**: {_percent(y['fraction'])} ({y['passed']} of {y['samples']} samples), 95 % interval "
             f"{_percent(y['ci95'][0])} to {_percent(y['ci95'][1])} (Clopper-Pearson).",
             f"- **Matters most**: {': '.join(most) if most else _no_ranking(sens)}.",
             f"- Verdict: {yield_verdict(y, most)}.", "",
             f"{h} Process parameters varied",
             md.table([(_unit_label(_param_label(p), _param_unit(p)), p["dist"], _param_values(p))
                       for p in spec["parameters"]], ("parameter", "distribution", "values")),
             f"Sampling: {report['sampling']['description']}; {md.fmt(report['timing']['seconds_per_sample'], 3)} s "
             f"per sample ({run['scheduler']} scheduler, {run['workers']} worker "
             f"thread{'' if run['workers'] == 1 else 's'}).", "",
             f"{h} Metrics over the samples",
             "Each metric's unit is in its row; p10 and p90 are the 10th and 90th percentiles over the samples.", "",
             md.table([(_unit_label(k, metric_unit(k)), v["direction"].split()[0], md.fmt(v["nominal"], 4),
                        md.fmt(v["mean"], 4),
                        md.fmt(100 * (v["mean"] / v["nominal"] - 1) if v["nominal"] else None, 3),
                        md.fmt(v["p10"], 4), md.fmt(v["p90"], 4), md.fmt(v["worst_decile_mean"], 4))
                       for k, v in report["metrics"].items()],
                      ("metric", "better", "nominal", "mean", "mean change (%)", "p10", "p90", "worst-decile mean")),
             f"{h} Yield",
             f"{y['passed']} of {y['samples']} samples meet every threshold: yield {_percent(y['fraction'])}, 95 % "
             f"interval {_percent(y['ci95'][0])} to {_percent(y['ci95'][1])} ({y['interval']}); judged against a "
             f"goal of {_percent(y.get('goal', YIELD_GOAL))}.", "",
             md.table([(f"{m} {t}", md.fmt(100 * y["per_threshold"][m], 3)) for m, t in y["thresholds"].items()],
                      ("threshold", "samples passing (%)")),
             md.figure(folder, prefix + "distributions.png", "each metric over the samples, nominal element dashed")]
    oat, sob = sens.get("one_at_a_time"), sens.get("sobol")
    if (oat and oat["rows"]) or sob:
        parts.append(f"{h} Which mask and effect matters")
    if oat and oat["rows"]:
        unit = metric_unit(oat["metric"])
        param_units = {p["name"]: _param_unit(p) for p in spec["parameters"]}
        parts += [f"One at a time: each parameter at its -1 and +1 sigma quantiles (15.9 % and 84.1 %), the others "
                  f"at their centre; change of {oat['metric']} from {md.fmt(oat['centre_value'], 4, unit)}, "
                  "largest first.", "",
                  md.table([(_unit_label(r["label"], param_units.get(r["param"], "")), md.fmt(r["low_value"], 4),
                             md.fmt(r["high_value"], 4), md.fmt(r["low_delta"], 3), md.fmt(r["high_delta"], 3))
                            for r in oat["rows"]],
                           ("mask and effect", "-1 sigma value", "+1 sigma value", f"change at -1 sigma ({unit})",
                            f"change at +1 sigma ({unit})")),
                  md.figure(folder, prefix + "tornado.png", f"change of {oat['metric']} at -1 / +1 sigma")]
    if sob:
        parts += [f"Sobol indices of {sob['metric']} ({sob['runs']} runs, ± 95 % bootstrap interval): the share of "
                  "its variance each mask and effect causes alone (first order) and with its interactions (total). "
                  "An interval wider than the index means the run is too short to rank them (raise --sobol-base).",
                  "", md.table([(g, md.fmt_pm(a, b, 3, None), md.fmt_pm(c, d, 3, None))
                                for g, a, b, c, d in zip(sob["groups"], sob["S1"], sob["S1_conf"], sob["ST"],
                                                         sob["ST_conf"])],
                               ("mask and effect", "first order S1 (share of variance)",
                                "total ST (share of variance)"))]
    return parts


def tolerance_page(report: dict, folder: str | Path) -> Path:
    """The whole ``report.md`` of ``doe tolerance``, beside its report.json."""
    title = f"# Tolerance analysis of `{report['design']}`"
    warning = [f"**Warning:** {report['metric_note']}."] if report.get("metric_note") else []
    return md.write_markdown(Path(folder) / "report.md",
                             [title, *warning, *tolerance_sections(report, folder), md.json_link()])
