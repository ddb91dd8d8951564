"""One tolerance sample: process parameters -> fabricated surface -> coded PSF -> metrics.

:class:`Evaluator` holds everything a worker needs (levels, camera, wavelengths, the spec,
the metric set) and is shipped to each worker once. Its PSF engine is built lazily, once per
thread, and never pickled.

Sampling (the per-sample cost): the process model runs on the whole element at
``process_upsample`` samples per design pixel, is area-averaged to ``oversample`` samples
per pixel and goes through :class:`doedesign.engine.psf.PSFEngine` at ``pitch / oversample``
(coded view only: the uncoded half is clear glass, untouched by the process), at the
design's wavelengths and depths. See :mod:`masks.fabricated` for what this grid misses.

A sample runs where its engine computes (``device``, :mod:`doedesign.engine.backend`): the
process render, the PSFs and the metrics' reductions all on that device (one copy of each
formula, the same on NumPy and CuPy); the job's metrics cross to the host as one small vector.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass

import numpy as np

from doedesign.camera import Camera
from doedesign.engine.backend import Array, Backend
from doedesign.engine.psf import PSFEngine

from ..fabricated import fabricated_height
from ..process import ProcessParams
from .metrics import MetricSet
from .spec import ToleranceSpec

__all__ = ["Evaluator", "evaluate_batch"]


@dataclass
class Evaluator:
    """Everything needed to evaluate samples of one design under one spec.

    ``metrics`` is None until it is set up on the nominal PSF, which the evaluator itself
    computes (:func:`masks.tolerance.analysis.build_evaluator`).
    """

    levels: np.ndarray
    pitch_m: float
    material: str
    camera: Camera
    wavelengths_m: np.ndarray
    depths_m: np.ndarray
    spec: ToleranceSpec
    base: ProcessParams
    metrics: MetricSet | None
    oversample: int = 2
    process_upsample: int | None = None
    device: str = "cpu"  # where samples are computed (doedesign.engine.backend)
    surround: str = "open"  # around the design inside the lens aperture (doedesign.camera.SURROUNDS)

    def __post_init__(self):
        self._local = threading.local()

    def __getstate__(self):
        state = dict(self.__dict__)
        state.pop("_local", None)
        return state

    def __setstate__(self, state):
        self.__dict__.update(state)
        self._local = threading.local()

    @property
    def engine(self) -> PSFEngine:
        engine = getattr(self._local, "engine", None)
        if engine is None:
            q = self.oversample
            shape = (self.levels.shape[0] * q, self.levels.shape[1] * q)
            engine = PSFEngine(self.camera, self.pitch_m / q, shape, self.material, self.wavelengths_m,
                               self.depths_m, device=self.device, surround=self.surround)
            self._local.engine = engine
        return engine

    @property
    def backend(self) -> Backend:
        """Where this thread's samples are computed (the engine's backend)."""
        return self.engine.backend

    def height(self, values: dict, seed: int | None = None) -> Array:
        """Fabricated height map (m) for parameter values (SI, by :attr:`Param.name <masks.tolerance.spec.Param.name>`), an
        array of :attr:`backend` (NumPy on the CPU)."""
        params = self.spec.params_for(values, self.base, seed=seed)
        return fabricated_height(self.levels, self.pitch_m, params, self.oversample, self.process_upsample,
                                 backend=self.backend)

    def _coded_stack(self, height_m: Array) -> Array:
        return self.engine.psf_stack(height_m, views=("coded",))[0, ...]

    def coded_psf(self, height_m: Array) -> np.ndarray:
        """Coded PSF (depths, wavelengths, rows, cols) of a height map on the engine's grid (NumPy)."""
        return self.backend.to_host(self._coded_stack(height_m))

    def __call__(self, job):
        """Metrics of one job ``{"id", "values", "seed", ...}``; returns the job plus ``metrics``."""
        t0 = time.perf_counter()
        psf = self._coded_stack(self.height(job["values"], job.get("seed")))
        return {**job, "metrics": self.metrics(psf, self.backend), "seconds": time.perf_counter() - t0}


def evaluate_batch(evaluator: Evaluator, jobs: list[dict]) -> list[dict]:
    """Evaluate a list of jobs in order (one dask task)."""
    return [evaluator(job) for job in jobs]
