"""The Markdown pages a person reads beside ``doe compare``'s and ``doe diagnose``'s report.json.

Each page starts with a summary in words (what was found and how sure it is), then tables
with units, the figures inline and a link to the JSON. The demo page
(:func:`metrology.pipeline.markdown_report`) reuses the same sections. Built from the
shared blocks of :mod:`doedesign.report_md`.
"""

from __future__ import annotations

import math
from pathlib import Path

from doedesign import report_md as md

__all__ = ["BIAS_TOLERANCE_UM", "COMPARE_FIGURES", "DEPTH_TOLERANCE_PERCENT", "DIAGNOSE_FIGURES",
           "OVERLAY_TOLERANCE_UM", "SIGNIFICANCE", "compare_findings", "compare_page", "compare_sections",
           "diagnose_page", "diagnose_sections", "instrument_parts", "match_sentence", "psf_merit", "terrace_sections",
           "texture_sections"]

# Verdict rules. A depth or overlay is called off nominal when it is both significant (beyond
# 3 standard errors) and large enough to matter: 2 % of a depth (a 10 nm error costs 0.07 %
# efficiency, so 2 % is a process-control figure, not an optical one) and 0.1 um of overlay
# (0.5 um on the 600 nm mask costs ~18 % efficiency, 0.1 um a few per cent).
DEPTH_TOLERANCE_PERCENT = 2.0
OVERLAY_TOLERANCE_UM = 0.1
BIAS_TOLERANCE_UM = 0.1
SIGNIFICANCE = 3.0

COMPARE_FIGURES = (("surface3d.png", "measured surface (3-D)"),
                   ("masks.png", "per-mask etch depth error, overlay and linewidth bias with 1-sigma bars"),
                   ("error_map.png", "height error against the design and against the fitted process model"),
                   ("levels.png", "level histogram with the fitted level means"),
                   ("psf.png", "PSF predicted from the measured heights beside the design's"),
                   ("texture.png", "radially averaged PSD of the residual (measured minus design)"))
DIAGNOSE_FIGURES = (("residual_steps.png", "residual map after each named effect"),
                    ("breakdown.png", "where the residual lives (by edge distance, level, density)"))


def _off(value, err, tolerance):
    """True when ``value`` is beyond ``tolerance`` and beyond SIGNIFICANCE standard errors."""
    if value is None or not math.isfinite(value):
        return None
    err = err if err is not None and math.isfinite(err) else 0.0
    return abs(value) > tolerance and abs(value) > SIGNIFICANCE * err


def _get(seq, i, j=None):
    try:
        v = seq[i] if j is None else seq[i][j]
    except (IndexError, TypeError, KeyError):
        return None
    return v


def compare_findings(rep: dict) -> list[tuple[int, str, str]]:
    """Per-mask findings of a comparison report: list of (mask, what, text) for what is off nominal."""
    found = []
    for j, nominal in enumerate(rep.get("etch_depths_nominal_nm") or []):
        pct = _get(rep.get("etch_depths_error_percent"), j)
        err_pct = (_get(rep.get("etch_depths_err_nm"), j) or 0.0) / nominal * 100 if nominal else None
        if _off(pct, err_pct, DEPTH_TOLERANCE_PERCENT):
            found.append((j, "etch_depth", f"mask {j} etched {md.fmt(_get(rep['etch_depths_nm'], j), 4)} nm "
                                            f"against {md.fmt(nominal, 4)} nm ({pct:+.1f} %)"))
        for axis, name in ((0, "dx"), (1, "dy")):
            ov, ov_err = _get(rep.get("overlay_um"), j, axis), _get(rep.get("overlay_err_um"), j, axis)
            if j > 0 and _off(ov, ov_err, OVERLAY_TOLERANCE_UM):
                found.append((j, "mask_overlay", f"mask {j} overlay {name} = {md.fmt_pm(ov, ov_err, 3, 'um')}"))
        bias, bias_err = _get(rep.get("linewidth_bias_um"), j), _get(rep.get("linewidth_bias_err_um"), j)
        if _off(bias, bias_err, BIAS_TOLERANCE_UM):
            found.append((j, "linewidth_bias", f"mask {j} linewidth bias {md.fmt_pm(bias, bias_err, 3, 'um')}"))
    return found


def match_sentence(rep: dict) -> str:
    """How sure the comparison is that the field shows the design, in words (registration quality)."""
    match = rep.get("match") or {}
    corr, edges = match.get("readout_correlation"), match.get("edges_found")
    text = (f"the field's heights correlate {md.fmt(corr, 3)} with the printed design and step the design's way at "
            f"{md.fmt(100 * edges, 3) if edges is not None else md.MISSING} % of its "
            f"{match.get('design_edges', md.MISSING)} edges in the field")
    confident = match.get("confidence") == "high" if match else None
    if match.get("forced") and not confident:
        return md.verdict(False, "", f"the comparison was forced although {match.get('problem') or text}; the "
                                     "numbers below may belong to another design or field")
    return md.verdict(confident, f"the measurement shows the design: {text}", f"weak match: {text}")


def psf_merit(psf: dict) -> tuple[str, list, list, str]:
    """The PSF section's figure: (name, design values, fabricated values, what it counts).

    The design's own target when the report has it (``design_on_target``), else the design
    PSF's core (``design_in_psf_core``): a different quantity under a different name.
    """
    merit = psf.get("merit") or {}
    for key, name in (("on_target", "light on the design's target"), ("in_psf_core", "light in the design PSF's core"),
                      ("on_given_pixels", "light on the given target pixels")):
        if f"design_{key}" in psf:
            return (merit.get("name", name), psf.get(f"design_{key}") or [], psf.get(f"measured_{key}") or [],
                    merit.get("counted_on", ""))
    return "light on target", [], [], ""


def compare_sections(rep: dict, folder: str | Path, prefix: str = "", level: int = 2) -> list[str]:
    """Markdown parts of a comparison: summary, per-mask table, PSF table, figures."""
    h = "#" * level
    findings = compare_findings(rep)
    depth_ok = not any(f[1] == "etch_depth" for f in findings)
    overlay_ok = not any(f[1] == "mask_overlay" for f in findings)
    reg = rep.get("registration") or {}
    parts = [f"{h} Summary",
             f"- Match: {match_sentence(rep)}.",
             "- Etch depths: " + md.verdict(depth_ok, f"every mask within {DEPTH_TOLERANCE_PERCENT:g} % of nominal",
                                           "; ".join(f[2] for f in findings if f[1] == "etch_depth")) + ".",
             "- Overlay: " + md.verdict(overlay_ok, f"every mask within {OVERLAY_TOLERANCE_UM:g} um of mask 0",
                                       "; ".join(f[2] for f in findings if f[1] == "mask_overlay")) + ".",
             f"- Height error against the design: {md.fmt(rep.get('height_error_rms_nm'), 3, 'nm')} rms "
             f"(feature interiors {md.fmt(rep.get('height_error_interior_rms_nm'), 3, 'nm')}, against the fitted "
             f"process model {md.fmt(rep.get('height_error_model_rms_nm'), 3, 'nm')}); roughness "
             f"{md.fmt(rep.get('roughness_rms_nm'), 3, 'nm')} rms.",
             f"- Registration: pixel {md.fmt(reg.get('pixel_size_um'), 5, 'um')}, rotation "
             f"{md.fmt(reg.get('rotation_deg'), 3, 'deg')}, "
             f"{'mirrored' if reg.get('flip') else 'not mirrored'}{', transposed' if reg.get('transpose') else ''}.",
             "",
             f"{h} Per mask (measured against nominal, ± 1 standard error)",
             "Overlay is relative to mask 0 (x toward increasing design column, y up); bias is the growth of "
             "every opening edge (+ = wider).", ""]
    rows = []
    for j, nominal in enumerate(rep.get("etch_depths_nominal_nm") or []):
        rows.append((f"mask {j}", md.fmt(nominal, 4),
                     md.fmt_pm(_get(rep.get("etch_depths_nm"), j), _get(rep.get("etch_depths_err_nm"), j), 4),
                     md.fmt(_get(rep.get("etch_depths_error_percent"), j), 2),
                     md.fmt_pm(_get(rep.get("overlay_um"), j, 0), _get(rep.get("overlay_err_um"), j, 0), 2),
                     md.fmt_pm(_get(rep.get("overlay_um"), j, 1), _get(rep.get("overlay_err_um"), j, 1), 2),
                     md.fmt_pm(_get(rep.get("linewidth_bias_um"), j), _get(rep.get("linewidth_bias_err_um"), j), 2),
                     "off nominal" if any(f[0] == j for f in findings) else "nominal"))
    parts.append(md.table(rows, ("mask", "nominal depth (nm)", "measured depth (nm)", "depth error (%)",
                                 "overlay dx (um)", "overlay dy (um)", "linewidth bias (um)", "verdict")))
    parts += terrace_sections(rep.get("terrace_fit"), h)
    parts += texture_sections(rep.get("texture"), h)
    psf = rep.get("psf")
    if isinstance(psf, dict) and psf.get("wavelengths_nm"):
        name, design, made, counted = psf_merit(psf)
        own = name == "light on the design's target"
        parts += [f"{h} {name[0].upper() + name[1:]}, design against the fabricated element",
                  f"Fraction of the coded half-aperture's light on {counted or 'the target pixels'}, predicted from "
                  "the fitted process; "
                  + ("the design's own figure of merit, as in its design report." if own else
                     "not the design's figure of merit (the design names no target at these wavelengths)."), ""]
        prow = [(md.fmt(wl, 4), md.fmt(d, 4), md.fmt(m, 4),
                 md.fmt(100 * (m - d) / d if d else None, 2))
                for wl, d, m in zip(psf["wavelengths_nm"], design, made)]
        parts.append(md.table(prow, ("wavelength (nm)", f"design: {name} (fraction of light)",
                                     f"fabricated: {name} (fraction of light)", "change (%)")))
    parts += instrument_parts(rep, h)
    parts.append(f"{h} Figures")
    parts += [md.figure(folder, prefix + name, caption) for name, caption in COMPARE_FIGURES]
    return parts


def instrument_parts(rep: dict, h: str = "##") -> list[str]:
    """What levelling removed as the instrument's (tilt, scan lines), the lattice of a periodic
    design and a binary design's duty cycle, when the comparison reports them."""
    art = rep.get("instrument_artefacts") or {}
    lat = rep.get("lattice") or {}
    duty = rep.get("duty_cycle") or {}
    lines = [f"- Removed in levelling as the instrument's, not the relief: tilt "
             f"{md.fmt(art.get('tilt_x_nm_per_px'), 3, 'nm')} per pixel along x and "
             f"{md.fmt(art.get('tilt_y_nm_per_px'), 3, 'nm')} along y"
             + (f"; scan-line offsets {md.fmt(art.get('scan_line_offsets_rms_nm'), 3, 'nm')} rms "
                f"({md.fmt(art.get('scan_line_offsets_pv_nm'), 3, 'nm')} peak to valley over "
                f"{art.get('scan_lines')} lines) of the raster scan" if art.get("raster_scan") else "") + "."]
    if lat:
        px, py = lat.get("period_um_xy") or (None, None)
        cell = lat.get("depth_per_cell") or {}
        lines.append(f"- Lattice (registered modulo its period): {md.fmt(px, 4, 'um')} along x, "
                     f"{md.fmt(py, 4, 'um')} along y at the file's pixel size, turned "
                     f"{md.fmt(lat.get('turn_deg'), 3, 'deg')}, shear {md.fmt(lat.get('shear_deg'), 2, 'deg')}; "
                     f"step per cell {md.fmt_pm(cell.get('depth_nm'), cell.get('err_nm'), 4, 'nm')} "
                     f"(scatter {md.fmt(cell.get('std_nm'), 2, 'nm')} over {cell.get('cells')} cells).")
    if duty.get("unetched_fraction") is not None:
        lines.append(f"- Duty cycle (unetched share of the area): "
                     f"{md.fmt_pm(duty['unetched_fraction'], duty.get('unetched_fraction_err'), 4)} "
                     f"(design {md.fmt(duty.get('design_unetched_fraction'), 4)}; edges moved "
                     f"{md.fmt_pm(duty.get('edge_shift_um'), duty.get('edge_shift_err_um'), 2, 'um')}).")
    return [f"{h} Instrument, lattice and duty cycle", *lines, ""] if art else []


def terrace_sections(terrace: dict | None, h: str = "##") -> list[str]:
    """The terrace fit beside the camera-frame fit: a verdict line, then per mask and per step."""
    if not isinstance(terrace, dict):
        return []
    check = terrace.get("against_camera_frame") or {}
    warnings = check.get("warnings") or []
    parts = [f"{h} Terrace fit beside the camera-frame fit (± 1 standard uncertainty)",
             "- " + md.verdict(check.get("agree"), "the two fits agree on every step and mask within twice their "
                               "combined standard uncertainty (k = 2)", "; ".join(warnings) or "not compared") + ".",
             f"- Terraces: {md.fmt(terrace.get('margin_px'), 3)} px from every design or measured step (ISO 5436-1's "
             f"central third on a line), common background of degree {terrace.get('background_degree')}, residual "
             f"{md.fmt(terrace.get('rms_residual_nm'), 3, 'nm')} rms.", ""]
    rows = [(f"mask {j}", md.fmt_pm(m.get("terrace_nm"), m.get("terrace_err_nm"), 4),
             md.fmt_pm(m.get("camera_frame_nm"), m.get("camera_frame_err_nm"), 4), md.fmt(m.get("difference_nm"), 3),
             md.fmt(m.get("limit_nm"), 3), {True: "agree", False: "WARNING: differ"}.get(m.get("agree"), "not compared"))
            for j, m in enumerate(check.get("masks") or [])]
    rows += [(s.get("name", "").removeprefix("step "), md.fmt_pm(s.get("terrace_nm"), s.get("terrace_err_nm"), 4),
              md.fmt_pm(s.get("camera_frame_nm"), s.get("camera_frame_err_nm"), 4), md.fmt(s.get("difference_nm"), 3),
              md.fmt(s.get("limit_nm"), 3), {True: "agree", False: "WARNING: differ"}.get(s.get("agree"), "not measured"))
             for s in check.get("steps") or []]
    if rows:
        parts.append(md.table(rows, ("etch depth or step", "terrace fit (nm)", "camera-frame fit (nm)",
                                     "difference (nm)", "k = 2 limit (nm)", "verdict")))
    return parts


def texture_sections(texture: dict | None, h: str = "##") -> list[str]:
    """ISO 25178 height parameters of each level's flat interiors and of the residual, its band rms."""
    if not isinstance(texture, dict):
        return []
    parts = [f"{h} Surface texture (ISO 25178, about each region's own mean, no S/L filter)", ""]
    rows = [(f"level {k} flat interiors", md.fmt(d.get("Sa_nm"), 3), md.fmt(d.get("Sq_nm"), 3),
             md.fmt(d.get("Sz_nm"), 3), d.get("pixels"))
            for k, d in enumerate(texture.get("levels") or []) if d.get("pixels")]
    res = texture.get("residual") or {}
    rows.append(("residual (measured - design)", md.fmt(res.get("Sa_nm"), 3), md.fmt(res.get("Sq_nm"), 3),
                 md.fmt(res.get("Sz_nm"), 3), res.get("pixels")))
    parts.append(md.table(rows, ("region", "Sa (nm)", "Sq (nm)", "Sz (nm)", "pixels")))
    bands = [(f"{md.fmt(b.get('wavelength_from_um'), 3)} to "
              f"{md.fmt(b.get('wavelength_to_um'), 3) if b.get('wavelength_to_um') is not None else 'field'}",
              md.fmt(b.get("rms_nm"), 3)) for b in res.get("bands") or []]
    if bands:
        parts += ["", "The residual's rms by band of spatial wavelength (from its PSD, Hann window):", "",
                  md.table(bands, ("spatial wavelength (um)", "rms (nm)"))]
    return parts


def _param_text(name, value, err, unit):
    if unit == "m" and value is not None:
        scale, shown = (1e9, "nm") if abs(value) < 1e-6 else (1e6, "um")
        return f"{name.removesuffix('_m')} {md.fmt_pm(value * scale, None if err is None else err * scale, 3, shown)}"
    return f"{name} {md.fmt_pm(value, err, 3, unit)}".rstrip()


def _um(v):
    return v * 1e6 if isinstance(v, (int, float)) else None


def _partial(match):
    """A partial match as the page says it: the effect, and what it leaves on its footprint."""
    ratio, share = match.get("residual_on_footprint_over_floor"), match.get("footprint_excess_explained")
    if ratio is None or share is None:
        return match["effect"]
    return f"{match['effect']} ({ratio:.2f}x the floor there, {100 * share:.0f} % of its excess explained)"


def diagnose_sections(rep: dict, folder: str | Path, prefix: str = "", level: int = 2) -> list[str]:
    """Markdown parts of a diagnosis: summary in words, the steps with the shrinking residual, figures."""
    h = "#" * level
    unit_scale, unit = (1e9, "nm") if rep.get("units") == "m" else (1.0, rep.get("units") or "")
    named = [e for e in rep.get("effects_found") or [] if e not in (rep.get("measurement_artefacts") or [])]
    initial, final, floor = (rep.get(k) for k in ("initial_residual_rms", "final_residual_rms", "noise_floor"))

    def r(v, with_unit=True):
        return md.fmt(v * unit_scale if isinstance(v, (int, float)) else None, 3, unit if with_unit else "")

    explained = not rep.get("unexplained")
    parts = [f"{h} Summary",
             f"- Fabrication effects named: {', '.join(named) if named else 'none'}; measurement artefacts: "
             f"{', '.join(rep.get('measurement_artefacts') or []) or 'none'}.",
             f"- Residual: {r(initial)} rms before, {r(final)} after, against a noise floor of {r(floor)}.",
             "- " + md.verdict(explained, "the named effects explain the measurement down to the noise floor",
                               "a structured residual remains that no candidate effect explains; treat the "
                               "named effects as the strongest found, not the whole story") + ".",
             "", f"{h} Steps (each added effect and how far the residual shrank)", ""]
    where = rep.get("unexplained_where")
    if where:
        partial = ", ".join(_partial(p) for p in rep.get("partial_matches") or [])
        extra = [f"- Where the unexplained residual lives: {where.get('summary', md.MISSING)}"]
        inadequate = where.get("instrument_model_inadequate")
        if inadequate:
            withheld = ", ".join(inadequate.get("withheld") or []) or "none"
            extra.append(f"- Instrument model inadequate: {inadequate.get('message')} (withheld: {withheld}).")
        if partial:
            extra.append(f"- Not named, they fit only part of the residual on their own footprint: {partial}.")
        parts[4:4] = extra
    small = rep.get("below_resolution")
    if isinstance(small, dict):
        share = small.get("floor_power_share")
        parts.insert(parts.index(""), f"- Not named, below the model's resolution: {small.get('effect')} would explain "
                     f"{md.fmt(100 * share if isinstance(share, (int, float)) else None, 2, '%')} of the noise "
                     "floor's power, within what the instrument model's own error leaves.")
    stopped = rep.get("stopped_early")
    if isinstance(stopped, dict):
        more = "`--wall-limit-s`" if stopped.get("limit") == "wall" else "`--cpu-budget-s`"
        parts.insert(4, f"- Stopped early: {stopped.get('reason')} (final residual "
                        f"{md.fmt(stopped.get('final_over_floor'), 3)} x the noise floor). Rerun without {more} "
                        "(the default: no limit) for a finished diagnosis; until then this field says nothing "
                        "about the candidates not tried.")
    if rep.get("summary"):
        # The summary's first line: INCOMPLETE (and what was not tried) where a user's limit ended it.
        parts.insert(1, f"- {rep['summary']}.")
    inst = ((rep.get("inputs") or {}).get("placement") or {}).get("instrument")
    if isinstance(inst, dict):
        parts.insert(4, "- Instrument's lateral transfer ({}): blur {} um, fill factor {}, NA {}.".format(
            inst.get("source"), md.fmt_pm(_um(inst.get("blur_sigma_m")), _um(inst.get("blur_sigma_uncertainty_m")), 3, ""),
            md.fmt_pm(inst.get("fill_factor"), inst.get("fill_factor_uncertainty"), 3, ""),
            md.fmt_pm(inst.get("na"), inst.get("na_uncertainty"), 3, "") if inst.get("na") else "none fitted"))
    rows = []
    for i, step in enumerate(rep.get("steps") or [], 1):
        params = step.get("params") or {}
        errs = step.get("uncertainties") or {}
        units = step.get("units") or {}
        text = "; ".join(_param_text(k, v, errs.get(k), units.get(k)) for k, v in params.items())
        rows.append((i, step.get("effect"), "artefact" if step.get("measurement_artefact") else step.get("kind"),
                     text or md.MISSING, r(step.get("residual_rms_before"), False),
                     r(step.get("residual_rms_after"), False),
                     md.fmt(step.get("criterion_change"), 4)))
    if rows:
        parts.append(md.table(rows, ("step", "effect", "kind", "fitted parameters (± 1 s.e.)",
                                     f"residual before ({unit})", f"residual after ({unit})",
                                     "criterion change (BIC, lower is better)")))
    else:
        parts.append("No effect is named, yet a structured residual remains: the measurement does not agree with the "
                     "ideal model (the summary says why nothing was named).\n" if rep.get("unexplained") else
                     "No effect lowered the criterion: the measurement agrees with the ideal model.\n")
    # What each named fabrication effect's parameters refer to (an etch gradient's and a mask
    # rotation's reference point is the design's centre, not the camera field's).
    fab = [s for s in rep.get("steps") or [] if not s.get("measurement_artefact") and s.get("description")]
    if fab:
        parts += ["What the named effects mean (conventions and reference points):", ""]
        parts += [f"- {s.get('effect')}: {s['description']}" for s in fab] + [""]
    parts.append(f"{h} Figures")
    parts += [md.figure(folder, prefix + name, caption) for name, caption in DIAGNOSE_FIGURES]
    return parts


def compare_page(rep: dict, folder: Path) -> Path:
    """The whole ``report.md`` of ``doe compare``."""
    title = f"# Comparison of `{rep.get('measurement')}` with `{rep.get('design')}`"
    return md.write_markdown(folder / "report.md", [title, *compare_sections(rep, folder), md.json_link()])


def diagnose_page(rep: dict, folder: Path) -> Path:
    """The whole ``report.md`` of ``doe diagnose``."""
    inputs = rep.get("inputs") or {}
    source = inputs.get("measured") or inputs.get("measured_psf")
    title = f"# Diagnosis of `{source}` against `{inputs.get('design')}`"
    return md.write_markdown(folder / "report.md", [title, *diagnose_sections(rep, folder), md.json_link()])
