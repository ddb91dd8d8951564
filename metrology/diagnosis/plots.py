"""Figures of a diagnosis: the residual map step by step and where the residual lives."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from doedesign.fileio import save_figure

__all__ = ["plot_breakdown", "plot_steps"]


def _scale(domain: str) -> tuple[float, str]:
    return (1e9, "nm") if domain == "height" else (1.0, "fraction")


def plot_steps(maps: list[np.ndarray], titles: list[str], rms: list[float], domain: str,
               path: str | Path) -> Path:
    """Residual maps (row 0 at the top) with their titles and rms, in the units of ``domain``
    ("height": metres, shown in nm; else fractions of the light); returns the path."""
    import matplotlib.pyplot as plt

    scale, unit = _scale(domain)
    lim = np.nanpercentile(np.abs(maps[0]), 99) * scale or 1.0
    fig, axes = plt.subplots(1, len(maps), figsize=(3.2 * len(maps), 3.4), squeeze=False)
    for ax, m, t, r in zip(axes[0], maps, titles, rms):
        im = ax.imshow(m * scale, cmap="RdBu_r", vmin=-lim, vmax=lim, origin="upper", interpolation="nearest")
        ax.set_title(f"{t}\nrms {r * scale:.3g} {unit}", fontsize=9)
        ax.set_xticks([])
        ax.set_yticks([])
    fig.colorbar(im, ax=axes[0].tolist(), shrink=0.8, label=f"measured - model ({unit}); row 0 at top")
    return save_figure(fig, path)


def plot_breakdown(before: dict, after: dict, domain: str, path: str | Path) -> Path:
    """Mean residual by each breakdown key (a dict of ``edges``, ``mean``, ``rms`` per key),
    ``before`` and ``after`` the diagnosis; returns the path."""
    import matplotlib.pyplot as plt

    scale, unit = _scale(domain)
    keys = [k for k, v in before.items() if "rms" in v]
    fig, axes = plt.subplots(1, max(len(keys), 1), figsize=(3.4 * max(len(keys), 1), 3.0), squeeze=False)
    for ax, key in zip(axes[0], keys):
        for label, bd, style in (("before", before, "o-"), ("after", after, "s--")):
            b = bd[key]
            centres = 0.5 * (np.asarray(b["edges"][1:]) + np.asarray(b["edges"][:-1]))
            x = centres * 1e6 if key.endswith("_m") else centres
            ax.plot(x, np.asarray(b["mean"]) * scale, style, ms=3, label=f"mean {label}")
        ax.axhline(0, color="k", lw=0.5)
        ax.set_xlabel(f"{key[:-2]} (um)" if key.endswith("_m") else key, fontsize=8)
        ax.set_ylabel(f"residual ({unit})", fontsize=8)
        ax.tick_params(labelsize=7)
    axes[0][0].legend(fontsize=7)
    return save_figure(fig, path)
