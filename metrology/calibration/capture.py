"""One narrowband capture to a calibrated PSF window, and captures to a :class:`~metrology.calibration.stack.PSFStack`.

Per capture: background subtraction, centring on the uncoded view's peak (or a given axis),
normalization (see :mod:`metrology.calibration.psfstack` for the energy bookkeeping) and
cropping to the sensor window around the axis.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence

import numpy as np
from numpy.typing import ArrayLike
from scipy import ndimage

from doedesign.errors import DoeError
from doedesign.progress import Progress

from .stack import BACKGROUNDS, NORMALIZATIONS, PSFStack, check_wavelengths

__all__ = ["build_stack", "calibrate_capture", "centroid", "crop_to_window", "estimate_background", "find_peak"]

log = logging.getLogger(__name__)


def estimate_background(image: np.ndarray, method: str = "border", border_px: int = 16,
                        percentile: float = 20.0) -> float:
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


def find_peak(image: np.ndarray, smooth_px: float = 1.0) -> tuple[int, int]:
    """(row, col) of the brightest pixel after a small Gaussian smoothing (suppresses hot pixels)."""
    smooth = ndimage.gaussian_filter(np.asarray(image, dtype=float), smooth_px) if smooth_px else image
    row, col = np.unravel_index(np.argmax(smooth), smooth.shape)
    return int(row), int(col)


def centroid(image: np.ndarray, centre: ArrayLike, radius_px: float,
             iterations: int = 5) -> tuple[float, float]:
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


def crop_to_window(image: np.ndarray, centre: tuple[float, float], window_shape: tuple[int, int] = (512, 512),
                   axis_pixel: tuple[int, int] = (256, 256)) -> np.ndarray:
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


def calibrate_capture(coded: np.ndarray, uncoded: np.ndarray, window_shape: tuple[int, int] = (512, 512),
                      axis_pixel: tuple[int, int] = (256, 256), centre: tuple[float, float] | None = None,
                      dark: np.ndarray | None = None, background: str = "border", border_px: int = 16,
                      percentile: float = 20.0, normalization: str = "uncoded",
                      name: str = "capture") -> tuple[np.ndarray, dict]:
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


def build_stack(captures: Sequence[tuple[np.ndarray, np.ndarray]], wavelengths_m: ArrayLike, pixel_pitch_m: float,
                window_shape: tuple[int, int] = (512, 512), axis_pixel: tuple[int, int] = (256, 256),
                centre: tuple[float, float] | None = None, darks: np.ndarray | None = None,
                background: str = "border", normalization: str = "uncoded",
                spectrum_wavelengths_m: ArrayLike | None = None, spectra: ArrayLike | None = None,
                depth_m: float = np.inf, names: Sequence[str] | None = None) -> PSFStack:
    """A :class:`~metrology.calibration.stack.PSFStack` from one (coded, uncoded) view pair per wavelength.

    ``darks`` is one (coded, uncoded) dark pair for all captures or None; ``spectra`` the
    measured spectrum of each band on ``spectrum_wavelengths_m`` (optional).
    """
    wl = check_wavelengths(wavelengths_m)
    if len(captures) != wl.size:
        raise DoeError(f"{len(captures)} captures for {wl.size} wavelengths; give one capture per wavelength")
    names = names or [f"capture at {w * 1e9:g} nm" for w in wl]
    psf = np.empty((2, wl.size) + tuple(window_shape))
    info: dict[str, list] = {}
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
    band_spectra = None
    spectrum_wl = None if spectrum_wavelengths_m is None else np.asarray(spectrum_wavelengths_m, dtype=float)
    if spectra is not None:
        if spectrum_wavelengths_m is None:
            raise DoeError("spectra given without their spectrum_wavelengths_m")
        band_spectra = np.asarray(spectra, dtype=float)
        spectrum_wl = check_wavelengths(spectrum_wavelengths_m, "spectrum wavelengths")
        if band_spectra.shape != (wl.size, spectrum_wl.size):
            raise DoeError(f"spectra must be ({wl.size} bands, {spectrum_wl.size} samples), "
                           f"got {band_spectra.shape}")
    return PSFStack(psf=psf, wavelengths_m=wl, pixel_pitch_m=pixel_pitch_m, axis_pixel=axis_pixel,
                    normalization=normalization, depth_m=depth_m, spectrum_wavelengths_m=spectrum_wl,
                    spectra=band_spectra, info=info)
