"""Diffraction orders of a PSF stack: locating them, extrapolating a stack to wavelengths the
source cannot reach (400-440 nm) from the predicted order positions, and comparing a measured
stack with a predicted one order by order."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import ArrayLike
from scipy import ndimage

from doedesign.engine.psf import PSFResult
from doedesign.errors import DoeError

from .capture import centroid, crop_to_window
from .stack import WAVELENGTH_TOLERANCE_M, PSFStack, _match_wavelength, as_stack, check_wavelengths

__all__ = ["compare_stacks", "extrapolate_orders", "locate_orders", "order_energies"]


def locate_orders(psf2d: np.ndarray, axis_pixel: Sequence[float] | np.ndarray, orders: Sequence[int] = (0, 1, 2),
                  exclude_radius_px: float = 8.0, refine_radius_px: float = 3.0,
                  guess: tuple[float, float] | None = None) -> np.ndarray:
    """Positions (row, col) of diffraction orders in a grating-like PSF.

    The 0th order of an on-axis source is at the axis. The first order is the brightest spot
    outside ``exclude_radius_px`` of the axis (or the brightest spot near ``guess``, an offset
    from the axis), refined by its centroid; order ``m`` lies at ``m`` times the first-order
    offset (equal spacing of the grating equation in the paraxial regime).

    Returns
    -------
    ndarray (len(orders), 2)
    """
    psf2d = np.asarray(psf2d, dtype=float)
    axis = np.asarray(axis_pixel, dtype=float)
    r, c = np.indices(psf2d.shape)
    dist2 = (r - axis[0]) ** 2 + (c - axis[1]) ** 2
    if guess is None:
        search = np.where(dist2 > exclude_radius_px ** 2, psf2d, -np.inf)
    else:
        g = axis + np.asarray(guess, dtype=float)
        search = np.where((r - g[0]) ** 2 + (c - g[1]) ** 2 <= exclude_radius_px ** 2, psf2d, -np.inf)
    if not np.isfinite(search).any():
        raise DoeError("no pixel left to search for the first diffraction order")
    peak = np.unravel_index(np.argmax(search), psf2d.shape)
    first = np.array(centroid(psf2d, peak, refine_radius_px)) - axis
    return np.array([axis + m * first for m in orders])


def extrapolate_orders(stack: PSFStack, predicted: PSFStack | PSFResult, target_wavelengths_m: ArrayLike,
                       source_wavelength_m: float | None = None, orders: Sequence[int] = (0, 1, 2),
                       patch_radius_px: float | None = None, positions: str = "simulated") -> PSFStack:
    """Fill in wavelengths the source cannot reach from one measured band (the seed's method).

    The measured coded PSF at ``source_wavelength_m`` (default: the shortest measured) is cut
    into one patch per diffraction order (pixels nearest that order, within ``patch_radius_px``);
    each patch is moved to where the predicted PSF puts that order at the target wavelength.
    The patches' energies -- the relative intensities of the orders -- are kept. The uncoded
    view is the source band's measured one.

    Parameters
    ----------
    stack : PSFStack
    predicted : PSFStack or PSFResult
        Simulated PSFs at the source and every target wavelength (order positions).
    target_wavelengths_m : sequence of float
    orders : sequence of int
    patch_radius_px : float, optional
        Default: half the first-order distance at the source wavelength (patches never overlap).
    positions : {"simulated", "relative"}
        "simulated": orders go to the predicted positions; "relative": the measured source
        positions plus the predicted change (keeps an offset between measurement and model).

    Returns
    -------
    PSFStack
        The input stack with the target wavelengths added (``measured`` False there) and
        ``info["extrapolation"]`` recording source, positions and the energy kept per band.
    """
    predicted = as_stack(predicted)
    targets = check_wavelengths(target_wavelengths_m, "extrapolation wavelengths")
    if positions not in ("simulated", "relative"):
        raise DoeError(f"positions must be 'simulated' or 'relative', got {positions!r}")
    if source_wavelength_m is None:
        source_wavelength_m = stack.wavelengths_m[stack.measured][0]
    si = _match_wavelength(stack.wavelengths_m, source_wavelength_m, "the measured stack")
    if np.any(np.abs(stack.wavelengths_m[:, None] - targets[None, :]).min(axis=0) <= WAVELENGTH_TOLERANCE_M):
        raise DoeError("extrapolation wavelengths must not repeat measured ones")
    meas = stack.view("coded")[si]
    axis_m = np.asarray(stack.axis_pixel, float)
    axis_p = np.asarray(predicted.axis_pixel, float)
    pred_s = locate_orders(predicted.view("coded")[_match_wavelength(predicted.wavelengths_m, stack.wavelengths_m[si],
                                                                     "the predicted stack")], axis_p, orders)
    first_idx = list(orders).index(1) if 1 in orders else None
    spacing = np.linalg.norm(pred_s[first_idx] - axis_p) if first_idx is not None else None
    if patch_radius_px is None:
        if spacing is None:
            raise DoeError("give patch_radius_px when the first order is not among the orders")
        patch_radius_px = spacing / 2
    # Measured order positions: the centroid near each predicted one (the model may be off a little).
    meas_pos = np.array([centroid(meas, np.round(axis_m + p - axis_p).astype(int), max(patch_radius_px / 2, 2))
                         for p in pred_s])
    r, c = np.indices(meas.shape)
    d2 = np.stack([(r - p[0]) ** 2 + (c - p[1]) ** 2 for p in meas_pos])
    owner = np.argmin(d2, axis=0)
    inside = d2.min(axis=0) <= patch_radius_px ** 2
    patches = [np.where(inside & (owner == k), meas, 0.0) for k in range(len(orders))]
    kept = float(sum(p.sum() for p in patches) / meas.sum()) if meas.sum() > 0 else 0.0
    new_psf, record = [], []
    for wl in targets:
        pred_t = locate_orders(predicted.view("coded")[_match_wavelength(predicted.wavelengths_m, wl,
                                                                         "the predicted stack")],
                               axis_p, orders, guess=(pred_s[first_idx] - axis_p) * wl / stack.wavelengths_m[si]
                               if first_idx is not None else None)
        goal = axis_m + (pred_t - axis_p) if positions == "simulated" else meas_pos + (pred_t - pred_s)
        coded = sum(ndimage.shift(p, g - m, order=1, mode="constant") for p, g, m in zip(patches, goal, meas_pos))
        new_psf.append(np.stack([coded, stack.view("uncoded")[si]]))
        record.append({"wavelength_nm": wl * 1e9, "order_positions": goal.tolist()})
    wl_all = np.concatenate([stack.wavelengths_m, targets])
    order = np.argsort(wl_all)
    psf_all = np.concatenate([stack.psf, np.stack(new_psf, axis=1)], axis=1)[:, order]
    measured = np.concatenate([stack.measured, np.zeros(targets.size, bool)])[order]
    info = dict(stack.info)
    info["extrapolation"] = {"source_wavelength_nm": stack.wavelengths_m[si] * 1e9, "orders": list(orders),
                             "source_order_positions": meas_pos.tolist(), "patch_radius_px": float(patch_radius_px),
                             "energy_kept": kept, "positions": positions, "targets": record}
    spectra = None
    if stack.spectra is not None:
        spectra = np.concatenate([stack.spectra, np.full((targets.size, stack.spectra.shape[1]), np.nan)])[order]
    return PSFStack(psf=psf_all, wavelengths_m=wl_all[order], pixel_pitch_m=stack.pixel_pitch_m,
                    axis_pixel=stack.axis_pixel, measured=measured, normalization=stack.normalization,
                    depth_m=stack.depth_m, spectrum_wavelengths_m=stack.spectrum_wavelengths_m, spectra=spectra,
                    info=info)


# -- comparison -------------------------------------------------------------------------------------------
def order_energies(psf2d: np.ndarray, positions: np.ndarray, radius_px: float) -> np.ndarray:
    """Energy within ``radius_px`` of each order position (pixels nearest that order only)."""
    r, c = np.indices(psf2d.shape)
    d2 = np.stack([(r - p[0]) ** 2 + (c - p[1]) ** 2 for p in positions])
    owner = np.argmin(d2, axis=0)
    inside = d2.min(axis=0) <= radius_px ** 2
    return np.array([psf2d[inside & (owner == k)].sum() for k in range(len(positions))])


def compare_stacks(measured: PSFStack, predicted: PSFStack | PSFResult, orders: Sequence[int] = (0, 1, 2),
                   order_radius_px: float | None = None, target: np.ndarray | None = None,
                   name: str = "predicted") -> tuple[dict, np.ndarray]:
    """Per-wavelength comparison of a measured stack with predicted PSFs.

    Parameters
    ----------
    measured : PSFStack
    predicted : PSFStack or PSFResult
        Must hold every measured wavelength; cropped around its axis to the measured window.
    orders : sequence of int
        Diffraction orders to locate (grating-like elements); empty to skip.
    order_radius_px : float, optional
        Radius of an order's energy disk; default a third of the first-order distance.
    target : ndarray (rows, cols) or (wavelengths, rows, cols), optional
        Weights of the target region (1 inside); "energy on target" is the coded PSF's sum over it.
    name : str
        Name of the prediction (for messages and the report).

    Returns
    -------
    report : dict
        Per wavelength: positions and energies of the orders (measured and predicted), energy in
        window, energy on target, rms and peak of the difference.
    difference : ndarray (2, wavelengths, rows, cols)
        measured - predicted, in the stack's normalization.
    """
    predicted = as_stack(predicted)
    axis = np.asarray(measured.axis_pixel)
    idx = [_match_wavelength(predicted.wavelengths_m, wl, f"the {name} PSFs") for wl in measured.wavelengths_m]
    pred = crop_to_window(predicted.psf[:, idx], predicted.axis_pixel, measured.psf.shape[-2:], measured.axis_pixel)
    difference = measured.psf - pred
    if target is not None:
        target = np.broadcast_to(np.asarray(target, dtype=float), measured.psf.shape[1:])
    assert measured.measured is not None  # set by PSFStack.__post_init__
    rows = []
    for i, wl in enumerate(measured.wavelengths_m):
        row = {"wavelength_nm": float(wl * 1e9), "measured": bool(measured.measured[i]),
               "energy_in_window": {"measured": measured.psf[:, i].sum(axis=(-2, -1)).tolist(),
                                    name: pred[:, i].sum(axis=(-2, -1)).tolist()},
               "difference_rms": [float(np.sqrt(np.mean(d ** 2))) for d in difference[:, i]],
               "difference_max_abs": [float(np.abs(d).max()) for d in difference[:, i]]}
        if orders:
            pos_p = locate_orders(pred[0, i], axis, orders)
            first = np.linalg.norm(pos_p[list(orders).index(1)] - axis) if 1 in orders else 8.0
            radius = order_radius_px or max(first / 3, 2.0)
            pos_m = np.array([centroid(measured.psf[0, i], np.round(p).astype(int), max(radius / 2, 2)) for p in pos_p])
            row["orders"] = list(orders)
            row["order_positions"] = {"measured": pos_m.tolist(), name: pos_p.tolist()}
            row["order_energies"] = {"measured": order_energies(measured.psf[0, i], pos_m, radius).tolist(),
                                     name: order_energies(pred[0, i], pos_p, radius).tolist()}
            row["order_radius_px"] = float(radius)
        if target is not None:
            row["energy_on_target"] = {"measured": float((measured.psf[0, i] * target[i]).sum()),
                                       name: float((pred[0, i] * target[i]).sum())}
        rows.append(row)
    return {"prediction": name, "normalization": measured.normalization, "wavelengths": rows}, difference
