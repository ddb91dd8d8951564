"""The first stage of the optical proximity correction: a density mask with a length scale.

:mod:`masks.opc`'s level set moves the drawn mask's edges a cell at a time, so it finds the
corrections near the drawn geometry (edge offsets, small serifs) but not the larger ones a print
through 30 um asks for on a fine element: measured on a 32 px element of one mask edge per pixel
on its two shallow masks, 100 level-set steps reach a field overlap of 0.933 (drawn 0.886).

Method (density-based inverse lithography with a minimum length scale, as in topology
optimization: Wang, Lazarov and Sigmund, Struct. Multidisc. Optim. 43, 767, 2011): a density
``rho`` in [0, 1] per mask-grid cell, started at ``0.25 + 0.5 drawn``; a Gaussian filter of
sigma ``filter_sigma_cells`` (the length scale: no feature much narrower than the filter
survives); a smoothed step ``(tanh(beta eta) + tanh(beta (rho~ - eta))) / (tanh(beta eta) +
tanh(beta (1 - eta)))``, ``eta = 0.5``, whose slope ``beta`` is raised in stages (4, 16, 64) so the
density ends nearly binary; the cells averaged to the print grid's coverage and imaged through
the gap (:func:`masks.proximity.aerial_image_vjp`); the objective is the soft print's squared
error ``sum (sigmoid(b (I - t)) - target)^2`` (target: the drawn opening less the chromium undercut),
minimized by L-BFGS-B within the bounds, a fixed number of iterations per stage (deterministic).
The density is then cut at 0.5 and made manufacturable with the level set's own rule
(:func:`masks.opc.correct_mask` then applies its minimum-feature rule: every opening and chrome area at
least the minimum feature, and polishes the result with its level set).

What it gains and what it costs (tests/masks/test_opc_element.py, docs/limits.md): on that element at
30 um, 0.971 with 0.9 um features (0.976 after the level set's polish) and 0.995 with 0.45 um features;
about 15 s of CPU per 384^2-cell mask. The gray density before the cut reaches 0.99-1.0: the loss
is in the binary cut and the minimum feature.
"""

from __future__ import annotations

import math

import numpy as np
from scipy import fft as sfft
from scipy import ndimage, optimize, special

from .litho import block_coverage
from .proximity import ProximityOptics, aerial_image_vjp, reach_m

__all__ = ["BETAS", "density_mask", "density_sigma_cells", "project"]

#: Slopes of the smoothed step, one L-BFGS-B stage each.
BETAS = (4.0, 16.0, 64.0)
# The step's midpoint.
_ETA = 0.5
#: Filter sigma per minimum-feature cell (measured: 2.75 cells for 4-cell features, 2 for 2).
_SIGMA_PER_FEATURE = 0.7


def density_sigma_cells(min_feature_cells: int) -> float:
    """The filter's sigma (mask cells) for a minimum feature: ``0.7`` of it, at least 2 cells."""
    return max(_SIGMA_PER_FEATURE * int(min_feature_cells), 2.0)


def project(x: np.ndarray, beta: float) -> tuple[np.ndarray, np.ndarray]:
    """The smoothed step of a filtered density and its derivative (both of ``x``'s shape)."""
    norm = math.tanh(beta * _ETA) + math.tanh(beta * (1 - _ETA))
    th = np.tanh(beta * (x - _ETA))
    return (math.tanh(beta * _ETA) + th) / norm, beta * (1 - th ** 2) / norm


def density_mask(soft_target: np.ndarray, step_m: float, optics: ProximityOptics, threshold: float,
                 subgrid: int, sigma_cells: float, iterations: int, steepness: float) -> np.ndarray:
    """The density stage's binary mask (before the minimum-feature rule), on the mask grid.

    Parameters
    ----------
    soft_target : ndarray of float32, shape (rows, cols)
        What the resist must clear on the print grid (the drawn opening less the undercut).
    step_m : float
        Print-grid step (m).
    optics, threshold
        The exposure (:class:`masks.proximity.ProximityOptics`, the clearing level).
    subgrid : int
        Mask cells per print cell a side.
    sigma_cells : float
        The filter's sigma (mask cells): the length scale.
    iterations : int
        L-BFGS-B iterations per stage of :data:`BETAS`.
    steepness : float
        The soft print's slope ``b``.

    Returns
    -------
    ndarray of bool, shape (rows * subgrid, cols * subgrid)
    """
    target = np.asarray(soft_target, dtype=np.float32)
    rows, cols = target.shape
    s = int(subgrid)
    pad = int(math.ceil(reach_m(optics, step_m) / step_m)) + 1
    shape = (sfft.next_fast_len(rows + 2 * pad), sfft.next_fast_len(cols + 2 * pad))
    inner = (slice(pad, pad + rows), slice(pad, pad + cols))
    drawn = np.repeat(np.repeat(target > 0.5, s, axis=0), s, axis=1)
    rho = 0.25 + 0.5 * drawn.astype(np.float64)
    b, t = float(steepness), float(threshold)

    for beta in BETAS:
        def cost(x, beta=beta):
            filtered = ndimage.gaussian_filter(x.reshape(drawn.shape), sigma_cells, mode="constant")
            density, slope = project(filtered, beta)
            padded = np.zeros(shape, dtype=np.float32)
            padded[inner] = block_coverage(density, s)
            image, vjp = aerial_image_vjp(padded, step_m, optics)
            soft = special.expit(b * (image[inner] - t))
            residual = soft - target
            cot = np.zeros(shape, dtype=np.float32)
            cot[inner] = 2 * b * residual * soft * (1 - soft)
            grad = np.repeat(np.repeat(vjp(cot)[inner] / (s * s), s, axis=0), s, axis=1) * slope
            grad = ndimage.gaussian_filter(grad, sigma_cells, mode="constant")  # the filter is its own adjoint
            return float((residual.astype(np.float64) ** 2).sum()), grad.ravel()

        found = optimize.minimize(cost, rho.ravel(), jac=True, method="L-BFGS-B", bounds=optimize.Bounds(np.zeros(rho.size), np.ones(rho.size)),
                                  options={"maxiter": int(iterations)})
        rho = found.x.reshape(drawn.shape)
    density, _ = project(ndimage.gaussian_filter(rho, sigma_cells, mode="constant"), BETAS[-1])
    return density > 0.5
