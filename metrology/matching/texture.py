"""Surface texture figures beside the DOE figures: ISO 25178 Sa, Sq, Sz, the PSD and band rms.

For each level's flat interiors (:func:`metrology.matching.terrace.flat_interiors`, about the
level's own mean) and for the residual (measured minus design):

- ``Sq`` (root mean square height) through SurfaceTopography (``rms_height_from_area`` on the
  masked heights);
- ``Sa`` (arithmetic mean height, mean of ``|z - mean|``) and ``Sz`` (maximum height, highest
  peak plus deepest pit, ``max - min``) by hand: SurfaceTopography has neither (its
  ``mad_height`` is a median-based robust rms, not Sa);
- for the residual, the radially averaged PSD and its rms in bands of spatial wavelength through
  SurfaceTopography (``power_spectrum_from_area``, ``integrate_psd``, Hann window: the field is
  not periodic). Invalid pixels are filled with the residual's mean first (the PSD needs a
  complete grid); the band rms squares sum to the windowed variance (Parseval).

The bands are set by the design's pitch: below one pitch (edge residue, roughness), one to ten
pitches (the DOE's own features), over ten pitches (form, levelling). No filter (S-, L- or
F-operator of ISO 25178-3) is applied beyond the levelling the comparison did.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

__all__ = ["BAND_EDGES_PITCH", "Texture", "band_rms", "field_texture", "height_parameters", "residual_psd"]

log = logging.getLogger(__name__)

# Band edges in design pitches (spatial wavelength): (0, 1), (1, 10), (10, inf).
BAND_EDGES_PITCH = (1.0, 10.0)


def _topography(height_m, pixel_m):
    from SurfaceTopography import Topography

    rows, cols = height_m.shape
    # SurfaceTopography indexes (x, y): the transpose of the row-major map.
    heights = np.ascontiguousarray(np.ma.getdata(height_m).T)
    if np.ma.is_masked(height_m):
        heights = np.ma.masked_array(heights, mask=np.ascontiguousarray(np.ma.getmaskarray(height_m).T))
    return Topography(heights, (cols * pixel_m, rows * pixel_m), periodic=False)


def height_parameters(height_m: np.ndarray, pixel_m: float, mask: np.ndarray | None = None) -> dict:
    """ISO 25178 Sa, Sq, Sz (m) of the pixels in ``mask`` about their own mean.

    Parameters
    ----------
    height_m : ndarray (rows, cols)
    pixel_m : float
    mask : ndarray of bool, optional
        Pixels counted (default: every finite one).

    Returns
    -------
    dict
        ``Sa_m``, ``Sq_m`` (SurfaceTopography), ``Sz_m`` and ``pixels``; None values with no pixel.
    """
    h = np.asarray(height_m, float)
    use = np.isfinite(h) if mask is None else (np.asarray(mask, bool) & np.isfinite(h))
    n = int(use.sum())
    if n == 0:
        return {"Sa_m": None, "Sq_m": None, "Sz_m": None, "pixels": 0}
    z = h[use]
    topo = _topography(np.ma.masked_array(np.where(use, h, 0.0), mask=~use), pixel_m)
    sq = float(topo.rms_height_from_area())
    return {"Sa_m": float(np.mean(np.abs(z - z.mean()))), "Sq_m": sq, "Sz_m": float(z.max() - z.min()),
            "pixels": n}


def residual_psd(residual_m: np.ndarray, pixel_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Radially averaged PSD of a residual map (SurfaceTopography, Hann window).

    Returns
    -------
    q_per_m, psd_m4 : ndarray
        Wavevector magnitude (rad/m) and the isotropic PSD ``C(q)`` (m^4).
    """
    topo = _topography(_filled(residual_m), pixel_m)
    q, c = topo.power_spectrum_from_area(window="hann")
    ok = np.isfinite(c)
    return np.asarray(q)[ok], np.asarray(c)[ok]


def band_rms(residual_m: np.ndarray, pixel_m: float, bands_m: list[tuple[float, float]]) -> list[float]:
    """Rms of a residual map in bands of spatial wavelength ``[lo, hi)`` (m), from its 2-D PSD.

    Every wavevector of the 2-D FFT in the band counts (``integrate_psd``, Hann window); the
    squares of bands that tile all wavelengths sum to the windowed variance.
    """
    topo = _topography(_filled(residual_m), pixel_m)
    out = []
    for lo, hi in bands_m:
        q_lo, q_hi = 2 * np.pi / hi if np.isfinite(hi) else -1.0, 2 * np.pi / lo if lo > 0 else np.inf
        out.append(float(np.sqrt(max(topo.integrate_psd(_band(q_lo, q_hi), window="hann"), 0.0))))
    return out


def _band(q_lo, q_hi):
    """The band's indicator of ``|q|`` (one argument: SurfaceTopography passes the norm)."""
    return lambda q: ((q > q_lo) & (q <= q_hi)).astype(float)


def _filled(residual_m):
    r = np.asarray(residual_m, float)
    ok = np.isfinite(r)
    mean = float(r[ok].mean()) if ok.any() else 0.0
    return np.where(ok, r - mean, 0.0)


@dataclass
class Texture:
    """Texture figures of a comparison.

    Attributes
    ----------
    levels : list of dict
        Per level: ``Sa_m``, ``Sq_m``, ``Sz_m``, ``pixels`` of its flat interiors.
    residual : dict
        The same of the residual (measured minus design), plus ``bands`` (``lo_m``, ``hi_m``,
        ``rms_m``).
    q_per_m, psd_m4 : ndarray
        The residual's radially averaged PSD.
    """

    levels: list
    residual: dict
    q_per_m: np.ndarray
    psd_m4: np.ndarray

    def report(self) -> dict:
        """JSON summary in nm (the PSD is in ``texture.png``)."""
        nm = 1e9

        def conv(d):
            return {k.replace("_m", "_nm"): (v * nm if isinstance(v, float) else v) for k, v in d.items()
                    if k != "bands"}

        res = conv(self.residual)
        res["bands"] = [{"wavelength_from_um": b["lo_m"] * 1e6,
                         "wavelength_to_um": b["hi_m"] * 1e6 if np.isfinite(b["hi_m"]) else None,
                         "rms_nm": b["rms_m"] * nm} for b in self.residual["bands"]]
        return {"levels": [conv(d) for d in self.levels], "residual": res,
                "method": "ISO 25178 Sa, Sq, Sz about each region's own mean, no S/L filter; Sq, PSD and band "
                          "rms through SurfaceTopography (Hann window, invalid pixels at the mean), Sa and Sz "
                          "by hand; levels: flat interiors of the terrace fit's rule over the whole field"}


def field_texture(height_m: np.ndarray, labels: np.ndarray, flat: np.ndarray, residual_m: np.ndarray,
                  pixel_m: float, pitch_m: float, n_levels: int) -> Texture:
    """Sa, Sq, Sz of each level's flat interiors and of the residual, its PSD and band rms.

    Parameters
    ----------
    height_m : ndarray (rows, cols)
        Levelled heights.
    labels : ndarray of int
        Design level at each pixel.
    flat : ndarray of bool
        Flat interiors (:func:`metrology.matching.terrace.flat_interiors`).
    residual_m : ndarray (rows, cols)
        Measured minus design (NaN = invalid).
    pixel_m, pitch_m : float
        Pixel size and the design's pitch (sets the bands).
    n_levels : int

    Returns
    -------
    Texture
    """
    levels = [height_parameters(height_m, pixel_m, flat & (labels == k)) for k in range(n_levels)]
    res = height_parameters(residual_m, pixel_m)
    edges = [0.0, *(e * pitch_m for e in BAND_EDGES_PITCH), np.inf]
    bands = list(zip(edges[:-1], edges[1:]))
    res["bands"] = [{"lo_m": lo, "hi_m": hi, "rms_m": r}
                    for (lo, hi), r in zip(bands, band_rms(residual_m, pixel_m, bands))]
    q, c = residual_psd(residual_m, pixel_m)
    return Texture(levels=levels, residual=res, q_per_m=q, psd_m4=c)
