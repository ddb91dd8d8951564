"""Measured PSF stacks: from separated views to calibrated, comparable, exportable PSFs.

Pipeline per narrowband capture (one wavelength): background subtraction, centring on the
uncoded view's peak (or a given axis), normalization, cropping to the sensor window around the
axis; then extrapolation to wavelengths the source cannot reach, comparison with predicted
PSFs, and export for reconstruction networks and the diagnosis stage.

Energy bookkeeping (default ``normalization="uncoded"``): both views of a wavelength are divided
by the uncoded view's total over the whole background-subtracted frame, before cropping. Both
halves of the aperture pass the same light, so the numbers are directly the engine's quantity
(fraction of the light through a view's half-aperture per pixel): the uncoded window sum is the
share the window holds, the coded window sum is the coded efficiency relative to the uncoded
half, and light leaving the window is not hidden by renormalizing after the crop.

Arrays are row-major, row 0 at the top; a stack's axis sits at ``axis_pixel`` (row, col).
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy import ndimage

from doedesign.errors import DoeError
from doedesign.fileio import atomic_path, dumps_json, write_npz
from doedesign.progress import Progress
from doedesign.psf import VIEWS, read_psf_arrays

__all__ = ["BACKGROUNDS", "NORMALIZATIONS", "PSFStack", "WAVELENGTH_TOLERANCE_M", "as_stack",
           "band_centroid_fwhm", "build_stack", "calibrate_capture", "centroid", "check_wavelengths",
           "compare_stacks", "crop_to_window", "estimate_background", "extrapolate_orders", "find_peak",
           "load_stack", "locate_orders", "network_array", "order_energies", "read_stack",
           "save_network_npy", "save_stack"]

log = logging.getLogger(__name__)

NORMALIZATIONS = ("uncoded", "per_view")
BACKGROUNDS = ("border", "percentile", "none")
# Two wavelengths closer than this are the same band when matching measured and predicted stacks.
WAVELENGTH_TOLERANCE_M = 0.5e-9


@dataclass
class PSFStack:
    """Calibrated PSFs of both views over a set of wavelengths.

    Attributes
    ----------
    psf : ndarray (2, wavelengths, rows, cols)
        Views in :data:`doedesign.psf.VIEWS` order (coded, uncoded), normalized as
        ``normalization`` says; row 0 at the top, the axis at ``axis_pixel``.
    wavelengths_m : ndarray, strictly increasing
    pixel_pitch_m : float
    axis_pixel : (int, int)
    measured : ndarray of bool
        False for wavelengths filled in by :func:`extrapolate_orders`.
    normalization : str
    depth_m : float
        Point-source distance (inf: collimated source).
    spectrum_wavelengths_m, spectra : ndarray or None
        Each band's measured source spectrum, (K,) and (wavelengths, K).
    info : dict
        Per-wavelength bookkeeping lists (background, peak position, totals, ...).
    """

    psf: np.ndarray
    wavelengths_m: np.ndarray
    pixel_pitch_m: float
    axis_pixel: tuple = (256, 256)
    measured: np.ndarray = None
    normalization: str = "uncoded"
    depth_m: float = np.inf
    spectrum_wavelengths_m: np.ndarray = None
    spectra: np.ndarray = None
    info: dict = field(default_factory=dict)

    def __post_init__(self):
        self.psf = np.asarray(self.psf, dtype=float)
        self.wavelengths_m = check_wavelengths(self.wavelengths_m)
        if self.psf.ndim != 4 or self.psf.shape[0] != 2 or self.psf.shape[1] != self.wavelengths_m.size:
            raise DoeError(f"PSF stack must be (2 views, {self.wavelengths_m.size} wavelengths, rows, cols), "
                           f"got {self.psf.shape}")
        if self.measured is None:
            self.measured = np.ones(self.wavelengths_m.size, bool)
        self.measured = np.asarray(self.measured, bool)
        self.axis_pixel = tuple(int(v) for v in self.axis_pixel)

    @property
    def views(self):
        return VIEWS

    @property
    def energy_in_window(self):
        """(views, wavelengths) sums of the window."""
        return self.psf.sum(axis=(-2, -1))

    def view(self, name):
        """(wavelengths, rows, cols) PSFs of one view."""
        return self.psf[VIEWS.index(name)]

    def band_stats(self):
        """Centroid and FWHM (m) of each band's spectrum, or None without spectra."""
        if self.spectra is None:
            return None
        return np.array([band_centroid_fwhm(self.spectrum_wavelengths_m, s) for s in self.spectra])


def check_wavelengths(wavelengths_m, name="wavelengths"):
    """Positive, finite, strictly increasing wavelengths as a float array, or DoeError."""
    wl = np.atleast_1d(np.asarray(wavelengths_m, dtype=float))
    if wl.size == 0:
        raise DoeError(f"{name}: no wavelengths given")
    if not np.all(np.isfinite(wl)) or np.any(wl <= 0):
        raise DoeError(f"{name}: wavelengths must be positive, got {np.round(wl * 1e9, 2).tolist()} nm")
    if np.any(np.diff(wl) <= 0):
        bad = int(np.flatnonzero(np.diff(wl) <= 0)[0])
        raise DoeError(f"{name}: wavelengths must increase strictly; {wl[bad] * 1e9:g} nm is followed by "
                       f"{wl[bad + 1] * 1e9:g} nm")
    return wl


# -- per-capture steps ---------------------------------------------------------------------------------
def estimate_background(image, method="border", border_px=16, percentile=20.0):
    """Background level of a frame: median of a border strip, or a low percentile of all pixels."""
    image = np.asarray(image, dtype=float)
    if method == "none":
        return 0.0
    if method == "percentile":
        return float(np.percentile(image, percentile))
    if method != "border":
        raise DoeError(f"unknown background method {method!r}; use one of {BACKGROUNDS} or a dark frame")
    b = int(border_px)
    if 2 * b >= min(image.shape):
        raise DoeError(f"background border of {b} px does not fit a {image.shape[0]} x {image.shape[1]} frame")
    strip = np.concatenate([image[:b].ravel(), image[-b:].ravel(), image[b:-b, :b].ravel(), image[b:-b, -b:].ravel()])
    return float(np.median(strip))


def find_peak(image, smooth_px=1.0):
    """(row, col) of the brightest pixel after a small Gaussian smoothing (suppresses hot pixels)."""
    smooth = ndimage.gaussian_filter(np.asarray(image, dtype=float), smooth_px) if smooth_px else image
    return tuple(int(v) for v in np.unravel_index(np.argmax(smooth), smooth.shape))


def centroid(image, centre, radius_px, iterations=5):
    """Intensity-weighted centroid (row, col) in a disk of ``radius_px`` around ``centre``.

    The disk is re-centred on the centroid ``iterations`` times: a disk that is off-centre on
    a spot biases its centroid toward the disk centre, a centred disk does not.
    """
    r, c = np.indices(np.shape(image))
    weights = np.clip(image, 0, None)
    cen = np.asarray(centre, dtype=float)
    for _ in range(max(int(iterations), 1)):
        disk = (r - cen[0]) ** 2 + (c - cen[1]) ** 2 <= radius_px ** 2
        w = np.where(disk, weights, 0.0)
        total = w.sum()
        if total <= 0:
            break
        new = np.array([(w * r).sum() / total, (w * c).sum() / total])
        if np.allclose(new, cen, atol=1e-4):
            cen = new
            break
        cen = new
    return float(cen[0]), float(cen[1])


def crop_to_window(image, centre, window_shape=(512, 512), axis_pixel=(256, 256)):
    """Window of ``window_shape`` with frame pixel ``centre`` (row, col) placed at ``axis_pixel``.

    Parts of the window outside the frame are zero. The leading axes of ``image`` (if any) are kept.
    """
    image = np.asarray(image)
    rows, cols = image.shape[-2:]
    if not (0 <= centre[0] < rows and 0 <= centre[1] < cols):
        raise DoeError(f"centre {tuple(centre)} lies outside the {rows} x {cols} frame")
    out = np.zeros(image.shape[:-2] + tuple(window_shape), dtype=image.dtype)
    r0, c0 = centre[0] - axis_pixel[0], centre[1] - axis_pixel[1]
    fr0, fr1 = max(r0, 0), min(r0 + window_shape[0], rows)
    fc0, fc1 = max(c0, 0), min(c0 + window_shape[1], cols)
    out[..., fr0 - r0:fr1 - r0, fc0 - c0:fc1 - c0] = image[..., fr0:fr1, fc0:fc1]
    return out


def calibrate_capture(coded, uncoded, window_shape=(512, 512), axis_pixel=(256, 256), centre=None,
                      dark=None, background="border", border_px=16, percentile=20.0,
                      normalization="uncoded", name="capture"):
    """One wavelength's views to normalized, centred windows.

    Parameters
    ----------
    coded, uncoded : ndarray (rows, cols)
        Separated (crosstalk-compensated) monochrome views.
    window_shape, axis_pixel : see :class:`doedesign.camera.Camera`.
    centre : (int, int), optional
        Frame pixel of the optical axis; default the uncoded view's peak.
    dark : (ndarray, ndarray), optional
        Dark frames of (coded, uncoded); subtracted instead of estimating a background level.
    background : {"border", "percentile", "none"}
    normalization : {"uncoded", "per_view"}
        "uncoded": both views over the uncoded view's whole-frame total (see the module notes);
        "per_view": each view over its own whole-frame total.

    Returns
    -------
    window : ndarray (2, rows, cols)
        Coded and uncoded windows.
    info : dict
    """
    coded = np.asarray(coded, dtype=float)
    uncoded = np.asarray(uncoded, dtype=float)
    if coded.shape != uncoded.shape:
        raise DoeError(f"{name}: coded view {coded.shape} and uncoded view {uncoded.shape} differ in size")
    if normalization not in NORMALIZATIONS:
        raise DoeError(f"unknown normalization {normalization!r}; use one of {NORMALIZATIONS}")
    views = np.stack([coded, uncoded])
    if dark is not None:
        dark = np.asarray(dark, dtype=float)
        if dark.shape != views.shape:
            raise DoeError(f"{name}: dark frames are {dark.shape[1:]} but the capture is {coded.shape}")
        views = views - dark
        levels = [float(np.median(d)) for d in dark]
    else:
        levels = [estimate_background(v, background, border_px, percentile) for v in views]
        views = views - np.array(levels)[:, None, None]
    if centre is None:
        centre = find_peak(views[1])
    totals = views.sum(axis=(-2, -1))
    if totals[1] <= 0:
        raise DoeError(f"{name}: the uncoded view holds no light after background subtraction")
    if normalization == "uncoded":
        scale = np.array([totals[1], totals[1]])
    else:
        if totals[0] <= 0:
            raise DoeError(f"{name}: the coded view holds no light after background subtraction")
        scale = totals
    window = crop_to_window(views / scale[:, None, None], centre, window_shape, axis_pixel)
    info = {"background": levels, "centre": [int(centre[0]), int(centre[1])],
            "uncoded_centroid": list(centroid(views[1], centre, 3.0)),
            "frame_total": totals.tolist(), "coded_to_uncoded_total": float(totals[0] / totals[1]),
            "energy_in_window": window.sum(axis=(-2, -1)).tolist()}
    return window, info


def build_stack(captures, wavelengths_m, pixel_pitch_m, window_shape=(512, 512), axis_pixel=(256, 256),
                centre=None, darks=None, background="border", normalization="uncoded",
                spectrum_wavelengths_m=None, spectra=None, depth_m=np.inf, names=None):
    """A :class:`PSFStack` from one (coded, uncoded) view pair per wavelength.

    ``darks`` is one (coded, uncoded) dark pair for all captures or None; ``spectra`` the
    measured spectrum of each band on ``spectrum_wavelengths_m`` (optional).
    """
    wl = check_wavelengths(wavelengths_m)
    if len(captures) != wl.size:
        raise DoeError(f"{len(captures)} captures for {wl.size} wavelengths; give one capture per wavelength")
    names = names or [f"capture at {w * 1e9:g} nm" for w in wl]
    psf = np.empty((2, wl.size) + tuple(window_shape))
    info = {}
    with Progress(wl.size, desc="PSF stack") as bar:
        for i, (coded, uncoded) in enumerate(captures):
            psf[:, i], one = calibrate_capture(coded, uncoded, window_shape, axis_pixel, centre, darks, background,
                                               normalization=normalization, name=names[i])
            for key, value in one.items():
                info.setdefault(key, []).append(value)
            bar.update(1)
    centres = np.array(info["centre"])
    if wl.size > 1 and np.ptp(centres, axis=0).max() > 2:
        log.warning("uncoded peaks spread over %s px across wavelengths (lateral colour or a moving source?)",
                    np.ptp(centres, axis=0).tolist())
    if spectra is not None:
        spectra = np.asarray(spectra, dtype=float)
        spectrum_wavelengths_m = check_wavelengths(spectrum_wavelengths_m, "spectrum wavelengths")
        if spectra.shape != (wl.size, spectrum_wavelengths_m.size):
            raise DoeError(f"spectra must be ({wl.size} bands, {spectrum_wavelengths_m.size} samples), "
                           f"got {spectra.shape}")
    return PSFStack(psf=psf, wavelengths_m=wl, pixel_pitch_m=pixel_pitch_m, axis_pixel=axis_pixel,
                    normalization=normalization, depth_m=depth_m, spectrum_wavelengths_m=spectrum_wavelengths_m,
                    spectra=spectra, info=info)


def band_centroid_fwhm(wavelengths_m, spectrum):
    """Centroid and full width at half maximum (m) of a measured source spectrum."""
    wl = np.asarray(wavelengths_m, dtype=float)
    s = np.clip(np.asarray(spectrum, dtype=float) - np.min(spectrum), 0, None)
    if s.max() <= 0:
        raise DoeError("a band's spectrum holds no signal")
    cen = float((wl * s).sum() / s.sum())
    above = np.flatnonzero(s >= s.max() / 2)
    lo, hi = above[0], above[-1]
    # Linear interpolation of the half-maximum crossings on both flanks.
    left = wl[lo] if lo == 0 else np.interp(s.max() / 2, [s[lo - 1], s[lo]], [wl[lo - 1], wl[lo]])
    right = wl[hi] if hi == wl.size - 1 else np.interp(s.max() / 2, [s[hi + 1], s[hi]], [wl[hi + 1], wl[hi]])
    return cen, float(right - left)


# -- diffraction orders and extrapolation ---------------------------------------------------------------
def locate_orders(psf2d, axis_pixel, orders=(0, 1, 2), exclude_radius_px=8.0, refine_radius_px=3.0, guess=None):
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


def _match_wavelength(wavelengths_m, wl, what):
    idx = np.flatnonzero(np.abs(np.asarray(wavelengths_m) - wl) <= WAVELENGTH_TOLERANCE_M)
    if idx.size == 0:
        raise DoeError(f"{what} has no PSF at {wl * 1e9:g} nm (it holds "
                       f"{', '.join(f'{w * 1e9:g}' for w in wavelengths_m)} nm)")
    return int(idx[0])


def as_stack(psf_result, depth_index=0):
    """A :class:`PSFStack` from a :class:`doedesign.psf.PSFResult` (one depth) or a stack."""
    if isinstance(psf_result, PSFStack):
        return psf_result
    try:
        coded = psf_result.view("coded")[depth_index]
        uncoded = psf_result.view("uncoded")[depth_index]
    except ValueError:
        raise DoeError(f"predicted PSFs must hold both views, got {psf_result.views}") from None
    return PSFStack(psf=np.stack([coded, uncoded]), wavelengths_m=psf_result.wavelengths_m,
                    pixel_pitch_m=psf_result.pixel_pitch_m, axis_pixel=psf_result.axis_pixel,
                    depth_m=float(psf_result.depths_m[depth_index]))


def extrapolate_orders(stack, predicted, target_wavelengths_m, source_wavelength_m=None, orders=(0, 1, 2),
                       patch_radius_px=None, positions="simulated"):
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
def order_energies(psf2d, positions, radius_px):
    """Energy within ``radius_px`` of each order position (pixels nearest that order only)."""
    r, c = np.indices(psf2d.shape)
    d2 = np.stack([(r - p[0]) ** 2 + (c - p[1]) ** 2 for p in positions])
    owner = np.argmin(d2, axis=0)
    inside = d2.min(axis=0) <= radius_px ** 2
    return np.array([psf2d[inside & (owner == k)].sum() for k in range(len(positions))])


def compare_stacks(measured, predicted, orders=(0, 1, 2), order_radius_px=None, target=None, name="predicted"):
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


# -- export -----------------------------------------------------------------------------------------------------
def network_array(stacks):
    """The layout reconstruction networks load: (2, H, W, C), uncoded view first.

    ``stacks`` is one :class:`PSFStack` (C = wavelengths) or a list of stacks at increasing
    depths, giving (2, D, H, W, C).
    """
    single = isinstance(stacks, PSFStack)
    arrs = []
    for s in [stacks] if single else stacks:
        arrs.append(np.moveaxis(s.psf[[VIEWS.index("uncoded"), VIEWS.index("coded")]], 1, -1))
    if not single and len({a.shape for a in arrs}) != 1:
        raise DoeError("stacks at different depths must share window and wavelengths")
    return arrs[0] if single else np.stack(arrs, axis=1)


def save_network_npy(stacks, path):
    """Write :func:`network_array` as ``.npy`` atomically (float32)."""
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        np.save(fh, network_array(stacks).astype(np.float32))
    return Path(path)


def save_stack(stack, path):
    """Write the tool's PSF ``.npz``: the fields of :meth:`doedesign.psf.PSFResult.save` plus calibration ones.

    ``psf`` is (views, depths=1, wavelengths, rows, cols) with views (coded, uncoded), so
    :meth:`PSFResult.load` and the diagnosis stage read it; ``measured`` flags extrapolated
    bands; ``bandwidth_fwhm_m`` / ``band_centroid_m`` come from the spectra (NaN without).
    """
    stats = stack.band_stats()
    if stats is None:
        stats = np.full((stack.wavelengths_m.size, 2), np.nan)
    extra = {}
    if stack.spectra is not None:
        extra = {"spectrum_wavelengths_m": stack.spectrum_wavelengths_m, "spectra": stack.spectra}
    return write_npz(
        path, psf=stack.psf[:, None], views=np.array(VIEWS), wavelengths_m=stack.wavelengths_m,
        depths_m=np.array([stack.depth_m]), depth_m=np.float64(stack.depth_m),
        pixel_pitch_m=np.float64(stack.pixel_pitch_m), energy_in_window=stack.energy_in_window[:, None],
        axis_pixel=np.asarray(stack.axis_pixel), measured=stack.measured,
        normalization=np.str_(stack.normalization), band_centroid_m=stats[:, 0], bandwidth_fwhm_m=stats[:, 1],
        sampling=np.str_(dumps_json({"source": "measured"}, indent=None)), info=np.str_(dumps_json(stack.info, indent=None)),
        **extra)


def read_stack(path):
    """Read a PSF stack ``.npz`` (a measured stack, :func:`save_stack` or a PSFResult file).

    The one set of rules for PSF-stack files: ``psf`` is (views, wavelengths, rows, cols),
    (wavelengths, rows, cols) for one view, or 5-D with a single depth; ``views`` names each
    view from :data:`doedesign.psf.VIEWS` (default ``("coded",)`` for one view);
    ``wavelengths_m`` are in metres; ``depths_m`` (first) or ``depth_m`` give the source
    distance; ``axis_pixel`` is (row, col), row 0 at the top.

    Returns
    -------
    dict
        ``psf`` (views, wavelengths, rows, cols) in the file's view order, ``views``,
        ``wavelengths_m``, ``pixel_pitch_m``, ``depth_m`` and ``axis_pixel`` (None when
        absent), and the optional ``measured``, ``normalization``, ``spectrum_wavelengths_m``,
        ``spectra`` and ``info`` (None when absent).
    """
    path = Path(path)
    data = read_psf_arrays(path, ("psf", "wavelengths_m", "pixel_pitch_m"), what="PSF stack")
    psf = np.asarray(data["psf"], dtype=float)
    wl = np.atleast_1d(np.asarray(data["wavelengths_m"], dtype=float))
    if psf.ndim == 5:
        if psf.shape[1] != 1:
            raise DoeError(f"{path}: holds {psf.shape[1]} depths; load one depth with PSFResult.load")
        psf = psf[:, 0]
    if psf.ndim == 3:
        psf = psf[None]
    if psf.ndim != 4 or psf.shape[1] != wl.size:
        raise DoeError(f"{path}: psf must be (wavelengths, rows, cols) or (views, wavelengths, rows, cols) "
                       f"with {wl.size} wavelengths, got shape {psf.shape}")
    if np.any(~(wl > 100e-9)) or np.any(wl > 20e-6):
        raise DoeError(f"{path}: wavelengths_m must be in metres, got {wl.tolist()}")
    views = tuple(str(v) for v in data["views"]) if "views" in data else ("coded",)
    if len(views) != psf.shape[0] or len(set(views)) != len(views) or any(v not in VIEWS for v in views):
        raise DoeError(f"{path}: {psf.shape[0]} view(s) in psf but views lists {list(views)} "
                       f"(each one of {list(VIEWS)})")
    if "depths_m" in data:
        depth = float(np.atleast_1d(data["depths_m"])[0])
    else:
        depth = float(data["depth_m"]) if "depth_m" in data else None
    axis = tuple(int(v) for v in data["axis_pixel"]) if "axis_pixel" in data else None
    info = data.get("info")
    return {"psf": psf, "views": views, "wavelengths_m": wl, "pixel_pitch_m": float(data["pixel_pitch_m"]),
            "depth_m": depth, "axis_pixel": axis, "measured": data.get("measured"),
            "normalization": str(data["normalization"]) if "normalization" in data else None,
            "spectrum_wavelengths_m": data.get("spectrum_wavelengths_m"), "spectra": data.get("spectra"),
            "info": json.loads(str(info)) if info is not None else None}


def load_stack(path):
    """Read a PSF stack of both views (see :func:`read_stack` for the rules) as a :class:`PSFStack`."""
    d = read_stack(path)
    if sorted(d["views"]) != sorted(VIEWS):
        raise DoeError(f"{path}: a calibrated stack holds both views {list(VIEWS)}, got {list(d['views'])}")
    psf = d["psf"][[d["views"].index(v) for v in VIEWS]]
    return PSFStack(psf=psf, wavelengths_m=d["wavelengths_m"], pixel_pitch_m=d["pixel_pitch_m"],
                    axis_pixel=d["axis_pixel"] or (256, 256), measured=d["measured"],
                    normalization=d["normalization"] or "uncoded",
                    depth_m=np.inf if d["depth_m"] is None else d["depth_m"],
                    spectrum_wavelengths_m=d["spectrum_wavelengths_m"], spectra=d["spectra"], info=d["info"] or {})
