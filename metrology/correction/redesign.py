"""Re-design for the fitted process (``doe correct --redesign``): what the masks cannot fix.

The plain correction turns the fab's knobs (etch targets, aligner, drawn edges) against the
systematic errors. The re-design instead keeps the process as it was measured (or as the job
sheet leaves it) and changes the element: the design loop
(:func:`doedesign.optimizer.optimize.design_doe`) runs with the fitted process as its nominal
process, so that the new levels, made with that process, give the best merit. A systematic etch-depth error on one mask changes the height of every level that uses
that mask; the re-design absorbs it by choosing, per pixel, the level whose *actual* height
gives the wanted phase, and by re-optimizing the heights against the element's target.

How:

- the process: the measured wafer of :func:`metrology.correction.merit.params_for_wafer` (every
  combined parameter at its mean; with a job sheet, ``--redesign-for corrected``, the corrected
  wafer: what the knobs leave), as a smooth process sample on continuous heights
  (:class:`masks.tolerance.smooth.SmoothProcess`: etch depth, etch gradient, linewidth bias,
  overlay and rotation; loading, blur, sidewalls and trenches act in the merit only). With
  ``robust_samples`` > 0, draws of the measured spreads are added and the loop minimizes the mean
  loss over all of them; they are draws ``samples .. samples + robust_samples - 1`` of the merit's
  seed, so out of the merit's own sample;
- the start: the design's levels remapped, level ``k`` -> the level whose height under the
  fitted etch depths is nearest to level ``k``'s nominal height modulo the 2 pi height at the
  design wavelength (the identity for an ideal process), then the loop's continuous stage and
  its annealing back to the levels, short (``iterations``), as the start is already close. The
  loop's quantized result is kept only where its loss (under the fitted process) is no higher
  than the start's; pixels the coded view does not see keep their levels;
- the target: the design's own built-in target (:func:`masks.tolerance.metrics.design_target`),
  else the light of its ideal element on the pixels its merit scores; the loss is the kind's
  default where it has one (Bayer: the design's own objective, the soft minimum of the colours;
  spots: L1 and energy, for their balance too; depth rings: L1), else the light missing from the
  target pixels (the merit itself);
- the merit: the re-designed levels in the design's own evaluator (the same target pixels and
  metrics) under the same process and Monte Carlo draws as the wafer it stands beside
  (:func:`metrology.correction.merit.wafer_merit`).
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from doedesign.design import Design
from doedesign.errors import DoeError
from doedesign.levels import design_levels
from doedesign.progress import Progress

from .jobsheet import check_offsets
from .merit import change_percent, merit_evaluator, params_for_wafer, wafer_merit
from .systematic import Estimate

if TYPE_CHECKING:
    from doedesign.optimizer.losses import LossSpec
    from doedesign.targets import Target
    from masks.tolerance.evaluate import Evaluator

__all__ = ["DEFAULT_ITERATIONS", "redesign", "redesign_target", "remap_levels", "write_redesign"]

log = logging.getLogger(__name__)

#: Evaluations of the continuous stage; the annealing gets a quarter of it per stage.
DEFAULT_ITERATIONS = 20


def remap_levels(levels: np.ndarray, actual_depths_m: np.ndarray, step_m: float,
                 n_levels: int) -> tuple[np.ndarray, list]:
    """Each level -> the level whose actual depth is nearest its nominal depth, modulo ``n_levels`` steps.

    Parameters
    ----------
    levels : ndarray of int
    actual_depths_m : ndarray
        Depth of each level as etched (``n_levels`` values, m).
    step_m : float
        Nominal level step; level ``k`` should be ``k step`` deep, and ``n_levels`` steps are
        one 2 pi height at the design wavelength (the same phase).

    Returns
    -------
    levels : ndarray of int16, the remapped levels
    table : list of int, the level each level became
    """
    period = n_levels * step_m
    wanted = np.arange(n_levels) * step_m
    miss = actual_depths_m[None, :] - wanted[:, None]
    miss = (miss + period / 2) % period - period / 2
    table = np.argmin(np.abs(miss), axis=1)
    return table[np.asarray(levels)].astype(np.int16), [int(v) for v in table]


def redesign_target(design: Design, ev: Evaluator) -> tuple[Target, LossSpec]:
    """The target the re-design optimizes, and its loss (see the module docstring).

    The design's built-in target (:func:`masks.tolerance.metrics.design_target`), else the light
    of its ideal element on the pixels the merit scores (``ev``'s target pixels, the brightest
    holding 90 % of the ideal PSF).
    """
    from doedesign import targets
    from doedesign.optimizer.losses import LossSpec
    from masks.tolerance.metrics import design_target

    camera = ev.camera
    target = design_target(design, camera, ev.wavelengths_m, ev.depths_m)
    if target is None:
        assert ev.metrics is not None  # build_evaluator sets it up
        psf = ev.coded_psf(ev.height({})) * ev.metrics.target_mask
        sums = psf.sum(axis=(-2, -1), keepdims=True)
        if not np.all(sums > 0):
            raise DoeError(f"{design.name}: its ideal element puts no light on its target pixels; nothing to "
                           "re-design toward")
        target = targets.Target(psf / sums, ev.wavelengths_m, ev.depths_m, axis_pixel=tuple(camera.axis_pixel),
                                name=f"{design.name} ideal PSF",
                                meta={"kind": "image", "source": "the design's ideal PSF on the merit's pixels"})
    kind = str(target.meta.get("kind", "image"))
    loss = LossSpec.parse(targets.DEFAULT_LOSS.get(kind, "l1" if kind == "depth" else "energy"))
    return target, loss


def _settings(design: Design, iterations: int, seed: int):
    """The design's own optimizer settings (its metadata), short, from a given start, on the CPU."""
    from doedesign.optimizer.optimize import OptimizerSettings

    stored = design.metadata.get("optimizer")
    saved = stored if isinstance(stored, dict) else {}
    names = {f.name for f in dataclasses.fields(OptimizerSettings)}
    keep = {k: v for k, v in saved.items() if k in names and k not in ("starts", "device", "max_time_s")}
    keep.update(max_iter=int(iterations), anneal_iter=max(2, int(iterations) // 4), seed=int(seed), init="zeros",
                starts=(), start_iter=None, reweight_rounds=0, quantize=True, device="cpu")
    if keep.get("objective") == "maxmin":  # the max-min has no robust form; the soft minimum does
        keep["objective"] = "softmin"
    try:
        return OptimizerSettings(**keep)
    except (DoeError, TypeError) as exc:
        raise DoeError(f"{design.name}: its recorded optimizer settings cannot be reused for the re-design: "
                       f"{exc}") from None


def redesign(design: Design, estimates: Sequence[Estimate], nominal_depths_m: Sequence[float], *,
             iterations: int = DEFAULT_ITERATIONS, robust_samples: int = 0, samples: int = 12, seed: int = 0,
             source: str = "design", merit: dict | None = None, jobs: Sequence[dict] | None = None,
             min_feature_m: float | None = None) -> tuple[Design, dict]:
    """Re-design ``design`` for the fitted process and predict its merit (see the module docstring).

    Parameters
    ----------
    design : Design
    estimates : sequence of Estimate
        The combined diagnoses (:func:`metrology.correction.systematic.combine_fields`).
    nominal_depths_m : sequence of float
        The diagnosed nominal etch depths.
    iterations : int
        Evaluations of the design loop's continuous stage (the annealing adds five stages of a
        quarter of it each).
    robust_samples : int
        Draws of the measured spreads added to the central fitted process.
    samples, seed
        The merit's Monte Carlo draws and their seed (as for the other wafers).
    merit : dict, optional
        :func:`metrology.correction.merit.predict_merit`'s result, for the change against the design.
    jobs : sequence of dict, optional
        The job sheet (:func:`metrology.correction.jobsheet.job_entries`): re-design for the
        corrected process instead (the knobs turned, what they leave), the new masks drawn with
        the sheet's edge offsets (checked against ``min_feature_m``).

    Returns
    -------
    design : Design, the re-designed element (its levels; metadata of the design plus ``redesign``)
    report : dict, strict-JSON ready: the process, the level remapping, the loop's figures and
        ``merit`` (``central``, ``samples``, ``draws``, ``parameters``, ``primary_change_percent``)
    """
    from doedesign.optimizer.optimize import coded_support, design_doe
    from masks.process import ProcessParams
    from masks.tolerance.metrics import DIRECTIONS
    from masks.tolerance.robust import SMOOTH_EFFECTS
    from masks.tolerance.smooth import SmoothProcess
    from masks.tolerance.spec import ToleranceSpec

    if int(iterations) < 1 or int(robust_samples) < 0:
        raise DoeError(f"re-design: iterations must be >= 1 and robust samples >= 0, got {iterations} and "
                       f"{robust_samples}")
    n_levels, n_masks = design.n_levels, design.n_masks
    if len(nominal_depths_m) != n_masks:
        raise DoeError(f"{source}: {len(nominal_depths_m)} diagnosed mask depths for a {n_levels}-level design")
    for_corrected = jobs is not None
    against = "corrected_wafer" if for_corrected else "measured_wafer"
    spec = ToleranceSpec(params=params_for_wafer(estimates, jobs or [], nominal_depths_m, corrected=for_corrected),
                         source=f"doe correct: {'corrected' if for_corrected else 'measured'} process (re-design)")
    base = ProcessParams.ideal(depths_m=nominal_depths_m)
    central = spec.params_for(spec.nominal_values(), base, seed=seed)
    step = design.level_step_m(n_levels)
    binary = np.array([step * 2 ** j for j in range(n_masks)])
    processes = [central]
    for k in range(int(robust_samples)):
        values, s = spec.draw(seed, samples + k)
        processes.append(spec.params_for(values, base, seed=s))
    perturbations = [SmoothProcess(p, binary, step, design.pitch_m, n_levels) for p in processes]
    not_modelled = sorted({p.effect for p in spec.params if p.effect not in SMOOTH_EFFECTS and (p.a or p.b)})
    if not_modelled:
        log.warning("re-design: %s act in the merit only (not modelled on the design loop's heights)",
                    ", ".join(not_modelled))
    # Level k as etched: the sum of the fitted depths of its mask bits.
    bits = (np.arange(n_levels)[:, None] >> np.arange(n_masks)) & 1
    actual = bits @ np.asarray(central.etch_depth, float)
    levels = design_levels(design, n_levels, source)
    start_levels, table = remap_levels(levels, actual, step, n_levels)
    ev = merit_evaluator(design, nominal_depths_m, source)
    target, loss = redesign_target(design, ev)
    settings = _settings(design, iterations, seed)
    kind = str(target.meta.get("kind", "image"))
    log.info("re-design of %s: %d process sample(s), %d iterations", source, len(perturbations), iterations)
    run = design_doe(target, ev.camera, design.pitch_m, design.shape, design.material, design.design_wavelength_m,
                     loss=loss, settings=settings, init_height_m=-start_levels * step, perturbations=perturbations)
    new = run.design
    assert new.levels is not None  # the loop quantizes (settings: quantize=True)
    history = run.report["loss_history"]
    start_loss = float(history["continuous"][0])
    final_loss = float(run.report["quantized"]["loss"])
    # The loop's quantized result against its start, both under the fitted process: keep the better.
    kept = "design loop" if final_loss <= start_loss else "remapped levels (the loop's result scored worse)"
    # Pixels the coded view does not see are left as they were (the loop holds them at 0).
    seen = coded_support(ev.camera, design.pitch_m, design.shape)
    new.levels = np.where(seen, new.levels if final_loss <= start_loss else start_levels, levels).astype(np.int16)
    new.height_m = -new.levels * step
    if jobs is not None:  # for_corrected
        _check_offsets(new, jobs, min_feature_m, source)
    name = f"{design.name}_redesign"
    new.metadata = {**design.metadata, "name": name, "optimizer": dataclasses.asdict(settings),
                    "redesign": {"of": source, "process": spec.describe()["parameters"],
                                 "robust_samples": int(robust_samples), "level_remap": table}}
    new.aperture = design.aperture if design.aperture is not None else new.aperture
    remapped_only = dataclasses.replace(ev, levels=np.where(seen, start_levels, levels).astype(np.int16))
    remapped_only.spec = spec
    remap_merit = remapped_only({"id": "remap", "values": spec.nominal_values(), "seed": seed})["metrics"]
    ev = dataclasses.replace(ev, levels=np.asarray(new.levels, np.int16))
    with Progress(samples + 1, desc="doe correct: re-design merit") as bar:
        wafer = wafer_merit(ev, spec, samples, seed, "redesigned_wafer", bar)
    assert ev.metrics is not None  # build_evaluator sets it up
    primary = ev.metrics.primary
    notes = []
    if merit is not None:
        lower = DIRECTIONS.get(primary) == "lower"
        wafer["primary_change_percent"] = change_percent(wafer["central"][primary],
                                                         merit["design"]["central"][primary], lower)
        if wafer["primary_change_percent"] <= merit[against]["primary_change_percent"]:
            theirs = merit[against]["central"]
            better = [f"{k} {v:.4g} against {theirs[k]:.4g}" for k, v in wafer["central"].items()
                      if k in theirs and (v < theirs[k] if DIRECTIONS.get(k) == "lower" else v > theirs[k])]
            notes.append(f"the re-design is predicted no better than the design made with the same process in "
                         f"{primary} ({wafer['central'][primary]:.4g} against {theirs[primary]:.4g})"
                         + (f", better in {'; '.join(better)} (the loop's objective is {settings.objective}"
                            f"{', ' + kind if settings.objective == 'loss' else ''})" if better else "")
                         + f": keep the design where {primary} is what counts, or re-design with more iterations")
    if not_modelled:
        notes.append(f"{', '.join(not_modelled)}: in the merit, not in the design loop (no smooth model)")
    report = {
        "of": source, "name": name, "process_of": "corrected_wafer" if for_corrected else "measured_wafer",
        "compare_with": against, "target": kind, "loss": dataclasses.asdict(loss),
        "iterations": int(iterations), "anneal_iterations_per_stage": settings.anneal_iter,
        "evaluations": run.report["evaluations"], "robust_samples": int(robust_samples),
        "process_samples": len(perturbations), "process": spec.describe()["parameters"],
        "not_modelled_in_the_loop": not_modelled,
        "level_depths_as_etched_nm": [float(v) * 1e9 for v in actual],
        "level_remap": table, "levels_changed_fraction": float(np.mean((new.levels != levels)[seen])),
        "levels_changed_from_remap_fraction": float(np.mean((new.levels != start_levels)[seen])),
        "loss_at_start": start_loss, "loss_final": min(final_loss, start_loss),
        "loss_of_the_loop": final_loss, "quantized_from": run.report.get("quantized_from"), "kept": kept,
        "remap_only_central": remap_merit, "notes": notes, "merit": wafer,
    }
    return new, report


def _check_offsets(new: Design, jobs: Sequence[dict], min_feature_m: float | None, source: str) -> None:
    """Refuse a re-design whose masks cannot be drawn with the job sheet's edge offsets."""
    from masks.decompose import levels_to_masks

    assert new.levels is not None  # a re-design is quantized
    masks = levels_to_masks(new.levels, len(jobs))
    check_offsets(masks, new.pitch_m, jobs, min_feature_m, f"{source}: the re-design")


def write_redesign(folder: str | Path, new: Design, report: dict, *, depths_m: Sequence[float],
                   layers: Sequence[int], mirrored: bool, jobs: Sequence[dict] | None = None) -> dict:
    """Write ``folder/design.npz``, ``folder/masks/`` (as ``doe masks``) and ``folder/redesign.json``;
    return the report without its merit (the job sheet has it beside the other wafers').

    The masks carry the diagnosed nominal etch depths. Re-designed for the process as measured
    (no knob turned) they are drawn as ``doe masks`` draws them; for the corrected process
    (``jobs``) with the job sheet's edge offsets, and the job sheet's etch targets and aligner
    settings apply to them as to the plain correction's.
    """
    from doedesign.fileio import write_json
    from masks.element import write_element

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    new.save(folder / "design.npz")
    if jobs is None:
        masks = write_element(new, folder / "masks", source=str(folder / "design.npz"), mirrored=mirrored,
                              depths_m=depths_m, layers=layers)
    else:
        from doedesign.fileio import output_run
        from masks.corrected import write_offset_element

        with output_run(folder / "masks", f"doe correct --redesign {new.name}"):
            masks = write_offset_element(new, folder / "masks", [j["drawn_edge_offset_um"] * 1e-6 for j in jobs],
                                         source=str(folder / "design.npz"), mirrored=mirrored, depths_m=depths_m,
                                         layers=layers)
    report = {**report, "design_file": "design.npz", "masks_file": str(Path("masks") / Path(masks["file"]).name),
              "masks_verification": masks["verification"]}
    write_json(folder / "redesign.json", report)
    return {k: v for k, v in report.items() if k != "merit"}
