"""PSF files and wavelength lists: the container of a computed PSF stack and its ``.npz``.

:class:`PSFResult` holds both views' pixel-integrated PSFs on the sensor window (see
:mod:`doedesign.engine.psf` for the model); :func:`parse_wavelengths_nm` reads the CLI's wavelength lists.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike

from ..errors import DoeError
from ..fileio import dumps_json, read_npz, write_npz

__all__ = ["MAX_WAVELENGTHS", "PSFResult", "VIEWS", "parse_wavelengths_nm", "read_psf_arrays"]

#: The PSF's views in array order: through the DOE's half of the aperture, then through the other half.
VIEWS = ("coded", "uncoded")

@dataclass
class PSFResult:
    """PSFs of both views on the sensor window.

    Attributes
    ----------
    psf : ndarray (views, depths, wavelengths, rows, cols)
        Fraction of the light through each view's half-aperture falling in each sensor pixel.
        Row 0 is the top of the window; the axis is at ``axis_pixel``.
    energy_in_window : ndarray (views, depths, wavelengths)
        ``psf.sum((-2, -1))``: the part of that light the window holds.
    surround : str or None
        What surrounded the design inside the lens aperture (:data:`doedesign.camera.SURROUNDS`); None
        for a file written before the convention was recorded (computed as ``open``).
    coded_clear_fraction : float or None
        Share of the coded view's light that its clear region passes (the design's
        ``aperture`` and the surround): the most the coded PSF can hold.
    """

    psf: np.ndarray
    views: tuple
    wavelengths_m: np.ndarray
    depths_m: np.ndarray
    pixel_pitch_m: float
    axis_pixel: tuple = (256, 256)
    sampling: dict = field(default_factory=dict)
    surround: str | None = None
    coded_clear_fraction: float | None = None

    @property
    def energy_in_window(self) -> np.ndarray:
        return self.psf.sum(axis=(-2, -1))

    def view(self, name: str) -> np.ndarray:
        """The PSF of one view, shaped (depths, wavelengths, rows, cols)."""
        return self.psf[list(self.views).index(name)]

    def polychromatic(self, weights: ArrayLike) -> np.ndarray:
        """Spectrally weighted PSF (views, depths, rows, cols); weights are normalized to sum 1."""
        w = np.asarray(weights, dtype=float)
        if w.shape != (len(self.wavelengths_m),) or np.any(w < 0) or w.sum() <= 0:
            raise DoeError(f"spectral weights must be {len(self.wavelengths_m)} non-negative numbers, not all zero")
        return np.tensordot(self.psf, w / w.sum(), axes=([2], [0]))

    def save(self, path: str | Path) -> Path:
        """Write the PSF ``.npz`` (fields documented in the file-formats page of the docs)."""
        return write_npz(
            path, psf=self.psf, views=np.array(self.views), wavelengths_m=np.asarray(self.wavelengths_m),
            depths_m=np.asarray(self.depths_m), pixel_pitch_m=np.float64(self.pixel_pitch_m),
            energy_in_window=self.energy_in_window, axis_pixel=np.asarray(self.axis_pixel),
            sampling=np.str_(dumps_json(self.sampling, indent=None)),
            **({} if self.surround is None else {"surround": np.str_(self.surround)}),
            **({} if self.coded_clear_fraction is None
               else {"coded_clear_fraction": np.float64(self.coded_clear_fraction)}))

    def summary(self) -> dict:
        """Dictionary for ``doe inspect``: shape, views, wavelengths, energies and the surround."""
        from ..camera import describe_surround

        return {"kind": "psf", "shape": list(self.psf.shape[-2:]), "views": list(self.views),
                "wavelengths_nm": [float(v) * 1e9 for v in self.wavelengths_m],
                "depths_m": [float(v) for v in self.depths_m], "pixel_pitch_m": float(self.pixel_pitch_m),
                "energy_in_window": {v: self.energy_in_window[i].tolist() for i, v in enumerate(self.views)},
                "surround": self.surround or "not recorded (computed as open)",
                "surround_means": describe_surround(self.surround or "open"),
                "coded_clear_fraction": self.coded_clear_fraction}

    @classmethod
    def load(cls, path: str | Path) -> PSFResult:
        """Read a PSF ``.npz`` written by :meth:`save`."""
        path = Path(path)
        data = read_psf_arrays(path, ("psf", "views", "wavelengths_m", "depths_m", "pixel_pitch_m"))
        psf = data["psf"]
        if psf.ndim != 5:
            raise DoeError(f"{path}: psf must be (views, depths, wavelengths, rows, cols), got shape {psf.shape}")
        return cls(psf=psf, views=tuple(str(v) for v in data["views"]), wavelengths_m=data["wavelengths_m"],
                   depths_m=data["depths_m"], pixel_pitch_m=float(data["pixel_pitch_m"]),
                   axis_pixel=tuple(int(v) for v in data.get("axis_pixel", (256, 256))),
                   surround=str(data["surround"]) if "surround" in data else None,
                   coded_clear_fraction=float(data["coded_clear_fraction"]) if "coded_clear_fraction" in data
                   else None)


def read_psf_arrays(path: str | Path, required: Iterable[str], what: str = "PSF file") -> dict[str, np.ndarray]:
    """All arrays of a PSF ``.npz`` after checking the ``required`` fields; errors name the file."""
    return read_npz(path, required, what)


# Most wavelengths one command computes (each is a full PSF per view and depth).
MAX_WAVELENGTHS = 1000


def parse_wavelengths_nm(text: str) -> np.ndarray:
    """Wavelengths in metres from ``"486,589,656"`` or ``"400:700:10"`` (inclusive), in nm."""
    text = str(text).strip()
    try:
        if ":" in text:
            parts = [float(v) for v in text.split(":")]
            if len(parts) != 3 or not np.all(np.isfinite(parts)) or parts[2] <= 0 or parts[1] < parts[0]:
                raise ValueError
            count = (parts[1] - parts[0]) / parts[2] + 1
            if count > MAX_WAVELENGTHS:
                raise DoeError(f"wavelengths {text!r}: {count:.3g} wavelengths; at most {MAX_WAVELENGTHS} "
                               "(use a larger step)")
            values = np.arange(parts[0], parts[1] + parts[2] / 2, parts[2])
        else:
            values = np.array([float(v) for v in text.split(",") if v.strip()])
    except ValueError:
        raise DoeError(f"wavelengths {text!r}: use a list like 486,589,656 or a range like 400:700:10 (nm)") from None
    if values.size == 0 or values.size > MAX_WAVELENGTHS:
        raise DoeError(f"wavelengths {text!r}: need 1 to {MAX_WAVELENGTHS} wavelengths in nm")
    if not np.all((values >= 100) & (values <= 20000)):
        raise DoeError(f"wavelengths {text!r}: each must lie in 100..20000 nm")
    return values * 1e-9

