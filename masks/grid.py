"""Where the design pixels sit on the plate: the pixel grid, GDS units and layers, and a
scanline rasterizer that turns read-back polygons into pixels.

Plate coordinates are micrometres (library unit 1e-6 m, precision 1e-9 m), y up, the
element centred on the die centre (0, 0). Pixel ``(r, c)`` of the design (row 0 at the
top) spans ``x in [x0 + c p, x0 + (c+1) p]`` and ``y in [y0 - (r+1) p, y0 - r p]``: rows
run toward decreasing y. With ``mirrored=True`` every x is negated (contact printing, the
mask is used face down), so columns run toward decreasing x.

Tone: ``"dark"`` (dark field, the default) draws on each mask layer the area its etch opens
(bit set: clear on the photomask, resist exposed, Cr and glass etched); ``"clear"`` (clear
field) draws the complement inside the element grid (the chrome that protects unetched
pixels).

The rasterizer (:func:`rasterize_points`) is written apart from :mod:`masks.polygons`, so
the read-back check does not share code with the polygon builder.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from doedesign.errors import DoeError

__all__ = ["narrowest_runs_px", "APERTURE_LAYER", "DEFAULT_LAYERS", "DIE_LAYER", "ELEMENT_CELL", "FORMATS", "GDS_VERTEX_CEILING",
           "MAX_VERTICES", "MIN_VERTICES", "PRECISION_M", "PixelGrid", "SUFFIXES", "TEXT_LAYER", "TONES", "UNIT_M",
           "check_layers", "drawn_masks", "rasterize_layer", "rasterize_points", "vertex_limits"]

UNIT_M = 1e-6
PRECISION_M = 1e-9
MAX_VERTICES = 199  #: GDSII default: the vertex limit most mask-shop tools accept
MIN_VERTICES = 5  #: gdstk's fracture returns nothing for 4 and write_gds then ignores the limit
GDS_VERTEX_CEILING = 8190  # an XY record's 16-bit length holds 8191 points, the closing one included
FORMATS = ("gds", "oasis")
SUFFIXES = {"gds": ".gds", "oasis": ".oas"}
TONES = ("dark", "clear")
DEFAULT_LAYERS = (1, 2, 3, 4)
APERTURE_LAYER = 10
DIE_LAYER = 11
TEXT_LAYER = 20
ELEMENT_CELL = "ELEMENT"


@dataclass(frozen=True)
class PixelGrid:
    """Where the design pixels sit on the plate.

    Attributes
    ----------
    shape : (rows, cols)
    pitch_dbu : int
        Pixel pitch in database units (nm).
    mirrored : bool
        x -> -x applied (contact printing).
    """

    shape: tuple
    pitch_dbu: int
    mirrored: bool = False

    @classmethod
    def centred(cls, shape: tuple[int, int], pitch_m: float, mirrored: bool = False) -> PixelGrid:
        """Grid of ``shape`` pixels of ``pitch_m`` centred on (0, 0)."""
        pitch_dbu = pitch_m / PRECISION_M
        if not (np.isfinite(pitch_dbu) and pitch_dbu >= 1):
            raise DoeError(f"pixel pitch {pitch_m} m is not a positive length of at least 1 nm")
        if abs(pitch_dbu - round(pitch_dbu)) > 1e-6 * pitch_dbu:
            raise DoeError(f"pixel pitch {pitch_m * 1e9:.4f} nm is not a whole number of the 1 nm "
                           "GDS database unit; pixel edges would be rounded")
        return cls(tuple(int(s) for s in shape), int(round(pitch_dbu)), bool(mirrored))

    @property
    def origin_dbu(self) -> tuple[int, int]:
        """(x, y) of the top-left corner of pixel (0, 0) before mirroring, in nm."""
        rows, cols = self.shape
        return -(cols * self.pitch_dbu) // 2, (rows * self.pitch_dbu) // 2

    @property
    def pitch_um(self) -> float:
        return self.pitch_dbu * PRECISION_M / UNIT_M

    def to_um(self, colrow: np.ndarray) -> np.ndarray:
        """Pixel-corner indices ``(col, row)`` -> plate coordinates (um), float array."""
        return self.dbu_to_um(np.asarray(colrow) * self.pitch_dbu)

    def dbu_to_um(self, xy_dbu: np.ndarray) -> np.ndarray:
        """Offsets ``(along the columns, down the rows)`` in nm from the corner of pixel (0, 0)
        -> plate coordinates (um), float array (off-grid vertices, e.g. offset edges)."""
        xy_dbu = np.asarray(xy_dbu)
        x0, y0 = self.origin_dbu
        x = x0 + xy_dbu[..., 0]
        y = y0 - xy_dbu[..., 1]
        if self.mirrored:
            x = -x
        return np.stack([x, y], axis=-1) * (PRECISION_M / UNIT_M)

    def to_index(self, xy_um: np.ndarray) -> np.ndarray:
        """Plate coordinates (um) -> fractional pixel-corner indices ``(col, row)``."""
        xy = np.asarray(xy_um, dtype=np.float64) * (UNIT_M / PRECISION_M)
        x0, y0 = self.origin_dbu
        x = -xy[..., 0] if self.mirrored else xy[..., 0]
        return np.stack([(x - x0) / self.pitch_dbu, (y0 - xy[..., 1]) / self.pitch_dbu], axis=-1)

    def bbox_um(self) -> tuple[tuple[float, float], tuple[float, float]]:
        """((xmin, ymin), (xmax, ymax)) of the element in um."""
        corners = self.to_um(np.array([[0, 0], [self.shape[1], self.shape[0]]]))
        return tuple(corners.min(axis=0)), tuple(corners.max(axis=0))

    def report(self) -> dict:
        """The ``pixel_grid`` entry of ``report.json``."""
        x0, y0 = self.origin_dbu
        x0 = -x0 if self.mirrored else x0
        return {"origin_um": [x0 * 1e-3, y0 * 1e-3], "pitch_um": self.pitch_um,
                "shape": list(self.shape), "rows": "toward decreasing y",
                "columns": "toward decreasing x" if self.mirrored else "toward increasing x",
                "mirrored": self.mirrored,
                "origin_is": "outer corner of pixel (0, 0) at the start of row 0 and column 0"}


def drawn_masks(masks: np.ndarray, tone: str = "dark") -> np.ndarray:
    """What each layer draws: the open (etched) pixels for dark field, the rest for clear field."""
    if tone not in TONES:
        raise DoeError(f"tone must be one of {', '.join(TONES)}, got {tone!r}")
    masks = np.asarray(masks, dtype=bool)
    return masks if tone == "dark" else ~masks


def check_layers(layers: Sequence[int], n_masks: int) -> tuple:
    """One distinct GDS layer 0..255 per mask, clear of the aperture/die/text layers."""
    layers = tuple(int(v) for v in layers)
    if len(layers) != n_masks:
        raise DoeError(f"need one GDS layer per mask: {n_masks} masks, got layers {list(layers)}")
    if len(set(layers)) != len(layers) or min(layers) < 0 or max(layers) > 255:
        raise DoeError(f"mask layers must be distinct numbers 0..255, got {list(layers)}")
    if set(layers) & {APERTURE_LAYER, DIE_LAYER, TEXT_LAYER}:
        raise DoeError(f"mask layers {list(layers)} collide with the aperture/die/text layers "
                       f"{APERTURE_LAYER}, {DIE_LAYER}, {TEXT_LAYER}")
    return layers


def vertex_limits(formats: Sequence[str], max_vertices: int | None | str = "default") -> dict:
    """Largest vertex count of one polygon in each layout format written.

    Parameters
    ----------
    formats : sequence of {"gds", "oasis"}
    max_vertices : int, None or "default"
        One limit for every file (None: no limit, OASIS only); "default" gives GDSII
        :data:`MAX_VERTICES` and OASIS no limit (the format has none).

    Returns
    -------
    dict
        Format -> int, or None for no limit.
    """
    formats = tuple(formats)
    if not formats or any(f not in FORMATS for f in formats) or len(set(formats)) != len(formats):
        raise DoeError(f"layout formats must be distinct ones of {', '.join(FORMATS)}, got {list(formats)}")
    if isinstance(max_vertices, str):
        if max_vertices != "default":
            raise DoeError(f"max_vertices must be a number, None or 'default', got {max_vertices!r}")
        return {f: MAX_VERTICES if f == "gds" else None for f in formats}
    if max_vertices is not None:
        if int(max_vertices) != max_vertices or max_vertices < MIN_VERTICES:
            raise DoeError(f"--max-vertices must be an integer >= {MIN_VERTICES} or none, got {max_vertices}")
        max_vertices = int(max_vertices)
    if "gds" in formats and (max_vertices is None or max_vertices > GDS_VERTEX_CEILING):
        raise DoeError(f"--max-vertices {'none' if max_vertices is None else max_vertices}: a GDSII polygon "
                       f"holds at most {GDS_VERTEX_CEILING} vertices; give a smaller limit or --format oasis")
    return {f: max_vertices for f in formats}


def rasterize_layer(polygons: list[np.ndarray], grid: PixelGrid) -> tuple[np.ndarray, list[str]]:
    """Scanline fill of polygons on the pixel grid (pixel-exact Manhattan input only).

    Parameters
    ----------
    polygons : list of ndarray (k, 2)
        Vertices in plate coordinates (um), as read from a file.
    grid : PixelGrid

    Returns
    -------
    coverage : ndarray of int32, shape grid.shape
        How many polygons cover each pixel (1 inside, 0 outside; 2+ means overlap).
    problems : list of str
        Off-grid vertices, non-Manhattan edges, vertices outside the grid, too many vertices.
    """
    if not polygons:
        return np.zeros(grid.shape, np.int32), []
    counts = np.array([len(p) for p in polygons])
    return rasterize_points(grid.to_index(np.concatenate(polygons)), counts, grid)


def rasterize_points(idx: np.ndarray, counts: np.ndarray, grid: PixelGrid,
                     max_vertices: int | None = MAX_VERTICES) -> tuple[np.ndarray, list[str]]:
    """:func:`rasterize_layer` on flat arrays: ``idx`` (n, 2) (col, row) indices of the
    vertices of all polygons (float: checked to lie on the grid; integer: taken as exact),
    ``counts`` vertices per polygon; polygons over ``max_vertices`` (None: no limit) are a
    problem."""
    rows, cols = grid.shape
    problems: list[str] = []
    counts = np.asarray(counts, np.int64)
    if counts.size == 0:
        return np.zeros(grid.shape, np.int32), problems
    if max_vertices is not None and counts.max() > max_vertices:
        problems.append(f"{int((counts > max_vertices).sum())} polygons exceed {max_vertices} vertices")
    if np.asarray(idx).dtype.kind in "iu":
        pts = np.array(idx, np.int64)  # exact indices (a copy: clipped below)
    else:
        rounded = np.rint(idx)
        if np.abs(idx - rounded).max() > 1e-6:
            problems.append(f"{int((np.abs(idx - rounded) > 1e-6).any(axis=1).sum())} vertices off the pixel grid")
        pts = rounded.astype(np.int64)
    if pts.min() < 0 or pts[:, 0].max() > cols or pts[:, 1].max() > rows:
        problems.append("vertices outside the element's pixel grid")
        pts[:, 0] = np.clip(pts[:, 0], 0, cols)
        pts[:, 1] = np.clip(pts[:, 1], 0, rows)
    del idx
    ends = np.cumsum(counts)
    starts = ends - counts
    x, y = pts[:, 0].astype(np.int32), pts[:, 1].astype(np.int32)
    del pts
    # each vertex's successor; each polygon closes on its first vertex
    xn, yn = np.roll(x, -1), np.roll(y, -1)
    xn[ends - 1], yn[ends - 1] = x[starts], y[starts]
    diagonal = (x != xn) & (y != yn)
    if diagonal.any():
        problems.append(f"{int(diagonal.sum())} edges are not axis-parallel")
    del diagonal
    # Orientation from the shoelace area: a polygon counts +1 inside whichever way it winds.
    area2 = np.add.reduceat(x.astype(np.int64) * yn - xn.astype(np.int64) * y, starts)
    vertical = np.nonzero((x == xn) & (y != yn))[0]
    polygon = np.searchsorted(ends, vertical, side="right")
    w = np.sign(yn[vertical] - y[vertical]) * -np.sign(area2)[polygon]
    xc = x[vertical].astype(np.int64)
    lo = np.minimum(y[vertical], yn[vertical])
    hi = np.maximum(y[vertical], yn[vertical])
    del x, y, xn, yn, vertical, polygon
    width = cols + 1
    diff = np.bincount(np.concatenate([lo * width + xc, hi * width + xc]),
                       np.concatenate([w, -w]), minlength=(rows + 1) * width)
    coverage = np.rint(diff).astype(np.int32).reshape(rows + 1, width)
    del diff
    np.cumsum(coverage, axis=0, out=coverage)
    np.cumsum(coverage, axis=1, out=coverage)
    return np.ascontiguousarray(coverage[:rows, :cols]), problems


def narrowest_runs_px(mask: np.ndarray) -> tuple[int | None, int | None]:
    """Narrowest opening and narrowest gap between two openings (pixels), along rows and columns.

    A gap counts only between openings (not to the element's rim). None when there is none.
    """
    mask = np.asarray(mask, bool)
    opens, gaps = [], []
    for m in (mask, mask.T):
        padded = np.pad(m, ((0, 0), (1, 1))).astype(np.int8)
        d = np.diff(padded, axis=1)
        r_up, c_up = np.nonzero(d == 1)
        r_dn, c_dn = np.nonzero(d == -1)
        # Runs come in the same row-major order: the k-th rise pairs with the k-th fall.
        if r_up.size:
            opens.append(int((c_dn - c_up).min()))
            same_row = r_up[1:] == r_dn[:-1]
            if same_row.any():
                gaps.append(int((c_up[1:] - c_dn[:-1])[same_row].min()))
    return (min(opens) if opens else None), (min(gaps) if gaps else None)
