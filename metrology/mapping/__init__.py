"""Maps of a whole element: tiles diagnosed on Dask (:mod:`.tiles_map`), models fitted to them (:mod:`.models`)."""

from metrology.mapping.models import fit_depth_model, fit_overlay_model
from metrology.mapping.tiles_map import MAP_EFFECTS, diagnose_tile, map_tiles, open_map, run_map

__all__ = ["MAP_EFFECTS", "diagnose_tile", "fit_depth_model", "fit_overlay_model", "map_tiles", "open_map", "run_map"]
