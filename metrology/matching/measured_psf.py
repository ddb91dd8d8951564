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

The figure of merit is the design's own: the light on the target the design was made for
(its ``metadata["target"]``, rebuilt by :func:`masks.tolerance.metrics.design_target_mask`,
the same pixels the design report and the tolerance analysis count), at the target's
wavelengths and source distance. A design without a target gets a different quantity under
a different name: the light in the design PSF's core (its brightest pixels holding
``DEFAULT_TARGET_FRACTION`` of its window light, :func:`masks.fabricated.target_from_psf`).
Both PSFs come from the element the masks print (:func:`doedesign.levels.printed_height_m`).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike

from doedesign.engine.psf import PSFEngine
from doedesign.errors import DoeError
from doedesign.levels import design_levels, printed_height_m
from doedesign.camera import describe_surround, resolve_surround
from masks.fabricated import DEFAULT_TARGET_FRACTION, fabricated_height, target_from_psf
from masks.tolerance.metrics import design_target_mask, design_wavelengths_depths

if TYPE_CHECKING:
    from doedesign.camera import Camera
    from doedesign.design import Design
    from doedesign.progress import Progress
    from masks.process_params import ProcessParams

__all__ = ["DEFAULT_TARGET_FRACTION", "DEFAULT_WAVELENGTHS_M", "MERIT_NAMES", "MIN_APERTURE_PX_COARSE_DESIGN",
           "PSFComparison", "compare_psf", "target_from_psf"]


log = logging.getLogger(__name__)

# Apertures at least this many DOE pixels wide get the design PSF on the DOE grid (see compare_psf).
MIN_APERTURE_PX_COARSE_DESIGN = 800
#: Wavelengths of the comparison when the design names no target (hydrogen F, sodium D, hydrogen C).
DEFAULT_WAVELENGTHS_M = (486e-9, 589e-9, 656e-9)
#: What the light is counted on: the design's own target, or (a different quantity) the design PSF's core.
MERIT_NAMES = {"design_target": "light on the design's target",
               "psf_core": "light in the design PSF's core",
               "given": "light on the given target pixels"}


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
        The pixels the light is counted on (see ``target_source``).
    design_on_target, measured_on_target : ndarray (n_wl,)
        Light on those pixels, as a fraction of all the light through the coded half.
    design_in_window, measured_in_window : ndarray (n_wl,)
    oversample : int
    target_source : str
        ``"design_target"`` (the design's own target: its figure of merit), ``"psf_core"``
        (the design PSF's brightest pixels, for a design without a target, or wavelengths
        it has none at) or ``"given"`` (the caller's); :data:`MERIT_NAMES` names them.
    depth_m : float
        Source distance of the PSFs (``inf``: optical infinity).
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
    target_source: str = "psf_core"
    depth_m: float = float("inf")
    surround: str = "open"
    coded_clear_fraction: float = 1.0

    @property
    def merit_name(self) -> str:
        """What ``*_on_target`` measures, in words."""
        return MERIT_NAMES[self.target_source]

    @property
    def difference(self) -> np.ndarray:
        """Measured minus design PSF."""
        return self.measured_psf - self.design_psf

    def report(self) -> dict:
        """The merit and the light in the window per wavelength, design against fabricated (JSON summary).

        The keys say what was counted: ``design_on_target`` / ``measured_on_target`` on the
        design's own target, ``design_in_psf_core`` / ``measured_in_psf_core`` on the PSF core,
        ``*_on_given_pixels`` on the caller's pixels.
        """
        key = {"design_target": "on_target", "psf_core": "in_psf_core"}.get(self.target_source, "on_given_pixels")
        wl_nm = [float(v) for v in self.wavelengths_m * 1e9]
        per = {}
        for i, w in enumerate(wl_nm):
            per[f"{w:.0f}"] = {
                f"design_{key}": float(self.design_on_target[i]),
                f"measured_{key}": float(self.measured_on_target[i]),
                "energy_lost": float(self.design_on_target[i] - self.measured_on_target[i]),
                "relative_loss": float(1 - self.measured_on_target[i] / self.design_on_target[i]),
                "design_in_window": float(self.design_in_window[i]),
                "measured_in_window": float(self.measured_in_window[i]),
                "difference_rms": float(np.sqrt(np.mean(self.difference[i] ** 2))),
            }
        counted = {"design_target": "the pixels of the target the design was made for (its metadata)",
                   "psf_core": f"the design PSF's core: its brightest pixels holding {DEFAULT_TARGET_FRACTION:.0%} "
                               "of its window light (the design names no target at these wavelengths)",
                   }.get(self.target_source, "target pixels given by the caller")
        return {
            "wavelengths_nm": wl_nm,
            "depth_m": self.depth_m if np.isfinite(self.depth_m) else "inf",
            "merit": {"name": self.merit_name, "target": self.target_source, "counted_on": counted},
            f"design_{key}": [float(v) for v in self.design_on_target],
            f"measured_{key}": [float(v) for v in self.measured_on_target],
            "per_wavelength": per,
            "oversample": self.oversample,
            "surround": self.surround,
            "surround_means": describe_surround(self.surround),
            "coded_clear_fraction": self.coded_clear_fraction,
            "method": ("fitted process (etch depths, overlay, linewidth bias) of the measured field applied to "
                       "the whole design by the process model on a pitch/oversample grid; coded view; light as a "
                       "fraction of the light through the coded half-aperture, counted on " + counted),
        }


def compare_psf(design: Design, params: ProcessParams, camera: Camera | None = None,
                wavelengths_m: ArrayLike | None = None, oversample: int = 2,
                target: np.ndarray | None = None, progress: Progress | None = None) -> PSFComparison:
    """Coded PSF of the design and of the design made with ``params``.

    Parameters
    ----------
    design : doedesign.design.Design
    params : masks.process.ProcessParams
        Fitted process (e.g. ``Comparison.fitted_params()``).
    camera : Camera, optional
        Default: the design's own (:meth:`Design.camera <doedesign.design.Design.camera>`).
    wavelengths_m : sequence of float, optional
        Default: the wavelengths of the design's target, else :data:`DEFAULT_WAVELENGTHS_M`.
        Wavelengths the target does not have get the PSF core instead (a different merit).
    oversample : int
        Samples per DOE pixel per axis for both surfaces.
    target : ndarray of bool (rows, cols) or (n_wl, rows, cols), optional
        Pixels to count the light on instead of the design's target (reported as ``"given"``).

    Returns
    -------
    PSFComparison
    """
    q = int(oversample)
    if q < 1:
        raise DoeError(f"oversample must be a positive integer, got {oversample}")
    camera = camera or design.camera()
    assert camera is not None  # missing="seed": a design without one gets the seed camera
    own_wls, own_depths = design_wavelengths_depths(design, camera)
    own_mask = design_target_mask(design, camera, own_wls, own_depths[:1])
    wls = np.atleast_1d(np.asarray(own_wls if wavelengths_m is None and own_mask is not None else
                                   DEFAULT_WAVELENGTHS_M if wavelengths_m is None else wavelengths_m, float))
    depth = float(own_depths[0]) if own_mask is not None else float(camera.focus_distance_m)
    levels = design_levels(design)
    printed = printed_height_m(design)
    fine_measured = fabricated_height(levels, design.pitch_m, params, q)
    fine_shape = fine_measured.shape
    surround = resolve_surround(None, design.metadata, design.source_path or design.name)[0]
    engine = PSFEngine(camera, design.pitch_m / q, fine_shape, design.material, wls, depths_m=[depth],
                       surround=surround)
    # The design is piecewise constant on its own pixels, so its PSF on the DOE grid equals the one
    # on the finer grid at a quarter of the cost (q = 2), except at the circular aperture's edge,
    # which the two grids sample differently: ~0.3 / N of the light for an N-pixel aperture
    # (0.5 % at 64 px). Take the shortcut only where that is below 0.04 %.
    n_ap = np.inf if camera.aperture_diameter_m is None else camera.aperture_diameter_m / design.pitch_m
    if q == 1 or n_ap < MIN_APERTURE_PX_COARSE_DESIGN:
        psf_d = engine.psf(np.kron(printed, np.ones((q, q))), views=("coded",)).view("coded")[0]
    else:
        coarse = PSFEngine(camera, design.pitch_m, design.shape, design.material, wls, depths_m=[depth],
                           surround=surround)
        psf_d = coarse.psf(printed, views=("coded",)).view("coded")[0]
    if progress is not None:
        progress.update(1, status="design PSF")
    psf_m = engine.psf(fine_measured, views=("coded",)).view("coded")[0]
    if progress is not None:
        progress.update(1, status="measured PSF")
    source = "given" if target is not None else "psf_core"
    if target is None:
        planes = [np.flatnonzero(np.isclose(own_wls, w, rtol=1e-6, atol=0)) for w in wls]
        if own_mask is not None and all(p.size for p in planes):
            target, source = own_mask[0, [int(p[0]) for p in planes]], "design_target"
        else:
            target = target_from_psf(psf_d)
    target = np.broadcast_to(np.asarray(target, bool), psf_d.shape)
    on_d = np.array([p[t].sum() for p, t in zip(psf_d, target)])
    on_m = np.array([p[t].sum() for p, t in zip(psf_m, target)])
    return PSFComparison(wavelengths_m=np.asarray(engine.wavelengths_m), design_psf=psf_d, measured_psf=psf_m,
                         target=np.array(target), design_on_target=on_d, measured_on_target=on_m,
                         design_in_window=psf_d.sum(axis=(1, 2)), measured_in_window=psf_m.sum(axis=(1, 2)),
                         oversample=q, target_source=source, depth_m=depth, surround=surround,
                         coded_clear_fraction=engine.clear_fraction)
