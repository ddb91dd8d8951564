"""The measured PSF stack: its container, its wavelengths and spectra, and its files.

A :class:`PSFStack` holds both views' calibrated PSFs over a set of wavelengths (arrays
row-major, row 0 at the top, the axis at ``axis_pixel``); it is saved as the tool's PSF
``.npz``, read back from it or from a predicted PSF file, and exported for reconstruction
networks as ``(2, H, W, C)`` (uncoded view first).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from doedesign.engine.psf import VIEWS, PSFResult, read_psf_arrays
from doedesign.errors import DoeError
from doedesign.fileio import atomic_path, dumps_json, parse_json, write_npz

__all__ = ["BACKGROUNDS", "NORMALIZATIONS", "PSFStack", "WAVELENGTH_TOLERANCE_M", "as_stack", "band_centroid_fwhm",
           "check_wavelengths", "load_stack", "network_array", "read_stack", "save_network_npy", "save_stack"]

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
        Views in :data:`doedesign.engine.result.VIEWS` order (coded, uncoded), normalized as
        ``normalization`` says; row 0 at the top, the axis at ``axis_pixel``.
    wavelengths_m : ndarray, strictly increasing
    pixel_pitch_m : float
    axis_pixel : (int, int)
    measured : ndarray of bool
        False for wavelengths filled in by :func:`~metrology.calibration.orders.extrapolate_orders`.
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
    measured: np.ndarray | None = None  # an array after __post_init__
    normalization: str = "uncoded"
    depth_m: float = np.inf
    spectrum_wavelengths_m: np.ndarray | None = None
    spectra: np.ndarray | None = None
    info: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
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
    def views(self) -> tuple[str, ...]:
        return VIEWS

    @property
    def energy_in_window(self) -> np.ndarray:
        """(views, wavelengths) sums of the window."""
        return self.psf.sum(axis=(-2, -1))

    def view(self, name: str) -> np.ndarray:
        """(wavelengths, rows, cols) PSFs of one view."""
        return self.psf[VIEWS.index(name)]

    def band_stats(self) -> np.ndarray | None:
        """Centroid and FWHM (m) of each band's spectrum, or None without spectra."""
        if self.spectra is None or self.spectrum_wavelengths_m is None:
            return None
        return np.array([band_centroid_fwhm(self.spectrum_wavelengths_m, s) for s in self.spectra])


def check_wavelengths(wavelengths_m: ArrayLike, name: str = "wavelengths") -> np.ndarray:
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


def band_centroid_fwhm(wavelengths_m: ArrayLike, spectrum: ArrayLike) -> tuple[float, float]:
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


def _match_wavelength(wavelengths_m, wl, what):
    idx = np.flatnonzero(np.abs(np.asarray(wavelengths_m) - wl) <= WAVELENGTH_TOLERANCE_M)
    if idx.size == 0:
        raise DoeError(f"{what} has no PSF at {wl * 1e9:g} nm (it holds "
                       f"{', '.join(f'{w * 1e9:g}' for w in wavelengths_m)} nm)")
    return int(idx[0])


def as_stack(psf_result: PSFResult | PSFStack, depth_index: int = 0) -> PSFStack:
    """A :class:`PSFStack` from a :class:`doedesign.engine.result.PSFResult` (one depth) or a stack."""
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


def network_array(stacks: PSFStack | Sequence[PSFStack]) -> np.ndarray:
    """The layout reconstruction networks load: (2, H, W, C), uncoded view first.

    ``stacks`` is one :class:`PSFStack` (C = wavelengths) or a list of stacks at increasing
    depths, giving (2, D, H, W, C).
    """
    listed = [stacks] if isinstance(stacks, PSFStack) else list(stacks)
    single = isinstance(stacks, PSFStack)
    arrs = []
    for s in listed:
        arrs.append(np.moveaxis(s.psf[[VIEWS.index("uncoded"), VIEWS.index("coded")]], 1, -1))
    if not single and len({a.shape for a in arrs}) != 1:
        raise DoeError("stacks at different depths must share window and wavelengths")
    return arrs[0] if single else np.stack(arrs, axis=1)


def save_network_npy(stacks: PSFStack | Sequence[PSFStack], path: str | Path) -> Path:
    """Write :func:`network_array` as ``.npy`` atomically (float32)."""
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        np.save(fh, network_array(stacks).astype(np.float32))
    return Path(path)


def save_stack(stack: PSFStack, path: str | Path) -> Path:
    """Write the tool's PSF ``.npz``: the fields of :meth:`doedesign.engine.result.PSFResult.save` plus calibration ones.

    ``psf`` is (views, depths=1, wavelengths, rows, cols) with views (coded, uncoded), so
    :meth:`PSFResult.load <doedesign.engine.result.PSFResult.load>` and the diagnosis stage read it; ``measured`` flags extrapolated
    bands; ``bandwidth_fwhm_m`` / ``band_centroid_m`` come from the spectra (NaN without).
    """
    stats = stack.band_stats()
    if stats is None:
        stats = np.full((stack.wavelengths_m.size, 2), np.nan)
    assert stack.measured is not None  # set by __post_init__
    extra: dict[str, Any] = {}
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


def read_stack(path: str | Path) -> dict:
    """Read a PSF stack ``.npz`` (a measured stack, :func:`save_stack` or a PSFResult file).

    The one set of rules for PSF-stack files: ``psf`` is (views, wavelengths, rows, cols),
    (wavelengths, rows, cols) for one view, or 5-D with a single depth; ``views`` names each
    view from :data:`doedesign.engine.result.VIEWS` (default ``("coded",)`` for one view);
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
    depth: float | None
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
            "info": parse_json(str(info), f"{path}: info") if info is not None else None}


def load_stack(path: str | Path) -> PSFStack:
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
