"""Starting designs: the initial height maps (:data:`~doedesign.optimizer.starts.INITS`) and the multi-start among them.

``init`` picks one start for :func:`doedesign.optimizer.optimize.design_doe`; ``starts`` adds others, each
optimized for a short stage, and the best goes on (all are in the report). ``router`` comes from
the coherent pupil model of :mod:`doedesign.optimizer.router`; the others are made here.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING, Any

import numpy as np

from ..errors import DoeError
from ..levels import N_LEVELS, wrap_height_m
from ..materials import get_material

if TYPE_CHECKING:
    from ..camera import Camera
    from ..materials import Material

__all__ = ["INITS", "initial_height", "multistart"]

#: Names of the optimizer's starting height maps (:func:`initial_height`).
INITS = ("random", "zeros", "streak", "grating", "lens", "router")


def _wrap_into(h, lower, step_m, n_levels):
    """Wrap heights modulo the 2 pi height into [lower, 0] (nearest end for the process gap)."""
    h = wrap_height_m(h, step_m, n_levels)
    return np.where(h < lower, np.where(h < lower - step_m / 2, 0.0, lower), h)


def initial_height(kind: str, shape: tuple[int, int], step_m: float, lower: float, rng: np.random.Generator,
                   n_levels: int = N_LEVELS, period_px: int = 16, arms: str = "+", pitch_m: float = 5.4e-6,
                   camera: Camera | None = None, design_wavelength_m: float = 550e-9,
                   material: str | Material = "fused_silica", focus_depth_m: float | None = None) -> np.ndarray:
    """A starting height map.

    Parameters
    ----------
    kind : {"random", "zeros", "streak", "grating", "lens"}
        ``random``: uniform in the bounds; ``zeros``: flat; ``streak``: rank-1 maps varying along
        one axis only (each spreads light along that axis), along columns in the top half and
        along rows in the bottom half for a "+" cross; ``grating``: a blazed staircase of
        ``period_px`` along columns, phase rising with column (first order toward higher
        column); ``lens``: the phase that refocuses the camera from its focus distance to
        ``focus_depth_m`` (a lens difference), wrapped into the bounds.
    """
    rows, cols = shape
    if kind == "random":
        return rng.uniform(lower, 0.0, shape)
    if kind == "zeros":
        return np.zeros(shape)
    if kind == "streak":
        along_cols = np.broadcast_to(rng.uniform(lower, 0.0, cols), shape)
        along_rows = np.broadcast_to(rng.uniform(lower, 0.0, rows)[:, None], shape)
        if arms == "h":
            return along_cols.copy()
        if arms == "v":
            return along_rows.copy()
        return np.where((np.arange(rows) < rows // 2)[:, None], along_cols, along_rows)
    if kind == "grating":
        level = (np.arange(cols) % period_px) * n_levels // period_px
        return np.tile(-(n_levels - 1 - level) * step_m, (rows, 1)).astype(float)
    if kind == "lens":
        if camera is None or focus_depth_m is None:
            raise DoeError("the lens initialization needs the camera and a depth to focus")
        y = (np.arange(rows) - (rows - 1) / 2) * pitch_m
        x = (np.arange(cols) - (cols - 1) / 2) * pitch_m
        r2 = y[:, None] ** 2 + x[None, :] ** 2

        def sag(d):
            return np.zeros_like(r2) if np.isinf(d) else r2 / (np.sqrt(r2 + d * d) + d)

        # The DOE cancels the defocus path of a point at focus_depth_m: that point comes to focus.
        opd = -(sag(focus_depth_m) - sag(camera.focus_distance_m))
        mat = get_material(material)
        h = opd / (mat.n(design_wavelength_m) - 1.0)
        return _wrap_into(h, lower, step_m, n_levels)
    raise DoeError(f"unknown initialization {kind!r}; choose from {', '.join(INITS)} or give a height map")


def multistart(kinds: Sequence[str], start: Callable[[str], np.ndarray],
               run_stage: Callable[..., tuple[np.ndarray, list[float]]],
               score: Callable[[np.ndarray], object], iterations: int,
               max_time_s: float | None = None) -> tuple[np.ndarray, list[dict], str]:
    """A short stage from each initial design; the one with the lowest loss goes on.

    Parameters
    ----------
    kinds : sequence of str
        The initial designs, in the order they are tried.
    start : callable
        ``start(kind) -> h``, the starting height map of ``kind``.
    run_stage : callable
        ``run_stage(h_start, max_iter, max_time_s, desc) -> (h, history)``, one nlopt stage.
    score : callable
        ``score(h)``: the energy on target to report beside each start's loss.
    iterations : int
        Evaluations per start.

    Returns
    -------
    height_m : ndarray, the best start after its stage
    tried : list of dict, ``init``, ``loss`` and ``energy_on_target`` of every start
    best : str, the kind that goes on
    """
    tried: list[dict[str, Any]] = []
    for kind in kinds:
        hs, hist = run_stage(start(kind), iterations, max_time_s, f"start {kind}")
        tried.append({"init": kind, "loss": min(hist), "height": hs, "energy_on_target": score(hs)})
    best = min(tried, key=lambda r: r["loss"])
    return best["height"], [{k: v for k, v in r.items() if k != "height"} for r in tried], best["init"]
