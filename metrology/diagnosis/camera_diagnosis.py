"""The camera-frame diagnosis of a measured height map (``doe diagnose --frame camera``).

On the camera window with the most design edges (cropped, never resampled), the measurement model
is part of the fitted model (:class:`~metrology.diagnosis.camera.CameraHeightProblem`): the
instrument stage chooses the lateral transfer's family members first
(:func:`~metrology.diagnosis.camera_nuisance.choose_transfer`; or the comparison's stage has,
on a larger window with its members fitted to convergence, and they start the diagnosis), then
the stepwise selection
(:func:`~metrology.diagnosis.engine.run_diagnosis`) names the effects. Spikes and invalid pixels
are excluded by a robust rule on the residual of the model that explains the data; the selection
runs again if the final model re-admits pixels, and the stage again once large fabrication effects
named hold most of what it saw.

Arrays are row-major with row 0 at the top of the camera image.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

import numpy as np

from doedesign.progress import Progress
from metrology.diagnosis import budget as clock
from metrology.diagnosis import engine as dg
from metrology.diagnosis.breakdown import shared_profile_gain
from metrology.diagnosis.camera import CAMERA, CameraHeightProblem
from metrology.diagnosis.camera_nuisance import RESTAGE_WINDOW_PX, STAGE_WINDOW_PX, InstrumentFamily, choose_transfer
from metrology.diagnosis.effects import effects_for
from metrology.diagnosis.parallel import one_thread
from metrology.diagnosis.tiles import TILED_WINDOW_PX, TiledCameraProblem
from metrology.matching.instrument import Placement
from metrology.matching.level import levelling_plane, robust_valid
from metrology.matching.transfer import LateralTransfer, as_transfer
from metrology.matching.window import busiest_camera_window

if TYPE_CHECKING:
    from masks.process_params import ProcessParams

__all__ = ["SCREEN_WINDOW_PX", "diagnose_camera"]

log = logging.getLogger(__name__)

# Camera pixels per side above which candidates are screened on a crop of the window.
SCREEN_WINDOW_PX = 128
# Share of the window's pixels the robust rule must re-admit or newly exclude under the final model
# for the selection (all of it) to run again: 3 of 25,000 cannot change what thousands of samples chose.
RERUN_SHARE = 0.005
# The instrument stage runs again once the fabrication effects named have brought the residual's
# energy below this share of what it saw (:func:`diagnose_camera`): they dominated it.
RESTAGE_SHARE = 0.5
# ... and only once what they leave is not mostly a fabrication effect still to be named: the
# shared edge profile must hold this share of the residual's excess over the floor. A point-sampled
# 0.226 um bias named before a 0.44 um overlay left a profile of 2 % (the restage then fitted the
# instrument as whole pixels, NA 0.95 and a batwing: 3.18x the floor); CSI fields whose restage
# found their objective held 18-36 % (half, the early rule's share, left one of them at 1.84x).
RESTAGE_PROFILE_SHARE = 0.1


class _Restage(Exception):
    """The stage, run again with the effects named, chose more of the family (arguments: its result, the steps)."""


def diagnose_camera(design_levels: np.ndarray, pitch_m: float, measured_height_m: np.ndarray, placement: Placement,
                    depths_m: Sequence[float] | None = None, candidates: Sequence[str] | None = None,
                    threshold: float = dg.DEFAULT_THRESHOLD, max_steps: int = 6, window_px: int = 160,
                    step_m: float | None = None, screen: tuple[ProcessParams, float] | None = None,
                    screen_window_px: int = SCREEN_WINDOW_PX, transfer: LateralTransfer | None = None,
                    limit: clock.Deadline | None = None,
                    batwing: Sequence[float] | None = None, family: InstrumentFamily | None = None) -> dg.Diagnosis:
    """Diagnose a measured height map on the camera's own pixels.

    Parameters
    ----------
    design_levels : ndarray of int
    pitch_m : float
    measured_height_m : ndarray
        Camera heights (m, z up), NaN = invalid; row 0 at the top of the camera image.
    placement : Placement
        Camera pixel -> design pixel (from :func:`metrology.matching.register.register`).
    window_px : int
        Side of the camera window with the most design edges that is fitted (cropped, not resampled).
    screen : (ProcessParams, float), optional
        Process and blur whose residual the robust rule first screens for spikes (e.g. the
        comparison's camera-frame fit; default the ideal process). The fit reruns on re-admitted pixels.
    screen_window_px : int
        A larger window screens the candidates on its busiest square of this size and refits
        the close ones on the whole window; one larger than :data:`~metrology.diagnosis.tiles.TILED_WINDOW_PX`
        is fitted on tiles (:mod:`metrology.diagnosis.tiles`), its maps the whole window's.
    transfer : LateralTransfer, optional
        A calibrated lateral transfer (``doe calibrate instrument``), held fixed; default: fitted
        as a nuisance, the objective's NA and the batwing included when the data ask for it
        (:func:`~metrology.diagnosis.camera_nuisance.choose_transfer`: before any fabrication effect, and again with those named
        once they hold most of the residual, the selection going on through a family that grew).
    batwing : (float, float), optional
        The calibration's batwing (amplitude, sigma_m), held with its transfer.
    family : InstrumentFamily, optional
        The members of the lateral transfer's family a comparison's instrument stage chose on the
        same field, with their values fitted to convergence on its window: where it chose any, the
        diagnosis starts from them instead of choosing again on its own smaller square (the
        stage again once fabrication effects are named still runs).
    limit : Deadline, optional
        A limit the user asked for (default none: every pass runs to its end). Past it no further
        round or revision starts and one under way stops
        (:func:`~metrology.diagnosis.engine.run_diagnosis`); a rerun on re-admitted pixels it cuts
        short leaves the previous pass. Either way the diagnosis is incomplete.

    Returns
    -------
    Diagnosis
        With ``placement`` (the refined placement and its uncertainties) and ``excluded_pixels``.
    """
    from masks.process import ProcessParams

    # Small linear algebra: BLAS threads would only spin beside the renders and worker threads.
    with one_thread(), Progress(3, desc="camera diagnosis") as bar:
        deadline = limit if limit is not None else clock.Deadline()
        meas = np.asarray(measured_height_m, float)
        r0, c0 = busiest_camera_window(np.asarray(design_levels), placement, meas.shape, window_px)
        size = min(window_px, *meas.shape)
        crop = meas[r0:r0 + size, c0:c0 + size]
        start = Placement(placement.matrix, placement.offset + placement.matrix @ np.array([r0, c0], float))
        base = ProcessParams.ideal(depths_m=depths_m) if depths_m is not None else ProcessParams.ideal()
        effects = effects_for("height", candidates, n_masks=base.n_masks)
        effects_by_name = {e.name: e for e in effects}
        finite = np.isfinite(crop)
        screen_params, screen_blur = screen if screen is not None else (base, CAMERA.start_values()[5])
        screen_blur = screen_blur if transfer is None else transfer
        # One render serves the noise floor and the robust rule (the screening model's).
        held: dict[str, Any] = {} if batwing is None else {"batwing": tuple(batwing)}
        first = CameraHeightProblem(design_levels, pitch_m, crop, start, screen_params, [], step_m=step_m,
                                    transfer=as_transfer(screen_blur), **held)
        keep = robust_valid(first.residual_map({CAMERA.name: np.zeros(5)}), finite)
        diag = problem = fit = None
        extras, prior, instrument_stage, noise, chosen_by = {}, None, None, first.noise, None

        def make(keep, **extras):
            # The floor is the measurement's, estimated on the screening model's residual (not the
            # ideal element's, whose process errors would leak into the interiors and raise it).
            problem = CameraHeightProblem(design_levels, pitch_m, crop, start, base, effects, step_m=step_m, keep=keep,
                                          noise=noise, instrument=first.instrument, transfer=transfer, **held, **extras)
            fit = TiledCameraProblem(problem) if size > TILED_WINDOW_PX else problem
            if size > screen_window_px:
                fit.screening = problem.crop(screen_window_px)
            return problem, fit

        def stage(named=None):
            # The instrument stage (:func:`~metrology.diagnosis.camera_nuisance.choose_transfer`) on the busiest square, then the floor
            # again through what it chose beyond blur and fill (an objective or a batwing rings into
            # the interiors), only ever lowered: a higher one is process error leaking in.
            if named is None and family is not None and any(family.chosen().values()):
                chosen, fitted, changes = family.chosen(), family.start(), dict(family.criterion_changes)
                log.info("instrument stage: the comparison's %s, from its fit on the field", chosen)
                source = "the comparison's instrument stage (on its window, refitted to convergence)"
            else:
                stage_px = min(size, RESTAGE_WINDOW_PX if named else STAGE_WINDOW_PX)
                chosen, fitted, changes = choose_transfer(
                    lambda **kw: make(keep, **kw)[0].crop(stage_px) if size > stage_px else make(keep, **kw)[1],
                    threshold, named)
                source = f"the diagnosis's instrument stage (on its {stage_px} px square)"
            floor = noise
            if any(chosen.values()):
                seen = (make(keep, **chosen)[0] if named else
                        CameraHeightProblem(design_levels, pitch_m, crop, start, screen_params, [], step_m=step_m,
                                            keep=keep, instrument=first.instrument, **chosen))
                again = seen.noise_at(fitted)
                log.info("noise floor %.3g m after the instrument stage (%.3g m before)", again.sigma, noise.sigma)
                floor = min(noise, again, key=lambda e: e.sigma)
            return chosen, fitted, changes, floor, source

        if transfer is None:
            bar.stage("instrument stage: the lateral transfer's family")
            extras, prior, instrument_stage, noise, chosen_by = stage()
        bar.update(1)
        done, carried = None, ()  # the last pass that ran to its end: (problem, fit, keep, diagnosis)
        restaged = transfer is not None

        def restage(model, steps):
            nonlocal restaged
            # A large fabrication effect (a 0.4 um bias) hid the instrument's edge profile from the
            # stage: once the named ones hold most of what it saw, it runs again with them, and if it
            # now chooses the objective or the batwing, the selection goes on through them.
            fab = {k: v for k, v in model.items() if k in effects_by_name and effects_by_name[k].kind != "artefact"}
            if (restaged or not fab or all(extras.values())
                    or steps[-1].residual_rms_after ** 2 > RESTAGE_SHARE * steps[0].residual_rms_before ** 2):
                return
            # Nor where what they leave holds no edge profile shared by every mask that would pay for
            # one parameter: a screen, not a bound (the family's refit earned -1082, the profile -472).
            r_map = fit.residual_map(model)
            rss, gain = shared_profile_gain(r_map, problem.edge_m, problem.base.etch_depth, problem.keep)
            n_eff = max(np.count_nonzero(problem.keep) / problem.noise.corr_area_px, 2.0)
            bound = n_eff * np.log(max(rss - gain, 1e-300) / rss) + np.log(n_eff)
            n = max(np.count_nonzero(problem.keep & np.isfinite(r_map)), 1)
            share = dg.excess_share(gain / n, rss / n, problem.noise.sigma)
            log.info("after %s: a shared edge profile would change the criterion by %.1f (%.0f %% of the "
                     "residual's excess over the floor)", sorted(fab), bound, 100 * share)
            if bound >= -threshold or share < RESTAGE_PROFILE_SHARE:
                return
            restaged = True
            again = stage({CAMERA.name: model[CAMERA.name], **fab})
            if any(again[0][k] and not extras[k] for k in extras):
                log.info("instrument stage again, with %s in the model: %s", sorted(fab), again[0])
                raise _Restage(again, steps)

        for k in range(4):
            bar.stage(f"selection, pass {k + 1}" + (f" (carried: {', '.join(s.effect for s in carried)})"
                                                    if carried else "" if k == 0 else " (re-admitted pixels)"))
            problem, fit = make(keep, **extras)
            # The criterion alone decides: the floor is good to ~5 %, and a gradient of a few tenths
            # of a nanometre still earns its parameters after the residual has reached it.
            try:
                diag = dg.run_diagnosis(fit, threshold=threshold, max_steps=max_steps, domain="height",
                                        quick_screen=True, stop_at_floor=False, prior=diag.model if diag else prior,
                                        limit=deadline, after_step=restage, carried=carried)
            except _Restage as again:
                (extras, prior, instrument_stage, noise, chosen_by), carried = again.args
                diag = None
                continue
            carried = ()  # a rerun on re-admitted pixels selects afresh
            if diag.stopped_early is not None:
                if done is not None:  # a rerun cut short: the last finished selection stands, incomplete
                    cut, (problem, fit, keep, diag) = diag.stopped_early, done
                    diag.tested = [c for c in diag.tested if c in diag.named]
                    diag.stopped_early = dict(cut, reason="time limit: the rerun on re-admitted pixels was cut "
                                              "short; the previous pass stands", untried=diag.untried,
                                              final_over_floor=diag.final_residual_rms / diag.noise_floor)
                break
            done = (problem, fit, keep, diag)
            r = crop - problem.render(diag.model)
            new_keep = robust_valid(np.where(np.isfinite(crop), r, np.nan)
                                    - levelling_plane(r, problem.keep, problem.curvature), np.isfinite(crop))
            if np.count_nonzero(new_keep != keep) <= RERUN_SHARE * keep.size:
                break
            keep = new_keep
        bar.update(1, "uncertainties")
        assert diag is not None and problem is not None and fit is not None  # the loop ends on a finished selection
        diag.map_step_m = problem.pixel_m
        if fit is not problem:
            # What the user reads is the whole window's (the counts stay the fitted tiles').
            diag.initial_residual_rms, diag.final_residual_rms = (
                float(np.sqrt(np.nanmean(m ** 2))) for m in (diag.residual_maps[0], diag.residual_maps[-1]))
        # The nuisance's uncertainties at the final model (the others held).
        errors = dg.standard_errors(fit, diag.model, list(problem.nuisance))
        diag.placement = problem.placement_report(diag.model, errors)
        if instrument_stage is not None:
            diag.placement["instrument"]["criterion_change"] = instrument_stage
            diag.placement["instrument"]["members_chosen_by"] = chosen_by
        diag.excluded_pixels = int(np.isfinite(crop).sum() - keep.sum())
        diag.window_camera_px = [r0, r0 + size, c0, c0 + size]
        bar.update(1, ", ".join(diag.named) or "nothing named")
        return diag
