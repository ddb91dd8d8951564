"""The trade-off between colours: a weight sweep of the max-min traces the Pareto front.

The weighted max-min ``max min_c E_c / w_c`` ends where the energies stand in the ratio of the
weights, on the front (where no colour gains without another losing). Each weight vector is
solved on the coherent pupil model (:mod:`doedesign.optimizer.router`), carried to the design grid and
scored exactly by the PSF engine, continuous and rounded to the 16 levels, so the figure shows
what the engine sees, not what the model predicts.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike

from ..camera import Camera
from ..engine.psf import PSFEngine
from ..levels import level_step_m, quantize
from ..progress import Progress
from ..targets import Target
from .router import pupil_model, router_heights, to_design_grid
from .settings import height_bounds

__all__ = ["front_figure", "pareto_front", "sweep_weights"]

log = logging.getLogger(__name__)


def sweep_weights(n_colours: int = 3, factors: Sequence[float] = (0.6, 1.6)) -> list[np.ndarray]:
    """Equal weights, then each colour in turn favoured and disfavoured by ``factors``."""
    out = [np.ones(n_colours)]
    for c in range(n_colours):
        for f in factors:
            w = np.ones(n_colours)
            w[c] = f
            out.append(w)
    return out


def pareto_front(camera: Camera, target: Target, pitch_m: float, shape: tuple[int, int],
                 material: str = "fused_silica", design_wavelength_m: float = 550e-9,
                 weights: Sequence[ArrayLike] | None = None, grid_px: int = 64, iterations: int = 100) -> list[dict]:
    """Front points: per weight vector the model, continuous and quantized energies on target.

    Returns
    -------
    list of dict
        ``weights``, ``model``, ``continuous``, ``quantized`` (energies per wavelength, depth 0).
    """
    step = level_step_m(material, design_wavelength_m)
    lower, _ = height_bounds(step)
    model = pupil_model(camera, target, material, grid_px)
    engine = PSFEngine(camera, pitch_m, shape, material, target.wavelengths_m, target.depths_m[:1])
    weights = weights if weights is not None else sweep_weights(target.wavelengths_m.size)
    points = []
    with Progress(len(weights), desc="Pareto front") as bar:
        for w in weights:
            h, e_model = router_heights(model, lower, w, iterations, target=target)
            h = to_design_grid(model, h, camera, pitch_m, shape)
            point = {"weights": np.asarray(w, float).tolist(), "model": e_model.tolist()}
            for name, hh in (("continuous", h), ("quantized", quantize(h, step).height_m)):
                psf = engine.psf(hh, views=("coded",)).psf[0, 0]
                point[name] = np.sum(psf * target.mask[0], axis=(-2, -1)).tolist()
            points.append(point)
            bar.update(1, status=f"weakest {min(point['quantized']):.3f}")
    return points


def front_figure(points: list[dict], bound: Sequence[float], chosen: Sequence[float], path: str | Path,
                 labels: Sequence[str] = ("R", "G", "B"), chosen_label: str = "chosen design") -> Path:
    """Pairwise projections of the front (quantized and continuous) with the bounds and the chosen design."""
    import matplotlib.pyplot as plt

    from ..fileio import save_figure

    q = np.array([p["quantized"] for p in points])
    c = np.array([p["continuous"] for p in points])
    pairs = [(0, 1), (0, 2), (1, 2)]
    fig, axes = plt.subplots(1, 3, figsize=(13, 4.3))
    for ax, (i, j) in zip(axes, pairs):
        ax.scatter(c[:, i], c[:, j], facecolors="none", edgecolors="tab:gray", label="front, continuous")
        ax.scatter(q[:, i], q[:, j], color="tab:blue", label="front, 16 levels")
        ax.axvline(bound[i], color="k", ls="--", lw=1)
        ax.axhline(bound[j], color="k", ls="--", lw=1, label="single-colour bound")
        ax.plot([chosen[i]], [chosen[j]], marker="*", ms=16, color="tab:red", ls="none", label=chosen_label)
        ax.plot([0, 1], [0, 1], color="0.8", lw=0.8)
        ax.set_xlim(0, max(bound[i], chosen[i]) * 1.08)
        ax.set_ylim(0, max(bound[j], chosen[j]) * 1.08)
        ax.set_xlabel(f"{labels[i]} energy on its pixel")
        ax.set_ylabel(f"{labels[j]} energy on its pixel")
    axes[0].legend(fontsize=7, loc="upper right")
    fig.suptitle("Colour trade-off: weighted max-min sweep (fractions of the coded half's light)")
    fig.tight_layout()
    return save_figure(fig, path)
