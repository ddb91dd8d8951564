"""Refractive index of DOE materials and the phase a height map imparts.

The phase at every wavelength is computed from the one physical height map,
``phi = 2 pi (n(lambda) - 1) h / lambda``; never from another wavelength's wrapped phase.
"""

from __future__ import annotations

from dataclasses import dataclass
from collections.abc import Sequence

import numpy as np
from numpy.typing import ArrayLike

from .errors import MaterialError

__all__ = ["FUSED_SILICA", "Material", "cauchy", "get_material", "register_material", "sellmeier", "table"]


@dataclass(frozen=True)
class Material:
    """A dispersive material, valid between ``min_wavelength_m`` and ``max_wavelength_m``.

    Parameters
    ----------
    name : str
        Registry name (e.g. ``"fused_silica"``).
    kind : {"sellmeier", "cauchy", "table"}
        ``sellmeier``: ``n^2 = 1 + sum B_i L^2 / (L^2 - C_i^2)`` with ``coefficients = (B, C)``
        and L, C in micrometres.
        ``cauchy``: ``n = A + B / L^2 + C / L^4 + ...`` with ``coefficients = (A, B, C, ...)``
        and L in micrometres.
        ``table``: ``coefficients = (wavelengths_m, n)``, interpolated linearly.
    """

    name: str
    kind: str
    coefficients: tuple
    min_wavelength_m: float
    max_wavelength_m: float
    reference: str = ""

    def n(self, wavelength_m: ArrayLike) -> np.ndarray | float:
        """Refractive index at ``wavelength_m`` (scalar or array, metres)."""
        wl = np.asarray(wavelength_m, dtype=float)
        if not np.all(np.isfinite(wl)) or np.any(wl <= 0):
            raise MaterialError(f"{self.name}: wavelengths must be positive and finite, got {wavelength_m!r}")
        lo, hi = self.min_wavelength_m, self.max_wavelength_m
        if np.any(wl < lo * (1 - 1e-9)) or np.any(wl > hi * (1 + 1e-9)):
            raise MaterialError(
                f"{self.name}: wavelength {np.atleast_1d(wl).min() * 1e9:.1f}-{np.atleast_1d(wl).max() * 1e9:.1f} nm "
                f"is outside the valid range {lo * 1e9:.0f}-{hi * 1e9:.0f} nm")
        L = wl * 1e6
        if self.kind == "sellmeier":
            B, C = self.coefficients
            L2 = L[..., None] ** 2
            n2 = 1.0 + np.sum(np.asarray(B) * L2 / (L2 - np.asarray(C) ** 2), axis=-1)
            return np.sqrt(n2)
        if self.kind == "cauchy":
            return sum(c / L ** (2 * i) for i, c in enumerate(self.coefficients))
        if self.kind == "table":
            wls, ns = self.coefficients
            return np.interp(wl, wls, ns)
        raise MaterialError(f"{self.name}: unknown dispersion kind {self.kind!r}")

    def height_2pi_m(self, wavelength_m: ArrayLike) -> np.ndarray | float:
        """Height step that delays the phase by exactly 2 pi at ``wavelength_m``."""
        return np.asarray(wavelength_m) / (self.n(wavelength_m) - 1.0)

    def phase(self, height_m: ArrayLike, wavelength_m: float) -> np.ndarray:
        """Transmitted phase (radians) of ``height_m`` at one wavelength, relative to air.

        Positive height (more glass) means more optical path and positive phase.
        """
        return 2.0 * np.pi * (self.n(wavelength_m) - 1.0) * np.asarray(height_m) / wavelength_m


_REGISTRY: dict[str, Material] = {}


def register_material(material: Material, overwrite: bool = False) -> Material:
    """Add a material to the registry so designs can name it."""
    if material.kind not in ("sellmeier", "cauchy", "table"):
        raise MaterialError(f"{material.name}: kind must be sellmeier, cauchy or table")
    if material.min_wavelength_m >= material.max_wavelength_m:
        raise MaterialError(f"{material.name}: empty wavelength range")
    if material.kind == "table":
        wls, ns = (np.asarray(a, dtype=float) for a in material.coefficients)
        if wls.shape != ns.shape or wls.ndim != 1 or wls.size < 2 or np.any(np.diff(wls) <= 0):
            raise MaterialError(f"{material.name}: table needs increasing wavelengths and one n per wavelength")
    if material.name in _REGISTRY and not overwrite:
        raise MaterialError(f"material {material.name!r} is already registered (use overwrite=True)")
    _REGISTRY[material.name] = material
    return material


def sellmeier(name: str, B: Sequence[float], C_um: Sequence[float], min_wavelength_m: float, max_wavelength_m: float,
              reference: str = "") -> Material:
    """Build and register a Sellmeier material (C in micrometres)."""
    return register_material(Material(name, "sellmeier", (tuple(B), tuple(C_um)),
                                      min_wavelength_m, max_wavelength_m, reference))


def cauchy(name: str, coefficients: Sequence[float], min_wavelength_m: float, max_wavelength_m: float,
           reference: str = "") -> Material:
    """Build and register a Cauchy material ``n = A + B/L^2 + ...`` (L in micrometres)."""
    return register_material(Material(name, "cauchy", tuple(coefficients),
                                      min_wavelength_m, max_wavelength_m, reference))


def table(name: str, wavelengths_m: ArrayLike, n: ArrayLike, reference: str = "") -> Material:
    """Build and register a tabulated material, linear interpolation between entries."""
    wls = tuple(float(w) for w in np.asarray(wavelengths_m, dtype=float).tolist())
    return register_material(Material(name, "table", (wls, tuple(float(v) for v in np.asarray(n, dtype=float).tolist())),
                                      min(wls), max(wls), reference))


def get_material(name: str | Material) -> Material:
    """Look a material up by name (or pass a :class:`Material` through)."""
    if isinstance(name, Material):
        return name
    try:
        return _REGISTRY[str(name)]
    except KeyError:
        raise MaterialError(f"unknown material {name!r}; known: {', '.join(sorted(_REGISTRY))}") from None


FUSED_SILICA = sellmeier(
    "fused_silica",
    B=(0.6961663, 0.4079426, 0.8974794),
    C_um=(0.0684043, 0.1162414, 9.896161),
    min_wavelength_m=0.21e-6,
    max_wavelength_m=3.71e-6,
    reference="I. H. Malitson, J. Opt. Soc. Am. 55, 1205 (1965), 20 C",
)
