"""The instrument's lateral transfer calibrated on a measured artefact of known geometry.

What metrologists do for an areal instrument's lateral response (cf. ISO 25178-600: the
instrument transfer function measured on a step or grating): a test structure whose geometry
is known (its design file, e.g. a grating or a step on the die; nominal depths from the
design or given) is measured, registered in the camera's frame as any element is
(:func:`metrology.matching.compare.compare_measurement`), and the instrument's lateral
transfer (pixel fill factor, Gaussian blur, and the objective's NA and an interferometer's
batwing where they earn their parameters, as the diagnosis's instrument stage chooses them:
:mod:`metrology.matching.transfer`) is fitted with the placement and the artefact's step
heights (a certified step is known to a percent; its height is not the transfer). The result
is a JSON file that ``doe compare --instrument`` and ``doe diagnose --instrument`` read and then
hold fixed.

Height scale. With the artefact's certified step heights (``step_heights_m``) the calibration
also fixes the instrument's height scale: the fitted step of each mask over its certified
height is that mask's estimate of the scale (measured height per true height); their weighted
mean is the scale, which compare and diagnose divide every measured height by. The masks must
agree on it (one scale, :data:`STEP_TOLERANCE` apart at most beyond their fitted uncertainty)
and it must be one a profilometer can have (within :data:`HEIGHT_SCALE_LIMIT` of 1): a
certified height given wrong is refused, not absorbed. Without certified heights the scale is
1 (not calibrated).

File (strict JSON, SI units): ``format`` = :data:`FORMAT`, ``version``, ``lateral_transfer``
(``blur_sigma_m``, ``fill_factor``, ``na`` (0 = no optical cut-off), ``wavelength_m`` and each
one's uncertainty; ``batwing``: ``amplitude``, ``sigma_m`` and their uncertainties, null when
the batwing did not earn its parameters; diagnose holds it, compare's model has none),
``artefact`` (design, measurement, fitted step heights), ``fit`` (residual and noise floor at
the fitted transfer, the family's members chosen and each combination's criterion change,
pixels), ``height_scale`` (``value``, ``uncertainty``, ``certified_step_heights_m``; value 1 and
no uncertainty when not calibrated). Camera arrays are row-major, row 0 at the top.
"""

from __future__ import annotations

import json
import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from doedesign.errors import DoeError
from metrology.matching.transfer import DEFAULT_WAVELENGTH_M, LateralTransfer

if TYPE_CHECKING:
    from doedesign.design import Design
    from metrology.formats.measurement import Measurement

__all__ = ["FORMAT", "HEIGHT_SCALE_LIMIT", "PIXEL_TOLERANCE", "STEP_TOLERANCE", "InstrumentCalibration",
           "apply_calibration", "calibrate_instrument", "height_scale", "read_calibration", "read_instrument"]

log = logging.getLogger(__name__)

#: The ``format`` field of an instrument calibration file.
FORMAT = "doe-toolkit instrument calibration"
VERSION = 1
#: The most a profilometer's height scale departs from 1: vendors specify step-height accuracy
#: within 0.5-1 % (CSI, confocal); an instrument out of calibration may be off by a few percent.
#: Beyond 5 % the certified height given is more likely wrong than the instrument.
HEIGHT_SCALE_LIMIT = 0.05
#: How far one mask's scale may stray from the common one beyond its fitted uncertainty: a
#: certified step's own uncertainty (about 1 %).
STEP_TOLERANCE = 0.01
#: A calibration holds for the objective and zoom it was made with: a measurement whose pixel
#: differs by more than this (relative) was taken with another, and the fill factor (a fraction
#: of the camera pixel) and the blur would not carry over.
PIXEL_TOLERANCE = 0.01


@dataclass(frozen=True)
class InstrumentCalibration:
    """What compare and diagnose hold of a calibration file: the lateral transfer, the height
    scale (measured per true height; 1 = not calibrated), the camera pixel it was made at (m;
    None in files that do not say), the file, and the batwing (amplitude, sigma_m) when it was
    fitted (diagnose holds it; compare's model has no batwing)."""

    transfer: LateralTransfer
    height_scale: float = 1.0
    pixel_m: float | None = None
    path: str = ""
    batwing: tuple[float, float] | None = None


def calibrate_instrument(design: Design, measurement: Measurement, depths_m: Sequence[float] | None = None,
                         window_px: int = 160, threshold: float = 10.0, wavelength_m: float = DEFAULT_WAVELENGTH_M,
                         source: str = "measurement", force: bool = False,
                         step_heights_m: Sequence[float] | None = None) -> dict[str, Any]:
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
        Go on when the measurement matches the design poorly, or when the certified heights
        and the measurement disagree (see :func:`height_scale`).
    step_heights_m : sequence of float, optional
        The artefact's certified step height per mask (its nominal depths in the fit, instead
        of ``depths_m``): the calibration then fixes the height scale too.

    Returns
    -------
    dict
        The calibration (see the module docstring); :func:`read_instrument` reads it back.
    """
    from metrology.diagnosis.parallel import one_thread

    from doedesign.levels import design_levels
    from masks.process import ProcessParams
    from metrology.diagnosis import engine as dg
    from metrology.diagnosis.camera import CameraHeightProblem
    from metrology.diagnosis.camera_nuisance import (BATWING, CAMERA, MEMBERS, OBJECTIVE, earned_members,
                                                     instrument_report, member_starts)
    from metrology.diagnosis.effects import get_effect
    from metrology.matching.compare import compare_measurement
    from metrology.matching.instrument import Placement
    from metrology.matching.level import robust_valid
    from metrology.matching.window import busiest_camera_window

    try:
        comp = compare_measurement(measurement, design, force=force, texture=False)
    except DoeError as exc:
        raise DoeError(f"{source}: {exc}") from None
    levels = design_levels(design)
    if step_heights_m is not None:
        if depths_m is not None:
            raise DoeError("give either the artefact's certified step heights or nominal depths, not both")
        depths_m = step_heights_m
    depths = list(design.etch_depths_m()) if depths_m is None else [float(v) for v in depths_m]
    if len(depths) != design.n_masks:
        raise DoeError(f"the artefact's step heights: one per mask ({design.n_masks}), got {len(depths)}")
    placement = comp.instrument_fit.placement
    meas = np.asarray(measurement.height_m, float)
    with one_thread():
        r0, c0 = busiest_camera_window(levels, placement, meas.shape, window_px)
        size = min(window_px, *meas.shape)
        crop = meas[r0:r0 + size, c0:c0 + size]
        start = Placement(placement.matrix, placement.offset + placement.matrix @ np.array([r0, c0], float))
        base = ProcessParams.ideal(depths_m=depths)
        depth = get_effect("etch_depth").for_masks(len(depths))
        assert depth is not None  # every mask has a depth
        first = CameraHeightProblem(levels, design.pitch_m, crop, start, comp.fitted_params(), [],
                                    transfer=LateralTransfer(comp.instrument_fit.blur_sigma_m,
                                                             comp.instrument_fit.transfer.fill_factor,
                                                             wavelength_m=wavelength_m))
        keep = robust_valid(first.residual_map({CAMERA.name: np.zeros(5)}), np.isfinite(crop))

        def make(objective, batwing, noise=first.noise):
            return CameraHeightProblem(levels, design.pitch_m, crop, start, base, [depth], keep=keep, noise=noise,
                                       instrument=first.instrument, objective=objective, batwing=batwing)

        def fit(model, objective=False, batwing=False):
            problem = make(objective, batwing)
            fitted, rss, errors = dg.fit_effects(problem, model, list(model), precise=True)
            return problem, fitted, rss, errors

        plain = fit({CAMERA.name: CAMERA.start_values(), depth.name: depth.start_values()})
        m0 = plain[1]
        n = plain[0].residual(m0).size
        n_eff = max(n / plain[0].noise.corr_area_px, 2.0)

        def crit(trial):
            return dg.bic_eff(trial[2], n, n_eff, sum(len(v) for v in trial[1].values()))

        # The members of the family the diagnosis's instrument stage tries, each fitted to
        # convergence from the blur-and-fill fit (the objective from both of its starts).
        fits: dict[tuple[str, ...], tuple[float, Any]] = {(): (crit(plain), plain)}
        for members in MEMBERS:
            for s in member_starts(members, m0, plain[0].transfer_of(m0)):
                trial = fit(s, objective="objective" in members, batwing="batwing" in members)
                c = crit(trial)
                if members not in fits or c < fits[members][0]:
                    fits[members] = (c, trial)
        current = fits[()][0]
        changes = {"+".join(m): float(c - current) for m, (c, _) in fits.items() if m}
        chosen = earned_members({m: c for m, (c, _) in fits.items() if m}, current, threshold)
        problem, model, rss, errors = fits[chosen][1]
        # The floor again at the fitted transfer: the first one, on the comparison's blur alone,
        # holds what an objective or a batwing rings into the interiors (2-3x the noise on a
        # CSI artefact), and its correlation area scaled every uncertainty up with it. It only
        # ever lowers the floor, as in the diagnosis.
        noise = problem.noise_at(model)
        if noise.sigma < problem.noise.sigma:
            problem = make(OBJECTIVE.name in model, BATWING in model, noise)
            errors = dg.standard_errors(problem, model, list(model))
    t = problem.transfer_of(model)
    cam_err = np.asarray(errors.get(CAMERA.name), float)
    na_err = float(np.asarray(errors.get(OBJECTIVE.name, [math.nan]))[0])
    lateral = instrument_report(t, cam_err[5], cam_err[6], na_err)
    lateral["source"] = f"calibrated on {source}"
    lateral["batwing"] = None
    if BATWING in model:
        bw, bw_err = (np.asarray(v, float) for v in (model[BATWING], errors.get(BATWING, [math.nan] * 2)))
        lateral["batwing"] = {"amplitude": float(bw[0]), "amplitude_uncertainty": float(bw_err[0]),
                              "sigma_m": float(bw[1]), "sigma_uncertainty_m": float(bw_err[1]),
                              "model": "edge overshoot, a signed Gaussian-derivative band-pass beside the objective"}
    lateral["camera_pixel_m"] = float(measurement.pixel_size_m)
    residual = float(np.sqrt(rss / n))
    steps = np.asarray(depths) * (1 + np.asarray(model[depth.name], dtype=float))
    steps_err = np.asarray(depths) * np.asarray(errors.get(depth.name), dtype=float)
    scale: dict[str, Any] = {"value": 1.0, "uncertainty": math.nan, "certified_step_heights_m": None,
             "note": "not calibrated (no certified step heights): measured heights are taken as they are"}
    if step_heights_m is not None:
        value, err = height_scale(steps, steps_err, depths, source, force)
        scale = {"value": value, "uncertainty": err, "certified_step_heights_m": depths,
                 "note": "measured height per true height; compare and diagnose divide measured heights by it"}
    log.info("instrument calibrated: blur %.3f um, fill %.2f, NA %.3f; residual %.3g m against a floor of %.3g m",
             t.sigma_m * 1e6, t.fill_factor, t.na, residual, problem.noise.sigma)
    return {"format": FORMAT, "version": VERSION, "lateral_transfer": lateral,
            "artefact": {"measurement": source, "step_heights_m": steps.tolist(),
                         "step_heights_uncertainty_m": steps_err.tolist(), "nominal_step_heights_m": depths},
            "height_scale": scale,
            "fit": {"residual_rms_m": residual, "noise_floor_m": problem.noise.sigma,
                    "objective_criterion_change": changes["objective"], "criterion_changes": changes,
                    "members": list(chosen), "pixels": int(n),
                    "window_camera_px": [r0, r0 + size, c0, c0 + size],
                    "conventions": "camera arrays row-major, row 0 at the top; SI units"}}


def height_scale(steps_m: Sequence[float], errors_m: Sequence[float], certified_m: Sequence[float],
                 source: str = "measurement", force: bool = False) -> tuple[float, float]:
    """The instrument's height scale (measured per true height) and its uncertainty from fitted
    steps and their certified heights.

    Each mask whose step the fit determined (a finite uncertainty under 5 % of the step: a
    mask absent from the window is not) gives ``step / certified``; the scale is their
    inverse-variance mean. Raises :class:`~doedesign.errors.DoeError` (unless ``force``) when one mask's ratio
    strays from their median by more than three times its uncertainty combined with
    :data:`STEP_TOLERANCE`, or when the scale lies beyond :data:`HEIGHT_SCALE_LIMIT` of 1: a
    certified height given wrong.
    """
    steps, errs, cert = (np.asarray(v, float) for v in (steps_m, errors_m, certified_m))
    ok = np.isfinite(errs) & (errs > 0) & (errs < 0.05 * steps)
    if not ok.any():
        raise DoeError(f"{source}: no step of the artefact was measured well enough to fix the height scale")
    ratio, sd = steps[ok] / cert[ok], errs[ok] / cert[ok]
    w = 1.0 / sd ** 2
    value = float(np.sum(w * ratio) / w.sum())
    # Against the median: one wrong height must not pull the common scale toward itself.
    spread = np.abs(ratio - np.median(ratio)) / np.sqrt(sd ** 2 + STEP_TOLERANCE ** 2)
    # The scatter between masks beyond their fitted errors also counts (a model imperfection).
    err = float(max(1.0 / np.sqrt(w.sum()), np.std(ratio) / np.sqrt(ratio.size)))
    masks = np.flatnonzero(ok)
    if spread.max() > 3 and not force:
        j = int(np.argmax(spread))
        raise DoeError(f"{source}: the certified step heights disagree with the measurement: mask {masks[j]} "
                       f"measures {steps[ok][j] * 1e9:.2f} nm against {cert[ok][j] * 1e9:.2f} nm certified "
                       f"(ratio {ratio[j]:.4f}, the masks' median {np.median(ratio):.4f}); check --step-height-nm "
                       "(or --force)")
    if abs(value - 1) > HEIGHT_SCALE_LIMIT and not force:
        raise DoeError(f"{source}: the measured steps are {value:.4f} x the certified heights, beyond the "
                       f"{HEIGHT_SCALE_LIMIT:.0%} a profilometer's height scale departs from 1; "
                       "check --step-height-nm (or --force)")
    return value, err


def read_instrument(path: str | Path) -> LateralTransfer:
    """The lateral transfer of a calibration file written by ``doe calibrate instrument``."""
    return read_calibration(path).transfer


def read_calibration(path: str | Path) -> InstrumentCalibration:
    """A calibration file written by ``doe calibrate instrument`` (height scale 1 and no pixel
    when the file has none)."""
    path = Path(path)
    try:
        data = json.loads(path.read_text())
        lat = data["lateral_transfer"]
        if data.get("format") != FORMAT:
            raise ValueError(f"not an instrument calibration (format {data.get('format')!r})")
        values = [float(lat[k]) for k in ("blur_sigma_m", "fill_factor", "na", "wavelength_m")]
        scale = float((data.get("height_scale") or {}).get("value", 1.0))
        pixel = lat.get("camera_pixel_m")
        pixel = None if pixel is None else float(pixel)
        batwing = lat.get("batwing")
        batwing = None if batwing is None else (float(batwing["amplitude"]), float(batwing["sigma_m"]))
    except FileNotFoundError:
        raise DoeError(f"{path}: instrument calibration file not found") from None
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise DoeError(f"{path}: not a readable instrument calibration: {exc}") from None
    sigma, fill, na, lam = values
    if not (0 <= sigma <= 5e-6 and 0 <= fill <= 1 and (na == 0 or 0.05 <= na <= 0.95) and 0.1e-6 <= lam <= 2e-6):
        raise DoeError(f"{path}: instrument calibration out of range (blur {sigma} m, fill factor {fill}, NA {na}, "
                       f"wavelength {lam} m)")
    if not abs(scale - 1) <= HEIGHT_SCALE_LIMIT:
        raise DoeError(f"{path}: instrument calibration's height scale {scale} lies beyond "
                       f"{HEIGHT_SCALE_LIMIT:.0%} of 1")
    if pixel is not None and not 1e-8 <= pixel <= 1e-3:
        raise DoeError(f"{path}: instrument calibration's camera pixel {pixel} m is out of range")
    if batwing is not None:
        from metrology.diagnosis.camera_nuisance import BATWING
        from metrology.diagnosis.effects import get_effect

        lo, hi = get_effect(BATWING).bounds()
        if not np.all((lo <= batwing) & (batwing <= hi)):
            raise DoeError(f"{path}: instrument calibration's batwing (amplitude {batwing[0]}, sigma {batwing[1]} m) "
                           f"is out of range (amplitude {lo[0]:g} to {hi[0]:g}, sigma {lo[1]:g} to {hi[1]:g} m)")
    return InstrumentCalibration(LateralTransfer(sigma, fill, na, lam), scale, pixel, str(path), batwing)


def apply_calibration(measurement: Measurement, cal: InstrumentCalibration | None,
                      source: str = "measurement") -> Measurement:
    """``measurement`` in true heights (divided by the calibration's height scale), after
    checking that it was taken at the calibration's camera pixel (the same objective and zoom).

    Raises
    ------
    DoeError
        The pixel sizes differ by more than :data:`PIXEL_TOLERANCE`.
    """
    from dataclasses import replace

    if cal is None:
        return measurement
    if cal.pixel_m is not None and abs(measurement.pixel_size_m / cal.pixel_m - 1) > PIXEL_TOLERANCE:
        raise DoeError(f"{source}: pixel {measurement.pixel_size_m * 1e6:.4g} um, but the instrument calibration "
                       f"{cal.path} was made at {cal.pixel_m * 1e6:.4g} um (another objective or zoom: its fill "
                       "factor and blur do not carry over); calibrate at this magnification")
    if cal.height_scale == 1.0:
        return measurement
    meta = {**measurement.metadata, "height_scale_applied": cal.height_scale}
    return replace(measurement, height_m=measurement.height_m / cal.height_scale, metadata=meta)
