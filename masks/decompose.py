"""Binary mask decomposition of a 2**n-level element: mask j etches 2**j steps.

Level ``k = sum_j bit_j(k) * 2**j``; mask j is *open* (its etch reaches the glass) where bit
j of the level is set. With etch depths ``d_j`` the etched height is
``-sum_j open_j * d_j`` whatever the depths are, which is how depth errors propagate.
Mask j is etched in process step j unless an ``etch_order`` says otherwise; the order does
not change the ideal surface, only the real one (see ``masks.process``).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike

from doedesign.errors import DoeError

if TYPE_CHECKING:
    from doedesign.design import Design

__all__ = ["DEFAULT_DEPTHS_M", "DEFAULT_ETCH_ORDER", "binary_depths_m", "check_etch_order",
           "levels_to_masks", "mask_bit", "masks_to_height", "masks_to_levels", "process_depths_m"]

#: Nominal etch depths of the four masks (m): 1, 2, 4 and 8 steps of ~75 nm (fused silica,
#: 550 nm, 16 levels). Real runs should pass 2**j * level_step_m(...).
DEFAULT_DEPTHS_M = (75e-9, 150e-9, 300e-9, 600e-9)

# Mask j is etched in step j: shallowest first.
DEFAULT_ETCH_ORDER = (0, 1, 2, 3)


def binary_depths_m(step_m: float, n_masks: int = 4) -> tuple[float, ...]:
    """Ideal etch depth of each mask, ``2**j * step_m`` (m)."""
    return tuple(float(step_m) * 2 ** j for j in range(int(n_masks)))


def process_depths_m(design: Design, depths_m: Sequence[float] | None = None, source: str | None = None) -> list[float]:
    """The etch depths a design's process was asked for, one per mask (m): the nominal model of
    ``doe diagnose`` and ``doe calibrate``.

    ``depths_m`` when given (checked: one per mask of the design); else the design's own
    (``metadata["mask_depths_m"]``); else, for a 16-level design, :data:`DEFAULT_DEPTHS_M`
    (75, 150, 300, 600 nm: the seed process's round figures, as before level counts were a
    design's property); else ``2**j`` level steps of the design.

    Parameters
    ----------
    design : doedesign.design.Design
    depths_m : sequence of float, optional
    source : str, optional
        File name for the error message.
    """
    n = design.n_masks
    if depths_m is not None:
        depths = [float(v) for v in depths_m]
        if len(depths) != n:
            raise DoeError(f"{source or design.name}: {len(depths)} etch depth(s) given; this {design.n_levels}-level "
                           f"design has {n} mask(s)")
        return depths
    if design.metadata.get("mask_depths_m") is None and design.n_levels == 2 ** len(DEFAULT_DEPTHS_M):
        return list(DEFAULT_DEPTHS_M)
    return list(design.etch_depths_m())


def check_etch_order(etch_order: Sequence[int], n_masks: int = 4) -> tuple[int, ...]:
    """Validate an etch order (a permutation of mask indices) and return it as a tuple.

    ``etch_order[i]`` is the mask etched in process step ``i``.
    """
    order = tuple(int(j) for j in etch_order)
    if sorted(order) != list(range(n_masks)):
        raise DoeError(f"etch order {list(order)} must list each mask 0..{n_masks - 1} exactly once")
    return order


def levels_to_masks(levels: np.ndarray, n_masks: int = 4) -> np.ndarray:
    """Split a level map into binary masks.

    Parameters
    ----------
    levels : ndarray of int
        Levels, 0 .. 2**n_masks - 1.
    n_masks : int
        Number of binary masks.

    Returns
    -------
    ndarray of bool, shape (n_masks,) + levels.shape
        ``masks[j]`` is True (open, etched) where bit j of the level is set.

    Raises
    ------
    DoeError
        Non-integer levels or levels outside 0 .. 2**n_masks - 1.
    """
    levels = np.asarray(levels)
    n_masks = int(n_masks)
    if not 1 <= n_masks <= 15:
        raise DoeError(f"n_masks must be between 1 and 15, got {n_masks}")
    if not np.issubdtype(levels.dtype, np.integer):
        raise DoeError(f"levels must be an integer array, got dtype {levels.dtype}")
    if levels.size:
        lo, hi = int(levels.min()), int(levels.max())
        if lo < 0 or hi >= 2 ** n_masks:
            raise DoeError(f"levels must lie in 0..{2 ** n_masks - 1} for {n_masks} masks, "
                           f"found {lo}..{hi}")
    return np.stack([mask_bit(levels, j) for j in range(n_masks)])


def mask_bit(levels: np.ndarray, j: int) -> np.ndarray:
    """Mask ``j`` of :func:`levels_to_masks` (True where bit ``j`` of the level is set), unchecked.

    For callers that checked the levels already and need one mask: it works in the levels'
    own integer type, with no int64 temporaries (a process render takes one per mask and sample).
    """
    levels = np.asarray(levels)
    return ((levels >> int(j)) & 1) != 0


def masks_to_levels(masks: np.ndarray) -> np.ndarray:
    """Recompose levels from binary masks (exact inverse of :func:`levels_to_masks`).

    Parameters
    ----------
    masks : ndarray of bool, shape (n_masks, rows, cols)

    Returns
    -------
    ndarray of int16
    """
    masks = _as_masks(masks)
    weights = (1 << np.arange(masks.shape[0], dtype=np.int16)).reshape((-1,) + (1,) * (masks.ndim - 1))
    return np.asarray(np.sum(masks * weights, axis=0, dtype=np.int16))


def masks_to_height(masks: np.ndarray, depths_m: ArrayLike) -> np.ndarray:
    """Etched height ``-sum_j masks[j] * depths_m[j]`` (m) for any etch depths.

    Parameters
    ----------
    masks : ndarray of bool, shape (n_masks, rows, cols)
    depths_m : sequence of float
        Etch depth of each mask (m), e.g. the measured ones.

    Returns
    -------
    ndarray of float64
    """
    masks = _as_masks(masks)
    depths = np.asarray(depths_m, dtype=np.float64)
    if depths.shape != (masks.shape[0],):
        raise DoeError(f"need one etch depth per mask: {masks.shape[0]} masks, got {depths.size} depths")
    if not np.all(np.isfinite(depths)):
        raise DoeError(f"etch depths must be finite, got {depths.tolist()}")
    return -np.tensordot(depths, masks.astype(np.float64), axes=1)


def _as_masks(masks):
    masks = np.asarray(masks)
    if masks.ndim < 2:
        raise DoeError(f"masks must be shaped (n_masks, rows, cols), got shape {masks.shape}")
    if masks.dtype != bool:
        if not np.issubdtype(masks.dtype, np.integer) or not np.isin(masks, (0, 1)).all():
            raise DoeError(f"masks must be boolean (or 0/1), got dtype {masks.dtype}")
        masks = masks.astype(bool)
    return masks
