"""Compare a measurement with the design and the process model (``doe compare``).

Stages, each in its own module:

- levelling and registration (:mod:`.level`, :mod:`.register`) against the heights the masks
  print from the design (:func:`doedesign.levels.printed_height_m`: a heights-only design is
  judged against the levels ``doe masks`` makes of it);
- whether the field shows the design at all, from the registration's quality (:mod:`.match`);
- level heights on feature interiors and etch depths from the level means (:mod:`.depths`);
- a point-sampled edge model for starting values of overlay, bias and edge blur
  (:mod:`.edges`);
- the reported etch depths, overlay and linewidth bias: fitted in the camera's own frame
  with the same measurement model as ``doe diagnose --frame camera`` (objective blur,
  pixel-area integration, placement refined with uncertainties, levelling projected out;
  :mod:`.instrument_fit`), through the member of the lateral transfer's family the data ask
  for (whole pixels or point samples; an objective and a batwing where the diagnosis's
  instrument stage chooses them: :mod:`.instrument_family`), the measured heights never
  resampled;
- error maps against the design and against the fitted model (:mod:`.forward`);
- an independent check of the level heights: a terrace fit of the levelled field on the
  camera-frame fit's window, each level from its flat interiors (:mod:`.terrace`), set beside
  the camera-frame fit step by step and mask by mask;
- surface texture figures (ISO 25178 Sa, Sq, Sz of each level's flat interiors and of the
  residual, the residual's PSD and band rms; :mod:`.texture`).

Coordinates: measurement arrays are row-major, row 0 at the top (camera order); design
pixel (i, j) is centred at design coordinates (i, j). Overlay is x toward increasing
design column, y up (toward decreasing design row), as in :mod:`masks.process`.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from doedesign.errors import DoeError
from doedesign.levels import design_levels, printed_height_m
from metrology.matching.duty import duty_cycle
from metrology.matching.edges import MAX_FIT_POINTS, WIDTH_10_90_PER_SIGMA, EdgeFit, fit_edges
from metrology.matching.forward import (crop_registration, design_height_on_measurement, error_map,
                                        fitted_process, process_on_measurement, shift_registration)
from metrology.matching.instrument_family import fit_instrument_family
from metrology.matching.instrument_fit import InstrumentFit, fit_in_camera_frame
from metrology.matching.match import assess_match, check_relief
from metrology.matching.transfer import LateralTransfer
from metrology.matching.register import design_on_measurement
from metrology.matching.terrace import TerraceFit, check_against, fit_terraces, flat_interiors
from metrology.matching.texture import Texture, field_texture
from metrology.matching.depths import (LEVEL_REPEATABILITY_M, MAX_EDGE_BAND_PITCH, DepthFit, LevelStats,
                                       binary_code_matrix, fit_etch_depths, interior_mask, level_heights)

if TYPE_CHECKING:
    from doedesign.design import Design
    from doedesign.progress import Progress
    from masks.process import ProcessParams
    from metrology.formats.measurement import Measurement
    from metrology.matching.level import LevelResult
    from metrology.matching.register import Registration

# The names below stay importable from here (the comparison's public API before the split).
__all__ = ["Comparison", "DepthFit", "EdgeFit", "InstrumentFit", "LEVEL_REPEATABILITY_M", "MAX_EDGE_BAND_PITCH",
           "MAX_FIT_POINTS", "WIDTH_10_90_PER_SIGMA", "binary_code_matrix", "compare_measurement",
           "crop_registration", "design_height_on_measurement", "error_map", "fit_edges", "fit_etch_depths",
           "fitted_process", "interior_mask", "level_heights", "process_on_measurement", "shift_registration"]

log = logging.getLogger(__name__)

# Camera pixels per side of the window on which depths, overlay and bias are fitted in the
# camera's frame (the one richest in every mask's edges).
INSTRUMENT_WINDOW_PX = 128
# The terrace fit keeps pixels this many camera pixels from every step, or this many edge
# widths (the edge fit's sigma), whichever is more.
TERRACE_MARGIN_PX = 3.0
TERRACE_MARGIN_SIGMAS = 3.0


@dataclass
class Comparison:
    """Everything :func:`compare_measurement` found; :meth:`~metrology.matching.compare.Comparison.report` is the JSON summary.

    Maps are on the measurement grid (row 0 at the top, camera order).
    """

    height_m: np.ndarray
    labels: np.ndarray
    interior: np.ndarray
    registration: Registration
    levelling: LevelResult
    stats: LevelStats
    depth_fit: DepthFit
    edge_fit: EdgeFit
    instrument_fit: InstrumentFit
    nominal_depths_m: np.ndarray
    error_design_m: np.ndarray
    error_model_m: np.ndarray
    model_window: tuple[int, int, int, int]
    spikes_removed: int
    roughness_m: float
    match: dict = field(default_factory=dict)
    lattice: dict | None = None
    duty_cycle: dict | None = None
    raster_scan: bool = False
    terrace_fit: TerraceFit | None = None
    terrace_check: dict = field(default_factory=dict)
    texture: Texture | None = None
    instrument_family: dict | None = None
    flat_residual_m: float = float("nan")

    def fitted_params(self) -> ProcessParams:
        """:class:`~masks.process_params.ProcessParams` with the depths, overlay and bias fitted in the camera's frame."""
        return fitted_process(self.instrument_fit, n_masks=self.nominal_depths_m.size)

    def artefacts(self) -> dict:
        """What levelling removed as the instrument's, not the relief's: the plane tilt and, for a
        raster scan, the scan lines' offsets."""
        found = self.levelling.artefacts()
        what = ("the instrument's: the sample's tilt under the scanner (a plane) and the scanner's line-to-line "
                "z offsets (one per scan line, its slow drift and jumps), removed in levelling on the unetched "
                "surface; not the etched relief" if self.raster_scan else
                "the instrument's: the sample's tilt under the objective (a plane), removed in levelling")
        return {**found, "attributed_to": what, "raster_scan": self.raster_scan}

    def report(self) -> dict:
        """The comparison's JSON summary (units in the keys)."""
        nm, um = 1e9, 1e6
        e, d, s, f = self.edge_fit, self.depth_fit, self.stats, self.instrument_fit
        _, rms_design = error_map(self.error_design_m, 0.0)
        inner_err = np.where(self.interior, self.error_design_m, np.nan)
        _, rms_inner = error_map(inner_err, 0.0)
        _, rms_model = error_map(self.error_model_m, 0.0)
        return {
            "etch_depths_nm": f.depths_m * nm,
            "etch_depths_err_nm": f.depths_err_m * nm,
            "etch_depths_nominal_nm": self.nominal_depths_m * nm,
            "etch_depths_error_percent": (f.depths_m / self.nominal_depths_m - 1) * 100,
            "etch_depths_levels_nm": d.depths_m * nm,
            "etch_depths_levels_err_nm": d.depths_err_m * nm,
            "etch_depths_edge_fit_nm": e.depths_m * nm,
            "etch_sum": {"chi2": d.chi2, "dof": d.dof, "p_value": d.p_value,
                         "level_residual_nm": d.residual_m * nm, "top_nm": d.top_m * nm,
                         "note": "mu_k = top - sum_j B_kj D_j over the level means; small p: etches do not add up"},
            "level_heights_nm": s.mean_m * nm,
            "level_std_nm": s.std_m * nm,
            "level_pixel_counts": s.count,
            "overlay_um": f.overlay_m * um,
            "overlay_err_um": f.overlay_err_m * um,
            "linewidth_bias_um": f.bias_m * um,
            "linewidth_bias_err_um": f.bias_err_m * um,
            "instrument_frame": {
                "window_camera_px": f.window_camera_px, "placement": f.placement_report,
                "blur_sigma_um": f.blur_sigma_m * um, "blur_sigma_err_um": f.blur_sigma_err_m * um,
                "fill_factor": f.transfer.fill_factor, "na": f.transfer.na,
                "wavelength_um": f.transfer.wavelength_m * um,
                "batwing": None if f.batwing is None else {"amplitude": f.batwing[0], "sigma_um": f.batwing[1] * um},
                "rms_residual_nm": f.rms_residual_m * nm, "rms_residual_flat_nm": self.flat_residual_m * nm,
                "pixels": f.n_pixels, "excluded_pixels": f.excluded_pixels,
                "family": self.instrument_family if self.instrument_family is not None else
                {"rule": "a calibrated lateral transfer (--instrument), held"},
                "method": "depths, overlay, bias, objective blur and placement fitted on the camera's own pixels "
                          "through the lateral transfer's member the data ask for (pixel fill factor 1 or 0; an "
                          "objective and a batwing where the diagnosis's instrument stage chooses them, held), or a "
                          "calibrated one; levelling projected out, the data not resampled; rms_residual_flat_nm on "
                          "the window's flat interiors (the terrace fit's margin from every step)"},
            "edge_fit_overlay_um": e.overlay_m * um,
            "edge_fit_linewidth_bias_um": e.bias_m * um,
            "edge_transition_width_um": e.transition_width_m * um,
            "edge_fit_rms_residual_nm": e.rms_residual_m * nm,
            "edge_fit_points": e.n_points,
            "roughness_rms_nm": self.roughness_m * nm,
            "registration": self.registration.to_dict(),
            "match": dict(self.match),
            "height_error_rms_nm": rms_design * nm,
            "height_error_interior_rms_nm": rms_inner * nm,
            "height_error_model_rms_nm": rms_model * nm,
            "model_window_rows_cols": list(self.model_window),
            "levelling": {"plane_m_per_px": self.levelling.plane[1:],
                          "method": "joint plane + one offset per level on feature interiors"},
            "spikes_removed": self.spikes_removed,
            "instrument_artefacts": self.artefacts(),
            **({"lattice": self.lattice} if self.lattice is not None else {}),
            **({"duty_cycle": self.duty_cycle} if self.duty_cycle is not None else {}),
            "terrace_fit": self._terrace_report(),
            "texture": None if self.texture is None else self.texture.report(),
            "conventions": ("overlay (dx, dy) of each mask relative to mask 0, x toward increasing design column, "
                            "y up; linewidth bias = growth of every opening edge (+ = wider); heights z up, "
                            "0 = unetched top; etch depths, overlay and bias from the camera-frame fit, "
                            "etch_depths_levels_nm from the level means; level heights on the central third of features (ISO 5436-1); "
                            "roughness = pooled rms about the level means on interiors, 5-sigma outliers out (includes instrument noise)"),
        }

    def _terrace_report(self) -> dict | None:
        t = self.terrace_fit
        if t is None:
            return {"against_camera_frame": dict(self.terrace_check)}
        nm = 1e9
        return {"level_heights_nm": t.heights_m * nm, "level_heights_err_nm": t.heights_err_m * nm,
                "steps_nm": t.steps_m * nm, "steps_err_nm": t.steps_err_m * nm,
                "etch_depths_nm": None if t.depths is None else t.depths.depths_m * nm,
                "etch_depths_err_nm": None if t.depths is None else t.depths.depths_err_m * nm,
                "terraces": t.terraces, "terrace_pixels": t.pixels, "margin_px": t.margin_px,
                "background_degree": t.degree, "rms_residual_nm": t.rms_residual_m * nm,
                "window_camera_px": list(self.model_window),
                "against_camera_frame": dict(self.terrace_check),
                "method": "each level's height from its flat terraces (margin_px from every design or measured "
                          "step; ISO 5436-1's central third on a line), all terraces fitted at once with a common "
                          "polynomial background, on the camera-frame fit's window; uncertainty: standard error of "
                          "the terraces' means (at least the pixel scatter's) and the level repeatability floor in "
                          "quadrature; agreement: |difference| <= 2 x combined standard uncertainty (k = 2)"}


def compare_measurement(measurement: Measurement, design: Design, n_masks: int | None = None,
                        window_px: int = INSTRUMENT_WINDOW_PX, progress: Progress | None = None,
                        force: bool = False, transfer: LateralTransfer | None = None,
                        batwing: tuple[float, float] | None = None, texture: bool = True) -> Comparison:
    """Level, register and compare a measurement with its design.

    Parameters
    ----------
    measurement : metrology.formats.measurement.Measurement
    design : doedesign.design.Design
    n_masks : int, optional
        Binary masks of the element (default: the design's own, ``log2(design.n_levels)``); the
        nominal etch depths are the design's (:meth:`~doedesign.design.Design.etch_depths_m`).
    window_px : int
        Camera pixels per side of the window on which depths, overlay and bias are fitted in
        the camera's frame (the level and edge fits use the whole field).
    progress : doedesign.progress.Progress, optional
        Advanced once per stage (6 stages).
    force : bool
        Go on when the field does not show the design (see :mod:`metrology.matching.match`).
    transfer : LateralTransfer, optional
        The instrument's calibrated lateral transfer (``doe calibrate instrument``), held fixed
        in the camera-frame fit (default: the member of the transfer's family the data ask for,
        :func:`metrology.matching.instrument_family.fit_instrument_family`).
    batwing : (float, float), optional
        The calibration's batwing (amplitude, sigma_m), held beside ``transfer``.
    texture : bool
        Compute the surface texture (:func:`~metrology.matching.texture.field_texture`); a
        diagnosis, which does not report it, skips it (SurfaceTopography's import alone, with
        pandas, is about 1.4 s).

    Returns
    -------
    Comparison

    Raises
    ------
    DoeError
        The field is flat or does not register; or it shows another design, lies off the
        element or is turned by a quarter turn and ``force`` is False.
    """
    from masks.decompose import binary_depths_m

    from doedesign.camera import resolve_surround

    from metrology.matching.lattice import cell_depths, edge_span, register_lattice
    from metrology.matching.level import level_joint, level_on_top, remove_spikes
    from metrology.matching.instrument import Placement
    from metrology.matching.register import register

    def step(name):
        log.info("compare: %s", name)
        if progress is not None:
            progress.update(1, status=name)

    pitch = design.pitch_m
    n_masks = design.n_masks if n_masks is None else int(n_masks)
    n_levels = 2 ** n_masks
    levels = design_levels(design, n_levels)
    printed = printed_height_m(design, n_levels)
    step_m = design.level_step_m(n_levels)
    nominal = np.array(design.etch_depths_m() if n_levels == design.n_levels else binary_depths_m(step_m, n_masks))
    h, n_spikes = remove_spikes(measurement.height_m)
    first = level_on_top(h)
    check_relief(first.height_m, step_m)
    step("levelled on level 0")
    raster = bool(measurement.metadata.get("raster_scan"))
    lattice = None
    if resolve_surround(None, design.metadata, design.source_path or design.name)[0] == "repeat":
        # One cell of a lattice: registered modulo the lattice onto the cell tiled over the field.
        reg, levels, printed, found = register_lattice(first.height_m, levels, printed, pitch,
                                                       measurement.pixel_size_m, measurement.pixel_size_y_m)
        lattice = found.report(measurement.pixel_size_m, measurement.pixel_size_y_m)
        span = edge_span(levels[:design.shape[0], :design.shape[1]])
    else:
        reg = register(first.height_m, printed, pitch, pixel_size_m=measurement.pixel_size_m)
        span = 1
    step("registered")
    check = assess_match(first.height_m, printed, step_m, reg, scanned=raster, edge_span=span)
    if not check.ok:
        if not force:
            raise DoeError(f"{check.problem}; --force compares anyway")
        log.warning("%s (forced)", check.problem)
    match = check.report(force)
    labels = design_on_measurement(levels, reg)
    interior = interior_mask(labels, 1.0 / reg.decompose()["scale"])
    joint = level_joint(h, np.where(interior, labels, -1), line_offsets=raster)
    height = joint.height_m
    st = level_heights(height, labels, interior, n_levels)
    depth_fit = fit_etch_depths(st)
    step("level heights")
    edge = fit_edges(height, levels, reg, pitch, depth_fit.depths_m, n_masks)
    step("edge fit")
    err_design, _ = error_map(height, design_height_on_measurement(printed, reg))
    # Depths, overlay and bias in the camera's frame, started from the level and edge fits.
    placement = Placement.from_registration(shift_registration(reg, edge.shift_m[0], pitch))
    pixel_area = reg.pixel_size_m ** 2 / 12.0  # variance of the pixel box
    blur0 = float(np.sqrt(max(edge.sigma_m ** 2 - pixel_area, (0.2e-6) ** 2)))

    def camera_fit(start=None, blur0_m=blur0, **kw):
        s = start
        return fit_in_camera_frame(height, levels, placement, pitch, depth_fit.depths_m if s is None else s.depths_m,
                                   edge.overlay_m if s is None else s.overlay_m, edge.bias_m if s is None else s.bias_m,
                                   blur0_m=blur0_m,
                                   window_px=window_px, **kw)

    family = None
    if transfer is not None:
        inst = camera_fit(transfer=transfer, batwing=batwing)
    else:
        inst, family = fit_instrument_family(camera_fit, height, levels, pitch, reg.pixel_size_m)
    r0, r1, c0, c1 = inst.window_camera_px
    err_model = np.full(height.shape, np.nan)
    err_model[r0:r1, c0:c1] = inst.residual_m
    step("camera-frame fit")
    px = reg.pixel_size_m
    margin = max(TERRACE_MARGIN_PX, TERRACE_MARGIN_SIGMAS * edge.sigma_m / px)
    try:
        terrace = fit_terraces(height[r0:r1, c0:c1], labels[r0:r1, c0:c1], n_levels, margin, step_m,
                               pitch_px=1.0 / reg.decompose()["scale"])
        terrace_check = check_against(terrace, inst.depths_m, inst.depths_err_m)
    except DoeError as exc:
        terrace, terrace_check = None, {"agree": None, "warnings": [f"no terrace fit: {exc}"]}
    for line in terrace_check["warnings"]:
        log.warning("terrace fit against the camera-frame fit: %s", line)
    flat = flat_interiors(height, labels, margin, step_m, 1.0 / reg.decompose()["scale"])
    in_flat = flat[r0:r1, c0:c1] & np.isfinite(inst.residual_m)
    flat_rms = float(np.sqrt(np.mean(inst.residual_m[in_flat] ** 2))) if in_flat.any() else float("nan")
    surface = field_texture(height, labels, flat, err_design, px, pitch, n_levels) if texture else None
    have = st.count > 0
    roughness = float(np.sqrt(np.sum(st.count[have] * st.std_m[have] ** 2) / st.count[have].sum()))
    step("done")
    if lattice is not None and n_levels == 2:
        lattice["depth_per_cell"] = cell_depths(height, labels, interior, reg, design.shape)
    duty = duty_cycle(levels, labels, inst.bias_m, inst.bias_err_m, pitch, reg) if n_masks == 1 else None
    return Comparison(height_m=height, labels=labels, interior=interior, registration=reg, levelling=joint,
                      stats=st, depth_fit=depth_fit, edge_fit=edge, instrument_fit=inst, nominal_depths_m=nominal,
                      error_design_m=err_design, error_model_m=err_model, model_window=(r0, r1, c0, c1),
                      spikes_removed=n_spikes, roughness_m=roughness, match=match, lattice=lattice, duty_cycle=duty,
                      raster_scan=raster,
                      terrace_fit=terrace, terrace_check=terrace_check, texture=surface, instrument_family=family,
                      flat_residual_m=flat_rms)
