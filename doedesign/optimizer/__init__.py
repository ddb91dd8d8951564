"""The design loop: a height map optimized with nlopt against a target PSF.

Public:

- :func:`~doedesign.optimizer.optimize.design_doe` and its :class:`~doedesign.optimizer.settings.OptimizerSettings`, returning a :class:`~doedesign.optimizer.optimize.DesignRun`;
- :class:`~doedesign.optimizer.losses.LossSpec` and :func:`~doedesign.optimizer.losses.make_loss`, the target's loss (``losses``).

Inside: ``optimize`` (the run), ``settings`` (its settings and height bounds), ``losses`` (loss
terms on the PSF), ``objectives`` (soft-min and max-min of colour planes), ``robust_loss``
(the loss over process perturbations), ``nlopt_driver`` (nlopt, progress and stops),
``anneal`` (the level penalty), ``starts`` (initial heights), ``router`` (the colour router
start), ``pareto`` (weight sweeps).
"""

from .losses import LossSpec, make_loss
from .optimize import DesignRun, design_doe
from .settings import OptimizerSettings

__all__ = ["DesignRun", "LossSpec", "OptimizerSettings", "design_doe", "make_loss"]
