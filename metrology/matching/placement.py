"""Where the camera's pixels lie on the design: an affine map from camera pixel centres to design pixels.

Rows and columns are row-major with row 0 at the top in both frames; design pixel (i, j) is
centred at (i, j). :meth:`Placement.refined` moves a placement by the fits' nuisance
parameters, :meth:`Placement.in_frame_of` turns a mask's printed motion into a placement.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from metrology.matching.register import Registration

__all__ = ["PLACEMENT_PARAMS", "Placement"]

#: Nuisance parameters of the placement, in the order of :meth:`Placement.refined`.
PLACEMENT_PARAMS = ("shift_row_px", "shift_col_px", "rotation_rad", "scale_row", "scale_col")



@dataclass(frozen=True)
class Placement:
    """Affine map from camera pixel (row, col) centres to design-pixel coordinates.

    Attributes
    ----------
    matrix : ndarray (2, 2)
    offset : ndarray (2,)
    """

    matrix: np.ndarray
    offset: np.ndarray

    @classmethod
    def from_registration(cls, registration: Registration) -> Placement:
        """The placement of a :class:`~metrology.matching.register.Registration`."""
        return cls(np.array(registration.matrix, float), np.array(registration.offset, float))

    def to_design(self, rows: np.ndarray | float, cols: np.ndarray | float,
                  ) -> tuple[np.ndarray | float, np.ndarray | float]:
        """Design coordinates (R, C) of camera coordinates (rows, cols)."""
        m, t = self.matrix, self.offset
        return m[0, 0] * rows + m[0, 1] * cols + t[0], m[1, 0] * rows + m[1, 1] * cols + t[1]

    def refined(self, values: Sequence[float] | np.ndarray, shape: tuple[int, int],
                centre_px: Sequence[float] | np.ndarray | None = None) -> Placement:
        """This placement moved by nuisance ``values`` (see :data:`PLACEMENT_PARAMS`).

        ``shift_row_px``, ``shift_col_px``: design pixels, of the field centre;
        ``rotation_rad``: counter-clockwise (y up) about the field centre; ``scale_row``,
        ``scale_col``: relative change of the camera pixel size along its rows and columns.
        The field centre is that of ``shape`` unless ``centre_px`` (camera row, col) is given
        (a crop refined as the field it was cut from).
        """
        dr, dc, a, sr, sc = (float(v) for v in values)
        centre = (np.asarray(shape, float) - 1) / 2 if centre_px is None else np.asarray(centre_px, float)
        rot = np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])
        matrix = rot @ self.matrix @ np.diag([1.0 + sr, 1.0 + sc])
        centre_design = self.matrix @ centre + self.offset + np.array([dr, dc])
        return Placement(matrix, centre_design - matrix @ centre)

    def in_frame_of(self, shift_rc: Sequence[float], rotation_rad: float, centre_rc: Sequence[float]) -> Placement:
        """The same camera pixels placed on an image before a rigid motion moved it.

        Where a mask printed with a shift and a rotation (:func:`masks.process.mask_motion`,
        in design pixels) shows under this placement, its etch printed in place is sampled
        under the returned one (:func:`masks.litho.inverse_motion`): a mask's overlay becomes
        a placement, as cheap to change as the camera's own.
        """
        from masks.litho import inverse_motion

        inverse, offset = inverse_motion((float(shift_rc[0]), float(shift_rc[1])), rotation_rad,
                                         (float(centre_rc[0]), float(centre_rc[1])))
        return Placement(inverse @ self.matrix, inverse @ self.offset + offset)
