"""What a domain (heights in the design frame, heights in the camera frame, PSF stacks)
supplies to the diagnosis's fitting loop: the :class:`~metrology.diagnosis.problem.Problem` base class.

Its own module so that the fits (:mod:`metrology.diagnosis.fitting`) and the selection
(:mod:`metrology.diagnosis.engine`) both name it without importing each other.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from metrology.diagnosis.noise import NoiseEstimate

__all__ = ["Problem"]


class Problem:
    """What a domain supplies to the fitting loop.

    Subclasses set ``effects`` (candidate Effect objects), ``noise`` (NoiseEstimate), optionally
    ``screening`` (a cheaper Problem with the same effects to screen candidates on), and
    implement ``residual(model) -> 1-D array`` (measured minus model, on the compared samples),
    ``residual_map(model) -> 2-D array`` and ``breakdown(residual_map) -> dict``.
    """

    effects: dict
    noise: NoiseEstimate
    units = "m"
    nuisance: dict = {}
    # Whether the forward model holds the instrument, so that a true effect leaves noise on its
    # footprint and a fabrication effect that does not may be withheld as a partial match. The
    # design-frame height fit resamples the data and does not close to the floor (issue 11).
    judges_partial_matches = False
    # Whether candidates are screened, and Jacobian columns computed, side by side in worker
    # threads (:mod:`metrology.diagnosis.parallel`; they share the problem and its locked render
    # caches, and must be safe to evaluate at once). Off where a problem's working arrays would
    # double the peak memory (the full-size PSF stack).
    parallel_fits = False
    # Whether the residual has kinks in the parameters (area-coverage edges crossing grid lines):
    # fits then take central-difference Jacobians; a smooth problem takes forward ones.
    kinks = True
    # Whether the problem fits a part of what its residual maps show (a large window fitted on
    # tiles): the structure test then counts the map's own samples.
    fits_part_of_map = False

    def residual(self, model: dict[str, np.ndarray]) -> np.ndarray:
        raise NotImplementedError

    def residual_map(self, model: dict[str, np.ndarray]) -> np.ndarray:
        raise NotImplementedError

    def breakdown(self, residual_map: np.ndarray) -> dict[str, dict]:
        return {}

    def structure_groups(self) -> list[np.ndarray]:
        """Label maps of bins for the structured-residual test (0 = excluded), one per way of
        grouping pixels that an unmodelled effect would show up in."""
        return []

    def instrument_signature(self, residual_map: np.ndarray, **kw: Any) -> dict | None:
        """Where the forward model holds an instrument: a dict when an unexplained residual is
        the instrument's (the same at every mask's edges), else None; ``kw``: the test's
        options (:func:`~metrology.diagnosis.breakdown.instrument_signature`)."""
        return None
