"""A large camera window fitted on tiles spread over it.

Every model evaluation of a camera-frame fit renders the process and the instrument on a
fine grid (about 0.12 um) over the whole window; on a 512 x 512 field that grid holds some
5000 x 5000 points and a fit's Jacobian needs dozens of them. The fits of a large window
therefore run on a few tiles spread evenly over it (4 x 4 squares of 48 camera pixels, some
37 000 pixels: twelve times the information of a 56 px window, with the field's full
extent for rotation, scale and gradients), each rendered on its own small fine grid. The
levelling is the whole field's (one piston and tilt for all tiles), and the placement is
refined about the field's centre, so the tiles move as one field.

What the user reads is the whole window: residual maps, the breakdown, the structure test
and the final residual are computed on every pixel of it with the model fitted on the tiles.

Arrays are row-major with row 0 at the top of the camera image.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np

from metrology.diagnosis import engine as dg
from metrology.matching.instrument import InstrumentModel
from metrology.matching.level import Leveller

if TYPE_CHECKING:
    from metrology.diagnosis.camera import CameraHeightProblem

__all__ = ["TILED_WINDOW_PX", "TILE_MARGIN_PX", "TILE_PX", "TILES_PER_SIDE", "TiledCameraProblem", "tile_origins"]

#: Camera windows larger than this (pixels per side) are fitted on tiles.
TILED_WINDOW_PX = 256

# Tiles per side and camera pixels per tile side.
TILES_PER_SIDE = 4
TILE_PX = 48
# Design pixels each tile renders around itself: the kernel's reach (~0.5 design px) plus a
# placement refinement of up to a design pixel.
TILE_MARGIN_PX = 2


def tile_origins(size_px: int, tile_px: int = TILE_PX, per_side: int = TILES_PER_SIDE) -> list[int]:
    """First camera pixel of each tile along one side of a ``size_px`` window: evenly spread,
    the first at 0 and the last ending at the window's edge."""
    if size_px <= tile_px:
        return [0]
    return sorted(set(int(v) for v in np.rint(np.linspace(0, size_px - tile_px, per_side))))


class TiledCameraProblem(dg.Problem):
    """The fits of a :class:`~metrology.diagnosis.camera.CameraHeightProblem` on its tiles.

    Parameters
    ----------
    whole : CameraHeightProblem
        The whole window: maps, breakdown and structure groups are its own.
    tile_px, per_side, margin_px : int
        Tile size (camera pixels), tiles per side, design pixels rendered around each tile.
    """

    units = "m"
    judges_partial_matches = True
    parallel_fits = True
    fits_part_of_map = True

    def __init__(self, whole: CameraHeightProblem, tile_px: int = TILE_PX, per_side: int = TILES_PER_SIDE,
                 margin_px: int = TILE_MARGIN_PX) -> None:
        self.whole = whole
        self.effects = whole.effects
        self.nuisance = whole.nuisance
        self.noise = whole.noise
        self.screening = None
        rows, cols = whole.measured.shape
        self.slices = [(slice(r, r + tile_px), slice(c, c + tile_px))
                       for r in tile_origins(rows, tile_px, per_side) for c in tile_origins(cols, tile_px, per_side)]
        # The tiles share one placement matrix, so one store of blur transfers serves them all.
        transfers = InstrumentModel.transfer_cache(max_items=32)
        self.tiles = [whole.sub(sr.start, sc.start, tile_px, margin_px=margin_px, transfers=transfers,
                                share=len(self.slices)) for sr, sc in self.slices]
        self.compared = np.zeros(whole.measured.shape, bool)
        for sl in self.slices:
            self.compared[sl] = whole.keep[sl]
        # One piston and tilt for the whole field, fitted on the tiles' pixels.
        self.leveller = Leveller(whole.measured.shape, self.compared, whole.curvature)

    def residual(self, model: dict[str, np.ndarray]) -> np.ndarray:
        diff = np.zeros(self.whole.measured.shape)
        for sl, tile in zip(self.slices, self.tiles):
            diff[sl] = np.where(tile.keep, tile.measured - tile.render(model), 0.0)
        return self.leveller(diff[self.compared])

    def residual_map(self, model: dict[str, np.ndarray]) -> np.ndarray:
        return self.whole.residual_map(model)

    def structure_groups(self) -> list[np.ndarray]:
        return self.whole.structure_groups()

    def breakdown(self, residual_map: np.ndarray) -> dict[str, dict]:
        return self.whole.breakdown(residual_map)

    def instrument_signature(self, residual_map: np.ndarray, **kw: Any) -> dict | None:
        return self.whole.instrument_signature(residual_map, **kw)
