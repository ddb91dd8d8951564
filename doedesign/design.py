"""The DOE design file: a ``.npz`` that numpy alone can read.

Fields
------
height_m : float64 (rows, cols)
    Surface height in metres, z up as a profilometer reports it: 0 at the unetched
    top surface, negative where glass was etched (level k is k steps deep).
    Row 0 is the top row; column 0 the left column. The array is centred on the
    optical axis. Flipping the sign point-reflects the PSF.
pitch_m : float
    DOE pixel pitch (square pixels).
material : str
    Registry name of the material (see :mod:`doedesign.materials`).
design_wavelength_m : float
    Wavelength at which the level step is a 2 pi / N phase step.
levels : int (rows, cols), optional
    Level index per pixel once quantized (0 = top surface, k = k steps deep).
aperture : bool (rows, cols), optional
    The clear region (True where light passes).
metadata : str
    JSON object: name, target, camera parameters, tool version, ``format_version``, and
    optional fields: ``n_levels`` (2, 4, 8, 16 or 32 levels, made by log2(n_levels) binary
    masks; default 16), ``mask_depths_m`` (the etch depth of each mask, shallowest bit first;
    default ``2**j`` level steps) and ``surround`` (``open``, ``opaque`` or ``repeat``: what
    surrounds the design inside the lens aperture, :data:`doedesign.camera.SURROUNDS`; default
    ``open``). A file without ``n_levels`` is a 16-level design, as every file written before
    it existed.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal, overload

import numpy as np

from . import __version__
from .camera import Camera
from .errors import DesignFileError, DoeError
from .fileio import atomic_path, dumps_json, parse_json, read_npz
from .levels import N_LEVELS, check_level_count, level_step_m, masks_for_levels, quantize
from .materials import get_material

__all__ = ["Design", "FORMAT_VERSION", "REQUIRED"]

FORMAT_VERSION = 1
MAX_NAME_CHARS = 200
REQUIRED = ("height_m", "pitch_m", "material", "design_wavelength_m", "metadata")


@dataclass
class Design:
    """A DOE height map with its pitch, material and provenance.

    Construct directly or with :meth:`load`; :meth:`validate` runs on both.
    """

    height_m: np.ndarray
    pitch_m: float
    material: str = "fused_silica"
    design_wavelength_m: float = 550e-9
    levels: np.ndarray | None = None
    aperture: np.ndarray | None = None
    metadata: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        # The file :meth:`load` read (not a field): errors found later, in the camera entry say,
        # name the file the user gave rather than the design's internal name.
        self.source_path: str | None = None
        self.height_m = np.asarray(self.height_m, dtype=np.float64)
        self.pitch_m = float(self.pitch_m)
        self.design_wavelength_m = float(self.design_wavelength_m)
        if self.levels is not None:
            self.levels = np.asarray(self.levels)
        if self.aperture is not None:
            self.aperture = np.asarray(self.aperture)
        self.metadata = dict(self.metadata)
        self.metadata.setdefault("format_version", FORMAT_VERSION)
        self.metadata.setdefault("tool_version", __version__)
        self.validate()

    @property
    def shape(self) -> tuple[int, int]:
        return self.height_m.shape

    @property
    def name(self) -> str:
        return self.metadata.get("name", "design")

    @property
    def n_levels(self) -> int:
        """Level count of the element (``metadata["n_levels"]``, default 16)."""
        return int(self.metadata.get("n_levels", N_LEVELS))

    @property
    def n_masks(self) -> int:
        """Binary masks that etch it: ``log2(n_levels)``."""
        return masks_for_levels(self.n_levels)

    def etch_depths_m(self) -> tuple[float, ...]:
        """Nominal etch depth of each mask (m), mask j etching bit j of the level.

        ``metadata["mask_depths_m"]`` when the design names them, else ``2**j`` level steps
        (:meth:`level_step_m`).
        """
        given = self.metadata.get("mask_depths_m")
        if given is not None:
            return tuple(float(v) for v in given)
        step = self.level_step_m()
        return tuple(step * 2 ** j for j in range(self.n_masks))

    def validate(self, source: str = "design") -> None:
        """Raise :class:`~doedesign.errors.DesignFileError` naming the field when anything is wrong."""
        h = self.height_m
        if h.ndim != 2 or min(h.shape) < 1:
            raise DesignFileError(f"{source}: height_m must be a 2-D array, got shape {h.shape}")
        if not np.all(np.isfinite(h)):
            raise DesignFileError(f"{source}: height_m holds {np.count_nonzero(~np.isfinite(h))} NaN or infinite values")
        if not (np.isfinite(self.pitch_m) and self.pitch_m > 0):
            raise DesignFileError(f"{source}: pitch_m must be positive, got {self.pitch_m}")
        if self.pitch_m > 1e-3:
            raise DesignFileError(f"{source}: pitch_m = {self.pitch_m} m is not a DOE pitch (metres expected)")
        if not (np.isfinite(self.design_wavelength_m) and 100e-9 < self.design_wavelength_m < 20e-6):
            raise DesignFileError(f"{source}: design_wavelength_m = {self.design_wavelength_m} is not a wavelength in metres")
        reach = max(float(h.max()), -float(h.min()))  # no temporary the size of the map
        if reach > 1e-3:
            raise DesignFileError(f"{source}: height_m reaches {reach:.3g} m; heights must be in metres")
        try:
            get_material(self.material)
        except DoeError as exc:
            raise DesignFileError(f"{source}: material: {exc}") from None
        for name in ("levels", "aperture"):
            arr = getattr(self, name)
            if arr is not None and arr.shape != h.shape:
                raise DesignFileError(f"{source}: {name} has shape {arr.shape}, height_m has {h.shape}")
        if self.levels is not None:
            if not np.issubdtype(self.levels.dtype, np.integer):
                raise DesignFileError(f"{source}: levels must be integers, got {self.levels.dtype}")
            if self.levels.size and self.levels.min() < 0:
                raise DesignFileError(f"{source}: levels must be non-negative, minimum is {self.levels.min()}")
        if self.aperture is not None and self.aperture.dtype != bool:
            raise DesignFileError(f"{source}: aperture must be boolean, got {self.aperture.dtype}")
        # Levels beyond the count are refused where they are used (quantize_design) and where a
        # file is read (check_levels), so that a wrong in-memory design still reaches the CLI's one line.
        _check_level_structure(source, self.metadata)

    def phase(self, wavelength_m: float) -> np.ndarray:
        """Phase (rad) of the height map at ``wavelength_m``, from the heights themselves."""
        return get_material(self.material).phase(self.height_m, wavelength_m)

    def height_2pi_m(self) -> float:
        """2 pi height at the design wavelength."""
        return float(get_material(self.material).height_2pi_m(self.design_wavelength_m))

    @overload
    def camera(self, missing: Literal["seed"] = "seed") -> Camera: ...

    @overload
    def camera(self, missing: str) -> Camera | None: ...

    def camera(self, missing: str = "seed") -> Camera | None:
        """The camera recorded in the metadata (``metadata["camera"]``, :meth:`Camera.to_dict <doedesign.camera.Camera.to_dict>`).

        Parameters
        ----------
        missing : {"seed", "none"}
            What a design without a camera entry gets: the seed paper's camera (``Camera()``)
            or None.

        Raises
        ------
        DesignFileError
            A camera entry that is not a valid camera description.
        """
        cam = self.metadata.get("camera")
        if cam is None:
            return Camera() if missing == "seed" else None
        where = self.source_path or self.name
        if not isinstance(cam, dict):
            raise DesignFileError(f"{where}: metadata camera must be a JSON object, got {type(cam).__name__}")
        try:
            return Camera.from_dict(cam)
        except (TypeError, ValueError, DoeError) as exc:
            raise DesignFileError(f"{where}: metadata camera entry is not a valid camera: {exc}") from None

    def level_step_m(self, n_levels: int | None = None) -> float:
        """Depth of one of ``n_levels`` levels (default: the design's own count) at this design's
        material and wavelength.

        See :func:`doedesign.levels.level_step_m`; the level map itself comes from
        :func:`doedesign.levels.design_levels`.
        """
        return level_step_m(self.material, self.design_wavelength_m, self.n_levels if n_levels is None else n_levels)

    def save(self, path: str | Path) -> Path:
        """Write the design atomically to ``path`` (``.npz``)."""
        arrays = dict(
            height_m=self.height_m,
            pitch_m=np.float64(self.pitch_m),
            material=np.str_(self.material),
            design_wavelength_m=np.float64(self.design_wavelength_m),
            metadata=np.str_(dumps_json(self.metadata, indent=None)),
        )
        if self.levels is not None:
            arrays["levels"] = self.levels.astype(np.int16)
        if self.aperture is not None:
            arrays["aperture"] = self.aperture.astype(bool)
        path = Path(path)
        with atomic_path(path) as tmp, open(tmp, "wb") as fh:
            np.savez_compressed(fh, **arrays)
        return path

    @classmethod
    def load(cls, path: str | Path) -> Design:
        """Read and validate a design file; errors name the file and the field."""
        path = Path(path)
        data = read_npz(path, REQUIRED, "design file", DesignFileError)
        metadata = parse_json(str(data["metadata"]), f"{path}: metadata", DesignFileError)
        if not isinstance(metadata, dict):
            raise DesignFileError(f"{path}: metadata must be a JSON object")
        _check_metadata(path, metadata)
        for k in ("pitch_m", "design_wavelength_m"):
            if data[k].ndim != 0 or data[k].dtype.kind not in "fiu":
                raise DesignFileError(f"{path}: {k} must be one real number, got {data[k].dtype} {data[k].shape}")
        if data["material"].ndim != 0 or data["material"].dtype.kind not in "US" or len(str(data["material"])) > 64:
            raise DesignFileError(f"{path}: material must be a name (text up to 64 characters)")
        if not np.issubdtype(data["height_m"].dtype, np.floating):
            raise DesignFileError(f"{path}: height_m must be floating point, got {data['height_m'].dtype}")
        design = cls.__new__(cls)
        design.height_m = data["height_m"].astype(np.float64)
        design.pitch_m = float(data["pitch_m"])
        design.material = str(data["material"])
        design.design_wavelength_m = float(data["design_wavelength_m"])
        design.levels = data.get("levels")
        design.aperture = data.get("aperture")
        design.metadata = metadata
        design.source_path = str(path)
        design.validate(source=str(path))
        design.check_levels(source=str(path))
        return design

    def check_levels(self, source: str = "design") -> None:
        """Refuse levels that contradict the heights: each height must round to its stored level
        under the level rule (:func:`doedesign.levels.quantize`: nearest step, 2 pi wrap).

        A design whose ``levels`` and ``height_m`` disagree would give masks of one element
        and PSFs of another.
        """
        if self.levels is None:
            return
        step = self.level_step_m()
        off = quantize(self.height_m, step, self.n_levels).levels != self.levels
        if off.any():
            r, c = np.argwhere(off)[0]
            raise DesignFileError(
                f"{source}: levels contradict height_m at {int(off.sum())} pixel(s); first at row {r}, col {c}: "
                f"level {int(self.levels[r, c])} means {-self.levels[r, c] * step * 1e9:.1f} nm, height_m is "
                f"{self.height_m[r, c] * 1e9:.1f} nm (step {step * 1e9:.2f} nm)")

    def summary(self) -> dict:
        """Dictionary for ``doe inspect --json``."""
        h = self.height_m
        out = {
            "kind": "design",
            "name": self.name,
            "shape": list(h.shape),
            "pitch_m": self.pitch_m,
            "size_m": [h.shape[0] * self.pitch_m, h.shape[1] * self.pitch_m],
            "material": self.material,
            "design_wavelength_m": self.design_wavelength_m,
            "height_min_m": float(h.min()),
            "height_max_m": float(h.max()),
            "height_2pi_m": self.height_2pi_m(),
            "levels": None,
            "n_levels": self.n_levels,
            "etch_depths_nm": [d * 1e9 for d in self.etch_depths_m()],
            "metadata": self.metadata,
        }
        if self.levels is not None:
            used, counts = np.unique(self.levels, return_counts=True)
            out["levels"] = {"count": int(self.levels.max()) + 1 if self.levels.size else 0,
                             "used": used.tolist(), "pixels": counts.tolist()}
        if self.aperture is not None:
            out["aperture_fraction"] = float(self.aperture.mean())
        out["surround"] = self.metadata.get("surround", "open (default)")
        return out


def _check_level_structure(source, metadata):
    """``n_levels`` one of 2..32 (powers of two) and ``mask_depths_m``, if given, one positive depth
    (m, under 10 um) per mask."""
    n = check_level_count(metadata.get("n_levels", N_LEVELS), f"{source}: metadata n_levels")
    depths = metadata.get("mask_depths_m")
    if depths is None:
        return
    n_masks = masks_for_levels(n)
    ok = isinstance(depths, (list, tuple)) and len(depths) == n_masks and all(
        isinstance(v, (int, float, np.floating, np.integer)) and not isinstance(v, bool) and np.isfinite(v)
        and 0 < v < 10e-6 for v in depths)
    if not ok:
        raise DesignFileError(f"{source}: metadata mask_depths_m must list {n_masks} etch depths in metres "
                              f"(0 to 10 um) for a {n}-level design, got {depths!r}")


def _check_metadata(path, metadata):
    """Types of the metadata fields the tool uses (a number as a name, a text version, ...)."""
    version = metadata.get("format_version", FORMAT_VERSION)
    if isinstance(version, bool) or not isinstance(version, int):
        raise DesignFileError(f"{path}: metadata format_version must be an integer, got {version!r}")
    if version > FORMAT_VERSION:
        raise DesignFileError(f"{path}: format_version {version} is newer than this tool reads ({FORMAT_VERSION})")
    name = metadata.get("name", "design")
    if not isinstance(name, str) or not name.strip() or len(name) > MAX_NAME_CHARS:
        shown = repr(name) if not isinstance(name, str) else f"{len(name)} characters"
        raise DesignFileError(f"{path}: metadata name must be text of 1 to {MAX_NAME_CHARS} characters, got {shown}")
    if "surround" in metadata:
        from .camera import check_surround

        try:
            check_surround(metadata["surround"], f"{path}: metadata surround")
        except DoeError as exc:
            raise DesignFileError(str(exc)) from None
    if "camera" in metadata and not isinstance(metadata["camera"], dict):
        raise DesignFileError(f"{path}: metadata camera must be an object, got {type(metadata['camera']).__name__}")

