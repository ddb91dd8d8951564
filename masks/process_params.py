"""Process parameters: one :class:`~masks.process_params.ProcessParams` holds every fabrication effect of a run.

Each field is an effect of :mod:`masks.effects` (``etch_depth`` per mask, ``mask_overlay`` per
mask as (dx, dy, rotation), ``linewidth_bias``, ``proximity_blur``, ...); SI units (m, rad;
``mask_rotation`` in degrees). The container checks ranges and shapes on construction, copies
its arrays, and round-trips through JSON (:meth:`ProcessParams.to_dict`, :meth:`ProcessParams.from_dict`).
:mod:`masks.process` prints the masks with them.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from doedesign.errors import DoeError

from .decompose import DEFAULT_DEPTHS_M

__all__ = ["ProcessParams", "finite_float"]

# Array-valued fields (copied, never shared) and those holding one row per mask.
_ARRAY_FIELDS = ("etch_depth", "mask_overlay", "linewidth_bias", "mask_rotation", "microtrenching",
                 "etch_gradient")
_PER_MASK_FIELDS = ("mask_overlay", "linewidth_bias", "mask_rotation", "microtrenching")


@dataclass
class ProcessParams:
    """Fabrication parameters of one wafer run, in SI units.

    Attributes
    ----------
    etch_depth : ndarray, shape (n_masks,)
        Actual depth of each mask's etch (m), mask order.
    mask_overlay : ndarray, shape (n_masks, 3)
        Per mask ``[dx_m, dy_m, rotation_rad]`` relative to mask 0 (row 0 is normally
        zeros); x toward increasing column, y up (toward decreasing row), rotation
        counter-clockwise about the centre of the design grid. None = no overlay error.
    linewidth_bias : ndarray, shape (n_masks,)
        Growth of every opening edge per mask (m); positive = openings wider. None = 0.
    proximity_blur : float
        Sigma of the Gaussian aerial-image blur through the contact gap (m); 0 = sharp.
    resist_threshold : float
        Aerial-image level at which the resist clears, in (0, 1); used only with blur.
    sidewall_slope : float
        Width of the etched step transition (m): a linear ramp ``d cot(theta)`` wide.
    etch_loading : float
        Fractional depth loss per unit local open fraction:
        ``depth_j(x) = d_j * (1 - etch_loading * rho_j(x))``.
    loading_radius : float
        Gaussian sigma (m) over which the local open fraction ``rho_j`` is averaged.
    roughness : float
        Rms random height noise (m), white on the fine grid.
    seed : int or None
        Seed of the roughness noise (None = fresh noise each call).
    mask_rotation : ndarray, shape (n_masks,)
        Rotation of each printed mask about the field centre (the centre of the design
        grid), in degrees as aligners quote it, counter-clockwise; adds to the rotation in
        ``mask_overlay``. None = 0.
    microtrenching : ndarray, shape (n_masks, 2)
        Per mask ``[depth_m, width_m]``: extra etch depth at the foot of the mask's etched
        edges inside the opening, ``depth_m * exp(-s / width_m)`` at distance ``s`` from a
        straight edge, at the mask's etch depth (it scales with the local etch depth, so
        with loading and gradient). None = no trenches.
    proximity_gap : float
        Mask-to-resist gap (m) of proximity printing (:mod:`masks.proximity`: angular spectrum,
        Hg g/h/i lines, collimation, resist blur, threshold ``resist_threshold``, chromium
        undercut); 0 = contact (the mask as drawn, or the Gaussian ``proximity_blur``). The two
        are exclusive.
    collimation_half_angle : float
        Illumination half-angle (rad) of proximity printing, 0..10 deg (default 2 deg).
    resist_blur : float
        Resist blur sigma (m) of proximity printing, 0..1 um (default 0.1 um).
    cr_undercut : float
        Lateral wet-etch undercut of the chromium hard mask (m, >= 0) in proximity printing.
    etch_gradient : ndarray, shape (2,)
        ``[x_per_m, y_per_m]``: relative etch-depth change per metre along x and y from the
        field centre, the same for every mask: ``depth_j(r) = d_j (1 + g . r)``
        (10 /m = 1 % per mm). None = uniform etch.
    """

    etch_depth: np.ndarray = field(default_factory=lambda: np.array(DEFAULT_DEPTHS_M, dtype=float))
    mask_overlay: np.ndarray | None = None
    linewidth_bias: np.ndarray | None = None
    proximity_blur: float = 0.0
    resist_threshold: float = 0.5
    sidewall_slope: float = 0.0
    etch_loading: float = 0.0
    loading_radius: float = 50e-6
    roughness: float = 0.0
    seed: int | None = None
    mask_rotation: np.ndarray | None = None
    microtrenching: np.ndarray | None = None
    etch_gradient: np.ndarray | None = None
    proximity_gap: float = 0.0
    collimation_half_angle: float = math.radians(2.0)
    resist_blur: float = 0.1e-6
    cr_undercut: float = 0.0

    def __post_init__(self) -> None:
        self.etch_depth = _float_array(self.etch_depth, "etch_depth")
        if self.etch_depth.ndim != 1 or not 1 <= self.etch_depth.size <= 15:
            raise DoeError(f"process parameter etch_depth must be a list of 1..15 depths (m), "
                           f"got shape {self.etch_depth.shape}")
        n = self.etch_depth.size
        if self.mask_overlay is None:
            self.mask_overlay = np.zeros((n, 3))
        if self.linewidth_bias is None:
            self.linewidth_bias = np.zeros(n)
        if self.mask_rotation is None:
            self.mask_rotation = np.zeros(n)
        if self.microtrenching is None:
            self.microtrenching = np.zeros((n, 2))
        if self.etch_gradient is None:
            self.etch_gradient = np.zeros(2)
        for name in _ARRAY_FIELDS[1:]:
            setattr(self, name, _float_array(getattr(self, name), name))
        if self.mask_overlay.shape != (n, 3):
            raise DoeError(f"process parameter mask_overlay must be shaped ({n}, 3) "
                           f"[dx_m, dy_m, rotation_rad] per mask, got {self.mask_overlay.shape}")
        if self.linewidth_bias.shape != (n,):
            raise DoeError(f"process parameter linewidth_bias must hold {n} values (m), "
                           f"got shape {self.linewidth_bias.shape}")
        if self.mask_rotation.shape != (n,):
            raise DoeError(f"process parameter mask_rotation must hold {n} angles (degrees), "
                           f"got shape {self.mask_rotation.shape}")
        if abs(self.mask_rotation).max() > 45:
            raise DoeError(f"process parameter mask_rotation must lie within +-45 degrees, "
                           f"got {self.mask_rotation.tolist()}")
        if self.microtrenching.shape != (n, 2):
            raise DoeError(f"process parameter microtrenching must be shaped ({n}, 2) "
                           f"[depth_m, width_m] per mask, got {self.microtrenching.shape}")
        depth, width = self.microtrenching.T
        if np.any(depth < 0) or np.any(width < 0) or np.any((depth > 0) & (width == 0)):
            raise DoeError(f"process parameter microtrenching needs depth_m >= 0 and width_m >= 0 "
                           f"(> 0 where depth_m > 0), got {self.microtrenching.tolist()}")
        if self.etch_gradient.shape != (2,):
            raise DoeError(f"process parameter etch_gradient must be [x_per_m, y_per_m], "
                           f"got shape {self.etch_gradient.shape}")
        for name in ("proximity_blur", "resist_threshold", "sidewall_slope", "etch_loading",
                     "loading_radius", "roughness", "proximity_gap", "collimation_half_angle", "resist_blur",
                     "cr_undercut"):
            setattr(self, name, finite_float(getattr(self, name), f"process parameter {name}"))
        if np.any(self.etch_depth < 0):
            raise DoeError(f"process parameter etch_depth must be >= 0 m, got {self.etch_depth.tolist()}")
        for name, hi in (("proximity_gap", 200e-6), ("collimation_half_angle", math.radians(10)),
                         ("resist_blur", 1e-6), ("cr_undercut", 5e-6)):
            if not 0 <= getattr(self, name) <= hi:
                raise DoeError(f"process parameter {name} must lie in [0, {hi:g}], got {getattr(self, name)}")
        if self.proximity_gap > 0 and self.proximity_blur > 0:
            raise DoeError("process parameters proximity_gap and proximity_blur are exclusive (the blur is "
                           "the contact print's stand-in for the gap)")
        for name in ("proximity_blur", "sidewall_slope", "roughness"):
            if getattr(self, name) < 0:
                raise DoeError(f"process parameter {name} must be >= 0 m, got {getattr(self, name)}")
        if not 0 < self.resist_threshold < 1:
            raise DoeError(f"process parameter resist_threshold must lie in (0, 1), got {self.resist_threshold}")
        if self.loading_radius <= 0:
            raise DoeError(f"process parameter loading_radius must be > 0 m, got {self.loading_radius}")
        if self.seed is not None:
            if isinstance(self.seed, bool) or not float(self.seed).is_integer():
                raise DoeError(f"process parameter seed must be an integer or None, got {self.seed!r}")
            self.seed = int(self.seed)

    @property
    def n_masks(self) -> int:
        """Number of binary masks (length of ``etch_depth``)."""
        return self.etch_depth.size

    @classmethod
    def ideal(cls, n_masks: int = 4, depths_m: ArrayLike | None = None) -> ProcessParams:
        """Perfect process: nominal depths, every effect off.

        Parameters
        ----------
        n_masks : int
            Number of masks; the default depths are ``DEFAULT_DEPTHS_M`` (4 masks) or
            ``75 nm * 2**j`` for another count.
        depths_m : sequence of float, optional
            Etch depth of each mask (m); overrides ``n_masks``.
        """
        if depths_m is None:
            n_masks = int(n_masks)
            if n_masks == len(DEFAULT_DEPTHS_M):
                depths_m = DEFAULT_DEPTHS_M
            else:
                depths_m = [DEFAULT_DEPTHS_M[0] * 2 ** j for j in range(max(n_masks, 0))]
        return cls(etch_depth=np.array(depths_m, dtype=float))

    def copy(self, **changes: Any) -> ProcessParams:
        """A copy with some fields replaced (arrays are copied, never shared)."""
        values = {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}
        values.update(changes)
        for name in _ARRAY_FIELDS:
            if values[name] is not None:
                values[name] = np.array(values[name], dtype=float)
        if "etch_depth" in changes and len(np.atleast_1d(changes["etch_depth"])) != self.n_masks:
            # A new mask count invalidates the per-mask arrays not given explicitly.
            for name in _PER_MASK_FIELDS:
                if name not in changes:
                    values[name] = None
        return type(self)(**values)

    def to_dict(self) -> dict:
        """JSON-friendly dict keyed by field name; lengths in m, angles in rad."""
        # __post_init__ fills every per-mask array left None.
        assert self.mask_overlay is not None and self.linewidth_bias is not None
        assert self.mask_rotation is not None and self.microtrenching is not None and self.etch_gradient is not None
        return {
            "etch_depth": self.etch_depth.tolist(),
            "mask_overlay": self.mask_overlay.tolist(),
            "linewidth_bias": self.linewidth_bias.tolist(),
            "proximity_blur": self.proximity_blur,
            "resist_threshold": self.resist_threshold,
            "sidewall_slope": self.sidewall_slope,
            "etch_loading": self.etch_loading,
            "loading_radius": self.loading_radius,
            "roughness": self.roughness,
            "seed": self.seed,
            "mask_rotation": self.mask_rotation.tolist(),
            "microtrenching": self.microtrenching.tolist(),
            "etch_gradient": self.etch_gradient.tolist(),
            "proximity_gap": self.proximity_gap,
            "collimation_half_angle": self.collimation_half_angle,
            "resist_blur": self.resist_blur,
            "cr_undercut": self.cr_undercut,
        }

    @classmethod
    def from_dict(cls, d: dict) -> ProcessParams:
        """Inverse of :meth:`to_dict`; missing keys take their defaults.

        Raises
        ------
        DoeError
            ``d`` is not a dict or has unknown keys.
        """
        if not isinstance(d, dict):
            raise DoeError(f"process parameters must be a JSON object, got {type(d).__name__}")
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(d) - known)
        if unknown:
            raise DoeError(f"unknown process parameter(s) {unknown}; known: {sorted(known)}")
        return cls(**d)


def finite_float(value: Any, what: str) -> float:
    """``value`` as a finite float, or a :class:`~doedesign.errors.DoeError` that names ``what`` and the value.

    The one check of a scalar process or tolerance number (masks.tolerance reads its spec
    files with it too).
    """
    try:
        number = float(value)
    except (TypeError, ValueError):
        raise DoeError(f"{what} must be a number, got {value!r}") from None
    if not math.isfinite(number):
        raise DoeError(f"{what} must be finite, got {number}")
    return number


def _float_array(value, name):
    try:
        arr = np.array(value, dtype=float)
    except (TypeError, ValueError):
        raise DoeError(f"process parameter {name} must be numeric, got {value!r}") from None
    if not np.all(np.isfinite(arr)):
        raise DoeError(f"process parameter {name} must be finite, got {arr.tolist()}")
    return arr
