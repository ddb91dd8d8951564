"""Figures shared by the CLI commands and the reports.

The backend is left to the caller (the ``doe`` CLI selects Agg; a notebook keeps its own).
"""

from __future__ import annotations

from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np
from matplotlib.axes import Axes
from matplotlib.figure import Figure

from .engine.psf import PSFResult
from .fileio import save_figure

__all__ = ["height_map_figure", "psf_figure", "save"]


def height_map_figure(height_m: np.ndarray, pitch_m: float, title: str = "height map",
                      ax: Axes | None = None) -> Figure | None:
    """Height map in nm with a micrometre scale (row 0 at the top)."""
    fig = None
    if ax is None:
        fig, ax = plt.subplots(figsize=(5, 4.2))
    rows, cols = height_m.shape
    extent = (0, cols * pitch_m * 1e6, rows * pitch_m * 1e6, 0)
    im = ax.imshow(height_m * 1e9, cmap="viridis", extent=extent, interpolation="nearest")
    ax.set_xlabel("x (um)")
    ax.set_ylabel("y (um, row 0 at top)")
    ax.set_title(title)
    plt.colorbar(im, ax=ax, label="height (nm)")
    return fig


def psf_figure(result: PSFResult, crop: int = 64, log: bool = True, title: str = "") -> Figure:
    """Montage of coded/uncoded PSFs per wavelength around the axis (first depth)."""
    views = list(result.views)
    nw = len(result.wavelengths_m)
    show = np.unique(np.linspace(0, nw - 1, min(nw, 6)).round().astype(int))
    fig, axes = plt.subplots(len(views), show.size, figsize=(2.6 * show.size, 2.6 * len(views)), squeeze=False)
    r0, c0 = result.axis_pixel
    for vi, view in enumerate(views):
        for k, wi in enumerate(show):
            img = result.psf[vi, 0, wi]
            r_lo, c_lo = max(r0 - crop, 0), max(c0 - crop, 0)
            sub = img[r_lo:r0 + crop + 1, c_lo:c0 + crop + 1]
            shown = np.log10(np.maximum(sub, sub.max() * 1e-5)) if log else sub
            ax = axes[vi, k]
            ax.imshow(shown, cmap="inferno", interpolation="nearest",
                      extent=(c_lo - c0 - 0.5, c_lo - c0 + sub.shape[1] - 0.5, r_lo - r0 + sub.shape[0] - 0.5, r_lo - r0 - 0.5))
            ax.set_title(f"{view} {result.wavelengths_m[wi] * 1e9:.0f} nm\nin window {img.sum():.1%}", fontsize=8)
            ax.tick_params(labelsize=7)
    axes[-1, 0].set_xlabel("column - axis (px)")
    axes[-1, 0].set_ylabel("row - axis (px)")
    if title:
        fig.suptitle(title + (" (log10)" if log else ""))
    fig.tight_layout()
    return fig


def save(fig: Figure, path: str | Path) -> Path:
    """Save ``fig`` atomically as PNG."""
    return save_figure(fig, path)
