"""The measurement model: the model surface as the profilometer's camera would report it.

A white-light interferometer blurs the surface through its objective, and each camera pixel
reports the mean height over its footprint on the sample; the field sits rotated, shifted and
possibly mirrored against the design, at a lateral scale known to a fraction of a percent.
This module renders the model into the camera's own pixel grid, so that model and data are
compared pixel by pixel and the data are never resampled or smoothed.

Method (one measurement model for ``doe compare`` and ``doe diagnose`` alike):

1. The model surface (design + process effects, :func:`masks.process.simulate_surface`) on a
   fine grid in the design frame (``pitch / ceil(pitch / 0.2 um)``) over the design pixels
   the camera field covers, unetched (0) outside the design. Step 2 treats each fine cell as
   uniform; an edge inside a cell (bias, overlay, rotation) or a sidewall's slope is not, so
   the cells carry their first moments into their neighbours
   (:func:`masks.moments.moment_corrected`). Against a 0.03 um grid, camera renders of an
   element with 80 nm biased edges differ by 0.25-0.65 nm rms at 0.2 um with the moments,
   1.1-2.9 nm without (0.3-0.9 nm at the former 0.125 um step); overlays by up to 0.39 nm
   (1.8), bias and overlay together 0.71 (4.0); a 0.3 um sidewall ramp by 0.01-0.23 nm
   (0.65-1.7 without); a 0.3 um batwing by 0.05-0.3 nm, the ideal element by up to 0.1 nm
   (point sampling's); 2-5 times more at 0.25 um.
   A render from nothing cached costs 0.4-0.5 of the 0.125 um step's without moments
   (``benchmarks/bench_fine_step.py``, ``tests/metrology/test_instrument.py``).
2. One kernel on that fine grid holds both the objective blur and the pixel footprint (the
   lateral transfer's family, fitted: fill factor, Gaussian blur, NA-limited objective,
   :mod:`metrology.matching.transfer`):
   ``K(a) = mean over the footprint y of integral over fine cell a of G_sigma(x - y)``, where
   the footprint is the camera pixel mapped into the design frame by the placement (a
   parallelogram: rotation, per-axis scale, mirror). Correlating the fine surface with ``K``
   gives, at every fine cell, the value a camera pixel centred there would report. Under an
   objective, ``K``'s continuous spectrum times the objective's transfer is used instead: the
   objective cuts the cells' spectral repeats that the discrete kernel's spectrum folds in.
3. That map is sampled at each camera pixel centre by a cubic spline (the map is smooth there:
   a step has been through the pixel box and the blur), so a change of placement costs one
   spline evaluation: shift, rotation and scale are cheap nuisance parameters of any fit.
4. Levelling (piston, tilt, optional curvature) is fitted linearly in the camera frame and
   projected out of the residual (:class:`metrology.matching.level.Leveller`).

Placement convention: camera pixel centre (row, col) lies at design-pixel coordinates
``matrix @ [row, col] + offset`` (design pixel (i, j) centred at (i, j)), as in
:class:`metrology.matching.register.Registration`; rows and columns are row-major with row 0
at the top in both frames. The footprint's shape is taken from the placement given when the
model is built (a later refinement changes scale by parts per thousand; its effect on the
footprint is far below the noise).
"""

from __future__ import annotations

import math
import threading
from collections import OrderedDict
from collections.abc import Callable, Iterable, Sequence
from dataclasses import replace
from typing import TYPE_CHECKING, Any

import numpy as np
import scipy.fft as sfft
import scipy.ndimage as ndi

from doedesign.errors import DoeError
from metrology.matching.array_cache import ArrayCache
from metrology.matching.placement import PLACEMENT_PARAMS, Placement
from metrology.matching.transfer import (LateralTransfer, as_transfer, footprint_kernel, kernel_half_width,
                                         objective_spectrum)

if TYPE_CHECKING:
    from masks.process_params import ProcessParams

__all__ = ["ArrayCache", "FINE_STEP_M", "InstrumentModel", "LateralTransfer", "PLACEMENT_PARAMS", "Placement",
           "beside_transfer", "footprint_kernel", "kernel_half_width"]

# Fine-grid spacing requested from the process model (m).
FINE_STEP_M = 0.2e-6
# Whether renders fold the first moments of edges inside fine cells into their neighbours.
MOMENTS = True
# Extra design pixels around the camera footprint: kernel reach plus any placement refinement.
MARGIN_PX = 3
# The largest objective blur (Gaussian sigma, m) a camera-frame fit may reach.
MAX_BLUR_M = 1.5e-6
# Fine cells between any pixel read and a cell the FFT's circular convolution wrapped around:
# the spline prefilter's decay (0.268^24 ~ 2e-14) plus the cubic spline's support.
_WRAP_GUARD = 26
# No FFT here starts scipy.fft's thread pool (``workers`` > 1): it can hang a later fork in the
# same process (the reason, measured: :mod:`doedesign.engine.threaded_fft`).
# Memory kept for the masks' etches between renders: a Jacobian's columns on a small window, and
# all four masks of one model on a whole 512 px field (210 MB each in float64).
ETCH_CACHE_BYTES = 1024 * 2 ** 20
# Crops' models an instrument model keeps (:meth:`InstrumentModel.part`): an instrument stage's
# window and a selection's screening square.
PARTS_KEPT = 2
# Factors of the objective's transfer kept (pixel footprint, blur, optical transfer): a
# Jacobian's values of the instrument's parameters.
TRANSFER_FACTORS_KEPT = 24
# Camera pixels' spline coordinates kept, one array per placement: a Jacobian's columns of the
# process sample new maps under the same placement.
COORDS_KEPT = 8


class InstrumentModel:
    """Render model surfaces into a camera's pixel grid.

    Parameters
    ----------
    levels : ndarray of int (rows, cols)
        Design levels, row 0 at the top.
    pitch_m : float
        Design pitch.
    shape : (int, int)
        Camera field (rows, cols).
    placement : Placement
        Starting placement; it sets the fine region and the footprint's shape.
    step_m : float
        Requested fine-grid spacing.
    margin_px : int
        Design pixels rendered around the camera footprint (the blur kernel's reach plus the
        largest placement refinement expected).
    transfers : ArrayCache, optional
        Store of Fourier transfers to share with other models of the same placement matrix,
        pitch and fine step (tiles of one field), so each blur's transfer is computed once.
    cache_bytes : int
        Memory kept for the masks' etches between renders (a field's tiles share one budget).
    moments : bool
        Edges and sidewall slopes inside a fine cell rendered with their first moments
        (:func:`masks.moments.moment_corrected`), not as uniform cells.
    """

    def __init__(self, levels: np.ndarray, pitch_m: float, shape: tuple[int, int], placement: Placement,
                 step_m: float = FINE_STEP_M, margin_px: int = MARGIN_PX,
                 transfers: ArrayCache | None = None, cache_bytes: int = ETCH_CACHE_BYTES,
                 moments: bool = MOMENTS) -> None:
        from masks.process import fine_upsample

        self.levels = np.asarray(levels)
        self.pitch_m = float(pitch_m)
        self.shape = tuple(int(v) for v in shape)
        self.placement = placement
        self.moments = bool(moments)
        self.upsample = fine_upsample(pitch_m, step_m)
        self.step_m = self.pitch_m / self.upsample
        corners = np.array([[r, c] for r in (-0.5, self.shape[0] - 0.5) for c in (-0.5, self.shape[1] - 0.5)])
        rr, cc = (np.asarray(v) for v in placement.to_design(corners[:, 0], corners[:, 1]))
        m = int(margin_px)
        self.window = (int(math.floor(rr.min())) - m, int(math.ceil(rr.max())) + m + 1,
                       int(math.floor(cc.min())) - m, int(math.ceil(cc.max())) + m + 1)
        rows, cols = self.levels.shape
        r0, r1, c0, c1 = self.window
        self.region = (max(r0, 0), min(r1, rows), max(c0, 0), min(c1, cols))
        if self.region[0] >= self.region[1] or self.region[2] >= self.region[3]:
            raise DoeError("the camera field does not overlap the design under this placement")
        self._etches = ArrayCache(cache_bytes, max_items=24)
        self._unit_spectra = ArrayCache(cache_bytes, max_items=8)
        self._coords = ArrayCache(cache_bytes // 8, max_items=COORDS_KEPT)
        self._transfers = transfers if transfers is not None else self.transfer_cache()
        # The objective's transfer's factors (pixel, blur, optical transfer) on this model's grid.
        self._transfer_factors = ArrayCache(ETCH_CACHE_BYTES // 4, max_items=TRANSFER_FACTORS_KEPT)
        # The last transfer with edge responses beside it: (transfer, beside, sum).
        self._beside: tuple[Any, tuple[np.ndarray, ...], np.ndarray] | None = None
        self._parts: OrderedDict = OrderedDict()  # :meth:`part`'s models, the newest last
        self._parts_lock = threading.Lock()

    def part(self, shape: tuple[int, int], placement: Placement) -> InstrumentModel:
        """The model of a crop of this camera field (``shape`` pixels from ``placement``), with the
        default margin and caches, kept for the next request of the same crop: problems on one
        window (an instrument stage's combinations) then share its etches, spectra and
        transfers, computed once. The same numbers as a new model's; the last
        ``PARTS_KEPT`` crops are kept."""
        key = (tuple(int(v) for v in shape), placement.matrix.tobytes(), placement.offset.tobytes())
        with self._parts_lock:
            model = self._parts.get(key)
            if model is None:
                model = InstrumentModel(self.levels, self.pitch_m, shape, placement, step_m=self.step_m,
                                        moments=self.moments)
                self._parts[key] = model
                while len(self._parts) > PARTS_KEPT:
                    self._parts.popitem(last=False)
            self._parts.move_to_end(key)
            return model

    @staticmethod
    def transfer_cache(max_items: int = 24) -> ArrayCache:
        """An empty store of Fourier transfers (one per lateral transfer and padded shape; the
        default holds a Jacobian's values of the instrument's parameters)."""
        return ArrayCache(2 * ETCH_CACHE_BYTES // 3, max_items=max_items)

    def fine_surface(self, params: ProcessParams) -> np.ndarray:
        """Model heights (m) on the fine grid of the window (0 outside the design).

        The surface is the sum of the masks' etches (:func:`masks.process.mask_etch`); each
        mask's etch is kept for the next calls, so a fit that changes one mask's parameters
        recomputes that mask only.
        """
        from masks.process import finish_surface

        pad = self._pad(params)
        total = None
        for j in range(params.n_masks):
            etch = self._etch(params, j, pad)
            total = -etch if total is None else np.subtract(total, etch, out=total)
        return self._placed(finish_surface(total, params, self.step_m, pad, moments=self.moments))

    def mask_surface(self, params: ProcessParams, mask: int) -> np.ndarray:
        """Mask ``mask``'s part of :meth:`fine_surface` (m, <= 0): its etch with the sidewall
        ramp. The parts sum to the whole surface when ``params`` has no roughness (the ramp is
        a linear filter)."""
        from masks.process import finish_surface

        if params.roughness > 0:
            raise DoeError("a rough surface is not the sum of its masks' parts")
        pad = self._pad(params)
        return self._placed(finish_surface(-self._etch(params, mask, pad), params, self.step_m, pad,
                                                   moments=self.moments))

    def _pad(self, params):
        # Fine pixels beyond the region for the sidewall ramp (applied to the summed etches).
        return int(math.ceil(params.sidewall_slope / self.step_m / 2)) + 2

    def _etch(self, params, mask, pad):
        """One mask's etch (m, >= 0) on the region padded by ``pad`` fine pixels, cached.

        The etch is linear in its depth ``D`` and its trench's depth ``t``: ``D E + t F(w)``, with
        ``E`` the untrenched etch at unit depth (coverage, loading and gradient only scale it) and
        ``F`` the trench of width ``w`` at unit depths (:func:`masks.process.mask_etch` deepens
        the etch by ``t / D`` times the foot profile). A change of either depth, every step of a
        fit with them free, costs a product, not a new print of the mask."""
        from masks.process import etch_key, mask_etch

        key = (etch_key(params, mask), pad)
        etch = self._etches.get(key)
        if etch is None:
            depth = float(params.etch_depth[mask])
            trench_m, width_m = (float(v) for v in params.microtrenching[mask])
            if trench_m > 0 and depth > 0:
                # E and F are kept; D E is not (it costs a product, and a fit tries many D).
                flat = self._etch(_varied(params, mask, depth=1.0, trench=(0.0, 0.0)), mask, pad)
                etch = flat * depth + trench_m * self._trench(params, mask, width_m, pad)
            elif (unit := _unit_depth(params, mask)) is None:
                etch = mask_etch(self.levels, self.pitch_m, params, mask, step_m=self.step_m, region=self.region,
                                 pad_px=pad, moments=self.moments)
            else:
                etch = self._etch(unit, mask, pad) * depth
            self._etches.put(key, etch)
        return etch

    def _trench(self, params, mask, width_m, pad):
        """``F(w)`` of :meth:`_etch`: the etch with unit depth and unit trench depth less the
        untrenched one, kept per trench width."""
        from masks.process import etch_key, mask_etch

        unit = _varied(params, mask, depth=1.0, trench=(1.0, width_m))
        key = ("trench", etch_key(unit, mask), pad)
        foot = self._etches.get(key)
        if foot is None:
            foot = mask_etch(self.levels, self.pitch_m, unit, mask, step_m=self.step_m, region=self.region,
                             pad_px=pad, moments=self.moments)
            foot -= self._etch(_varied(unit, mask, trench=(0.0, 0.0)), mask, pad)
            self._etches.put(key, foot)
        return foot

    def _placed(self, surface):
        """The region's surface in the window's fine grid (0, unetched, beyond the design)."""
        out = np.zeros(self._fine_shape())
        a, b = self._region_offset()
        out[a:a + surface.shape[0], b:b + surface.shape[1]] = surface
        return out

    def _region_offset(self):
        """Fine cells from the window's first cell to the region's (the design's part of it)."""
        return (self.region[0] - self.window[0]) * self.upsample, (self.region[2] - self.window[2]) * self.upsample

    def camera_map(self, fine_m: np.ndarray, sigma_m: float | LateralTransfer) -> np.ndarray:
        """Spline coefficients of what a camera pixel centred at each fine cell reports.

        One Fourier product holds the footprint kernel and the cubic spline prefilter (the
        inverse of the B-spline's transfer, ``6 / (4 + 2 cos w)`` per axis) on the surface
        padded with its edge values, so the map costs one real FFT pair. In single precision:
        its rounding (~1e-7 of the heights, ~1e-13 m) is far below any measurement's noise.
        """
        return self.map_of(self.spectrum(fine_m), sigma_m, overwrite=True)

    def spectrum(self, fine_m: np.ndarray) -> np.ndarray:
        """Real FFT of a fine surface padded for any blur within the camera's bounds: maps of
        one surface at several blurs, or of several surfaces summed (the transfer is linear),
        then cost one inverse FFT each (:meth:`map_of`)."""
        buf, inner = self._buffer()
        inner[...] = fine_m
        return self._padded_fft(buf)

    def mask_spectrum(self, params: ProcessParams, mask: int) -> np.ndarray:
        """:meth:`spectrum` of :meth:`mask_surface`, the mask's etch written straight into the
        FFT's buffer (no negated, cropped, placed or cast copies: on a whole 512 px field each
        was a 100-200 MB array whose fresh pages the kernel zeroed). The same numbers."""
        if params.sidewall_slope > 0:
            return self.spectrum(self.mask_surface(params, mask))
        if params.roughness > 0:
            raise DoeError("a rough surface is not the sum of its masks' parts")
        unit = _unit_depth(params, mask)
        if unit is not None:
            # Linear in the depth (see :meth:`_etch`): the unit-depth spectrum, kept, scaled.
            from masks.process import etch_key

            key = etch_key(unit, mask)
            spectrum = self._unit_spectra.get(key)
            if spectrum is None:
                spectrum = self._etch_spectrum(unit, mask)
                self._unit_spectra.put(key, spectrum)
            return spectrum * np.float32(params.etch_depth[mask])
        return self._etch_spectrum(params, mask)

    def _etch_spectrum(self, params, mask):
        """:meth:`mask_spectrum` without a sidewall ramp, computed."""
        pad = self._pad(params)
        etch = self._etch(params, mask, pad)
        core = etch[pad:etch.shape[0] - pad, pad:etch.shape[1] - pad]
        buf, inner = self._buffer()
        a, b = self._region_offset()
        if core.shape != inner.shape:
            inner[...] = 0.0  # unetched beyond the design
        np.negative(core, out=inner[a:a + core.shape[0], b:b + core.shape[1]], casting="unsafe")
        return self._padded_fft(buf)

    def map_of(self, spectrum: np.ndarray | Sequence[np.ndarray], sigma_m: float | LateralTransfer,
               overwrite: bool = False, factors: Sequence[np.ndarray] = (),
               beside: Sequence[np.ndarray] = ()) -> np.ndarray:
        """:meth:`camera_map` of the surface whose :meth:`spectrum` is given, or of the sum of
        surfaces whose spectra are (multiplied in place with ``overwrite``, when the caller owns
        the one spectrum given). ``factors``: transfers of linear filters of the surface on
        this FFT grid (:meth:`fourier_grid`), applied with the instrument's. ``beside``:
        transfers ``1 + b`` of the instrument's own edge responses (a batwing), whose ``b`` is
        added to the objective's optical transfer, not imaged through it: the whole transfer is
        ``pixel * blur * (MTF + sum b) * prod factors`` (:func:`beside_transfer`)."""
        h, shape = self._padding()
        rows, cols = self._fine_shape()
        transfer = self._transfer(shape, sigma_m)
        if len(beside):
            last = self._beside  # one read: worker threads replace it whole
            if last is not None and last[0] is transfer and len(last[1]) == len(beside) and all(
                    a is b for a, b in zip(last[1], beside)):
                # A Jacobian's columns for fabrication effects: the same cached transfer and edge
                # responses (held here, so no other array can take their identity).
                transfer = last[2]
            else:
                t = as_transfer(sigma_m)
                plain = self._transfer(shape, replace(t, na=0.0)) if t.na > 0 else transfer
                summed = beside_transfer(transfer, plain, beside)
                self._beside = (transfer, tuple(beside), summed)
                transfer = summed
        parts = [spectrum] if isinstance(spectrum, np.ndarray) else list(spectrum)
        if len(parts) == 1:
            product = np.multiply(parts[0], transfer, out=parts[0] if overwrite else None)
        else:
            product = np.add(parts[0], parts[1])
            for part in parts[2:]:
                product += part
            product *= transfer
        for factor in factors:
            product *= factor
        # A view: the spline sampler reads strided arrays as they are (a copy cost ~0.4 s a map
        # on a whole 512 px field).
        return sfft.irfft2(product, s=shape)[h:h + rows, h:h + cols]

    def fourier_grid(self) -> tuple[np.ndarray, np.ndarray]:
        """Angular frequencies (radians per fine cell) of :meth:`spectrum`'s rows and columns."""
        _, shape = self._padding()
        return 2 * np.pi * sfft.fftfreq(shape[0]), 2 * np.pi * sfft.rfftfreq(shape[1])

    def fourier_reach(self, placements: Iterable[Placement], sigma_m: float | LateralTransfer) -> int:
        """Fine cells a linear filter of the surface may reach and still act on this FFT grid as
        on the surface with its edges extended, for camera pixels under ``placements`` and the
        blur ``sigma_m``: the pixels' least distance to the FFT grid's edge, less the kernel's
        reach and the prefilter's guard (no wrapped-around cell then touches a pixel)."""
        h, _ = self._padding()
        least = min(self._clearance(pl) for pl in placements)
        return int(math.floor(least + h - self._reach(sigma_m) - _WRAP_GUARD))

    def _fine_shape(self):
        u = self.upsample
        return (self.window[1] - self.window[0]) * u, (self.window[3] - self.window[2]) * u

    def _buffer(self):
        """An FFT buffer (float32) and its view where the window's fine surface goes."""
        h, shape = self._padding()
        rows, cols = self._fine_shape()
        buf = np.empty(shape, np.float32)
        return buf, buf[h:h + rows, h:h + cols]

    def _padded_fft(self, buf):
        """Real FFT of ``buf`` once the surface in it is padded with its edge values (as
        ``np.pad(mode="edge")``: rows first, then columns, corners from the corners)."""
        h, shape = self._padding()
        rows, cols = self._fine_shape()
        buf[:h, h:h + cols] = buf[h, h:h + cols]
        buf[h + rows:, h:h + cols] = buf[h + rows - 1, h:h + cols]
        buf[:, :h] = buf[:, h:h + 1]
        buf[:, h + cols:] = buf[:, h + cols - 1:h + cols]
        return sfft.rfft2(buf)

    def _padding(self):
        """Pad (fine cells of edge values around the window) and FFT shape.

        The map is only read where :meth:`covers` allows, at least the kernel's reach inside
        the window; cells the circular convolution wraps around lie within that reach of the
        grid's edge, so a pad of :data:`_WRAP_GUARD` keeps them that many cells from every
        pixel read, where the spline prefilter's weight (pole 2 - sqrt(3): 0.268^26 ~ 1e-15)
        is nil. A pad sized for the largest blur, as before, only made every FFT larger."""
        h = _WRAP_GUARD
        rows, cols = self._fine_shape()
        return h, (sfft.next_fast_len(rows + 2 * h, real=True), sfft.next_fast_len(cols + 2 * h, real=True))

    def _reach(self, transfer):
        """Fine cells the lateral transfer reaches from a pixel centre: the footprint kernel's
        half width, or the objective's point spread where that reaches further."""
        t = as_transfer(transfer)
        k = kernel_half_width(self.placement.matrix, self.pitch_m, self.step_m, t.sigma_m, t.fill_factor)
        return max(k, int(math.ceil(t.optical_reach_m() / self.step_m)))

    def _transfer(self, shape, transfer):
        """Fourier transfer of correlation with the footprint kernel, the objective's optical
        transfer (:mod:`metrology.matching.transfer`) and the spline prefilter; kept per FFT
        shape and every parameter of the lateral transfer; under an objective, the kernel's
        continuous spectrum (:func:`metrology.matching.transfer.objective_spectrum`).

        In single precision, the prefilter applied per axis in place: on a whole 512 px field
        double-precision temporaries (some 800 MB of fresh pages) made each new blur cost 1.8 s.
        """
        t = as_transfer(transfer)
        key = (shape, t)
        spectrum = self._transfers.get(key)
        if spectrum is None:
            wr, wc = self.fourier_grid()
            prefilter = ((6.0 / (4.0 + 2.0 * np.cos(wr))).astype(np.float32),
                         (6.0 / (4.0 + 2.0 * np.cos(wc))).astype(np.float32))
            if t.na > 0:
                # Zero beyond the cut-off: the prefilter applied on the block inside it (the same numbers).
                spectrum = objective_spectrum(self.placement.matrix, self.pitch_m, self.step_m, t,
                                              wr / (2 * np.pi * self.step_m), wc / (2 * np.pi * self.step_m),
                                              np.complex64, weights=prefilter, factors=self._transfer_factors)
            else:
                kernel = footprint_kernel(self.placement.matrix, self.pitch_m, self.step_m, t.sigma_m,
                                          t.fill_factor)
                k = kernel.shape[0] // 2
                wrapped = np.zeros(shape, np.float32)
                # Correlation: value[a] = sum_d kernel[k + d] fine[a + d], i.e. convolution with
                # the kernel flipped, centred at index 0 (offset d at index d mod the shape).
                offsets = np.arange(-k, k + 1)
                wrapped[np.ix_(offsets % shape[0], offsets % shape[1])] = kernel[::-1, ::-1]
                spectrum = sfft.rfft2(wrapped, overwrite_x=True)
                spectrum *= prefilter[0][:, None]
                spectrum *= prefilter[1][None, :]
            self._transfers.put(key, spectrum)
        return spectrum

    def covers(self, placement: Placement, sigma_m: float | LateralTransfer) -> bool:
        """Whether every camera pixel under ``placement`` reads only the rendered window: its
        centre at least the kernel's reach (and the spline's support) inside the fine grid."""
        reach = self._reach(sigma_m) + 2
        return self._clearance(placement) >= reach

    def _clearance(self, placement):
        """Least distance (fine cells) of a camera pixel centre under ``placement`` to the edge
        of the window's fine grid: an affine map, so the corner pixels'."""
        rows, cols = self.shape
        fr, fc = self._fine_index(placement, np.array([0.0, 0.0, rows - 1.0, rows - 1.0]),
                                  np.array([0.0, cols - 1.0, 0.0, cols - 1.0]))
        n_r, n_c = self._fine_shape()
        return float(np.min([fr, n_r - 1 - fr, fc, n_c - 1 - fc]))

    def sample(self, coeffs: np.ndarray, placement: Placement) -> np.ndarray:
        """Camera-frame heights from :meth:`camera_map` coefficients under ``placement``."""
        key = (placement.matrix.tobytes(), placement.offset.tobytes())
        coords = self._coords.get(key)
        if coords is None:
            # The affine map broadcast over a row and a column of indices: the same numbers as
            # on a full index grid, without building one. Kept: building and stacking them cost a
            # fifth of a sample (11 of 53 ms on a 715 px field).
            r = np.arange(self.shape[0], dtype=float)[:, None]
            c = np.arange(self.shape[1], dtype=float)[None, :]
            coords = np.stack(np.broadcast_arrays(*self._fine_index(placement, r, c)))
            coords.flags.writeable = False
            self._coords.put(key, coords)
        return ndi.map_coordinates(coeffs, coords, output=np.float64, order=3, mode="nearest", prefilter=False)

    def _fine_index(self, placement, rows, cols):
        """Fine-cell index coordinates in the window of camera pixel centres (rows, cols)."""
        R, C = placement.to_design(rows, cols)
        u = self.upsample
        return (R - self.window[0] + 0.5) * u - 0.5, (C - self.window[2] + 0.5) * u - 0.5

    def render(self, params: ProcessParams, placement: Placement, sigma_m: float | LateralTransfer,
               surface: Callable[[np.ndarray, float], np.ndarray] | None = None) -> np.ndarray:
        """Model heights (m) in the camera frame, before levelling.

        Parameters
        ----------
        params : ProcessParams
        placement : Placement
        sigma_m : float or LateralTransfer
            The instrument's lateral transfer (a number: a Gaussian blur with full pixels).
        surface : callable, optional
            ``surface(fine_m, step_m) -> fine_m``: instrument artefacts acting on the surface
            before the blur (batwing) or any user surface effect.
        """
        fine = self.fine_surface(params)
        if surface is not None:
            fine = surface(fine, self.step_m)
        return self.sample(self.camera_map(fine, sigma_m), placement)


def _unit_depth(params, mask):
    """``params`` with mask ``mask`` etched to unit depth (1 m), when its etch is proportional
    to its depth (no microtrenching: the trench adds a depth of its own), else None; None too
    when the depth is already 1."""
    if params.microtrenching[mask][0] > 0 or float(params.etch_depth[mask]) == 1.0:
        return None
    return _varied(params, mask, depth=1.0)


def _varied(params, mask, depth=None, trench=None):
    """``params`` with mask ``mask``'s etch depth (m) or its trench ``(depth_m, width_m)`` replaced."""
    changes = {}
    if depth is not None:
        changes["etch_depth"] = np.array(params.etch_depth, float)
        changes["etch_depth"][mask] = depth
    if trench is not None:
        changes["microtrenching"] = np.array(params.microtrenching, float)
        changes["microtrenching"][mask] = trench
    return params.copy(**changes)


def beside_transfer(transfer: np.ndarray, plain: np.ndarray, beside: Sequence[np.ndarray]) -> np.ndarray:
    """``transfer + plain * sum(b - 1 for b in beside)``: the instrument's Fourier transfer
    (pixel, blur, objective and spline prefilter) with edge responses ``b - 1`` added beside the
    objective, whose part ``plain`` (the same without the objective) they pass through. A new
    array: ``transfer`` is a cached one."""
    extra = None
    for b in beside:
        extra = b - np.float32(1.0) if extra is None else extra + (b - np.float32(1.0))
    return transfer + plain * extra
