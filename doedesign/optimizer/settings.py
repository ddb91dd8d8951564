"""Settings of a design run (:func:`doedesign.optimizer.optimize.design_doe`) and the height
bounds each height range allows.

Kept apart from the run itself so that the objectives and the router, which the run calls, can
name the settings without importing the run.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..engine.backend import DEVICES
from ..errors import DoeError
from ..levels import N_LEVELS, check_level_count
from .nlopt_driver import ALGORITHMS
from .robust_loss import ROBUST_MEASURES
from .starts import INITS

__all__ = ["HEIGHT_RANGES", "OBJECTIVES", "WRAP_SPAN", "OptimizerSettings", "height_bounds"]

OBJECTIVES = ("loss", "softmin", "maxmin")
HEIGHT_RANGES = ("process", "2pi", "wrap")
# Bounds of the "wrap" range in 2 pi heights: wide enough never to bind, finite for nlopt.
WRAP_SPAN = 8


def height_bounds(step_m: float, n_levels: int = N_LEVELS, height_range: str = "process") -> tuple[float, float]:
    """(lower, upper) height bounds in metres for ``height_range`` (see the module docstring)."""
    if height_range == "process":
        return -(n_levels - 1) * step_m, 0.0
    if height_range == "2pi":
        return -n_levels * step_m, 0.0
    if height_range == "wrap":
        return -WRAP_SPAN * n_levels * step_m, WRAP_SPAN * n_levels * step_m
    raise DoeError(f"height range must be one of {HEIGHT_RANGES}, got {height_range!r}")


@dataclass
class OptimizerSettings:
    """Settings of :func:`~doedesign.optimizer.optimize.design_doe` (see the module docstring)."""

    algorithm: str = "LD_LBFGS"
    max_iter: int = 100
    ftol_rel: float = 1e-7
    max_time_s: float | None = None
    seed: int = 0
    init: str = "random"
    height_range: str = "process"
    n_levels: int = N_LEVELS
    quantize: bool = True
    anneal_iter: int = 20
    fab_weight: float = 0.0
    reweight_rounds: int = 0
    reweight_alpha: float = 1.0
    reweight_iter: int | None = None  # None: max_iter
    robust_measure: str = "mean"      # with perturbations: "mean" or "cvar" of the loss
    cvar_alpha: float = 0.25          # CVaR: share of the worst perturbations averaged
    objective: str = "loss"
    colour_weights: list | None = None  # per wavelength (or per plane) for softmin / maxmin
    softmin_tau: float = 0.01
    starts: tuple = ()  # further initial designs for a multi-start; the best after start_iter is kept
    start_iter: int | None = None  # None: max(max_iter // 4, 3)
    router_grid_px: int = 100
    router_iter: int = 150
    device: str = "cpu"  # where the PSF engine computes: "cpu", "gpu" or "auto" (doedesign.engine.backend)

    def __post_init__(self):
        self.n_levels = check_level_count(self.n_levels, "n_levels")
        if self.device not in DEVICES:
            raise DoeError(f"device must be one of {', '.join(DEVICES)}, got {self.device!r}")
        if self.objective not in OBJECTIVES:
            raise DoeError(f"objective must be one of {', '.join(OBJECTIVES)}, got {self.objective!r}")
        self.starts = tuple(self.starts)
        for s in (self.init, *self.starts):
            if s not in INITS:
                raise DoeError(f"unknown initialization {s!r}; choose from {', '.join(INITS)}")
        if not self.softmin_tau > 0:
            raise DoeError(f"softmin_tau must be positive, got {self.softmin_tau}")
        if self.algorithm not in ALGORITHMS:
            raise DoeError(f"algorithm must be one of {', '.join(ALGORITHMS)}, got {self.algorithm!r}")
        if int(self.max_iter) < 1:
            raise DoeError(f"iterations must be at least 1, got {self.max_iter}")
        if self.height_range not in HEIGHT_RANGES:
            raise DoeError(f"height range must be one of {HEIGHT_RANGES}, got {self.height_range!r}")
        if self.max_time_s is not None and not self.max_time_s > 0:
            raise DoeError(f"time limit must be positive, got {self.max_time_s}")
        if self.fab_weight < 0:
            raise DoeError("fab_weight must be >= 0")
        if int(self.reweight_rounds) < 0 or not (np.isfinite(self.reweight_alpha) and self.reweight_alpha > 0):
            raise DoeError(f"reweight_rounds must be >= 0 and reweight_alpha > 0, got {self.reweight_rounds} "
                           f"and {self.reweight_alpha}")
        if self.reweight_iter is not None and int(self.reweight_iter) < 1:
            raise DoeError(f"reweight_iter must be at least 1, got {self.reweight_iter}")
        if self.robust_measure not in ROBUST_MEASURES or not 0 < self.cvar_alpha <= 1:
            raise DoeError(f"robust_measure must be one of {ROBUST_MEASURES} and cvar_alpha in (0, 1], got "
                           f"{self.robust_measure!r} and {self.cvar_alpha}")
