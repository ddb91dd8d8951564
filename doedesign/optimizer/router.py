"""Colour-router starting designs from a coherent pupil model (point targets, one pixel per plane).

The light of plane ``p`` in a sensor pixel centred at ``u`` is the pixel integral of
``|sum_xi A(xi) t_p(xi) exp(-2 pi i xi . u / (lambda z))|^2`` (Fraunhofer, thin lens focused at
the target's depth), with ``t_p = exp(i phi_p(h))`` the DOE's transmission at that wavelength
and ``A`` the coded view's aperture. Its pixel integral is taken by a ``nq x nq`` Gauss-Legendre
rule, the slowly varying DOE pixel envelope is left out. Because the target pixels sit within a
few pixels of the axis, the wanted pupil phases vary by only about a wave across the aperture,
so the model is solved on a coarse pupil grid (``grid_px`` samples across the aperture, e.g.
100 = 86 um cells for the seed camera) in seconds and its height map is carried to the design
grid by nearest-cell lookup; the PSF engine then scores and refines it exactly.

The three colours are served at once by the max-min (:func:`doedesign.optimizer.objectives.maximize_min`):
every colour's phase comes from the same heights (``phi = 2 pi (n(lambda) - 1) h / lambda``), and the
wavelength dependence of the wrapped 16-level relief is what routes them. This is the initial
design ``init="router"`` of :func:`doedesign.optimizer.optimize.design_doe`.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from threadpoolctl import threadpool_limits

from ..errors import DoeError
from ..materials import get_material
from .objectives import maximize_min, plane_weights

if TYPE_CHECKING:
    from numpy.typing import ArrayLike

    from ..camera import Camera
    from ..targets import Target
    from .settings import OptimizerSettings

__all__ = ["MAX_TARGET_PIXELS", "PupilModel", "pupil_model", "router_heights", "router_start", "to_design_grid"]

log = logging.getLogger(__name__)

MAX_TARGET_PIXELS = 8  # per plane; extended targets are not point targets


@dataclass
class PupilModel:
    """The coherent pupil model of one camera and target on a coarse grid (see the module docstring)."""

    amplitude: np.ndarray       # (n,) aperture weight of each coarse sample on the coded view
    y_m: np.ndarray             # (n,) sample centres
    x_m: np.ndarray
    grid_shape: tuple
    support: np.ndarray         # (rows, cols) bool, coarse samples in the coded view
    cell_m: float
    phase_per_m: np.ndarray     # (planes,) phase per metre of height
    bases: list                 # per plane: (quadrature points x pixels, n) complex
    weights_q: list             # per plane: quadrature weights including the normalization
    plane_shape: tuple

    def energies(self, h: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Energies (planes,) and their gradients (planes, n) for coarse heights ``h`` (n,)."""
        e_out = np.empty(len(self.bases))
        g_out = np.empty((len(self.bases), h.size))
        for p, (basis, wq) in enumerate(zip(self.bases, self.weights_q)):
            k = self.phase_per_m[p]
            t = np.exp(1j * k * h)
            field = basis @ t
            e_out[p] = float(np.sum(wq * np.abs(field) ** 2))
            g_out[p] = 2 * np.real(((wq * field).conj() @ basis) * 1j * k * t)
        return e_out, g_out


def pupil_model(camera: Camera, target: Target, material: str = "fused_silica", grid_px: int = 100, nq: int = 3) -> PupilModel:
    """Build the :class:`PupilModel` of ``camera`` and a point ``target`` (at most a few pixels per plane)."""
    if camera.aperture_diameter_m is None:
        raise DoeError("the router model needs a camera with a circular aperture")
    mat = get_material(material)
    cell = camera.aperture_diameter_m / grid_px
    amp = camera.view_weights((grid_px, grid_px), cell)[0]
    support = amp > 0
    c = (np.arange(grid_px) - (grid_px - 1) / 2) * cell
    yy, xx = np.meshgrid(c, c, indexing="ij")
    a, y, x = amp[support], yy[support], xx[support]
    z = camera.sensor_distance_m
    pix = camera.pixel_pitch_m
    nodes, wts = np.polynomial.legendre.leggauss(nq)
    nodes, wts = nodes * pix / 2, wts * pix / 2
    r0, c0 = camera.axis_pixel
    norm = 1.0 / np.sum(a * a)
    bases, weights_q, kphase = [], [], []
    r2 = y * y + x * x
    for d, depth in enumerate(target.depths_m):
        for w, wl in enumerate(target.wavelengths_m):
            pixels = np.argwhere(target.mask[d, w])
            if len(pixels) > MAX_TARGET_PIXELS:
                raise DoeError(f"target {target.name!r}: {len(pixels)} target pixels in a plane; the router start "
                               f"is for point targets (at most {MAX_TARGET_PIXELS})")
            # Defocus of a point at `depth` seen by the lens focused at the camera's distance.
            opd = _sag(r2, depth) - _sag(r2, camera.focus_distance_m)
            rows, qw = [], []
            for i, j in pixels:
                for qy, wy in zip(nodes, wts):
                    for qx, wx in zip(nodes, wts):
                        uy, ux = (i - r0) * pix + qy, (j - c0) * pix + qx
                        rows.append(a * np.exp(1j * (2 * np.pi / wl) * (opd - (y * uy + x * ux) / z)))
                        qw.append(wy * wx * cell ** 2 / (wl * z) ** 2 * norm)
            bases.append(np.array(rows))
            weights_q.append(np.array(qw))
            kphase.append(float(mat.phase(1.0, wl)))
    return PupilModel(a, y, x, (grid_px, grid_px), support, cell, np.array(kphase), bases, weights_q,
                      target.intensity.shape[:2])


def _sag(r2, d):
    return np.zeros_like(r2) if np.isinf(d) else r2 / (np.sqrt(r2 + d * d) + d)


def router_heights(model: PupilModel, lower: float, weights: ArrayLike | None = None, max_iter: int = 300, h0: np.ndarray | None = None,
                   algorithm: str = "LD_MMA", target: Target | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Max-min heights on the coarse grid (n,) in [lower, 0], and the model energies per plane."""
    w = plane_weights(target, weights).ravel() if target is not None else np.ones(len(model.bases))
    x0 = np.zeros(model.amplitude.size) if h0 is None else np.asarray(h0, dtype=float)
    # The model's products are a few thousand samples long: BLAS threads only spin between
    # them (on a 16-core host they took 16x the CPU time and 30x the wall time of one thread).
    with threadpool_limits(limits=1, user_api="blas"):
        h, _ = maximize_min(model.energies, x0, lower, 0.0, w, algorithm, max_iter, desc="router")
        return h, model.energies(h)[0]


def to_design_grid(model: PupilModel, h_coarse: np.ndarray, camera: Camera, pitch_m: float, shape: tuple) -> np.ndarray:
    """Carry coarse heights to the design grid (nearest coarse cell); pixels outside stay 0."""
    coarse = np.zeros(model.grid_shape)
    coarse[model.support] = h_coarse
    rows, cols = shape
    y = (np.arange(rows) - (rows - 1) / 2) * pitch_m
    x = (np.arange(cols) - (cols - 1) / 2) * pitch_m
    n = model.grid_shape[0]
    iy = np.clip(np.floor(y / model.cell_m + n / 2).astype(int), 0, n - 1)
    ix = np.clip(np.floor(x / model.cell_m + n / 2).astype(int), 0, n - 1)
    return coarse[np.ix_(iy, ix)]


def router_start(target: Target, camera: Camera, pitch_m: float, shape: tuple, material: str, lower: float,
                 settings: OptimizerSettings) -> np.ndarray:
    """The ``router`` initial design: the coherent pupil model's max-min heights (:mod:`doedesign.optimizer.router`)."""
    # No finer than the design itself.
    model = pupil_model(camera, target, material, min(settings.router_grid_px, max(shape)))
    h, energies = router_heights(model, lower, settings.colour_weights, settings.router_iter, target=target)
    log.info("router start: model energies on target %s", np.round(energies, 4).tolist())
    return to_design_grid(model, h, camera, pitch_m, shape)
