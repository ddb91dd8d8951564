"""The job sheet: per mask, what the next run changes, from the combined estimates.

Conventions (those of ``doe compare`` and the process model): x toward increasing design
column, y up (toward row 0), rotations counter-clockwise with row 0 on top, about the centre of
the design grid, each mask relative to mask 0. The aligner's dial values are the NEGATIVE of
the measured errors (a mask printed 0.4 um to +x is placed 0.4 um to -x next time). The etch
target is what to aim at so that the etch lands on nominal: ``nominal / (1 + error)``, and,
with a significant etch loading ``L``, divided by ``1 - L rho`` with ``rho`` the mean local open
fraction over that mask's openings (the process model's loading rule,
:func:`masks.process.mask_etch`). The linewidth bias taken out is the measured one; the drawn
edges move by its negative.

Etch loading, what the fab can act on: ``doe diagnose`` reports one coefficient ``L`` of the
process model ``depth_j(x) = d_j (1 - L rho_j(x))``, a *depth* that varies with the local open
fraction. The etch time sets one depth per mask, so the target takes out the mean loss over the
mask's openings (the least-squares best uniform depth). What varies with the density is left:
binary masks cannot vary the local etch rate, and an edge offset moves where an opening ends,
not how deep it is (widening dense openings would even raise their density and their loading).
The job sheet says so in a warning with the measured coefficient and, per mask, the rms depth
left over the openings (:func:`loading_warnings`); a re-design for the measured process is the
remedy. The proof that the mean went out is each mask's measured mean depth error over its
openings, ``(1 + e_j)(1 - L rho_mean_j) - 1`` (``etch_mean_error_measured``), before and after.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from doedesign.errors import DoeError

from .systematic import DISAGREEMENT_CHI2, SIGNIFICANCE, Estimate, find_estimate

__all__ = ["check_offsets", "check_same_process", "job_entries", "loading_losses", "loading_warnings", "mask_label",
           "mean_loading_loss", "warnings_for"]


def loading_losses(masks: np.ndarray, pitch_m: float, depths_m: Sequence[float], loading: float
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Per mask, the mean and the rms about it of the fractional depth lost to etch loading over
    its openings (process model, at design-pixel resolution)."""
    from masks.process import ProcessParams, mask_etch

    params = ProcessParams(etch_depth=np.asarray(depths_m, float), etch_loading=float(loading))
    levels = np.zeros(np.shape(masks)[1:], np.int64)
    for j, m in enumerate(masks):
        levels = levels + (np.asarray(m, np.int64) << j)
    mean, rms = [], []
    for j, m in enumerate(masks):
        if not m.any():
            mean.append(0.0)
            rms.append(0.0)
            continue
        lost = 1.0 - mask_etch(levels, pitch_m, params, j, step_m=pitch_m)[m] / depths_m[j]
        mean.append(float(lost.mean()))
        rms.append(float(lost.std()))
    return np.array(mean), np.array(rms)


def mean_loading_loss(masks: np.ndarray, pitch_m: float, depths_m: Sequence[float], loading: float) -> np.ndarray:
    """Per mask, the mean fractional depth lost to etch loading over its openings (process model)."""
    return loading_losses(masks, pitch_m, depths_m, loading)[0]


def job_entries(estimates: Sequence[Estimate], masks: np.ndarray, pitch_m: float, depths_m: Sequence[float],
                layers: Sequence[int], datatype: int = 0) -> list[dict]:
    """One entry per mask: layer, datatype, nominal and target etch depth, aligner dials,
    linewidth bias taken out, and the corrections that went in (strict-JSON ready)."""
    n = len(depths_m)
    loading = find_estimate(estimates, "etch_loading", None, "loading")
    loss, rest = loading_losses(masks, pitch_m, depths_m, loading.mean) if loading else (np.zeros(n), np.zeros(n))
    # The measured mean depth error over each mask's openings, corrected or not (what the etch target acts on).
    measured_loss = loss
    if not loading:
        named = find_estimate(estimates, "etch_loading", None, "loading", corrected_only=False)
        if named and named.mean:
            measured_loss = mean_loading_loss(masks, pitch_m, depths_m, named.mean)
    entries = []
    for j in range(n):
        done = []
        nominal = float(depths_m[j])
        target = nominal
        depth = find_estimate(estimates, "etch_depth", j, "depth_error")
        if depth:
            target /= 1.0 + depth.mean
            done.append(f"etch depth error {depth.mean * 100:+.2f} % taken out of the target")
        if loading:
            target /= 1.0 - loss[j]
            done.append(f"etch loading {loading.mean:.3f}: mean loss {loss[j] * 100:.2f} % over the openings "
                        f"added to the target (density-dependent rest, rms {rest[j] * nominal * 1e9:.2f} nm, "
                        "not correctable by mask or etch)")
        measured_depth = find_estimate(estimates, "etch_depth", j, "depth_error", corrected_only=False)
        mean_error = (1.0 + (measured_depth.mean if measured_depth else 0.0)) * (1.0 - measured_loss[j]) - 1.0
        shift = [0.0, 0.0]
        for c, axis in enumerate(("dx", "dy")):
            e = find_estimate(estimates, "mask_overlay", j, axis)
            if e:
                shift[c] = -e.mean
        if any(shift):
            done.append(f"aligner offset {shift[0] * 1e6:+.3f}, {shift[1] * 1e6:+.3f} um")
        rot = find_estimate(estimates, "mask_rotation", j, "rotation")
        rotation = -rot.mean if rot else 0.0
        if rot:
            done.append(f"aligner rotation {rotation:+.4f} deg")
        bias = find_estimate(estimates, "linewidth_bias", j, "bias")
        bias_m = bias.mean if bias else 0.0
        if bias:
            done.append(f"edges drawn {-bias_m * 1e6:+.3f} um (linewidth bias {bias_m * 1e6:+.3f} um taken out)")
        entries.append({
            "mask": j, "layer": int(layers[j]), "datatype": int(datatype),
            "etch_depth_nm": nominal * 1e9, "etch_depth_target_nm": target * 1e9,
            "align_offset_um": [v * 1e6 for v in shift], "align_rotation_deg": rotation,
            "linewidth_bias_um": bias_m * 1e6, "drawn_edge_offset_um": -bias_m * 1e6,
            "etch_loading_mean_loss_fraction": float(loss[j]) if loading else 0.0,
            "etch_loading_residual_rms_nm": float(rest[j]) * nominal * 1e9 if loading else 0.0,
            "etch_mean_error_measured": float(mean_error),
            "corrections": done or ["none: nothing systematic and significant on this mask"]})
    return entries


def check_offsets(masks: np.ndarray, pitch_m: float, jobs: Sequence[dict], min_feature_m: float | None,
                  source: str) -> None:
    """Refuse (one line naming ``source`` and the mask) a job whose drawn edge offset the mask
    cannot take: an edge pushed past its neighbour or below ``min_feature_m`` (default
    :data:`masks.corrected.MIN_FEATURE_M`)."""
    from masks.corrected import MIN_FEATURE_M, offset_feasibility

    limit = MIN_FEATURE_M if min_feature_m is None else float(min_feature_m)
    for job in jobs:
        why = offset_feasibility(masks[job["mask"]], pitch_m, job["drawn_edge_offset_um"] * 1e-6, limit)
        if why:
            raise DoeError(f"{source}: mask {job['mask']}: a drawn edge offset of {job['drawn_edge_offset_um']:+.3f} "
                           f"um (taking out a linewidth bias of {job['linewidth_bias_um']:+.3f} um) cannot be "
                           f"drawn: {why}")


def warnings_for(estimates: Sequence[Estimate], fields: Sequence, jobs: Sequence[dict] = ()) -> list[str]:
    """Warnings for the job sheet: fields that disagree beyond their uncertainties (in sign, or
    in scatter on a corrected parameter), systematic effects no knob acts on, what of a
    compensated etch loading no knob removes (given the ``jobs``), diagnoses that left a
    residual unexplained. First (the sheet's first lines): the diagnoses a limit ended, and the
    effects fewer fields tested than were given."""
    out = incomplete_warnings(estimates, fields)
    scatter: list[str] = []
    spread: list[str] = []
    for e in estimates:
        signs = {np.sign(v - e.null) for v, s in zip(e.values, e.uncertainties) if abs(v - e.null) > SIGNIFICANCE * s}
        if len(signs) > 1 and e.systematic:
            out.append(f"{e.effect} {e.param}: the fields disagree in sign beyond their uncertainties "
                       f"(values {', '.join(f'{v:.4g}' for v in e.values)} {e.unit}); "
                       + ("corrected by the mean" if e.corrected else "not corrected"))
        elif e.chi2_per_dof is not None and e.chi2_per_dof > DISAGREEMENT_CHI2:
            (scatter if e.systematic else spread).append(f"{e.effect} {e.param} (chi2/dof {e.chi2_per_dof:.3g})")
        if e.systematic and not e.knob:
            out.append(f"{e.effect} {e.param} = {e.mean:.4g} {e.unit} is systematic but no mask, aligner or etch "
                       "setting corrects it")
    if scatter:
        out.append("the fields disagree beyond their fitted uncertainties on " + ", ".join(scatter)
                   + ": a field-to-field spread of the process; the between-field scatter, not the fits, sets "
                   "those means' standard errors")
    if spread:
        out.append("the fields scatter beyond their fitted uncertainties about a mean that is not significant on "
                   + ", ".join(spread) + ": reported as spread, not corrected")
    out += loading_warnings(estimates, jobs)
    for f in fields:
        if f.unexplained:
            out.append(f"{f.source}: its diagnosis left a structured residual unexplained; its effects may be incomplete")
    return out


def incomplete_warnings(estimates: Sequence[Estimate], fields: Sequence) -> list[str]:
    """The job sheet's first lines: each INCOMPLETE diagnosis (it says nothing about what it did not
    try), and each effect combined over fewer fields than were given."""
    out = [f"INCOMPLETE diagnosis {f.source}: a time limit ended it, and it counts only for what it named "
           f"({', '.join(f.params) or 'nothing'}); rerun doe diagnose without --wall-limit-s / --cpu-budget-s"
           for f in fields if f.incomplete]
    fewer = sorted({f"{e.effect} ({e.tested_in} of {e.fields})" for e in estimates if e.tested_in < e.fields})
    if fewer:
        out.append("combined only over the fields whose diagnosis tested them: " + ", ".join(fewer))
    return out


def loading_warnings(estimates: Sequence[Estimate], jobs: Sequence[dict]) -> list[str]:
    """The part of a compensated etch loading that no knob removes, with the measured values."""
    loading = find_estimate(estimates, "etch_loading", None, "loading")
    if not loading or not jobs:
        return []
    rest = ", ".join(f"mask {m['mask']} {m['etch_loading_residual_rms_nm']:.2f} nm" for m in jobs)
    return [f"etch_loading loading = {loading.mean:.4g} +- {loading.standard_error:.2g} is systematic: the etch targets "
            "take out its mean loss over each mask's openings, but the depth that varies with the local open fraction "
            f"(rms over the openings: {rest}) cannot be corrected by a mask edge, the aligner or the etch time "
            "(binary masks cannot vary the local etch rate); a re-design for the measured process can"]


def mask_label(job: dict) -> str:
    """The label line of a corrected mask: which corrections went in (a job entry of :func:`job_entries`)."""
    bits = []
    if job["drawn_edge_offset_um"]:
        bits.append(f"edges {job['drawn_edge_offset_um']:+.3f} um")
    if abs(job["etch_depth_target_nm"] - job["etch_depth_nm"]) > 1e-6:
        why = " incl. loading mean loss {:.2f} %".format(job["etch_loading_mean_loss_fraction"] * 100) \
            if job["etch_loading_mean_loss_fraction"] else ""
        bits.append(f"etch target {job['etch_depth_target_nm']:.1f} nm{why}")
    if any(job["align_offset_um"]) or job["align_rotation_deg"]:
        bits.append(f"align {job['align_offset_um'][0]:+.3f},{job['align_offset_um'][1]:+.3f} um "
                    f"{job['align_rotation_deg']:+.4f} deg")
    return "corrected: " + ", ".join(bits) if bits else "no correction"


def check_same_process(fields: Sequence) -> list[float]:
    """The nominal etch depths all diagnoses share (DoeError when they differ)."""
    first = fields[0].nominal_depths_m
    for f in fields[1:]:
        if len(f.nominal_depths_m) != len(first) or not np.allclose(f.nominal_depths_m, first, rtol=1e-6):
            raise DoeError(f"{f.source}: diagnosed against nominal etch depths {f.nominal_depths_m} m, "
                           f"{fields[0].source} against {first} m; diagnose every field with the same --depths-nm")
    return list(first)
