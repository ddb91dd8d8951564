"""Design files from phase or height maps made elsewhere, and maps from design files.

The library side of ``doe import`` and ``doe export``. Conventions, stated in the help and in
the design file's metadata (``import``):

- Arrays are row-major, row 0 at the top (the first row of a CSV, the top row of an image);
  the array is centred on the optical axis (its centre lies between the two middle pixels of
  an even side).
- Phase is the transmitted phase in radians at ``phase_wavelength_m``, more glass = more
  phase (:meth:`doedesign.materials.Material.phase`); it becomes height
  ``h = phase * h_2pi / (2 pi)`` and is wrapped into ``(-h_2pi, 0]`` by whole 2 pi heights.
- Height is z up, 0 at the unetched top, negative where etched (``sign="z_up"``), or the
  etch depth, positive into the glass (``sign="depth"``).

Readers are the libraries' own (numpy, scipy.io, h5py, tifffile, Pillow); only the choice
between them and the checks are written here.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from .budget import check_memory
from .design import Design
from .errors import DoeError
from .fileio import atomic_path, check_input_file, load_npy, read_npz
from .levels import check_level_count, quantize
from .materials import get_material

__all__ = ["EXPORT_WHAT", "FORMATS", "export_map", "import_design", "read_map"]

log = logging.getLogger(__name__)

#: File extensions ``doe import`` reads (and ``doe export`` writes where the format allows).
FORMATS = (".npy", ".npz", ".mat", ".tif", ".tiff", ".png", ".csv", ".txt", ".h5", ".hdf5")
EXPORT_WHAT = ("phase", "height", "levels")
HEIGHT_UNITS = {"m": 1.0, "um": 1e-6, "nm": 1e-9}


def _pick(arrays: dict, path: Path, array: str | None) -> np.ndarray:
    names = [k for k, v in arrays.items() if isinstance(v, np.ndarray) and v.dtype.kind in "fiub" and v.size > 1]
    if array is not None:
        if array not in arrays:
            raise DoeError(f"{path}: no array named {array!r}; it holds {', '.join(sorted(names)) or 'none'}")
        return np.asarray(arrays[array])
    if len(names) != 1:
        raise DoeError(f"{path}: {'no numeric array' if not names else 'several arrays (' + ', '.join(sorted(names)) + ')'}"
                       f"; name one with --array")
    return np.asarray(arrays[names[0]])


def _h5_arrays(path: Path) -> dict:
    import h5py

    out = {}
    with h5py.File(path, "r") as f:
        def visit(name, obj):
            if isinstance(obj, h5py.Dataset) and obj.dtype.kind in "fiub":
                check_memory(obj.size * 8, f"{path}: array {name}")
                out[name] = obj[()]
        f.visititems(visit)
    return out


def read_map(path: str | Path, array: str | None = None) -> tuple[np.ndarray, int | None]:
    """The 1-D or 2-D map in a file, as float64, and the image bit depth (8, 16) or None.

    Row 0 of the result is the top row of the file (an image's top row, a CSV's first line).
    MATLAB v7.3 files are HDF5 and store arrays transposed: they are transposed back.
    """
    path = check_input_file(path)
    ext = path.suffix.lower()
    bits = None
    try:
        if ext == ".npy":
            data = load_npy(path)
        elif ext == ".npz":
            data = _pick(read_npz(path, (), "map file"), path, array)
        elif ext == ".mat":
            import scipy.io

            try:
                mat = scipy.io.loadmat(path)
                data = _pick({k: v for k, v in mat.items() if not k.startswith("__")}, path, array)
            except NotImplementedError:  # v7.3: HDF5, column-major
                data = _pick(_h5_arrays(path), path, array).T
        elif ext in (".h5", ".hdf5"):
            data = _pick(_h5_arrays(path), path, array)
        elif ext in (".tif", ".tiff"):
            import tifffile

            data = tifffile.imread(path)
        elif ext == ".png":
            from PIL import Image

            with Image.open(path) as im:
                data = np.asarray(im)
        elif ext in (".csv", ".txt"):
            text = path.read_text()
            data = np.loadtxt(path, delimiter="," if "," in text else None, ndmin=1)
        else:
            raise DoeError(f"{path}: unknown map format {ext!r}; one of {', '.join(FORMATS)}")
    except DoeError:
        raise
    except Exception as exc:  # a reader's own failure on a damaged file: one line
        raise DoeError(f"{path}: not a readable {ext} map ({type(exc).__name__}: {exc})") from None
    data = np.asarray(data)
    if ext in (".tif", ".tiff", ".png"):
        if data.ndim == 3:
            raise DoeError(f"{path}: a {data.shape[-1]}-channel image; give a single-channel grey image")
        if data.dtype in (np.uint8, np.uint16):
            bits = 8 * data.dtype.itemsize
    if data.dtype.kind not in "fiub":
        raise DoeError(f"{path}: the map must be numeric, got {data.dtype}")
    if data.ndim == 2 and 1 in data.shape:
        data = data.ravel()
    if data.ndim not in (1, 2) or data.size < 2:
        raise DoeError(f"{path}: a map must be 2-D (or a 1-D radial profile), got shape {data.shape}")
    return np.asarray(data, dtype=np.float64), bits


def _radial(profile: np.ndarray, path: Path) -> np.ndarray:
    """A rotationally symmetric map of side ``2 len - 1`` from a profile sampled at r = 0, 1, .. px."""
    n = profile.size
    side = 2 * n - 1
    check_memory(side * side * 8 * 3, f"{path}: a {side} x {side} px element from its radial profile")
    r = np.hypot(*np.meshgrid(np.arange(side) - (n - 1), np.arange(side) - (n - 1), indexing="ij"))
    out = np.interp(r, np.arange(n), profile, right=np.nan)
    return out


def import_design(path: str | Path, *, pitch_m: float | None, phase_at_m: float | None = None,
                  height_unit: str | None = None, sign: str = "z_up", full_scale_rad: float | None = None,
                  wrapped: bool = False, n_levels: int = 16, material: str = "fused_silica",
                  design_wavelength_m: float | None = None, aperture: str | Path | None = None,
                  array: str | None = None, name: str | None = None) -> Design:
    """A design (quantized to ``n_levels``) from a phase or height map.

    Parameters
    ----------
    path : path
        The map (see :data:`FORMATS`); a 1-D array is a radial profile, r = 0 first, one pitch apart.
    pitch_m : float
        Pixel pitch (m); required.
    phase_at_m : float, optional
        The map is phase (rad) at this wavelength (m); it is also the design wavelength unless
        ``design_wavelength_m`` is given.
    height_unit : {"m", "um", "nm"}, optional
        The map is height in this unit (instead of ``phase_at_m``).
    sign : {"z_up", "depth"}
        Height convention (module docstring).
    full_scale_rad : float, optional
        For an 8/16-bit image: the full grey scale (256 or 65536 counts) stands for this many radians.
    wrapped : bool
        The phase is claimed wrapped: values must span at most 2 pi (a map far beyond is refused).
    n_levels : int
        2, 4, 8, 16 or 32.
    material, design_wavelength_m
        Of the element (default design wavelength: ``phase_at_m``, else 550 nm).
    aperture : path, optional
        Mask file (any map format): nonzero = clear. NaN pixels of the map are outside too.
    array : str, optional
        Array name in an ``.npz``, ``.mat`` or HDF5 file holding several.
    name : str, optional
        Design name (default the file's stem).

    Returns
    -------
    Design
        Heights and levels, the aperture, ``metadata["import"]`` stating the conventions.
    """
    path = Path(path)
    if pitch_m is None or not (np.isfinite(pitch_m) and 0 < pitch_m <= 1e-3):
        raise DoeError(f"{path}: give the pixel pitch (--pitch-um), got {pitch_m}")
    if (phase_at_m is None) == (height_unit is None):
        raise DoeError(f"{path}: say what the map holds: --phase-at-nm L (phase in radians) or --height-unit m|um|nm")
    n_levels = check_level_count(n_levels, f"{path}: --levels")
    data, bits = read_map(path, array)
    check_memory(data.size * 8 * 2, f"{path}: a {data.shape} map")
    if full_scale_rad is not None:
        if bits is None:
            raise DoeError(f"{path}: --full-scale-rad is for 8- or 16-bit grey images")
        if phase_at_m is None:
            raise DoeError(f"{path}: --full-scale-rad needs --phase-at-nm")
        data *= float(full_scale_rad) / 2 ** bits
    elif bits is not None and phase_at_m is not None:
        raise DoeError(f"{path}: an {bits}-bit image holds grey counts; give --full-scale-rad R")
    if data.ndim == 1:
        data = _radial(data, path)
    outside = ~np.isfinite(data)
    if outside.all():
        raise DoeError(f"{path}: every pixel is NaN or infinite")
    if aperture is not None:
        mask, _ = read_map(aperture)
        if mask.shape != data.shape:
            raise DoeError(f"{aperture}: aperture mask of shape {mask.shape}, the map has {data.shape}")
        outside |= ~(np.nan_to_num(mask) != 0)
    values = data  # converted in place: the map is this function's own copy
    values[outside] = 0.0
    wl = float(design_wavelength_m or phase_at_m or 550e-9)
    mat = get_material(material)
    if phase_at_m is not None:
        inside = ~outside
        span = float(np.max(values, where=inside, initial=-np.inf) - np.min(values, where=inside, initial=np.inf))
        del inside
        if wrapped and span > 2 * np.pi * 1.01:
            raise DoeError(f"{path}: a wrapped phase spans at most 2 pi, this map spans {span:.3g} rad "
                           f"({span / (2 * np.pi):.1f} x 2 pi): not a phase in radians?")
        if span > 2 * np.pi * 1e4:
            raise DoeError(f"{path}: the phase spans {span:.3g} rad (over 10^4 waves): not a phase in radians")
        height = values
        height *= float(mat.height_2pi_m(float(phase_at_m))) / (2 * np.pi)
    else:
        if height_unit not in HEIGHT_UNITS:
            raise DoeError(f"{path}: --height-unit must be one of m, um, nm, got {height_unit!r}")
        if sign not in ("z_up", "depth"):
            raise DoeError(f"{path}: height sign must be z_up or depth, got {sign!r}")
        height = values
        height *= HEIGHT_UNITS[height_unit] * (1.0 if sign == "z_up" else -1.0)
        if np.max(np.abs(height)) > 1e-3:
            raise DoeError(f"{path}: heights reach {np.max(np.abs(height)):.3g} m; is --height-unit right?")
    step = float(mat.height_2pi_m(wl)) / n_levels
    levels, summary = _quantize_in_blocks(height, step, n_levels)
    del height, values, data
    levels[outside] = 0
    meta = {"name": name or path.stem, "n_levels": n_levels,
            "import": {"source": str(path), "kind": "phase" if phase_at_m is not None else "height",
                       "phase_at_m": phase_at_m, "height_unit": height_unit, "sign": sign,
                       "full_scale_rad": full_scale_rad, "quantization": summary,
                       "convention": "row 0 at the top; array centred on the optical axis; z up, 0 = unetched "
                                     "top, negative etched; phase = 2 pi h / h_2pi, more glass more phase"}}
    return Design(np.multiply(levels, -step, dtype=np.float64), float(pitch_m), material=material, design_wavelength_m=wl, levels=levels,
                  aperture=~outside if outside.any() else None, metadata=meta)


def _quantize_in_blocks(height_m: np.ndarray, step_m: float, n_levels: int) -> tuple[np.ndarray, dict]:
    """:func:`doedesign.levels.quantize` of blocks of rows (the wrap is its own), so that its
    temporaries stay small beside a large map; the summary of the whole."""
    levels = np.empty(height_m.shape, np.int16)
    rows = max(1, (1 << 18) // max(height_m.shape[1], 1))  # 2 MB temporaries
    sq, worst, wrapped = 0.0, 0.0, 0
    for r in range(0, height_m.shape[0], rows):
        q = quantize(height_m[r:r + rows], step_m, n_levels)
        levels[r:r + rows] = q.levels
        sq += q.rms_error_m ** 2 * q.levels.size
        worst, wrapped = max(worst, q.max_error_m), wrapped + q.wrapped_pixels
    return levels, {"step_nm": step_m * 1e9, "n_levels": n_levels, "rms_error_nm": float(np.sqrt(sq / levels.size)) * 1e9,
                    "max_error_nm": worst * 1e9, "wrapped_pixels": wrapped}


def export_map(design: Design, what: str, out: str | Path, wavelength_m: float | None = None) -> Path:
    """Write a design's phase (rad at ``wavelength_m``, default its design wavelength), height (m,
    z up) or levels to ``out``; the format follows the extension (:data:`FORMATS`).

    Row 0 at the top. Images (.png, .tif) hold levels as grey counts (8-bit), or phase / height
    as 32-bit float TIFF (PNG: levels only).
    """
    out = Path(out)
    ext = out.suffix.lower()
    if what not in EXPORT_WHAT:
        raise DoeError(f"--what must be one of {', '.join(EXPORT_WHAT)}, got {what!r}")
    if ext not in FORMATS:
        raise DoeError(f"{out}: unknown format {ext!r}; one of {', '.join(FORMATS)}")
    from .levels import design_levels

    if what == "levels":
        data = design_levels(design)
    elif what == "height":
        data = design.height_m
    else:
        data = design.phase(float(wavelength_m or design.design_wavelength_m))
    if ext == ".png" and what != "levels":
        raise DoeError(f"{out}: PNG holds levels only (8-bit grey); write phase or height as .tif, .npy, ...")
    with atomic_path(out) as tmp:
        if ext == ".npy":
            with open(tmp, "wb") as fh:
                np.save(fh, data)
        elif ext == ".npz":
            with open(tmp, "wb") as fh:
                np.savez_compressed(fh, allow_pickle=True, **{what: data})
        elif ext == ".mat":
            import scipy.io

            with open(tmp, "wb") as fh:
                scipy.io.savemat(fh, {what: data})
        elif ext in (".h5", ".hdf5"):
            import h5py

            with h5py.File(tmp, "w") as f:
                f.create_dataset(what, data=data)
                f.attrs["convention"] = "row 0 at the top; centred on the optical axis"
        elif ext in (".tif", ".tiff"):
            import tifffile

            tifffile.imwrite(tmp, data.astype(np.uint8 if what == "levels" else np.float32))
        elif ext == ".png":
            from PIL import Image

            Image.fromarray(data.astype(np.uint8)).save(tmp, format="PNG")
        else:
            np.savetxt(tmp, data, delimiter="," if ext == ".csv" else " ",
                       fmt="%d" if what == "levels" else "%.10g")
    return out
