"""Which member of the lateral transfer's family ``doe compare``'s camera-frame fit holds.

The camera-frame fit (:func:`metrology.matching.instrument_fit.fit_in_camera_frame`) fits a
Gaussian blur through a held pixel fill factor. Two questions are answered from the data
before its result is reported:

* **Whole pixels or point samples.** A Gaussian blur and a pixel box of the same second moment
  (``sigma^2 + f a^2 / 12`` per axis, ``a`` the pixel side) give nearly the same edge; only the
  edge's higher moments (the box's flat top against the Gaussian's tails) tell them apart, so a
  fill factor fitted beside the blur trades against it on a small field (on a pixel-integrating
  file it ran to 0 with the blur at 0.458 um for the true 0.304 um, and the fitted depths moved
  off the terrace fit's). The two ends of the family, fill 1 (a camera that integrates its
  pixels) and fill 0 (one that samples their centres), are fitted instead, each with its own
  blur, on the same window; point samples are kept only when they lower the information
  criterion ``n_eff ln(RSS / N)`` by more than ``threshold`` (both have the same parameters,
  so this is a likelihood ratio with a stated margin, ``FILL_THRESHOLD``; whole pixels,
  the common camera, win a tie).
* **An objective or a batwing.** The diagnosis's instrument stage
  (:func:`metrology.diagnosis.camera_nuisance.choose_transfer`, the one rule for it) is run on
  the busiest square of the window with the fitted depths, overlay and bias in its model:
  where blur and fill factor leave an instrument's residual (an odd edge profile shared by the
  masks), it fits the objective's NA-limited transfer, the batwing and both, with a continuous
  fill factor, and keeps what earns its parameters. A coherence-scanning interferometer's file
  needs it: under a Gaussian blur with whole pixels its objective's long spread left 7 nm in
  the flat interiors against 0.67 nm of noise. The stage's fits are short ones on a square
  of the window: the members it chose are refitted on the whole window (the depths free),
  from its values and from a narrow batwing (``NARROW_BATWING``; from the stage's alone, a
  0.13 batwing at 0.2 um was fitted as -0.012 at 1.1 um beside NA 0.83 for 0.47), each to the
  criterion's tolerances, the better then to convergence (a calibration's tolerances: the
  same optimum as both starts fitted to convergence, at about half the refit's time), and the
  result is held in a last camera-frame fit of the depths, overlay, bias and placement.

A calibrated transfer (``--instrument``) is held as it is and none of this runs.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import Any

import numpy as np

from doedesign.errors import DoeError
from metrology.matching.instrument import Placement
from metrology.matching.instrument_fit import InstrumentFit

__all__ = ["FILL_THRESHOLD", "fit_instrument_family"]

log = logging.getLogger(__name__)

# Criterion drop (effective samples x log RSS ratio) the point-sampling camera must earn over
# whole pixels: the diagnosis's threshold for a parameter's worth of evidence.
FILL_THRESHOLD = 10.0
# A second start of the batwing (amplitude, sigma_m) in the last refit of the chosen members.
NARROW_BATWING = (0.1, 0.25e-6)


def _common_rss(a: InstrumentFit, b: InstrumentFit) -> tuple[float, float, int]:
    """Both fits' residual sums of squares over the pixels both kept (the robust rule may
    exclude a few others in one), and how many."""
    both = np.isfinite(a.residual_m) & np.isfinite(b.residual_m)
    return float(np.sum(a.residual_m[both] ** 2)), float(np.sum(b.residual_m[both] ** 2)), int(both.sum())


def _window_problem(fit: InstrumentFit, height_m: np.ndarray, levels: np.ndarray, pitch_m: float):
    """The diagnosis's camera problem on ``fit``'s window, its process the fitted depths,
    overlay and bias, and a factory ``make(objective, batwing)`` of the stage's problems."""
    from masks.process import ProcessParams
    from metrology.diagnosis.camera import CameraHeightProblem
    from metrology.diagnosis.camera_nuisance import CAMERA, STAGE_WINDOW_PX
    from metrology.diagnosis.effects import get_effect
    from metrology.matching.forward import fitted_process
    from metrology.matching.level import robust_valid

    r0, r1, c0, c1 = fit.window_camera_px
    crop = np.asarray(height_m, float)[r0:r1, c0:c1]
    field = fit.placement
    start = Placement(field.matrix, field.offset + field.matrix @ np.array([r0, c0], float))
    n_masks = fit.depths_m.size
    base: ProcessParams = fitted_process(fit, n_masks=n_masks)
    first = CameraHeightProblem(levels, pitch_m, crop, start, base, [], transfer=fit.transfer)
    keep = robust_valid(first.residual_map({CAMERA.name: np.zeros(5)}), np.isfinite(crop))
    depth = get_effect("etch_depth").for_masks(n_masks)
    assert depth is not None  # every mask has a depth
    size = crop.shape[0]

    def make(objective: bool = False, batwing: bool = False, whole: bool = False):
        problem = CameraHeightProblem(levels, pitch_m, crop, start, base, [depth], keep=keep, noise=first.noise,
                                      instrument=first.instrument, objective=objective, batwing=batwing)
        return problem.crop(STAGE_WINDOW_PX) if size > STAGE_WINDOW_PX and not whole else problem

    return first, make


def fit_instrument_family(fit: Callable[..., InstrumentFit], height_m: np.ndarray, levels: np.ndarray,
                          pitch_m: float, pixel_m: float, threshold: float = FILL_THRESHOLD,
                          ) -> tuple[InstrumentFit, dict[str, Any]]:
    """The camera-frame fit through the member of the lateral transfer's family the data ask for.

    Parameters
    ----------
    fit : callable
        ``fit(fill=..., blur0_m=..., start=InstrumentFit or None, transfer=..., batwing=...)``:
        the camera-frame fit of the comparison on its window (the same placement and window for
        every call), started from ``start``'s depths, overlay and bias when given.
    height_m : ndarray
        The levelled camera heights.
    levels : ndarray of int
        Design levels.
    pitch_m, pixel_m : float
        Design pitch and camera pixel.
    threshold : float
        Criterion drop that point samples (and the stage's objective or batwing) must earn.

    Returns
    -------
    (InstrumentFit, dict)
        The fit reported, and what chose it (each family's criterion, the stage's members and
        their criterion changes).
    """
    from metrology.diagnosis import engine as dg
    from metrology.diagnosis.camera_nuisance import BATWING, choose_transfer
    from metrology.diagnosis.parallel import fit_workers, parallel_map

    whole = fit(fill=1.0, start=None)
    # Point samples start from the blur of the same second moment (the box's variance added).
    blur0 = float(np.sqrt(whole.blur_sigma_m ** 2 + pixel_m ** 2 / 12.0))
    point = fit(fill=0.0, blur0_m=blur0, start=whole)
    rss_whole, rss_point, n = _common_rss(whole, point)
    try:
        first, make = _window_problem(whole, height_m, levels, pitch_m)
        corr_area, skipped = first.noise.corr_area_px, None
    except DoeError as exc:
        # No noise floor on the window (too few flat pixels): the pixels counted as independent,
        # and no instrument stage (its criteria need the floor).
        corr_area, skipped = 1.0, str(exc)
    n_eff = max(n / corr_area, 2.0)
    change = float(n_eff * np.log(max(rss_point, 1e-300) / max(rss_whole, 1e-300)))
    chosen = point if change < -threshold else whole
    report: dict[str, Any] = {
        "fill_factor_choice": {"whole_pixels_rms_nm": float(np.sqrt(rss_whole / n) * 1e9),
                               "point_samples_rms_nm": float(np.sqrt(rss_point / n) * 1e9),
                               "whole_pixels_blur_um": whole.blur_sigma_m * 1e6,
                               "point_samples_blur_um": point.blur_sigma_m * 1e6,
                               "criterion_change_point_samples": change, "threshold": threshold,
                               "effective_samples": n_eff, "chosen_fill_factor": chosen.transfer.fill_factor},
        "rule": ("fill factor 1 (whole pixels) and 0 (point samples) fitted, each with its blur; point samples kept "
                 "where they lower n_eff ln(RSS/N) by more than the threshold. Then the diagnosis's instrument stage "
                 "(choose_transfer) on the window with the fitted process: an objective (NA) and a batwing, with a "
                 "fitted fill factor, where they earn their parameters; those refitted to convergence on the window and "
                 "held in the last fit")}
    if skipped is None:
        try:
            if chosen is not whole:
                first, make = _window_problem(chosen, height_m, levels, pitch_m)
                first.noise  # noqa: B018 (estimated here, where a window without flat pixels says so)
            members, model, changes = choose_transfer(make, threshold)
        except DoeError as exc:
            skipped = str(exc)
    if skipped is not None:
        log.info("compare: no instrument stage: %s", skipped)
        report["stage"] = {"members": [], "skipped": skipped}
        return chosen, report
    report["stage"] = {"members": [k for k, v in members.items() if v], "criterion_changes": changes}
    if not any(members.values()):
        return chosen, report
    # The stage's fits are short ones on its square: the members it chose are fitted to
    # convergence on the whole window (the fitted process's depths free), as the diagnosis
    # refits them from what the stage returns.
    problem = make(**members, whole=True)
    free = [*problem.nuisance, *(k for k in problem.effects if k not in problem.nuisance)]
    start = {k: np.asarray(model.get(k, problem.effects[k].start_values()), float) for k in free}
    starts = [start]
    if BATWING in start:
        # A coherence-scanning instrument's overshoot is a fraction of a micrometre wide: the
        # stage's short fits from its 0.6 um start can end on a wide, weak batwing that trades
        # with the objective (NA 0.83 for 0.47, -0.012 at 1.1 um for 0.13 at 0.2 um).
        starts.append({**start, BATWING: np.array(NARROW_BATWING)})
    best = None
    # Each start to the criterion's tolerances (a third of a precise fit's evaluations): enough
    # to tell which optimum it reaches (rss 5.4e-14 against 2.6e-14 on a CSI null). The starts
    # are fitted side by side (each fit alone: the same results in one thread or two).
    fits = parallel_map(lambda s: dg.fit_effects(problem, s, free), starts, fit_workers(problem))
    for s, (fitted, rss, _) in zip(starts, fits):
        log.info("compare: instrument members refitted from %s: rss %.4g", {k: np.round(v, 9).tolist() for k, v in s.items()
                                                                            if k != "camera"}, rss)
        if best is None or rss < best[1]:
            best = (fitted, rss)
    assert best is not None  # starts holds the start
    # The best to a calibration's tolerances (``precise``): the diagnosis starts from this fit's
    # placement and process, and to the criterion's tolerances alone a CSI bias case's diagnosis
    # ended on a wide, weak batwing with a false 0.37 % etch depth (1.14x the floor, against the
    # bias alone at 1.00x).
    model, rss, _ = dg.fit_effects(problem, best[0], free, precise=True)
    log.info("compare: instrument members refitted to a calibration's tolerances: rss %.4g", rss)
    transfer = problem.transfer_of(model)
    batwing = tuple(float(v) for v in model[BATWING]) if BATWING in model else None
    log.info("compare: the instrument stage chose %s (NA %.3f, fill %.2f, blur %.3f um)",
             report["stage"]["members"], transfer.na, transfer.fill_factor, transfer.sigma_m * 1e6)
    return fit(start=chosen, transfer=transfer, batwing=batwing), report
