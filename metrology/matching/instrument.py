"""The measurement model: the model surface as the profilometer's camera would report it.

A white-light interferometer blurs the surface through its objective, and each camera pixel
reports the mean height over its footprint on the sample; the field sits rotated, shifted and
possibly mirrored against the design, at a lateral scale known to a fraction of a percent.
This module renders the model into the camera's own pixel grid, so that model and data are
compared pixel by pixel and the data are never resampled or smoothed.

Method (one measurement model for ``doe compare`` and ``doe diagnose`` alike):

1. The model surface (design + process effects, :func:`masks.process.simulate_surface`) on a
   fine grid in the design frame (``pitch / ceil(pitch / 0.125 um)``: at 0.25 um the
   process model's per-cell corner approximations alone leave ~1 nm rms on biased edges) over the design pixels
   the camera field covers, unetched (0) outside the design.
2. One kernel on that fine grid holds both the objective blur and the pixel footprint:
   ``K(a) = mean over the footprint y of integral over fine cell a of G_sigma(x - y)``, where
   the footprint is the camera pixel mapped into the design frame by the placement (a
   parallelogram: rotation, per-axis scale, mirror). Correlating the fine surface with ``K``
   gives, at every fine cell, the value a camera pixel centred there would report.
3. That map is sampled at each camera pixel centre by a cubic spline (the map is smooth there:
   a step has been through the pixel box and the blur), so a change of placement costs one
   spline evaluation: shift, rotation and scale are cheap nuisance parameters of any fit.
4. Levelling (piston, tilt, optional curvature) is fitted linearly in the camera frame and
   projected out of the residual.

Placement convention: camera pixel centre (row, col) lies at design-pixel coordinates
``matrix @ [row, col] + offset`` (design pixel (i, j) centred at (i, j)), as in
:class:`metrology.matching.register.Registration`; rows and columns are row-major with row 0
at the top in both frames. The footprint's shape is taken from the placement given when the
model is built (a later refinement changes scale by parts per thousand; its effect on the
footprint is far below the noise).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import scipy.ndimage as ndi
import scipy.signal as sig
from scipy.special import erf

from doedesign.errors import DoeError

if TYPE_CHECKING:
    from masks.process_params import ProcessParams
    from metrology.matching.register import Registration

__all__ = ["FINE_STEP_M", "InstrumentModel", "Leveller", "PLACEMENT_PARAMS", "Placement", "footprint_kernel",
           "levelling_basis", "robust_valid"]

# Fine-grid spacing requested from the process model (m).
FINE_STEP_M = 0.125e-6
# Extra design pixels around the camera footprint: kernel reach plus any placement refinement.
MARGIN_PX = 3
# Nuisance parameters of the placement, in the order of :meth:`Placement.refined`.
PLACEMENT_PARAMS = ("shift_row_px", "shift_col_px", "rotation_rad", "scale_row", "scale_col")


@dataclass(frozen=True)
class Placement:
    """Affine map from camera pixel (row, col) centres to design-pixel coordinates.

    Attributes
    ----------
    matrix : ndarray (2, 2)
    offset : ndarray (2,)
    """

    matrix: np.ndarray
    offset: np.ndarray

    @classmethod
    def from_registration(cls, registration: Registration) -> Placement:
        """The placement of a :class:`~metrology.matching.register.Registration`."""
        return cls(np.array(registration.matrix, float), np.array(registration.offset, float))

    def to_design(self, rows: np.ndarray | float, cols: np.ndarray | float,
                  ) -> tuple[np.ndarray | float, np.ndarray | float]:
        """Design coordinates (R, C) of camera coordinates (rows, cols)."""
        m, t = self.matrix, self.offset
        return m[0, 0] * rows + m[0, 1] * cols + t[0], m[1, 0] * rows + m[1, 1] * cols + t[1]

    def refined(self, values: Sequence[float], shape: tuple[int, int]) -> Placement:
        """This placement moved by nuisance ``values`` (see :data:`PLACEMENT_PARAMS`).

        ``shift_row_px``, ``shift_col_px``: design pixels, of the field centre;
        ``rotation_rad``: counter-clockwise (y up) about the field centre; ``scale_row``,
        ``scale_col``: relative change of the camera pixel size along its rows and columns.
        """
        dr, dc, a, sr, sc = (float(v) for v in values)
        centre = (np.asarray(shape, float) - 1) / 2
        rot = np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])
        matrix = rot @ self.matrix @ np.diag([1.0 + sr, 1.0 + sc])
        centre_design = self.matrix @ centre + self.offset + np.array([dr, dc])
        return Placement(matrix, centre_design - matrix @ centre)


def _cell_gaussian(x_m, step_m, sigma_m):
    """Integral of a unit Gaussian of width ``sigma_m`` centred at 0 over cells centred at ``x_m``."""
    s = max(float(sigma_m), 1e-3 * step_m) * math.sqrt(2.0)
    return 0.5 * (erf((x_m + step_m / 2) / s) - erf((x_m - step_m / 2) / s))


def footprint_kernel(matrix: np.ndarray, pitch_m: float, step_m: float, sigma_m: float) -> np.ndarray:
    """Blur-and-pixel kernel on the fine grid (see the module docstring, step 2).

    Parameters
    ----------
    matrix : ndarray (2, 2)
        Linear part of the placement (design pixels per camera pixel).
    pitch_m, step_m : float
        Design pitch and fine-grid spacing.
    sigma_m : float
        Objective blur (Gaussian standard deviation, m).

    Returns
    -------
    ndarray (2 k + 1, 2 k + 1)
        Weights summing to 1, centre at index ``k``; row 0 at the top.
    """
    m = np.asarray(matrix, float) * pitch_m
    side = max(np.abs(m).sum(axis=1))
    q = max(8, int(math.ceil(2.0 * side / max(sigma_m, step_m))))
    sub = (np.arange(q) + 0.5) / q - 0.5
    u, v = np.meshgrid(sub, sub, indexing="ij")
    y = m @ np.stack([u.ravel(), v.ravel()])  # footprint points (row, col offsets, m)
    k = int(math.ceil((side / 2 + 4.0 * sigma_m) / step_m)) + 1
    x = np.arange(-k, k + 1) * step_m
    # Each point stands for a 1/q sub-pixel: widen its Gaussian by that sub-pixel's variance so
    # the kernel's second moments are exact (the midpoint rule alone loses 1/q^2 of them).
    sub_var = np.diag(m @ m.T) / (12.0 * q * q)
    gr = _cell_gaussian(x[None, :] - y[0][:, None], step_m, math.sqrt(sigma_m ** 2 + sub_var[0]))
    gc = _cell_gaussian(x[None, :] - y[1][:, None], step_m, math.sqrt(sigma_m ** 2 + sub_var[1]))
    kernel = gr.T @ gc / y.shape[1]
    return kernel / kernel.sum()


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
    """

    def __init__(self, levels: np.ndarray, pitch_m: float, shape: tuple[int, int], placement: Placement,
                 step_m: float = FINE_STEP_M) -> None:
        from masks.process import fine_upsample

        self.levels = np.asarray(levels)
        self.pitch_m = float(pitch_m)
        self.shape = tuple(int(v) for v in shape)
        self.placement = placement
        self.upsample = fine_upsample(pitch_m, step_m)
        self.step_m = self.pitch_m / self.upsample
        corners = np.array([[r, c] for r in (-0.5, self.shape[0] - 0.5) for c in (-0.5, self.shape[1] - 0.5)])
        rr, cc = placement.to_design(corners[:, 0], corners[:, 1])
        self.window = (int(math.floor(rr.min())) - MARGIN_PX, int(math.ceil(rr.max())) + MARGIN_PX + 1,
                       int(math.floor(cc.min())) - MARGIN_PX, int(math.ceil(cc.max())) + MARGIN_PX + 1)
        rows, cols = self.levels.shape
        r0, r1, c0, c1 = self.window
        self.region = (max(r0, 0), min(r1, rows), max(c0, 0), min(c1, cols))
        if self.region[0] >= self.region[1] or self.region[2] >= self.region[3]:
            raise DoeError("the camera field does not overlap the design under this placement")
        self._cache = {}

    def fine_surface(self, params: ProcessParams) -> np.ndarray:
        """Model heights (m) on the fine grid of the window (0 outside the design)."""
        from masks.process import simulate_surface

        u = self.upsample
        r0, r1, c0, c1 = self.window
        out = np.zeros(((r1 - r0) * u, (c1 - c0) * u))
        s = simulate_surface(self.levels, self.pitch_m, params, step_m=self.step_m, region=self.region)
        a, b = (self.region[0] - r0) * u, (self.region[2] - c0) * u
        out[a:a + s.height_m.shape[0], b:b + s.height_m.shape[1]] = s.height_m
        return out

    def camera_map(self, fine_m: np.ndarray, sigma_m: float) -> np.ndarray:
        """Spline coefficients of what a camera pixel centred at each fine cell reports."""
        kernel = footprint_kernel(self.placement.matrix, self.pitch_m, self.step_m, sigma_m)
        value = sig.fftconvolve(np.pad(fine_m, kernel.shape[0] // 2, mode="edge"), kernel[::-1, ::-1], mode="valid")
        return ndi.spline_filter(value, order=3, mode="nearest")

    def sample(self, coeffs: np.ndarray, placement: Placement) -> np.ndarray:
        """Camera-frame heights from :meth:`camera_map` coefficients under ``placement``."""
        r, c = np.mgrid[:self.shape[0], :self.shape[1]].astype(float)
        R, C = placement.to_design(r, c)
        u = self.upsample
        fr = (R - self.window[0] + 0.5) * u - 0.5
        fc = (C - self.window[2] + 0.5) * u - 0.5
        return ndi.map_coordinates(coeffs, [fr, fc], order=3, mode="nearest", prefilter=False)

    def render(self, params: ProcessParams, placement: Placement, sigma_m: float,
               surface: Callable[[np.ndarray, float], np.ndarray] | None = None) -> np.ndarray:
        """Model heights (m) in the camera frame, before levelling.

        Parameters
        ----------
        params : ProcessParams
        placement : Placement
        sigma_m : float
            Objective blur.
        surface : callable, optional
            ``surface(fine_m, step_m) -> fine_m``: instrument artefacts acting on the surface
            before the blur (batwing) or any user surface effect.
        """
        fine = self.fine_surface(params)
        if surface is not None:
            fine = surface(fine, self.step_m)
        return self.sample(self.camera_map(fine, sigma_m), placement)


def levelling_basis(shape: tuple[int, int], curvature: bool = False) -> np.ndarray:
    """Columns of the levelling fit on a camera field: piston, tilt (col, row), curvature.

    Coordinates are centred and scaled to +-1 so the columns are well conditioned.
    """
    r, c = np.mgrid[:shape[0], :shape[1]].astype(float)
    r = (r - (shape[0] - 1) / 2) / max(shape[0] / 2, 1)
    c = (c - (shape[1] - 1) / 2) / max(shape[1] / 2, 1)
    cols = [np.ones(shape), c, r] + ([r * r + c * c] if curvature else [])
    return np.stack([x.ravel() for x in cols], axis=1)


class Leveller:
    """Projects piston, tilt (and optionally curvature) out of residuals on valid pixels."""

    def __init__(self, shape: tuple[int, int], valid: np.ndarray, curvature: bool = False) -> None:
        self.valid = np.asarray(valid, bool)
        basis = levelling_basis(shape, curvature)[self.valid.ravel()]
        self.q, _ = np.linalg.qr(basis)

    def coefficients(self, residual: np.ndarray) -> np.ndarray:
        """Projection coefficients (on the orthonormal basis) of a 1-D residual on valid pixels."""
        return self.q.T @ residual

    def __call__(self, residual: np.ndarray) -> np.ndarray:
        """The residual (1-D, valid pixels) with the levelling terms removed."""
        return residual - self.q @ (self.q.T @ residual)


def robust_valid(residual_map: np.ndarray, valid: np.ndarray, k: float = 6.0) -> np.ndarray:
    """Valid pixels whose residual lies within ``k`` robust sigmas (1.4826 MAD) of the median:
    spikes and fringe-order errors are excluded, never smoothed."""
    vals = residual_map[valid]
    med = np.median(vals)
    mad = 1.4826 * np.median(np.abs(vals - med))
    keep = valid.copy()
    keep[valid] = np.abs(vals - med) <= k * max(mad, 1e-15)
    return keep
