"""The height problem: a measured height map against the design through the process model.

Arrays are row-major with row 0 at the top; residuals are in metres.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

import numpy as np
import scipy.ndimage as ndi

from doedesign.errors import DoeError

from metrology.diagnosis.breakdown import binned, edge_breakdown, structure_groups
from metrology.diagnosis.effects import Effect, Parameter, apply_process, effects_for
from metrology.diagnosis.engine import DEFAULT_THRESHOLD, Problem, run_diagnosis
from metrology.diagnosis.noise import estimate_noise
from metrology.matching.instrument import ArrayCache
from metrology.matching.window import busiest_window

if TYPE_CHECKING:
    from doedesign.design import Design
    from masks.process_params import ProcessParams
    from metrology.diagnosis.budget import Deadline
    from metrology.diagnosis.engine import Diagnosis
    from metrology.formats.measurement import Measurement

__all__ = ["HeightProblem", "INTERIOR_MARGIN_M", "REGISTRATION", "diagnose_heights", "diagnose_measurement",
           "sampled_edge_distance_m", "signed_edge_distance_m"]

# Margin (m) around design edges excluded from the flat interiors used for the noise floor:
# wider than plausible overlay / bias slivers plus instrument blur.
INTERIOR_MARGIN_M = 1.6e-6
# Bytes of the masks' etches a problem keeps between its model evaluations (a 40 px window at
# 5 samples per pixel: 0.3 MB an etch).
ETCH_CACHE_BYTES = 64 * 2 ** 20


def _shift_all_masks(params, values):
    overlay = np.array(params.mask_overlay, dtype=float, copy=True)
    overlay[:, 0] += values[0]
    overlay[:, 1] += values[1]
    return params.copy(mask_overlay=overlay)


# A residual registration error of the measurement against the design moves every mask alike.
# It is a nuisance, always fitted (never named): registration is good to a fraction of a pixel.
REGISTRATION = Effect(
    "registration_shift", "height", "process",
    [Parameter(f"{ax}_m", "m", -2e-6, 2e-6, 0.2e-6) for ax in ("dx", "dy")], _shift_all_masks,
    "Residual shift of the registered measurement against the design (nuisance).", kind="calibration",
    order=-1)


def signed_edge_distance_m(mask: np.ndarray, step_m: float) -> np.ndarray:
    """Distance (m) of each pixel centre to the nearest edge of a boolean mask; positive inside."""
    inside = ndi.distance_transform_edt(mask) - 0.5
    outside = ndi.distance_transform_edt(~mask) - 0.5
    return np.where(mask, inside, -outside) * step_m


def sampled_edge_distance_m(mask: np.ndarray, ri: np.ndarray, ci: np.ndarray, fr: np.ndarray, fc: np.ndarray,
                            pitch_m: float) -> np.ndarray:
    """Distance (m) of points to the nearest edge of a boolean design-pixel mask, signed
    (positive inside): each point in design pixel (``ri``, ``ci``) at offset (``fr``, ``fc``)
    (design pixels, within +-0.5) from its centre; edges within one pixel (else 2 pixels)."""
    here = mask[ri, ci]
    rows, cols = mask.shape
    best = np.full(ri.shape, 2.0)
    for di in (-1, 0, 1):
        for dj in (-1, 0, 1):
            i, j = np.clip(ri + di, 0, rows - 1), np.clip(ci + dj, 0, cols - 1)
            other = mask[i, j] != here
            d = np.maximum(np.maximum(np.abs(fr - di) - 0.5, 0), np.maximum(np.abs(fc - dj) - 0.5, 0))
            best = np.where(other & (d < best), d, best)
    return np.where(here, best, -best) * pitch_m


class HeightProblem(Problem):
    """A measured height map against the design through the process model.

    Parameters
    ----------
    levels : ndarray of int (rows, cols)
        Design levels, row 0 at the top.
    pitch_m : float
    measured_height_m : ndarray
        The measurement on the fine model grid of ``region``: shape
        ``((row1 - row0) * u, (col1 - col0) * u)`` with ``u = pitch_m / step_m``; NaN = no data.
    step_m : float
    region : (row0, row1, col0, col1)
        Design pixels the measurement covers (half-open).
    base_params : ProcessParams
        The ideal process (the nominal etch depths).
    effects : list of Effect
    border_m : float
        Width excluded at the edges of the map (spectral filters see mirrored data there).
    fit_registration : bool
        Fit a residual shift of the whole pattern as a nuisance in every model.
    """

    units = "m"

    def __init__(self, levels: np.ndarray, pitch_m: float, measured_height_m: np.ndarray, step_m: float,
                 region: tuple[int, int, int, int], base_params: ProcessParams, effects: Sequence[Effect],
                 border_m: float = 3e-6, fit_registration: bool = True) -> None:
        from masks.decompose import levels_to_masks
        from masks.process import check_levels, fine_upsample

        self.levels = np.asarray(levels)
        # The masks' etches read the design checked once here (mask_etch's check reads it whole).
        self._checked_levels = check_levels(self.levels, base_params.n_masks)
        self.pitch_m = float(pitch_m)
        r0, r1, c0, c1 = (int(v) for v in region)
        self.region = (r0, r1, c0, c1)
        u = fine_upsample(pitch_m, step_m)
        if abs(pitch_m / u - step_m) > 1e-6 * step_m:
            raise DoeError(f"model grid step {step_m * 1e6:.4g} um must divide the design pitch "
                           f"{pitch_m * 1e6:.4g} um (resample the measurement first)")
        self.step_m = pitch_m / u
        self.upsample = u
        row0, row1, col0, col1 = self.region
        shape = ((row1 - row0) * u, (col1 - col0) * u)
        meas = np.asarray(measured_height_m, dtype=float)
        if meas.shape != shape:
            raise DoeError(f"measurement of shape {meas.shape} does not match the model grid {shape} "
                           f"of design region {self.region} at {u} samples per pixel")
        self.measured = meas
        self.base = base_params
        self.effects = {e.name: e for e in effects}
        if fit_registration:
            self.effects[REGISTRATION.name] = REGISTRATION
            self.nuisance = {REGISTRATION.name: REGISTRATION}
        b = int(np.ceil(border_m / self.step_m))
        keep = np.zeros(shape, dtype=bool)
        keep[b:shape[0] - b, b:shape[1] - b] = True
        self.valid = keep & np.isfinite(meas)
        if self.valid.sum() < 100:
            raise DoeError("the measurement has fewer than 100 valid pixels in the diagnosed region")
        # Design quantities on the fine grid, for the noise floor and the breakdown.
        lev = self.levels[row0:row1, col0:col1]
        self.fine_levels = np.repeat(np.repeat(lev, u, axis=0), u, axis=1)
        masks = levels_to_masks(lev, len(base_params.etch_depth))
        self.fine_masks = np.repeat(np.repeat(masks, u, axis=1), u, axis=2)
        self.edge_m = np.stack([signed_edge_distance_m(m, self.step_m) for m in self.fine_masks])
        self.any_edge_m = np.min(np.abs(self.edge_m), axis=0)
        m = int(np.ceil(INTERIOR_MARGIN_M / self.step_m))
        flat = (ndi.maximum_filter(self.fine_levels, size=2 * m + 1)
                == ndi.minimum_filter(self.fine_levels, size=2 * m + 1)) & self.valid
        groups, _ = ndi.label(flat)
        self.noise = estimate_noise(meas, groups)
        self._etches = ArrayCache(ETCH_CACHE_BYTES, max_items=64)
        # The etch loading's pattern density per window and mask (mask_etch's density_cache).
        self._densities: dict = {}

    def surface(self, model: dict[str, np.ndarray]) -> np.ndarray:
        """Model height map (m) on the fine grid with the effects in ``model`` applied."""
        chosen = sorted((self.effects[n] for n in model),
                        key=lambda e: (("process", "surface").index(e.stage), e.order))
        h = self.process_surface(apply_process(self.base, chosen, model))
        for e in chosen:
            if e.stage == "surface":
                h = e.apply(h, e.check(model[e.name]), self.step_m)
        return h

    def process_surface(self, params: ProcessParams) -> np.ndarray:
        """:func:`masks.process.simulate_surface` of the region, bit for bit, from the masks'
        etches (:func:`masks.process.mask_etch`) kept between calls: a fit's step or Jacobian
        column that moves one mask recomputes that mask only, and a mask's etch that is
        proportional to its depth (no loading, gradient or trench) is kept at unit depth, so a
        change of depth costs a product (the same product ``simulate_surface`` forms)."""
        from masks.process import finish_surface

        if params.roughness > 0:
            from masks.process import simulate_surface

            return simulate_surface(self.levels, self.pitch_m, params, step_m=self.step_m,
                                    region=self.region).height_m
        # Fine pixels beyond the region: the sidewall ramp's reach (a box of that width).
        pad = int(math.ceil(params.sidewall_slope / self.step_m / 2)) + 2
        row0, row1, col0, col1 = self.region
        height = np.zeros(((row1 - row0) * self.upsample + 2 * pad, (col1 - col0) * self.upsample + 2 * pad))
        for j in range(params.n_masks):
            height -= self._etch(params, j, pad)
        return finish_surface(height, params, self.step_m, pad)

    def _etch(self, params, mask, pad):
        """Mask ``mask``'s etch (m, >= 0) on the region padded by ``pad`` fine pixels, cached."""
        from masks.process import etch_key, mask_etch

        key = etch_key(params, mask)
        depth = float(params.etch_depth[mask])
        linear = params.etch_loading == 0 and not np.any(params.etch_gradient) and params.microtrenching[mask][0] <= 0
        if linear:
            # The key without the depth (etch_key's third entry): the etch at unit depth.
            key = ("unit",) + key[:2] + key[3:]
        key = (key, pad)
        etch = self._etches.get(key)
        if etch is None:
            if linear:
                depths = np.array(params.etch_depth, dtype=float)
                depths[mask] = 1.0
                params = params.copy(etch_depth=depths)
            etch = mask_etch(self._checked_levels, self.pitch_m, params, mask, step_m=self.step_m,
                             region=self.region, pad_px=pad, levels_checked=True, density_cache=self._densities)
            self._etches.put(key, etch)
        return etch * depth if linear else etch

    def residual(self, model: dict[str, np.ndarray]) -> np.ndarray:
        r = self.measured[self.valid] - self.surface(model)[self.valid]
        # The measurement's height zero is arbitrary: a piston is always removed (1 dof).
        return r - r.mean()

    def residual_map(self, model: dict[str, np.ndarray]) -> np.ndarray:
        out = np.full(self.measured.shape, np.nan)
        out[self.valid] = self.residual(model)
        return out

    def structure_groups(self) -> list[np.ndarray]:
        """Level x distance to the nearest edge (edge effects), level x 4 x 4 tiles of the field
        (density and position effects), and signed distance to each mask's edges."""
        return structure_groups(self.fine_levels, self.any_edge_m, self.edge_m, self.valid)

    def breakdown(self, residual_map: np.ndarray) -> dict[str, dict]:
        """Residual by signed distance to each mask's edges, level, density, position, frequency."""
        out = edge_breakdown(residual_map, self.edge_m, self.fine_levels, self.step_m)
        sigma_px = 50e-6 / self.step_m
        density = ndi.gaussian_filter(self.fine_masks.mean(axis=0).astype(float), sigma_px, mode="reflect")
        out["pattern_density"] = binned(residual_map, density, np.linspace(0, 1, 11))
        return out


def diagnose_heights(design_levels: np.ndarray, pitch_m: float, measured_height_m: np.ndarray, step_m: float,
                     region: tuple[int, int, int, int] | None = None, region_px: int = 40,
                     depths_m: Sequence[float] | None = None, candidates: Sequence[str] | None = None,
                     threshold: float = DEFAULT_THRESHOLD, max_steps: int = 6,
                     stop_at_floor: bool = True, limit: Deadline | None = None) -> Diagnosis:
    """Find, name and fit the effects that explain a measured height map.

    Parameters
    ----------
    design_levels : ndarray of int (rows, cols)
        The design's levels (0 = top surface), row 0 at the top.
    pitch_m : float
        Design pixel pitch.
    measured_height_m : ndarray
        Measured heights (m, z up) registered onto the fine model grid: fine pixel (a, b) of
        the map covers design coordinates ``row0 + (a + 0.5) / u - 0.5`` (likewise columns),
        ``u = pitch_m / step_m``. It covers either the whole design or ``region``.
    step_m : float
        Fine-grid spacing of the measurement; must divide ``pitch_m``.
    region : (row0, row1, col0, col1), optional
        Design pixels the measurement covers. Default: the whole design.
    region_px : int
        The diagnosis fits the window of at most this many design pixels per side that holds
        the most level edges (each model evaluation then costs milliseconds).
    depths_m : sequence of float, optional
        Nominal etch depths per mask (default: 75, 150, 300, 600 nm).
    candidates : list of str, optional
        Effects to try (default: every registered height-domain effect).
    threshold : float
        Criterion drop required to name an effect.
    max_steps : int
    stop_at_floor : bool
        Stop when the residual reaches the noise floor (default) or only on the criterion.
    limit : Deadline, optional
        A limit the user asked for (:func:`~metrology.diagnosis.engine.run_diagnosis`; default none).

    Returns
    -------
    Diagnosis
    """
    from masks.process import ProcessParams, fine_upsample

    levels = np.asarray(design_levels)
    if levels.ndim != 2:
        raise DoeError(f"design levels must be a 2-D array, got shape {levels.shape}")
    u = fine_upsample(pitch_m, step_m)
    meas = np.asarray(measured_height_m, dtype=float)
    if region is None:
        region = (0, levels.shape[0], 0, levels.shape[1])
    row0, row1, col0, col1 = (int(v) for v in region)
    if meas.shape != ((row1 - row0) * u, (col1 - col0) * u):
        raise DoeError(f"measurement of shape {meas.shape} does not cover design region {tuple(region)} "
                       f"at {u} samples per {pitch_m * 1e6:.3g} um pixel (expected "
                       f"{((row1 - row0) * u, (col1 - col0) * u)})")
    sub = busiest_window(levels[row0:row1, col0:col1], region_px)
    meas = meas[sub[0] * u:sub[1] * u, sub[2] * u:sub[3] * u]
    window = (row0 + sub[0], row0 + sub[1], col0 + sub[2], col0 + sub[3])
    base = ProcessParams.ideal(depths_m=depths_m) if depths_m is not None else ProcessParams.ideal()
    problem = HeightProblem(levels, pitch_m, meas, step_m, window, base,
                            effects_for("height", candidates, n_masks=base.n_masks))
    diag = run_diagnosis(problem, threshold=threshold, max_steps=max_steps, domain="height",
                         stop_at_floor=stop_at_floor, limit=limit)
    diag.map_step_m = problem.step_m
    return diag


def diagnose_measurement(design: Design, measurement: Measurement, region_px: int = 40, upsample: int = 5,
                         depths_m: Sequence[float] | None = None, candidates: Sequence[str] | None = None,
                         threshold: float = DEFAULT_THRESHOLD, source: str = "measurement",
                         force: bool = False, limit: Deadline | None = None) -> tuple[Diagnosis, dict[str, Any]]:
    """Diagnose a profilometer measurement of a design: prepare, register, choose the window.

    The comparison's preparation (despiked, levelled jointly on the registered levels,
    registered with the edge fit's sub-pixel refinement of the whole pattern's position), then
    :func:`diagnose_heights` on the window of the design best covered by the measurement.

    Parameters
    ----------
    design : Design
    measurement : Measurement
        As read by :func:`metrology.formats.readers.read_measurement`.
    region_px : int
        Design pixels per side of the window diagnosed (at least 8).
    upsample : int
        Model samples per design pixel per axis.
    depths_m : sequence of float, optional
        Nominal etch depths per mask (the ideal model; default :func:`masks.decompose.process_depths_m`).
    candidates : list of str, optional
    threshold : float
    source : str
        Name of the measurement in error messages (its file).
    force : bool
        Diagnose even when the field does not show the design (see :mod:`metrology.matching.match`).
    limit : Deadline, optional
        A limit the user asked for (:func:`diagnose_heights`; default none).

    Returns
    -------
    (Diagnosis, dict)
        The diagnosis and its inputs: the window (``region_design_px``, half-open design pixels,
        row 0 at the top), ``upsample``, ``registration_ncc`` and ``nominal_depths_m``.
    """
    from doedesign.levels import design_levels
    from masks.decompose import process_depths_m
    from metrology.matching.compare import compare_measurement, shift_registration
    from metrology.matching.register import resample_to_design

    if region_px < 8:
        raise DoeError(f"--region-px must be at least 8, got {region_px}")
    if upsample < 1:
        raise DoeError(f"--upsample must be a positive integer, got {upsample}")
    try:
        comp = compare_measurement(measurement, design, force=force, texture=False)
    except DoeError as exc:
        raise DoeError(f"{source}: {exc}") from None
    levelled = comp.height_m
    reg = shift_registration(comp.registration, comp.edge_fit.shift_m[0], design.pitch_m)
    coverage = np.isfinite(resample_to_design(levelled, reg, upsample=1))
    if coverage.sum() < 64:
        raise DoeError(f"{source}: the measurement covers only {int(coverage.sum())} design pixels after registration")
    rows, cols = np.nonzero(coverage)
    size = min(region_px, rows.max() - rows.min() + 1, cols.max() - cols.min() + 1)
    r0 = int(np.clip(round(rows.mean() - size / 2), 0, design.shape[0] - size))
    c0 = int(np.clip(round(cols.mean() - size / 2), 0, design.shape[1] - size))
    region = (r0, r0 + size, c0, c0 + size)
    fine = resample_to_design(levelled, reg, upsample=upsample, region=region)
    depths = process_depths_m(design, depths_m, source)
    diag = diagnose_heights(design_levels(design), design.pitch_m, fine, design.pitch_m / upsample,
                            region=region, region_px=size, depths_m=depths, candidates=candidates,
                            threshold=threshold, limit=limit)
    return diag, {"region_design_px": list(region), "upsample": upsample,
                  "registration_ncc": getattr(reg, "match_ncc", None), "nominal_depths_m": depths,
                  "match": comp.match}
