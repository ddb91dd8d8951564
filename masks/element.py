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

from doedesign.design import Design
from doedesign.fileio import output_run, save_figure, write_json
from doedesign.levels import N_LEVELS, quantize_design

from .decompose import binary_depths_m, levels_to_masks
from .gds import export_masks

__all__ = ["DIE_SIZE_M", "clear_aperture_m", "preview", "write_element"]

log = logging.getLogger(__name__)

#: Side of the square die (m).
DIE_SIZE_M = 10e-3


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


def preview(levels: np.ndarray, masks: np.ndarray, path: str | Path, title: str) -> None:
    """Figure of the level map and every mask (row 0 at the top, white = open/etched)."""
    import matplotlib.pyplot as plt

    n = masks.shape[0]
    fig, axes = plt.subplots(1, n + 1, figsize=(3 * (n + 1), 3.2))
    im = axes[0].imshow(levels, cmap="viridis", interpolation="nearest", vmin=0, vmax=2 ** n - 1)
    axes[0].set_title(f"{title}: levels")
    fig.colorbar(im, ax=axes[0], fraction=0.046)
    for j in range(n):
        axes[j + 1].imshow(masks[j], cmap="gray", interpolation="nearest", vmin=0, vmax=1)
        axes[j + 1].set_title(f"mask {j + 1} (bit {j}, open = white)")
    for ax in axes:
        ax.set_xticks([])
        ax.set_yticks([])
    save_figure(fig, path)


def write_element(design: Design, out: str | Path, *, source: str | None = None, tone: str = "dark",
                  mirrored: bool = False, depths_m: Sequence[float] | None = None,
                  layers: Sequence[int] = (1, 2, 3, 4), etch_order: Sequence[int] | None = None,
                  clear_aperture: float | None = None, oasis: bool = False) -> dict:
    """Write ``OUT/<name>.gds`` (read back and verified), ``OUT/masks.png`` and ``OUT/report.json``.

    Parameters
    ----------
    design : Design
        Its levels, or its heights quantized by :func:`doedesign.levels.quantize_design`.
    out : path
        Output directory.
    source : str, optional
        The design's file name (reports and messages).
    tone, mirrored, layers, etch_order, oasis
        See :func:`masks.gds.export_masks`.
    depths_m : sequence of float, optional
        Etch depth per mask (default ``2**j`` level steps).
    clear_aperture : float, optional
        Cr clear circle diameter (m); default :func:`clear_aperture_m`. None is drawn when it
        does not fit the die.

    Returns
    -------
    dict
        The report written to ``report.json``.
    """
    source = source or design.name
    levels, quantization = quantize_design(design, N_LEVELS, source)
    step = design.level_step_m(N_LEVELS)
    masks = levels_to_masks(levels, 4)
    depths = binary_depths_m(step, 4) if depths_m is None else list(depths_m)
    aperture = clear_aperture if clear_aperture is not None else clear_aperture_m(design)
    if aperture is not None and aperture >= DIE_SIZE_M:
        log.warning("%s: clear aperture %.2f mm does not fit the die; no Cr aperture drawn", source, aperture * 1e3)
        aperture = None
    out = Path(out)
    name = design.name
    # The folder says INCOMPLETE until the GDS, the preview and the report are all written.
    with output_run(out, f"doe masks {source}"):
        report = export_masks(out / f"{Path(name).name or 'design'}.gds", masks, design.pitch_m, layers=layers,
                              tone=tone, mirrored=mirrored, depths_m=depths, etch_order=etch_order, name=name,
                              clear_aperture_m=aperture, die_size_m=DIE_SIZE_M, oasis=oasis)
        report["design"] = source
        report["level_step_nm"] = step * 1e9
        report["quantization"] = None if quantization is None else quantization.summary()
        preview(levels, masks, out / "masks.png", name)
        write_json(out / "report.json", report)
    return report
