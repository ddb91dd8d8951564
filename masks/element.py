"""One DOE element's die from a design file: levels, binary masks, verified GDSII, preview, report.

The library side of ``doe masks`` (the command only parses its options), so the demo and
notebooks make the same files the command does. Arrays are row-major, row 0 at the top; the
GDS coordinates follow :mod:`masks.gds` (element centred on the die, rows toward decreasing y).
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from doedesign.budget import check_memory, mask_export_bytes
from doedesign.design import Design
from doedesign.errors import DoeError
from doedesign.fileio import atomic_path, output_run, safe_file_name, write_json
from doedesign.levels import quantize_design

from .decompose import levels_to_masks
from .gds import export_masks
from .grid import vertex_limits
from .plate import PlateDesign, export_plate

__all__ = ["DIE_SIZE_M", "LEVEL_COLOURS", "MIN_APERTURE_PX", "PREVIEW_PX", "clear_aperture_m", "preview",
           "write_element"]

log = logging.getLogger(__name__)

#: Side of the square die (m).
DIE_SIZE_M = 10e-3
#: Smallest clear aperture one may ask for, in DOE pixels: a smaller circle chromes the element.
MIN_APERTURE_PX = 4


def clear_aperture_m(design: Design) -> float | None:
    """Clear circle diameter: the camera's aperture from the metadata, else the aperture mask."""
    camera = design.camera(missing="none")
    if camera is not None and camera.aperture_diameter_m:
        return float(camera.aperture_diameter_m)
    if design.aperture is not None and design.aperture.any():
        rows, cols = np.nonzero(design.aperture)
        extent = max(rows.max() - rows.min(), cols.max() - cols.min()) + 1
        return float(extent * design.pitch_m)
    return None


#: viridis at the 16 levels (matplotlib's colormap sampled at k / 15), so the preview draws
#: without importing matplotlib: Pillow writes it in milliseconds, matplotlib costs a second.
LEVEL_COLOURS = np.array([[68, 1, 84], [72, 26, 108], [71, 47, 125], [65, 68, 135], [57, 86, 140], [49, 104, 142],
                          [42, 120, 142], [35, 136, 142], [31, 152, 139], [34, 168, 132], [53, 183, 121],
                          [84, 197, 104], [122, 209, 81], [165, 219, 54], [210, 226, 27], [253, 231, 37]], np.uint8)
PREVIEW_PX = 360  #: longest side of each panel


def preview(levels: np.ndarray, masks: np.ndarray, path: str | Path, title: str) -> None:
    """PNG of the level map and every mask (row 0 at the top, white = open/etched).

    Panels are scaled to at most :data:`PREVIEW_PX` pixels a side: the levels by nearest
    pixel, the masks by area (features finer than a preview pixel show as grey, not as
    moire); the level panel has a colour key of the 2**n levels underneath.
    """
    from PIL import Image, ImageDraw, ImageFont

    n = masks.shape[0]
    rows, cols = levels.shape
    scale = min(1.0, PREVIEW_PX / max(rows, cols))
    size = (max(1, round(cols * scale)), max(1, round(rows * scale)))
    colours = LEVEL_COLOURS[np.round(np.linspace(0, 15, 2 ** n)).astype(int)]
    panels = [Image.fromarray(colours[np.clip(levels, 0, 2 ** n - 1)]).resize(size, Image.Resampling.NEAREST)]
    panels += [Image.fromarray(masks[j].astype(np.uint8) * np.uint8(255)).resize(size, Image.Resampling.BOX)
               for j in range(n)]
    titles = [f"{title}: levels"] + [f"mask {j + 1} (bit {j}, open = white)" for j in range(n)]
    w, h = size
    gap, head, key = 16, 22, 28
    sheet = Image.new("RGB", (len(panels) * (w + gap) + gap, head + h + key + gap), "white")
    draw = ImageDraw.Draw(sheet)
    font = ImageFont.load_default(size=12)
    for k, (panel, text) in enumerate(zip(panels, titles)):
        x = gap + k * (w + gap)
        sheet.paste(panel, (x, head))
        draw.text((x, 4), text, fill="black", font=font)
    cell = w / len(colours)
    for k, colour in enumerate(colours):
        draw.rectangle([gap + k * cell, head + h + 6, gap + (k + 1) * cell, head + h + 16],
                       fill=tuple(int(c) for c in colour))
    draw.text((gap, head + h + 16), "0", fill="black", font=font)
    draw.text((gap + w - 14, head + h + 16), str(len(colours) - 1), fill="black", font=font)
    with atomic_path(path) as tmp:
        sheet.save(tmp, format="PNG")


def write_element(design: Design, out: str | Path, *, source: str | None = None, tone: str = "dark",
                  mirrored: bool = False, depths_m: Sequence[float] | None = None,
                  layers: Sequence[int] | None = None, etch_order: Sequence[int] | None = None,
                  clear_aperture: float | None = None, formats: Sequence[str] = ("gds",),
                  max_vertices: int | None | str = "default", plate: bool = False,
                  print_check: dict | None = None, corrected_masks: tuple[np.ndarray, int] | None = None) -> dict:
    """Write ``OUT/<name>.gds`` and/or ``OUT/<name>.oas`` (each read back and verified),
    ``OUT/<name>.lyp`` (KLayout layer names and colours), ``OUT/masks.png`` and ``OUT/report.json``.

    With ``plate``, also ``OUT/<name>_plate.gds`` (and/or ``.oas``, and its ``.lyp``): a
    full 4-inch wafer of this die placed by array references, with global alignment marks
    (:func:`masks.plate.export_plate`).

    Parameters
    ----------
    design : Design
        Its levels, or its heights quantized by :func:`doedesign.levels.quantize_design`.
    out : path
        Output directory.
    source : str, optional
        The design's file name (reports and messages).
    tone, mirrored, etch_order, formats, max_vertices
        See :func:`masks.gds.export_masks`.
    layers : sequence of int, optional
        GDS layer of each mask (default 1 .. M for the design's M = log2(n_levels) masks).
    plate : bool
        Also write the full-wafer plate (see above).
    print_check : dict, optional
        A :func:`masks.print_check.print_check` report, written as ``OUT/print_check.json`` and
        ``OUT/print_check.md`` in the same run (and its field overlap in ``report.json``). With
        ``corrected_masks`` it holds ``uncorrected`` (the drawn masks' check) and ``opc`` (the
        correction's summary) beside the corrected masks' figures.
    corrected_masks : (ndarray of bool, int), optional
        Masks drawn on a finer grid instead of the design's pixels (``masks.opc``'s pre-distorted
        masks, shape (n_masks, rows * k, cols * k)) and ``k``: the layout files (and plate) hold
        them, on a ``pitch / k`` grid, and are verified against them.
    depths_m : sequence of float, optional
        Etch depth per mask (default :meth:`doedesign.design.Design.etch_depths_m`: the design's
        own, else ``2**j`` level steps).
    clear_aperture : float, optional
        Cr clear circle diameter (m); default :func:`clear_aperture_m`. None is drawn when it
        does not fit the die.

    Returns
    -------
    dict
        The report written to ``report.json``.
    """
    source = source or design.name
    vertex_limits(formats, max_vertices)  # a bad format or limit costs nothing
    check_memory(mask_export_bytes(design.shape),
                 f"{source}: the masks of a {design.shape[0]} x {design.shape[1]} px design")
    if clear_aperture is not None and not MIN_APERTURE_PX * design.pitch_m <= clear_aperture <= DIE_SIZE_M:
        raise DoeError(f"clear aperture {clear_aperture * 1e3:g} mm: must lie between {MIN_APERTURE_PX} DOE pixels "
                       f"({MIN_APERTURE_PX * design.pitch_m * 1e3:g} mm) and the {DIE_SIZE_M * 1e3:g} mm die")
    levels, quantization = quantize_design(design, None, source)
    step = design.level_step_m()
    masks = levels_to_masks(levels, design.n_masks)
    pitch = design.pitch_m
    if corrected_masks is not None:
        masks, k = np.asarray(corrected_masks[0], dtype=bool), int(corrected_masks[1])
        if masks.shape != (design.n_masks, design.shape[0] * k, design.shape[1] * k):
            raise DoeError(f"{source}: corrected masks of shape {masks.shape} do not draw the {design.n_masks} masks "
                           f"of the {design.shape[0]} x {design.shape[1]} px design at {k} cells a pixel")
        pitch = design.pitch_m / k
    depths = list(design.etch_depths_m()) if depths_m is None else list(depths_m)
    layers = tuple(range(1, design.n_masks + 1)) if layers is None else layers
    aperture = clear_aperture if clear_aperture is not None else clear_aperture_m(design)
    if aperture is not None and aperture >= DIE_SIZE_M:
        log.warning("%s: clear aperture %.2f mm does not fit the die; no Cr aperture drawn", source, aperture * 1e3)
        aperture = None
    out = Path(out)
    # Cell names and labels in the GDS: printable text (a NUL would end a C string in the writer).
    name = "".join(c if c.isprintable() else "_" for c in design.name)
    # The file stem comes from the design's name: no separators or NULs, and short enough
    # that the longest suffix written still fits the file system's name limit.
    stem = safe_file_name(Path(name).name, "_plate.gds").removesuffix("_plate.gds")
    # The folder says INCOMPLETE until the GDS, the preview and the report are all written.
    with output_run(out, f"doe masks {source}"):
        report = export_masks(out / f"{stem}.gds", masks, pitch, layers=layers,
                              tone=tone, mirrored=mirrored, depths_m=depths, etch_order=etch_order, name=name,
                              clear_aperture_m=aperture, die_size_m=DIE_SIZE_M, formats=formats,
                              max_vertices=max_vertices)
        if plate:
            report["plate"] = export_plate(
                out / f"{stem}_plate.gds", PlateDesign(name, masks, pitch, aperture),
                formats=formats, max_vertices=max_vertices, layers=layers, tone=tone, mirrored=mirrored,
                depths_m=depths, etch_order=etch_order, die_size_m=DIE_SIZE_M)
        report["design"] = source
        report["level_step_nm"] = step * 1e9
        report["n_levels"] = design.n_levels
        report["quantization"] = None if quantization is None else quantization.summary()
        preview(levels, masks, out / "masks.png", name)
        if print_check is not None:
            from .print_check import print_check_page

            write_json(out / "print_check.json", print_check)
            with atomic_path(out / "print_check.md") as tmp:
                tmp.write_text(print_check_page(print_check, source))
            report["print_check"] = {"file": "print_check.json", "page": "print_check.md",
                                     "gap_um": print_check["gap_um"], "field_overlap": print_check["field_overlap"]}
            if "uncorrected" in print_check:
                report["print_check"]["field_overlap_uncorrected"] = print_check["uncorrected"]["field_overlap"]
        if corrected_masks is not None:
            report["opc_mask_grid_um"] = pitch * 1e6
        write_json(out / "report.json", report)
    return report
