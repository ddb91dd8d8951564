"""The coded PSF the fabricated element would give, beside the design's.

A profilometer field covers only part of the element (2 mm of an 8.64 mm aperture at
20x), too little to form the PSF at the sensor's resolution, and a periodic tiling of the
patch would turn the PSF into a comb of orders unlike the real one. So the fitted process
of the measured patch (etch depths, per-mask overlay, linewidth bias) is applied to the
whole design with :func:`masks.process.simulate_surface` on a grid of ``pitch / oversample``
and that surface goes through :class:`doedesign.engine.psf.PSFEngine`; the design is evaluated on the
same grid. The assumption is that the process does not vary across the die, which one field
cannot test.

Approximation: the engine takes one height per sample, so a mask sliver narrower than a
sample is height-averaged instead of mixing the two fields. Etch-depth errors come out
right at any ``oversample``; the scatter from sub-micron overlay and bias is underestimated,
strongly at ``oversample = 1`` (5.4 um samples, the CLI default for speed), less at 2.
Roughness is left out (1 nm rms costs ~3e-5, below everything else here).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike

from doedesign.engine.psf import PSFEngine
from doedesign.errors import DoeError
from doedesign.levels import design_levels
from masks.fabricated import DEFAULT_TARGET_FRACTION, fabricated_height, target_from_psf

if TYPE_CHECKING:
    from doedesign.camera import Camera
    from doedesign.design import Design
    from doedesign.progress import Progress
    from masks.process_params import ProcessParams

__all__ = ["DEFAULT_TARGET_FRACTION", "MIN_APERTURE_PX_COARSE_DESIGN", "PSFComparison", "compare_psf",
           "target_from_psf"]


log = logging.getLogger(__name__)

# Apertures at least this many DOE pixels wide get the design PSF on the DOE grid (see compare_psf).
MIN_APERTURE_PX_COARSE_DESIGN = 800


@dataclass
class PSFComparison:
    """Coded PSFs of the design and of the fabricated element (focus depth, each wavelength).

    Attributes
    ----------
    wavelengths_m : ndarray (n_wl,)
    design_psf, measured_psf : ndarray (n_wl, rows, cols)
        Fraction of the light through the coded half-aperture in each sensor pixel
        (row 0 at the top of the window).
    target : ndarray of bool (n_wl, rows, cols)
    design_on_target, measured_on_target : ndarray (n_wl,)
        Light on the target pixels, as a fraction of all the light through the coded half.
    design_in_window, measured_in_window : ndarray (n_wl,)
    oversample : int
    """

    wavelengths_m: np.ndarray
    design_psf: np.ndarray
    measured_psf: np.ndarray
    target: np.ndarray
    design_on_target: np.ndarray
    measured_on_target: np.ndarray
    design_in_window: np.ndarray
    measured_in_window: np.ndarray
    oversample: int

    @property
    def difference(self) -> np.ndarray:
        """Measured minus design PSF."""
        return self.measured_psf - self.design_psf

    def report(self) -> dict:
        """Light on target and in the window per wavelength, design against measured (JSON summary)."""
        wl_nm = [float(v) for v in self.wavelengths_m * 1e9]
        per = {}
        for i, w in enumerate(wl_nm):
            per[f"{w:.0f}"] = {
                "design_on_target": float(self.design_on_target[i]),
                "measured_on_target": float(self.measured_on_target[i]),
                "energy_lost": float(self.design_on_target[i] - self.measured_on_target[i]),
                "relative_loss": float(1 - self.measured_on_target[i] / self.design_on_target[i]),
                "design_in_window": float(self.design_in_window[i]),
                "measured_in_window": float(self.measured_in_window[i]),
                "difference_rms": float(np.sqrt(np.mean(self.difference[i] ** 2))),
            }
        return {
            "wavelengths_nm": wl_nm,
            "design_on_target": [float(v) for v in self.design_on_target],
            "measured_on_target": [float(v) for v in self.measured_on_target],
            "per_wavelength": per,
            "oversample": self.oversample,
            "method": ("fitted process (etch depths, overlay, linewidth bias) of the measured field applied to "
                       "the whole design by the process model on a pitch/oversample grid; coded view, in focus; "
                       "on_target = fraction of the light through the coded half-aperture landing on the target"),
        }


def compare_psf(design: Design, params: ProcessParams, camera: Camera | None = None,
                wavelengths_m: ArrayLike = (486e-9, 589e-9, 656e-9), oversample: int = 2,
                target: np.ndarray | None = None, progress: Progress | None = None) -> PSFComparison:
    """Coded PSF of the design and of the design made with ``params``.

    Parameters
    ----------
    design : doedesign.design.Design
    params : masks.process.ProcessParams
        Fitted process (e.g. ``Comparison.fitted_params()``).
    camera : Camera, optional
        Default: the design's own (:meth:`Design.camera`).
    wavelengths_m : sequence of float
    oversample : int
        Samples per DOE pixel per axis for both surfaces.
    target : ndarray of bool (rows, cols) or (n_wl, rows, cols), optional
        Target pixels; default :func:`target_from_psf` of the design's PSF.

    Returns
    -------
    PSFComparison
    """
    q = int(oversample)
    if q < 1:
        raise DoeError(f"oversample must be a positive integer, got {oversample}")
    camera = camera or design.camera()
    levels = design_levels(design)
    fine_measured = fabricated_height(levels, design.pitch_m, params, q)
    fine_shape = fine_measured.shape
    engine = PSFEngine(camera, design.pitch_m / q, fine_shape, design.material, wavelengths_m)
    # The design is piecewise constant on its own pixels, so its PSF on the DOE grid equals the one
    # on the finer grid at a quarter of the cost (q = 2), except at the circular aperture's edge,
    # which the two grids sample differently: ~0.3 / N of the light for an N-pixel aperture
    # (0.5 % at 64 px). Take the shortcut only where that is below 0.04 %.
    n_ap = np.inf if camera.aperture_diameter_m is None else camera.aperture_diameter_m / design.pitch_m
    if q == 1 or n_ap < MIN_APERTURE_PX_COARSE_DESIGN:
        psf_d = engine.psf(np.kron(design.height_m, np.ones((q, q))), views=("coded",)).view("coded")[0]
    else:
        coarse = PSFEngine(camera, design.pitch_m, design.shape, design.material, wavelengths_m)
        psf_d = coarse.psf(design.height_m, views=("coded",)).view("coded")[0]
    if progress is not None:
        progress.update(1, status="design PSF")
    psf_m = engine.psf(fine_measured, views=("coded",)).view("coded")[0]
    if progress is not None:
        progress.update(1, status="measured PSF")
    if target is None:
        target = target_from_psf(psf_d)
    target = np.broadcast_to(np.asarray(target, bool), psf_d.shape)
    on_d = np.array([p[t].sum() for p, t in zip(psf_d, target)])
    on_m = np.array([p[t].sum() for p, t in zip(psf_m, target)])
    return PSFComparison(wavelengths_m=np.asarray(engine.wavelengths_m), design_psf=psf_d, measured_psf=psf_m,
                         target=np.array(target), design_on_target=on_d, measured_on_target=on_m,
                         design_in_window=psf_d.sum(axis=(1, 2)), measured_in_window=psf_m.sum(axis=(1, 2)),
                         oversample=q)
