"""Diagnosis in the camera's frame: the measurement model is part of the fitted model.

The measured heights stay on the profilometer's own pixels (never resampled or smoothed). The
model (design + process effects) is rendered into those pixels by
:class:`metrology.matching.instrument.InstrumentModel`: the instrument's lateral transfer
(fitted: :mod:`metrology.diagnosis.camera_nuisance`) under the placement (rotation, per-axis
scale, shift, mirror); piston and tilt are projected out. The placement and the transfer are
nuisance parameters refitted with every model (started from the registration), so the
fabrication effects are judged on what the instrument leaves. The diagnosis that fits this
problem (window, instrument stage, selection passes) is
:func:`metrology.diagnosis.camera_diagnosis.diagnose_camera`.

Arrays are row-major with row 0 at the top of the camera image.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Sequence
from dataclasses import replace
from typing import TYPE_CHECKING, Any

import numpy as np
import scipy.ndimage as ndi

from doedesign.errors import DoeError
from masks.process import design_centre, etch_key, mask_motion, surface_key, without_motion
from metrology.diagnosis import engine as dg
from metrology.diagnosis.breakdown import edge_breakdown, instrument_signature, structure_groups
from metrology.diagnosis.camera_nuisance import (BATWING, CAMERA, DEFAULT_TRANSFER, OBJECTIVE, PLACED,
                                                 placement_report)
from metrology.diagnosis.effects import Effect, get_effect
from metrology.diagnosis.heights import INTERIOR_MARGIN_M, sampled_edge_distance_m
from metrology.diagnosis.noise import NoiseEstimate, estimate_noise
from metrology.diagnosis.parallel import parallel_map
from metrology.diagnosis.tiles import TILE_MARGIN_PX
from metrology.matching.instrument import ETCH_CACHE_BYTES, ArrayCache, InstrumentModel, Placement
from metrology.matching.level import Leveller
from metrology.matching.transfer import LateralTransfer
from metrology.matching.window import busiest_camera_window

if TYPE_CHECKING:
    from masks.process_params import ProcessParams

__all__ = ["CAMERA", "SUBSUMED", "CameraHeightProblem"]

log = logging.getLogger(__name__)

_UM = 1e-6
# Memory kept for rendered camera maps, as much for the masks' spectra (and a quarter of it for
# fine surfaces) between renders: on a whole 512 px field, one model's four masks (110 MB each).
RENDER_CACHE_BYTES = 640 * 2 ** 20
# Fields larger than this (pixels per side) render in blocks of about RENDER_BLOCK_PX (_render_blocked).
BLOCKED_FIELD_PX = 256
RENDER_BLOCK_PX = 128
# Sampled maps a problem keeps (:meth:`CameraHeightProblem._sampled`): a model's groups (one per
# mask motion, at most one per mask) and a Jacobian's columns' new ones beside them.
SAMPLES_KEPT = 32
# Effects the camera model already holds (the blur is part of its kernel).
SUBSUMED = ("instrument_blur",)


class CameraHeightProblem(dg.Problem):
    """Measured camera heights against the design through process and instrument models.

    Parameters
    ----------
    levels : ndarray of int (rows, cols)
        Design levels, row 0 at the top.
    pitch_m : float
    measured_height_m : ndarray
        Camera heights (m), NaN = invalid; row 0 at the top of the camera image.
    placement : Placement
        Starting placement (from the registration).
    base_params : ProcessParams
    effects : list of Effect
    step_m : float
        Fine-grid spacing of the process model.
    curvature : bool
        Also project out a curvature term in the levelling.
    keep : ndarray of bool, optional
        Pixels compared (default: the finite ones).
    noise : NoiseEstimate, optional
        The measurement's noise floor, when already estimated on a better model's residual
        (default: estimated here on the residual against ``base_params``).
    instrument : InstrumentModel, optional
        The measurement model of another problem on the same crop and placement (its etches shared).
    centre_px : (float, float), optional
        Camera pixel about which the placement is refined (default: the crop's centre; a screening
        crop uses its window's, so both read the nuisance values alike).
    cache_bytes : int
        Memory for rendered camera maps, as much for the masks' spectra, a quarter for fine surfaces.
    transfer : LateralTransfer, optional
        A calibrated lateral transfer, held fixed (only the placement fitted); default: fitted (blur,
        fill factor, the objective's NA with ``objective``; the rest from :data:`~metrology.diagnosis.camera_nuisance.DEFAULT_TRANSFER`).
    objective : bool
        Fit the objective's NA-limited transfer (:data:`~metrology.diagnosis.camera_nuisance.OBJECTIVE`) as a nuisance too.
    batwing : bool or (float, float)
        True: fit the batwing (the registered ``batwing`` effect) as a nuisance of the
        instrument, not as a candidate; (amplitude, sigma_m): a calibration's, held.
    """

    units = "m"
    judges_partial_matches = True
    parallel_fits = True

    def __init__(self, levels: np.ndarray, pitch_m: float, measured_height_m: np.ndarray, placement: Placement,
                 base_params: ProcessParams, effects: Sequence[Effect], step_m: float | None = None,
                 curvature: bool = False, keep: np.ndarray | None = None,
                 noise: NoiseEstimate | None = None, instrument: InstrumentModel | None = None,
                 centre_px: Sequence[float] | None = None, cache_bytes: int = RENDER_CACHE_BYTES,
                 transfer: LateralTransfer | None = None,
                 objective: bool = False, batwing: bool | Sequence[float] = False) -> None:
        from masks.decompose import levels_to_masks

        self.levels = np.asarray(levels)
        self.pitch_m = float(pitch_m)
        self.measured = np.asarray(measured_height_m, float)
        self.placement = placement
        self.centre_px = (np.asarray(self.measured.shape, float) - 1) / 2 if centre_px is None else centre_px
        self.screening = None
        kw: dict[str, Any] = {} if step_m is None else {"step_m": step_m}
        self.instrument = instrument or InstrumentModel(self.levels, pitch_m, self.measured.shape, placement, **kw)
        self.base = base_params
        self.batwing = batwing if isinstance(batwing, bool) else tuple(float(v) for v in batwing)
        self.held = {BATWING: np.array(self.batwing)} if not isinstance(batwing, bool) else {}
        self.effects = {e.name: e for e in effects if e.name not in SUBSUMED + (OBJECTIVE.name, *self.held)}
        self.fixed_transfer = transfer
        self.transfer0 = transfer if transfer is not None else DEFAULT_TRANSFER
        self.objective = bool(objective) and transfer is None
        self.effects[CAMERA.name] = CAMERA if transfer is None else PLACED
        self.nuisance = {CAMERA.name: self.effects[CAMERA.name]}
        if self.objective:
            self.effects[OBJECTIVE.name] = self.nuisance[OBJECTIVE.name] = OBJECTIVE
        if self.batwing is True:
            self.effects[BATWING] = self.nuisance[BATWING] = get_effect(BATWING)
        self.curvature = curvature
        self.keep = np.isfinite(self.measured) if keep is None else np.asarray(keep, bool)
        if self.keep.sum() < 100:
            raise DoeError("the measurement has fewer than 100 valid pixels in the diagnosed field")
        self.leveller = Leveller(self.measured.shape, self.keep, curvature)
        # Bytes bound a large field's caches, counts a small window's (fits revisit dozens of maps).
        self._fine = ArrayCache(cache_bytes // 4, max_items=2)
        self._coeffs = ArrayCache(cache_bytes, max_items=32)
        self._spectra = ArrayCache(cache_bytes, max_items=24)
        self._factors = ArrayCache(cache_bytes, max_items=12)
        self._factor_reach: dict[Any, Any] = {}
        self._lock = threading.Lock()  # the factors and their reach change together
        # Design quantities at each camera pixel (nearest design pixel): noise, structure, breakdown.
        r, c = placement.to_design(*np.mgrid[:self.measured.shape[0], :self.measured.shape[1]].astype(float))
        ri = np.clip(np.rint(r).astype(int), 0, self.levels.shape[0] - 1)
        ci = np.clip(np.rint(c).astype(int), 0, self.levels.shape[1] - 1)
        self.cam_levels = self.levels[ri, ci]
        masks = levels_to_masks(self.levels, len(base_params.etch_depth))
        # Distance (m) of each camera pixel centre to the nearest edge of each mask, signed
        # (positive inside the opening), from the design pixel geometry.
        fr, fc = r - np.rint(r), c - np.rint(c)
        self.edge_m = np.stack([sampled_edge_distance_m(m, ri, ci, fr, fc, self.pitch_m) for m in masks])
        self.any_edge_m = np.min(np.abs(self.edge_m), axis=0)
        self.pixel_m = self.pitch_m * float(np.sqrt(abs(np.linalg.det(placement.matrix))))
        self._noise = noise
        self._maps = ArrayCache(cache_bytes, max_items=4)
        # Each motion group's sampled map under its placement (:meth:`_render_masks`): a Jacobian
        # column that moves or changes one mask resamples that mask's group only.
        self._samples = ArrayCache(cache_bytes // 8, max_items=SAMPLES_KEPT)

    @property
    def noise(self) -> NoiseEstimate:
        """The measurement's noise floor: the one given, or estimated (on first use) on the
        flat interiors of the residual against the base process, the nuisances at their starts."""
        if self._noise is None:
            self._noise = self.noise_at({CAMERA.name: self.effects[CAMERA.name].start_values()})
        return self._noise

    @noise.setter
    def noise(self, value: NoiseEstimate) -> None:
        self._noise = value

    def noise_at(self, model: dict[str, np.ndarray]) -> NoiseEstimate:
        """The noise floor on the flat interiors (each about its plane) of the residual to ``model``."""
        flat = (self.any_edge_m > INTERIOR_MARGIN_M) & self.keep
        groups, _ = ndi.label(flat & (self.cam_levels >= 0))
        first = self.measured - self.render(model)
        levelled = np.full(first.shape, np.nan)
        levelled[self.keep] = self.leveller(first[self.keep])
        return estimate_noise(np.where(self.keep, levelled, np.nan), np.where(self.keep, groups, 0), trend="plane")

    def render(self, model: dict[str, np.ndarray]) -> np.ndarray:
        """Model heights in the camera frame (before levelling).

        Each mask's etch is rendered in place and sampled under the camera's placement taken into
        that mask's frame (its overlay and rotation, :meth:`Placement.in_frame_of <metrology.matching.placement.Placement.in_frame_of>`): a change of
        placement or of a mask's motion costs a spline sampling, not a new surface. Blur, pixel box,
        sidewall ramp and linear surface effects commute with the sum of the masks and with their
        motions; a non-linear surface effect, roughness, or a motion that would sample beyond the
        rendered window sends the render through the summed fine surface instead.
        """
        if max(self.measured.shape) > BLOCKED_FIELD_PX:
            return self._render_blocked(model)
        cam = np.asarray(model.get(CAMERA.name, self.effects[CAMERA.name].start_values()), float)
        model = {**self.held, **model}
        chosen = sorted((self.effects.get(n) or get_effect(n) for n in model if n not in (CAMERA.name, OBJECTIVE.name)),
                        key=lambda e: (("process", "surface").index(e.stage), e.order))
        params = self.base
        for e in chosen:
            if e.stage == "process":
                params = e.apply(params, e.check(model[e.name]))
        surface = [e for e in chosen if e.stage == "surface"]
        surface_values = tuple((e.name, tuple(np.asarray(model[e.name], float))) for e in surface)
        blur = self.transfer_of(model)
        placement = self.placement.refined(cam[:5], self.measured.shape, self.centre_px)
        if params.roughness == 0 and all(e.linear for e in surface):
            centre = design_centre(self.levels.shape)
            motions = [mask_motion(params, j, self.pitch_m) for j in range(params.n_masks)]
            moved = {m: placement.in_frame_of(*m, centre) for m in motions}
            if all(self.instrument.covers(pl, blur) for pl in moved.values()):
                out = self._render_masks(without_motion(params), surface, model, surface_values, blur, motions,
                                         moved)
                if out is not None:
                    return out
        # Keyed by the process the model amounts to (a candidate at its null start renders what
        # the model without it does) and the surface effects.
        key = (surface_key(params), surface_values)
        # By stage: the placement only resamples the camera map, the blur only remakes it from
        # the fine surface, and only process parameters remake that surface.
        coeffs = self._coeffs.get((key, blur))
        if coeffs is None:
            # An instrument's edge response beside its objective (a batwing) is mapped without
            # the objective's transfer and added (:meth:`InstrumentModel.map_of`).
            apart = [e for e in surface if e.beside_objective] if blur.na > 0 else []
            fine = self._fine.get((key, bool(apart)))
            if fine is None:
                fine = self.instrument.fine_surface(params)
                for e in surface:
                    if e not in apart:
                        fine = e.apply(fine, e.check(model[e.name]), self.instrument.step_m)
                self._fine.put((key, bool(apart)), fine)
            coeffs = self.instrument.camera_map(fine, blur)
            if apart:
                edge = sum(e.apply(fine, e.check(model[e.name]), self.instrument.step_m) - fine for e in apart)
                coeffs = coeffs + self.instrument.camera_map(edge, replace(blur, na=0.0))
            self._coeffs.put((key, blur), coeffs)
        return self.instrument.sample(coeffs, placement)

    def transfer_of(self, model: dict[str, np.ndarray]) -> LateralTransfer:
        """The lateral transfer of ``model``: its camera nuisance's blur and fill factor and its
        objective's NA where it holds them, else this problem's (calibrated or default) ones."""
        cam = np.asarray(model.get(CAMERA.name, ()), float)
        t = self.transfer0
        na = float(np.asarray(model[OBJECTIVE.name])[0]) if OBJECTIVE.name in model else t.na
        return LateralTransfer(cam[5] if cam.size > 5 else t.sigma_m, cam[6] if cam.size > 6 else t.fill_factor,
                               na, t.wavelength_m)

    def _render_masks(self, still, surface, model, surface_values, blur, motions, placements):
        """The masks printed in place (``still``), each group that shares a motion summed in the
        Fourier domain into one camera map, sampled under that motion's placement. Spectra are kept
        per mask, maps per group and blur (a change of blur: one inverse FFT per group; of motion: a
        sampling). A Fourier transfer (a batwing) multiplies the maps' spectra; any other surface
        effect acts on each mask's fine surface."""
        step = self.instrument.step_m
        factors, beside, direct = [], [], []
        reach = self.instrument.fourier_reach(placements.values(), blur) if surface else 0
        for e in surface:
            factor = self._fourier_factor(e, model[e.name], reach) if e.fourier is not None else None
            if factor is None:
                direct.append(e)
            else:
                (beside if e.beside_objective else factors).append(factor)
        if blur.na > 0 and any(e.beside_objective for e in direct):
            # An edge response beside the objective that the FFT grid cannot hold: the whole
            # surface's route keeps it out of the objective's transfer.
            return None
        direct_values = tuple((e.name, tuple(np.asarray(model[e.name], float))) for e in direct)
        out = np.zeros(self.measured.shape)
        for motion in dict.fromkeys(motions):
            group = [j for j, m in enumerate(motions) if m == motion]
            keys = tuple((etch_key(still, j), still.sidewall_slope, direct_values) for j in group)
            coeffs = self._coeffs.get((keys, blur, surface_values))
            if coeffs is None:
                spectra = []
                for j, key in zip(group, keys):
                    spectrum = self._spectra.get(key)
                    if spectrum is None:
                        if direct:
                            fine = self.instrument.mask_surface(still, j)
                            for e in direct:
                                fine = e.apply(fine, e.check(model[e.name]), step)
                            spectrum = self.instrument.spectrum(fine)
                        else:
                            spectrum = self.instrument.mask_spectrum(still, j)
                        self._spectra.put(key, spectrum)
                    spectra.append(spectrum)
                coeffs = self.instrument.map_of(spectra, blur, factors=factors, beside=beside)
                self._coeffs.put((keys, blur, surface_values), coeffs)
            out += self._sampled(coeffs, (keys, blur, surface_values), placements[motion])
        return out

    def _sampled(self, coeffs, key, placement):
        """``self.instrument.sample(coeffs, placement)``, kept per map ``key`` and placement (the
        same numbers: a group a model step leaves alone is not sampled again)."""
        key = (key, placement.matrix.tobytes(), placement.offset.tobytes())
        values = self._samples.get(key)
        if values is None:
            values = self.instrument.sample(coeffs, placement)
            values.flags.writeable = False
            self._samples.put(key, values)
        return values

    def _fourier_factor(self, effect, values, reach):
        """``effect``'s transfer on the instrument's FFT grid, or None when its taps reach
        further than ``reach`` cells (the effect finds that out before computing anything);
        kept for the last few values, with the reach it was made for."""
        key = (effect.name, tuple(np.asarray(values, float)))
        with self._lock:
            factor, made_for = self._factors.get(key), self._factor_reach.get(key, reach)
        if factor is None or reach < made_for:
            wr, wc = self.instrument.fourier_grid()
            factor = effect.fourier(effect.check(values), self.instrument.step_m, wr, wc, reach)
            if factor is not None:
                with self._lock:  # the reach of the factors still kept only
                    self._factors.put(key, factor)
                    self._factor_reach = {k: r for k, r in self._factor_reach.items() if k in self._factors}
                    self._factor_reach[key] = reach
        return factor

    def residual(self, model: dict[str, np.ndarray]) -> np.ndarray:
        return self.leveller(self.measured[self.keep] - self.render(model)[self.keep])

    def crop(self, size_px: int) -> CameraHeightProblem:
        """The same problem on the ``size_px`` square of its window with the most design edges
        (same process, effects, noise floor and placement frame), to screen candidates on."""
        r0, c0 = busiest_camera_window(self.levels, self.placement, self.measured.shape, size_px)
        log.info("candidates screened on the %d px camera window at (%d, %d)", min(size_px, *self.measured.shape), r0, c0)
        return self.sub(r0, c0, size_px)

    def sub(self, r0: int, c0: int, size_px: int, margin_px: int | None = None,
            transfers: ArrayCache | None = None, share: int = 1) -> CameraHeightProblem:
        """The same problem on the ``size_px`` square of its window from camera pixel (r0, c0):
        same process, effects, noise floor and placement frame (a refinement of the whole field
        places the part alike). ``margin_px``: design pixels its instrument renders around it;
        ``transfers``: a Fourier-transfer store shared with the field's other parts; ``share``:
        how many parts share the memory budgets of its caches."""
        size = min(size_px, *self.measured.shape)
        return self._part(slice(r0, r0 + size), slice(c0, c0 + size), margin_px, transfers, share, self.noise)

    def _part(self, rows, cols, margin_px, transfers, share, noise, keep=None):
        """:meth:`sub` on the camera pixels ``rows`` x ``cols`` (slices); ``keep``: its pixels (default: the field's)."""
        r0, c0 = rows.start, cols.start
        shape = (rows.stop - r0, cols.stop - c0)
        start = Placement(self.placement.matrix, self.placement.offset + self.placement.matrix @ np.array([r0, c0], float))
        instrument = self.instrument.part(shape, start) if margin_px is None else None
        if margin_px is not None:
            instrument = InstrumentModel(self.levels, self.pitch_m, shape, start, step_m=self.instrument.step_m,
                                         margin_px=margin_px, transfers=transfers,
                                         cache_bytes=ETCH_CACHE_BYTES // max(share, 1))
        return CameraHeightProblem(self.levels, self.pitch_m, self.measured[rows, cols], start, self.base,
                                   [e for n, e in self.effects.items() if n not in self.nuisance],
                                   step_m=self.instrument.step_m, curvature=self.curvature,
                                   keep=self.keep[rows, cols] if keep is None else keep, noise=noise,
                                   instrument=instrument, centre_px=np.asarray(self.centre_px, float) - [r0, c0],
                                   cache_bytes=RENDER_CACHE_BYTES // max(share, 1), transfer=self.fixed_transfer,
                                   objective=self.objective, batwing=self.batwing)

    def _render_blocked(self, model):
        """:meth:`render` of a large field in blocks of about :data:`RENDER_BLOCK_PX` pixels, each on
        its own fine grid with a margin past the kernel's reach and a placement refinement (the
        stitched map is the whole field's to the FFTs' rounding), side by side in worker threads.
        They keep nothing: a field is rendered once per model (its map is kept for a few), and here
        each array kept in a cache would come from fresh pages the kernel zeroes (100-200 MB)."""
        key = tuple((name, tuple(np.asarray(v, float).ravel())) for name, v in sorted(model.items()))
        out = self._maps.get(key)
        if out is None:
            rows, cols = self.measured.shape
            edges = [np.linspace(0, n, -(-n // RENDER_BLOCK_PX) + 1).round().astype(int) for n in (rows, cols)]
            blocks = [(slice(int(r0), int(r1)), slice(int(c0), int(c1)))
                      for r0, r1 in zip(edges[0][:-1], edges[0][1:]) for c0, c1 in zip(edges[1][:-1], edges[1][1:])]
            transfers = InstrumentModel.transfer_cache()
            keep = np.ones(self.measured.shape, bool)

            def block_map(block):
                part = self._part(*block, TILE_MARGIN_PX, transfers, 1, self._noise, keep=keep[block])
                return part.render(model)

            out = np.empty(self.measured.shape)
            for block, part_map in zip(blocks, parallel_map(block_map, blocks)):
                out[block] = part_map
            out.flags.writeable = False
            self._maps.put(key, out)
        return out

    def residual_map(self, model: dict[str, np.ndarray]) -> np.ndarray:
        out = np.full(self.measured.shape, np.nan)
        out[self.keep] = self.residual(model)
        return out

    def structure_groups(self) -> list[np.ndarray]:
        """Level x edge distance, level x 4 x 4 field tiles, signed distance to two masks' edges."""
        return structure_groups(self.cam_levels, self.any_edge_m, self.edge_m, self.keep)

    def breakdown(self, residual_map: np.ndarray) -> dict[str, dict]:
        """Residual by signed distance to each mask's edges, level, field position, frequency."""
        return edge_breakdown(residual_map, self.edge_m, self.cam_levels, self.pixel_m)

    def instrument_signature(self, residual_map: np.ndarray, **kw: Any) -> dict | None:
        """Whether the residual is the instrument's (:func:`.breakdown.instrument_signature`, ``kw``)."""
        return instrument_signature(residual_map, self.edge_m, self.base.etch_depth, self.keep, self.noise.sigma,
                                    self.noise.corr_area_px, **kw)

    def placement_report(self, model: dict[str, np.ndarray], errors: dict[str, np.ndarray] | None = None) -> dict:
        """The refined placement and the lateral transfer, with uncertainties (NaN where held)."""
        return placement_report(self, model, errors)
