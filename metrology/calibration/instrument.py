"""The instrument's lateral transfer calibrated on a measured artefact of known geometry.

What metrologists do for an areal instrument's lateral response (cf. ISO 25178-600: the
instrument transfer function measured on a step or grating): a test structure whose geometry
is known (its design file, e.g. a grating or a step on the die; nominal depths from the
design or given) is measured, registered in the camera's frame as any element is
(:func:`metrology.matching.compare.compare_measurement`), and the instrument's lateral
transfer (pixel fill factor, Gaussian blur, the objective's NA when it earns its parameter,
:mod:`metrology.matching.transfer`) is fitted with the placement and the artefact's step
heights (a certified step is known to a percent; its height is not the transfer). The result
is a JSON file that ``doe compare --instrument`` and ``doe diagnose --instrument`` read and then
hold fixed.

File (strict JSON, SI units): ``format`` = :data:`FORMAT`, ``version``, ``lateral_transfer``
(``blur_sigma_m``, ``fill_factor``, ``na`` (0 = no optical cut-off), ``wavelength_m`` and each
one's uncertainty), ``artefact`` (design, measurement, fitted step heights), ``fit``
(residual and noise floor, pixels). Camera arrays are row-major, row 0 at the top.
"""

from __future__ import annotations

import json
import logging
import math
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from doedesign.errors import DoeError
from metrology.matching.transfer import DEFAULT_WAVELENGTH_M, LateralTransfer

if TYPE_CHECKING:
    from doedesign.design import Design
    from metrology.formats.measurement import Measurement

__all__ = ["FORMAT", "calibrate_instrument", "read_instrument"]

log = logging.getLogger(__name__)

FORMAT = "doe-toolkit instrument calibration"
VERSION = 1


def calibrate_instrument(design: Design, measurement: Measurement, depths_m: Sequence[float] | None = None,
                         window_px: int = 160, threshold: float = 10.0, wavelength_m: float = DEFAULT_WAVELENGTH_M,
                         source: str = "measurement", force: bool = False) -> dict[str, Any]:
    """Fit the lateral transfer on a measured artefact of known geometry.

    Parameters
    ----------
    design : Design
        The artefact's geometry (its levels and pitch).
    measurement : Measurement
    depths_m : sequence of float, optional
        Nominal step of each mask (default: the design's binary depths); fitted within their
        tolerance, reported as ``artefact.step_heights_m``.
    window_px : int
        Camera pixels per side of the window fitted (the one richest in edges).
    threshold : float
        Criterion drop the objective's NA must earn.
    wavelength_m : float
        Mean wavelength of the instrument (the NA-limited transfer's; only NA / lambda is measured).
    source : str
        The measurement's name in messages.
    force : bool
        Go on when the measurement matches the design poorly.

    Returns
    -------
    dict
        The calibration (see the module docstring); :func:`read_instrument` reads it back.
    """
    from threadpoolctl import threadpool_limits

    from doedesign.levels import design_levels
    from masks.decompose import binary_depths_m
    from masks.process import ProcessParams
    from metrology.diagnosis import engine as dg
    from metrology.diagnosis.camera import CameraHeightProblem
    from metrology.diagnosis.camera_nuisance import CAMERA, OBJECTIVE, instrument_report, objective_starts
    from metrology.diagnosis.effects import get_effect
    from metrology.matching.compare import compare_measurement
    from metrology.matching.instrument import Placement, robust_valid
    from metrology.matching.window import busiest_camera_window

    try:
        comp = compare_measurement(measurement, design, force=force)
    except DoeError as exc:
        raise DoeError(f"{source}: {exc}") from None
    levels = design_levels(design)
    depths = list(binary_depths_m(design.level_step_m(16), 4)) if depths_m is None else [float(v) for v in depths_m]
    placement = comp.instrument_fit.placement
    meas = np.asarray(measurement.height_m, float)
    with threadpool_limits(limits=1, user_api="blas"):
        r0, c0 = busiest_camera_window(levels, placement, meas.shape, window_px)
        size = min(window_px, *meas.shape)
        crop = meas[r0:r0 + size, c0:c0 + size]
        start = Placement(placement.matrix, placement.offset + placement.matrix @ np.array([r0, c0], float))
        base = ProcessParams.ideal(depths_m=depths)
        depth = get_effect("etch_depth")
        first = CameraHeightProblem(levels, design.pitch_m, crop, start, comp.fitted_params(), [],
                                    transfer=LateralTransfer(comp.instrument_fit.blur_sigma_m,
                                                             wavelength_m=wavelength_m))
        keep = robust_valid(first.residual_map({CAMERA.name: np.zeros(5)}), np.isfinite(crop))

        def fit(objective, model):
            problem = CameraHeightProblem(levels, design.pitch_m, crop, start, base, [depth], keep=keep,
                                          noise=first.noise, instrument=first.instrument, objective=objective)
            free = list(model)
            fitted, rss, errors = dg.fit_effects(problem, model, free)
            return problem, fitted, rss, errors

        plain, m0, rss0, e0 = fit(False, {CAMERA.name: CAMERA.start_values(), depth.name: depth.start_values()})
        optic = None
        rss1 = np.inf
        for init in objective_starts(m0, plain.transfer_of(m0)):
            trial = fit(True, init)
            if trial[2] < rss1:
                optic, m1, rss1, e1 = trial
        n = plain.residual(m0).size
        n_eff = max(n / plain.noise.corr_area_px, 2.0)
        change = dg.bic_eff(rss1, n, n_eff, 12) - dg.bic_eff(rss0, n, n_eff, 11)
        problem, model, rss, errors = (optic, m1, rss1, e1) if change < -threshold else (plain, m0, rss0, e0)
    t = problem.transfer_of(model)
    cam_err = np.asarray(errors.get(CAMERA.name), float)
    na_err = float(np.asarray(errors.get(OBJECTIVE.name, [math.nan]))[0])
    lateral = instrument_report(t, cam_err[5], cam_err[6], na_err)
    lateral["source"] = f"calibrated on {source}"
    residual = float(np.sqrt(rss / n))
    log.info("instrument calibrated: blur %.3f um, fill %.2f, NA %.3f; residual %.3g m against a floor of %.3g m",
             t.sigma_m * 1e6, t.fill_factor, t.na, residual, problem.noise.sigma)
    return {"format": FORMAT, "version": VERSION, "lateral_transfer": lateral,
            "artefact": {"measurement": source,
                         "step_heights_m": (np.asarray(depths) * (1 + np.asarray(model[depth.name], float))).tolist(),
                         "step_heights_uncertainty_m": (np.asarray(depths)
                                                        * np.asarray(errors.get(depth.name), float)).tolist(),
                         "nominal_step_heights_m": depths},
            "fit": {"residual_rms_m": residual, "noise_floor_m": problem.noise.sigma,
                    "objective_criterion_change": float(change), "pixels": int(n),
                    "window_camera_px": [r0, r0 + size, c0, c0 + size],
                    "conventions": "camera arrays row-major, row 0 at the top; SI units"}}


def read_instrument(path: str | Path) -> LateralTransfer:
    """The lateral transfer of a calibration file written by ``doe calibrate instrument``."""
    path = Path(path)
    try:
        data = json.loads(path.read_text())
        lat = data["lateral_transfer"]
        if data.get("format") != FORMAT:
            raise ValueError(f"not an instrument calibration (format {data.get('format')!r})")
        values = [float(lat[k]) for k in ("blur_sigma_m", "fill_factor", "na", "wavelength_m")]
    except FileNotFoundError:
        raise DoeError(f"{path}: instrument calibration file not found") from None
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise DoeError(f"{path}: not a readable instrument calibration: {exc}") from None
    sigma, fill, na, lam = values
    if not (0 <= sigma <= 5e-6 and 0 <= fill <= 1 and (na == 0 or 0.05 <= na <= 0.95) and 0.1e-6 <= lam <= 2e-6):
        raise DoeError(f"{path}: instrument calibration out of range (blur {sigma} m, fill factor {fill}, NA {na}, "
                       f"wavelength {lam} m)")
    return LateralTransfer(sigma, fill, na, lam)
