"""3-D rendering of a measured surface with pyvista, off screen.

Rendering needs an OpenGL context; on a headless machine without one (no display, no
OSMesa/EGL) it fails, and the caller gets the reason instead of an exception, so a
comparison report never dies on a picture.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from doedesign.fileio import atomic_path

__all__ = ["render_surface"]

log = logging.getLogger(__name__)


def render_surface(height_m: np.ndarray, pixel_size_m: float, path: str | Path, z_exaggeration: float | None = None,
                   max_side: int = 250, title: str | None = None) -> str | None:
    """Render a height map as a shaded 3-D surface to a PNG.

    Parameters
    ----------
    height_m : ndarray
        Heights (m), NaN where invalid; row 0 at the top of the image (drawn at the far
        side, largest y), column 0 at the left.
    pixel_size_m : float
    path : str or Path
        PNG written atomically.
    z_exaggeration : float, optional
        Vertical scale; default makes the height range a tenth of the field width.
    max_side : int
        The map is decimated to at most this many samples per side.

    Returns
    -------
    str or None
        None on success, else why it failed (nothing is written then).
    """
    try:
        import pyvista as pv
    except ImportError as exc:  # pragma: no cover - pyvista is a declared dependency
        return f"pyvista unavailable: {exc}"
    h = np.asarray(height_m, float)
    step = max(1, int(np.ceil(max(h.shape) / max_side)))
    h = h[::step, ::step]
    finite = np.isfinite(h)
    if not finite.any():
        return "no valid pixels to render"
    z_um = np.where(finite, h, np.nanmedian(h)) * 1e6
    rows, cols = h.shape
    x = np.arange(cols) * pixel_size_m * step * 1e6
    # Row 0 is the top of the image: it goes to the largest y so the view matches the plots.
    y = (rows - 1 - np.arange(rows)) * pixel_size_m * step * 1e6
    span = max(np.ptp(z_um), 1e-6)
    if z_exaggeration is None:
        z_exaggeration = 0.1 * max(x[-1] if cols > 1 else 1.0, y[0] if rows > 1 else 1.0) / span
    xx, yy = np.meshgrid(x, y)
    pv.OFF_SCREEN = True
    try:
        grid = pv.StructuredGrid(xx, yy, z_um * z_exaggeration)
        grid["height_nm"] = (z_um * 1e3).ravel(order="F")
        plotter = pv.Plotter(off_screen=True, window_size=[720, 540])
        plotter.add_mesh(grid, scalars="height_nm", cmap="viridis", show_scalar_bar=True,
                         scalar_bar_args={"title": "height (nm)"})
        plotter.add_text(title or f"measured surface (z x{z_exaggeration:.0f})", font_size=10)
        plotter.view_isometric()  # type: ignore[call-arg]  # pyvista's decorator stub drops the bound self
        import matplotlib.pyplot as plt

        image = plotter.screenshot(return_img=True)
        assert image is not None  # return_img=True returns the image
        with atomic_path(path) as tmp:
            plt.imsave(tmp, image, format="png")
        plotter.close()
    except Exception as exc:  # noqa: BLE001 - any VTK/OpenGL failure must become a report line
        log.warning("3-D rendering failed: %s", exc)
        return f"3-D rendering failed: {type(exc).__name__}: {exc}"
    return None
