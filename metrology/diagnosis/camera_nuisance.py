"""The instrument's nuisances in the camera frame: the placement, the lateral transfer's family
and the stage that chooses its members before any fabrication effect.

:data:`CAMERA` (placement, Gaussian blur, pixel fill factor) is always fitted; the objective's
NA-limited transfer (:data:`OBJECTIVE`) and the batwing join it when the data ask for them
(:func:`choose_transfer`); with a calibrated transfer only the placement is fitted
(:data:`PLACED`). The family and its conventions: :mod:`metrology.matching.transfer`.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from metrology.diagnosis import engine as dg
from metrology.diagnosis.effects import Effect, Parameter, get_effect
from metrology.diagnosis.parallel import fit_workers, parallel_map
from metrology.diagnosis.tiles import TiledCameraProblem
from metrology.matching.instrument import MAX_BLUR_M, PLACEMENT_PARAMS
from metrology.matching.transfer import NA_BOUNDS, LateralTransfer

if TYPE_CHECKING:
    from metrology.diagnosis.camera import CameraHeightProblem

__all__ = ["BATWING", "CAMERA", "DEFAULT_TRANSFER", "InstrumentFamily", "MEMBERS", "NESTING", "OBJECTIVE", "PLACED", "RESTAGE_WINDOW_PX",
           "STAGE_FREE", "STAGE_WINDOW_PX",
           "choose_transfer", "earned_members", "instrument_report", "member_params", "member_starts",
           "objective_starts", "placement_report"]

log = logging.getLogger(__name__)

_UM = 1e-6
# The instrument stage (:func:`choose_transfer`) fits on the busiest square of at most this many
# camera pixels per side.
STAGE_WINDOW_PX = 96
# The stage run again with named fabrication effects held (:func:`choose_transfer`'s ``held``)
# fits on a smaller square: with the effect's own residual gone, the instrument's edge profile
# earns hundreds there (a CSI with an overlay held: objective and batwing -578 on 64 px, -1346 on
# 96), and at 96 px its eleven short fits cost 39 CPU s, more than the budget left after the first
# pass could pay for a restart (19 s on 64 px). On 48 px (13 s) a 0.06 batwing beside the
# objective no longer earned, and a false etch loading paid for it.
RESTAGE_WINDOW_PX = 64
# Odd share of the shared edge profile (:func:`~metrology.diagnosis.breakdown.instrument_signature`)
# the blur and fill factor must leave for the stage to try the objective and the batwing.
STAGE_ODD_SHARE = 0.5
# Range of each mask's amplitude of that profile the stage accepts: wider than the final rule's
# full amplitude, since the blur and fill factor were just fitted mostly to the deepest mask's
# edges, and the shallow masks' shares of what they leave scatter (a CSI-like null: 2.1, 0.35,
# 0.93, 0.86). The stage only offers the members; the information criterion keeps them or not.
STAGE_AMPLITUDES = (0.25, 4.0)
# Share of the edge residual that profile must hold for the stage: less than the final rule's,
# since a fabrication effect of one mask (an overlay of 0.3 um) may hold most of what the blur
# and fill factor leave while the instrument's shared part stays significant beside it.
STAGE_SHARE = 0.3
# The batwing: a candidate, or a nuisance of the instrument once the instrument stage chose it.
BATWING = "batwing"
#: The combinations of the family's members beyond blur and fill factor that are tried.
MEMBERS = (("objective",), ("batwing",), ("objective", "batwing"))
#: Fabrication effects freed, once the stage has fitted its combinations, in a second short fit
#: of each from its optimum, whose criteria then choose (never named by it, left out of what it
#: returns): an objective's transfer lowers the steps of fine features, which an etch depth that
#: is not the design's can pay for. On a boxcar instrument's file with etch loading and a
#: gradient, objective and batwing earned 4283 on an instrument that has neither, and the
#: selection ended at 4.2x the floor. Freed in the first fits instead, the depths slowed the
#: short fits into a wrong optimum (a CSI null: fill factor 0 against 0.96, a false loading).
STAGE_FREE = ("etch_depth",)
# Members that can act as nothing (the batwing at zero amplitude; the objective cannot: its
# widest aperture still lowers the transfer at mid frequencies).
NESTING = ("batwing",)



def _no_op(*args):
    return args[0]


#: The camera placement and the instrument's lateral transfer (Gaussian blur, pixel fill
#: factor: :mod:`metrology.matching.transfer`): always fitted, never named.
CAMERA = Effect(
    "camera", "height", "surface",
    [Parameter("shift_row_px", "design px", -1.0, 1.0, 0.01), Parameter("shift_col_px", "design px", -1.0, 1.0, 0.01),
     Parameter("rotation_rad", "rad", -0.01, 0.01, 2e-5), Parameter("scale_row", "1", -0.03, 0.03, 2e-4),
     Parameter("scale_col", "1", -0.03, 0.03, 2e-4),
     Parameter("blur_sigma_m", "m", 0.0, MAX_BLUR_M, 0.05 * _UM, 0.4 * _UM, smooth=True),
     Parameter("fill_factor", "1", 0.0, 1.0, 0.05, 1.0, smooth=True)],
    _no_op, "Placement of the camera field on the design and the instrument's lateral transfer (nuisance).",
    kind="artefact", order=-1)
#: The objective's NA-limited optical transfer: a nuisance of the instrument when the data ask
#: for it (chosen before any fabrication effect, ``instrument_stage``), never named.
OBJECTIVE = Effect(
    "objective", "height", "surface",
    [Parameter("na", "1", NA_BOUNDS[0], NA_BOUNDS[1], 0.02, 0.4, smooth=True)],
    _no_op, "The objective's NA-limited optical transfer, cut-off 2 NA / lambda (nuisance).",
    kind="artefact", order=-1)
#: The placement alone: the camera nuisance of an instrument whose transfer a calibration holds.
PLACED = Effect("camera", "height", "surface", CAMERA.params[:5], _no_op,
                "Placement of the camera field on the design (nuisance; the lateral transfer calibrated).",
                kind="artefact", order=-1)
#: The lateral transfer's parameters a model does not hold (full pixels, no optical cut-off).
DEFAULT_TRANSFER = LateralTransfer(sigma_m=0.4 * _UM, fill_factor=1.0, na=0.0)

def instrument_report(t: LateralTransfer, sigma_err_m: float = np.nan, fill_err: float = np.nan,
                      na_err: float = np.nan, calibrated: bool = False) -> dict[str, Any]:
    """The lateral transfer as a report gives it (and a calibration file holds it): SI units,
    uncertainties NaN where a parameter was held."""
    return {"model": "pixel box (fill factor: area fraction, a centred square of side sqrt(fill) pixels) "
                     "* Gaussian blur * (NA-limited incoherent objective (cut-off 2 NA / lambda; na 0 = none) "
                     "+ batwing band-pass, when fitted)",
            "blur_sigma_m": t.sigma_m, "blur_sigma_uncertainty_m": float(sigma_err_m),
            "fill_factor": t.fill_factor, "fill_factor_uncertainty": float(fill_err),
            "na": t.na, "na_uncertainty": float(na_err), "wavelength_m": t.wavelength_m,
            "source": "calibration (held fixed)" if calibrated else "fitted with the placement"}


@dataclass(frozen=True)
class InstrumentFamily:
    """The lateral transfer's family members an instrument stage chose and their fitted values
    (``doe compare``'s stage, refitted to convergence on its window,
    :func:`metrology.matching.instrument_family.fit_instrument_family`).

    Attributes
    ----------
    transfer : LateralTransfer
        Blur, fill factor and the objective's NA (0: no objective chosen).
    batwing : (float, float) or None
        The batwing (amplitude, sigma_m), where chosen.
    criterion_changes : dict
        The stage's criterion change of each combination it tried (``"objective"``, ...).
    """

    transfer: LateralTransfer
    batwing: Sequence[float] | None = None
    criterion_changes: dict[str, float] = field(default_factory=dict)

    def chosen(self) -> dict[str, bool]:
        """The ``objective`` and ``batwing`` flags of a camera problem (:func:`choose_transfer`'s)."""
        return {"objective": self.transfer.na > 0, "batwing": self.batwing is not None}

    def start(self) -> dict[str, np.ndarray]:
        """The nuisances' values at the start placement: what :func:`choose_transfer` returns."""
        t = self.transfer
        # No refinement of the placement: the diagnosis's start placement is the comparison's.
        model = {CAMERA.name: np.array([*np.zeros(len(PLACEMENT_PARAMS)), t.sigma_m, t.fill_factor])}
        if t.na > 0:
            model[OBJECTIVE.name] = np.array([t.na])
        if self.batwing is not None:
            model[BATWING] = np.array(self.batwing, float)
        return model


def objective_starts(model: dict[str, np.ndarray], transfer: LateralTransfer) -> list[dict[str, np.ndarray]]:
    """Starts of a fit with the objective's NA from a fit without it (``model``, whose lateral
    transfer is ``transfer``): the same blur and fill factor under the widest aperture (the
    model barely changed, so the fit can only improve on it), and an aperture whose transfer
    halves where the fitted blur's does (chinese hat at s = 0.404, Gaussian at 0.187 / sigma)
    with most of the blur handed to it."""
    cam = np.array(model[CAMERA.name], float)
    wide = {**model, OBJECTIVE.name: np.array([NA_BOUNDS[1]])}
    na0 = 0.187 * transfer.wavelength_m / (2 * 0.404 * max(transfer.sigma_m, 0.05 * _UM))
    narrow_cam = cam.copy()
    narrow_cam[5] *= 0.3
    narrow = {**model, CAMERA.name: narrow_cam, OBJECTIVE.name: np.clip([na0], *NA_BOUNDS)}
    return [wide, narrow]


def choose_transfer(make: Callable[..., CameraHeightProblem | TiledCameraProblem], threshold: float,
                    held: dict[str, np.ndarray] | None = None,
                    ) -> tuple[dict[str, bool], dict[str, np.ndarray], dict[str, float]]:
    """The instrument's family members beyond blur and fill factor that the data ask for, chosen
    before any fabrication effect: the nuisances (placement, blur, fill factor) are fitted alone;
    when they leave an instrument's residual (an odd edge profile shared by every mask), the
    objective's NA, the batwing and both together are fitted, and the combination with the
    lowest information criterion is kept when it lowers it by more than ``threshold`` (both
    only when they beat each alone by as much). Where one earns, every combination and the
    blur and fill factor alone are fitted again with the effects of :data:`STAGE_FREE` free
    (a combination then left above one it nests fitted once more from that one's optimum:
    ``_refit_nested``), and those criteria choose (the effects left out of what this returns). Short fits with
    forward differences: the diagnosis refits the nuisances to convergence from what this
    returns.

    Parameters
    ----------
    make : callable
        ``make(objective=bool, batwing=bool) -> Problem``.
    threshold : float
    held : dict, optional
        Fabrication effects a first selection named (name -> values): in every model of the
        stage and refitted with the nuisances (its ``camera`` entry, if any, starts the
        placement and transfer). A large fabrication effect (a 0.4 um bias, an
        overlay of one mask) hides the instrument's own edge profile from a stage that runs
        before any; with it in the model, the profile shows.

    Returns
    -------
    (dict, dict, dict)
        The chosen ``objective`` and ``batwing`` flags, the nuisances' fitted values (the
        diagnosis's start) and each tried combination's criterion change (``"objective"``,
        ``"batwing"``, ``"objective+batwing"``).
    """
    state = {"objective": False, "batwing": False}
    named = bool(held)
    held = dict(held or {})
    camera = held.pop(CAMERA.name, CAMERA.start_values())
    plain = make(**state)
    problems = {(): plain}

    def problem_of(members):
        # One problem per combination, shared by its first fits, the nested refit and the second look.
        if members not in problems:
            problems[members] = make(**{k: k in members for k in state})
        return problems[members]

    model, rss, _ = dg.fit_effects(plain, {CAMERA.name: camera, **held}, [CAMERA.name, *held], max_iter=12,
                                   central=False)
    n = plain.residual(model).size
    n_eff = max(n / plain.noise.corr_area_px, 2.0)

    def crit(problem, rss):
        return dg.bic_eff(rss, n, n_eff, sum(e.n_params for e in problem.nuisance.values()))  # held: in all alike

    current = crit(plain, rss)
    # Only an instrument's residual (an odd profile shared by every mask's edges) asks for more of
    # the family: elsewhere the stage costs one short fit. With named effects held, the members
    # are always tried (once per diagnosis): what a large effect's fit leaves on the edges mixes
    # with the instrument's profile (an overlay's fit under the wrong transfer), and the
    # criterion, not the profile's shape, decides.
    left = None if named else plain.instrument_signature(
        plain.residual_map(model), share=STAGE_SHARE, amplitudes=STAGE_AMPLITUDES, every_mask=False)
    if not named and (left is None or left["odd_share"] < STAGE_ODD_SHARE):
        log.info("instrument stage: blur and fill factor leave no instrument residual")
        return dict(state), model, {}
    transfer = (plain.whole if isinstance(plain, TiledCameraProblem) else plain).transfer_of(model)
    # Every combination is fitted from the blur-and-fill fit: the objective's NA and the batwing
    # trade against each other (a CSI's batwing sits beside its objective's transfer), so the
    # objective alone runs to the widest aperture where both together find the real one. The
    # larger combinations first: one nests another when the members it adds can act as nothing
    # (:data:`NESTING`: the batwing at zero amplitude; no aperture is no objective), and then
    # (up to the short fits' convergence) its RSS is at most the other's. A nested combination
    # whose criterion, bounded so from a fitted one, cannot beat the blur and fill factor alone
    # by the threshold is not fitted: a third of the stage where the family adds nothing.
    fits: dict[tuple[str, ...], tuple[float, dict[str, np.ndarray]]] = {}
    def short(task):
        problem, start, names = task
        fitted, rss, _ = dg.fit_effects(problem, start, names, max_iter=12, central=False)
        return crit(problem, rss), fitted

    for wave in _waves(sorted(MEMBERS, key=len, reverse=True)):
        tasks = []
        for members in wave:
            bounds = [fits[m][0] - (member_params(m) - member_params(members)) * np.log(n_eff) for m in fits
                      if _nests(m, members)]
            if bounds and max(bounds) >= current - threshold:
                continue
            problem = problem_of(members)
            tasks += [(members, (problem, start, [*problem.nuisance, *held]))
                      for start in member_starts(members, model, transfer)]
        for (members, _), (c, fitted) in zip(tasks, _fit_all(plain, [t for _, t in tasks], short)):
            if members not in fits or c < fits[members][0]:
                fits[members] = (c, fitted)
    # A combination that nests a fitted one is fitted again from the nested one's optimum, the
    # members it adds at their start values: its short fits from the blur-and-fill start can
    # end in another optimum (a CSI's objective and batwing: NA 0.51 against 0.36, -947 against
    # the objective alone's -1132, and a false etch loading paid for the difference).
    _refit_nested(fits, problem_of, short, list(held))
    free = [k for k in STAGE_FREE if k not in held and k in getattr(plain, "effects", {})]
    if free and earned_members({m: c for m, (c, _) in fits.items()}, current, threshold):
        log.info("instrument stage before %s were freed: %s", free,
                 {"+".join(m): round(c - current, 1) for m, (c, _) in fits.items()})
        extra = {k: plain.effects[k].start_values() for k in free}
        names = [*held, *free]
        refits = [(plain, {**model, **extra}, [CAMERA.name, *names])]
        refits += [(problem_of(m), {**fitted, **extra}, [*problem_of(m).nuisance, *names]) for m, (_, fitted) in fits.items()]
        (current, model), *again = _fit_all(plain, refits, short)
        fits = dict(zip(fits, again))
        # The refits are short too: one that ends above a combination it nests has not reached its
        # optimum (a CSI null's objective and batwing -3371 against the objective alone's -3388,
        # for a 0.105 batwing at 0.21 um), and is fitted again from the nested one's.
        _refit_nested(fits, problem_of, short, names, above_only=True)
    changes = {"+".join(m): c - current for m, (c, _) in fits.items()}
    chosen = earned_members({m: c for m, (c, _) in fits.items()}, current, threshold)
    if chosen:
        model = fits[chosen][1]
        state = {k: k in chosen for k in state}
    log.info("instrument stage: %s (criterion changes %s)", state, {k: round(v, 1) for k, v in changes.items()})
    return state, _without(model, free), {k: float(v) for k, v in changes.items()}


def _refit_nested(fits: dict[tuple[str, ...], tuple[float, dict[str, np.ndarray]]], problem_of: Callable[[Any], Any],
                  short: Callable[[Any], Any], names: list[str], above_only: bool = False) -> None:
    """Each combination of ``fits`` (members -> (criterion, model), updated in place) that nests
    another fitted again, ``names`` free with its nuisances, from the best nested one's optimum
    with the members it adds at their start values (the batwing, the one member that nests);
    kept where its criterion is lower. ``above_only``: only a combination whose criterion lies
    above a nested one's (a short fit that stopped short of its optimum, which bounds the
    nested one's)."""
    for members in [m for m in fits if len(m) > 1]:
        inner = [m for m in fits if _nests(members, m)]
        if not inner:
            continue
        best = min(inner, key=lambda m: fits[m][0])
        if above_only and fits[members][0] <= fits[best][0]:
            continue
        problem = problem_of(members)
        start = {**fits[best][1], BATWING: get_effect(BATWING).start_values()}
        c, fitted = short((problem, start, [*problem.nuisance, *names]))
        if c < fits[members][0]:
            fits[members] = (c, fitted)


def _nests(outer: tuple[str, ...], inner: tuple[str, ...]) -> bool:
    """Whether the combination ``outer`` holds ``inner`` as a special case: it adds only members
    that can act as nothing (:data:`NESTING`), so its fit bounds ``inner``'s criterion."""
    return set(inner) < set(outer) and set(outer) - set(inner) <= set(NESTING)


def _waves(ordered: list[tuple[str, ...]]) -> list[list[tuple[str, ...]]]:
    """``ordered`` (larger combinations first) in waves whose members' fits are independent:
    each after every combination that nests it, whose fit may bound it out."""
    waves: list[list[tuple[str, ...]]] = []
    for members in ordered:
        after = max((i for i, wave in enumerate(waves) for m in wave if _nests(m, members)), default=-1)
        if after + 1 == len(waves):
            waves.append([])
        waves[after + 1].append(members)
    return waves


def _fit_all(plain: Any, tasks: list[Any], short: Callable[[Any], Any]) -> list[Any]:
    """``short(task)`` of every task in its order: side by side where the problem's fits are
    thread-safe (:func:`~metrology.diagnosis.parallel.parallel_map`), each then with its
    Jacobian's columns in its own thread. The stage's short fits are independent of each other
    within a wave, and their results do not depend on the threads (each fit is computed alone):
    on a CSI file the Jacobians' two threads kept 1.35 cores busy, the fits' serial steps the rest."""
    return list(parallel_map(short, tasks, fit_workers(plain)))


def _without(model: dict[str, np.ndarray], names: list[str]) -> dict[str, np.ndarray]:
    return {k: v for k, v in model.items() if k not in names}


def member_starts(members: tuple[str, ...], model: dict[str, np.ndarray],
                  transfer: LateralTransfer) -> list[dict[str, np.ndarray]]:
    """Starts of a fit with the family's ``members`` (of :data:`MEMBERS`) from a fit of the blur
    and fill factor alone (``model``, whose lateral transfer is ``transfer``): the objective's
    two (:func:`objective_starts`), the batwing at its start values."""
    starts = objective_starts(model, transfer) if "objective" in members else [model]
    if "batwing" in members:
        starts = [{**start, BATWING: get_effect(BATWING).start_values()} for start in starts]
    return starts


def member_params(members: tuple[str, ...]) -> int:
    """Parameters the family's ``members`` add to the blur and fill factor."""
    return sum((OBJECTIVE if m == "objective" else get_effect(BATWING)).n_params for m in members)


def earned_members(criteria: dict[tuple[str, ...], float], current: float, threshold: float) -> tuple[str, ...]:
    """The members of the lateral transfer's family that earn their parameters: of the tried
    combinations (``criteria``: members -> information criterion), the best that lowers the
    criterion of the blur and fill factor alone (``current``) by more than ``threshold``, and
    that of each of its single members by as much; ``()`` when none does."""
    for members, c in sorted(criteria.items(), key=lambda kv: kv[1]):
        if c >= current - threshold:
            break
        # A member not tried alone could not have earned alone (:func:`choose_transfer`).
        if len(members) == 1 or all(c < criteria.get((m,), current) - threshold for m in members):
            return members
    return ()


def placement_report(problem: Any, model: dict[str, np.ndarray],
                     errors: dict[str, np.ndarray] | None = None) -> dict[str, Any]:
    """The refined placement and the lateral transfer of a camera problem's ``model``, with
    uncertainties (camera pixels, degrees; NaN for a parameter held fixed)."""
    cam = np.asarray(model[CAMERA.name], float)
    errors = errors or {}
    err = np.full(7, np.nan)
    given = np.asarray(errors.get(CAMERA.name, ()), float)
    err[:given.size] = given
    na_err = float(np.asarray(errors.get(OBJECTIVE.name, [np.nan]), float)[0])
    t = problem.transfer_of(model)
    px_per_design = problem.pitch_m / problem.pixel_m
    final = problem.placement.refined(cam[:5], problem.measured.shape, problem.centre_px)
    batwing = model.get(BATWING, getattr(problem, "held", {}).get(BATWING))
    instrument = instrument_report(t, err[5], err[6], na_err if OBJECTIVE.name in model else np.nan,
                                   calibrated=problem.fixed_transfer is not None)
    # Fitted with the placement, or held by a calibration; None where the family left it out.
    instrument["batwing"] = None if batwing is None else np.asarray(batwing, float).tolist()
    return {"refinement": {name: float(v) for name, v in zip(PLACEMENT_PARAMS, cam[:5])},
            "shift_uncertainty_camera_px": [float(e * px_per_design) for e in err[:2]],
            "rotation_uncertainty_deg": float(np.degrees(err[2])),
            "scale_uncertainty": [float(e) for e in err[3:5]],
            "blur_sigma_um": t.sigma_m * 1e6, "blur_sigma_uncertainty_um": float(err[5] * 1e6),
            "instrument": instrument,
            "matrix": final.matrix.tolist(), "offset": final.offset.tolist(),
            "convention": "camera pixel centre (row, col) -> design pixel [R, C] = matrix @ [row, col] + offset"}
