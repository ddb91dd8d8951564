"""The level rule: level step, rounding to the nearest level, 2 pi wrap, levels of a design.

Every stage that turns heights into levels (the optimizer's finish, the masks, the comparison
and the diagnosis) calls this module, so they all see the same level map.

Sign convention (see CONTRIBUTING): z up, 0 at the unetched top surface, negative where
etched; level k is k steps deep, so its height is ``-k * step_m``, and ``n_levels`` steps make
one 2 pi phase delay at the design wavelength (:func:`level_step_m`).

The rule, for a depth of ``d = -h / step_m`` steps:

1. round to the nearest whole step, half a step rounding deeper: ``k = floor(d + 1/2)``
   (never floor, so the height error stays within +-step/2);
2. wrap ``k`` modulo ``n_levels`` into ``0 .. n_levels-1``.

Wrapping, not clipping, is what is physically right for an etched phase element: the element
acts through its phase, and ``n_levels`` steps are exactly one 2 pi delay at the design
wavelength, so a depth one step beyond the deepest level (or one step above the top surface,
which cannot be etched) is the same phase as level 0 (or level ``n_levels - 1``). Clipping
would instead move such a pixel by up to half the phase range. Examples with 16 levels:
``[15.6, -0.6, 17.2, -0.3, 2.5]`` steps deep give levels ``[0, 15, 1, 0, 3]``. The wrap is
exact at the design wavelength and approximate at others (dispersion), as for any
multi-level DOE.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Protocol

import numpy as np
from numpy.typing import ArrayLike

from .errors import DoeError
from .materials import Material, get_material

__all__ = ["LEVEL_COUNTS", "N_LEVELS", "QuantizeResult", "check_level_count", "design_levels", "level_step_m",
           "masks_for_levels", "printed_height_m", "quantize", "quantize_design", "wrap_height_m"]

log = logging.getLogger(__name__)

#: Levels of the four-mask process (2**4): the default level count of a design.
N_LEVELS = 16
#: Level counts a design may have: 2**M for M = 1 .. 5 binary masks.
LEVEL_COUNTS = (2, 4, 8, 16, 32)


def check_level_count(n_levels: object, where: str = "levels") -> int:
    """The level count as an int, refused (:class:`~doedesign.errors.DoeError` naming ``where``) unless it is one of
    :data:`LEVEL_COUNTS`: M binary masks etch 2**M levels, so no other count can be made."""
    if isinstance(n_levels, bool) or not isinstance(n_levels, (int, np.integer)) or int(n_levels) not in LEVEL_COUNTS:
        raise DoeError(f"{where}: the level count must be one of {', '.join(map(str, LEVEL_COUNTS))} "
                       f"(2**M for M = 1..5 masks), got {n_levels!r}")
    return int(n_levels)


def masks_for_levels(n_levels: int) -> int:
    """Binary masks that etch ``n_levels`` levels: ``log2(n_levels)`` (see :func:`check_level_count`)."""
    return int(check_level_count(n_levels)).bit_length() - 1


class LevelSource(Protocol):
    """What the level rule reads of a design (:class:`doedesign.design.Design` is one): its
    stored levels, if any, else its heights and level step. A protocol, so that the design file,
    which quantizes through this module, is not imported by it."""

    levels: np.ndarray | None
    height_m: np.ndarray

    @property
    def name(self) -> str: ...

    @property
    def n_levels(self) -> int: ...

    def level_step_m(self, n_levels: int | None = None) -> float: ...


def level_step_m(material: str | Material, design_wavelength_m: float, n_levels: int = N_LEVELS) -> float:
    """Depth of one level: the 2 pi height at the design wavelength divided by ``n_levels``.

    Parameters
    ----------
    material : str or doedesign.materials.Material
        Registry name or material object.
    design_wavelength_m : float
        Wavelength (m) at which ``n_levels`` steps make exactly one 2 pi phase delay.
    n_levels : int
        Number of levels (16 for four binary masks).

    Returns
    -------
    float
        Step depth in metres (74.74 nm for fused silica at 550 nm and 16 levels).
    """
    n_levels = int(n_levels)
    if n_levels < 2:
        raise DoeError(f"n_levels must be at least 2, got {n_levels}")
    return float(get_material(material).height_2pi_m(design_wavelength_m)) / n_levels


@dataclass
class QuantizeResult:
    """Outcome of :func:`quantize`.

    Attributes
    ----------
    levels : ndarray of int16
        Level per pixel, 0 .. n_levels-1 (0 = top surface).
    height_m : ndarray of float64
        Quantized height, ``-levels * step_m`` (zero or negative).
    error_m : ndarray of float64
        Original height minus quantized height, after wrapping the original by whole
        2 pi heights (``n_levels * step_m``); within +-step/2.
    rms_error_m, max_error_m : float
        RMS and largest absolute value of ``error_m``.
    wrapped_pixels : int
        Pixels whose height lay above the top surface or below the deepest level by more
        than half a step and were moved by a whole 2 pi height (optically equivalent at
        the design wavelength only).
    step_m : float
        The level step used.
    n_levels : int
        Number of levels.
    """

    levels: np.ndarray
    height_m: np.ndarray
    error_m: np.ndarray
    rms_error_m: float
    max_error_m: float
    wrapped_pixels: int
    step_m: float
    n_levels: int

    def summary(self) -> dict:
        """JSON-ready figures (nm) for reports."""
        return {"step_nm": self.step_m * 1e9, "n_levels": self.n_levels,
                "rms_error_nm": self.rms_error_m * 1e9, "max_error_nm": self.max_error_m * 1e9,
                "wrapped_pixels": self.wrapped_pixels}


def quantize(height_m: ArrayLike, step_m: float, n_levels: int = N_LEVELS) -> QuantizeResult:
    """Round a height map to the nearest etch level, wrapping by 2 pi heights where needed.

    The module's rule: level ``k = floor(-h / step_m + 1/2)`` (half a step rounds deeper,
    never floor, so the error is within +-step/2). Depths that round outside
    ``0 .. n_levels-1`` are brought back by whole multiples of ``n_levels`` levels, which is
    one 2 pi height each: the same phase at the design wavelength.

    Parameters
    ----------
    height_m : array_like
        Heights in metres, design sign convention (0 top, negative etched).
    step_m : float
        Level step depth (see :func:`level_step_m`).
    n_levels : int
        Number of levels.

    Returns
    -------
    QuantizeResult

    Raises
    ------
    DoeError
        NaN or infinite heights, non-positive step or fewer than two levels.
    """
    h = np.asarray(height_m, dtype=np.float64)
    step_m = float(step_m)
    n_levels = int(n_levels)
    if not (np.isfinite(step_m) and step_m > 0):
        raise DoeError(f"quantize: level step must be a positive length in metres, got {step_m}")
    if not 2 <= n_levels <= np.iinfo(np.int16).max:
        raise DoeError(f"quantize: n_levels must be between 2 and 32767, got {n_levels}")
    bad = ~np.isfinite(h)
    if bad.any():
        raise DoeError(f"quantize: height map holds {int(bad.sum())} NaN or infinite values")
    depth_steps = -h / step_m
    # Round first, then wrap the integer: identical to wrapping the height by whole 2 pi
    # heights before rounding (n_levels is an integer), without float-modulo edge cases.
    k_raw = np.floor(depth_steps + 0.5)
    levels = np.mod(k_raw, n_levels).astype(np.int16)
    wrapped = int(np.count_nonzero((k_raw < 0) | (k_raw >= n_levels)))
    error_m = (k_raw - depth_steps) * step_m
    quantized = -levels.astype(np.float64) * step_m
    return QuantizeResult(
        levels=levels, height_m=quantized, error_m=error_m,
        rms_error_m=float(np.sqrt(np.mean(error_m ** 2))) if error_m.size else 0.0,
        max_error_m=float(np.max(np.abs(error_m))) if error_m.size else 0.0,
        wrapped_pixels=wrapped, step_m=step_m, n_levels=n_levels)


def wrap_height_m(height_m: ArrayLike, step_m: float, n_levels: int = N_LEVELS) -> np.ndarray:
    """Heights brought into ``(-n_levels * step_m, 0]`` by whole 2 pi heights.

    The continuous counterpart of the wrap in :func:`quantize`: the same phase at the design
    wavelength, every height at or below the top surface.
    """
    period = int(n_levels) * float(step_m)
    return -np.mod(-np.asarray(height_m, dtype=np.float64), period)


def quantize_design(design: LevelSource, n_levels: int | None = None,
                    source: str | None = None) -> tuple[np.ndarray, QuantizeResult | None]:
    """Level map of a design and, when it had to be quantized, the quantization.

    Parameters
    ----------
    design : LevelSource
        A design; its ``levels`` are used when present, else its heights are quantized with
        :func:`quantize` at its own level step.
    n_levels : int, optional
        Number of levels (default: the design's own, ``design.n_levels``).
    source : str, optional
        File name for error messages (default: the design's name).

    Returns
    -------
    levels : ndarray of int16 (rows, cols)
        0 .. n_levels-1, row 0 at the top.
    quantization : QuantizeResult or None
        None when the design carried levels.

    Raises
    ------
    DoeError
        Stored levels that are not integers or lie outside ``0 .. n_levels-1``.
    """
    source = source or design.name
    n_levels = design.n_levels if n_levels is None else int(n_levels)
    if design.levels is not None:
        lv = np.asarray(design.levels)
        if not np.issubdtype(lv.dtype, np.integer):
            raise DoeError(f"{source}: levels must be integers, got {lv.dtype}")
        if lv.size and (lv.min() < 0 or lv.max() >= n_levels):
            raise DoeError(f"{source}: levels must lie in 0..{n_levels - 1}, found {lv.min()}..{lv.max()}")
        return lv.astype(np.int16), None
    q = quantize(design.height_m, design.level_step_m(n_levels), n_levels)
    log.info("%s: quantized to %d levels, rms error %.2f nm", source, n_levels, q.rms_error_m * 1e9)
    return q.levels, q


def design_levels(design: LevelSource, n_levels: int | None = None, source: str | None = None) -> np.ndarray:
    """Level map (int16, 0 .. n_levels-1) of a design (default: its own level count): see
    :func:`quantize_design`."""
    return quantize_design(design, n_levels, source)[0]


def printed_height_m(design: LevelSource, n_levels: int | None = None, source: str | None = None) -> np.ndarray:
    """The heights the masks print from a design: its levels (:func:`design_levels`) times its step.

    What a measurement of the element is judged against: a heights-only design (continuous,
    wrapped or not) becomes the same level map here as in ``doe masks``.

    Returns
    -------
    ndarray of float64 (rows, cols)
        ``-levels * step_m``: 0 at the unetched top, negative where etched; row 0 at the top.
    """
    n_levels = design.n_levels if n_levels is None else int(n_levels)
    levels = design_levels(design, n_levels, source)
    return -levels.astype(np.float64) * design.level_step_m(n_levels)
