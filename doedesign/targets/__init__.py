"""Target PSFs: what the sensor window should see, per depth and wavelength.

A :class:`~doedesign.targets.base.Target` holds the wanted intensity shaped (depths, wavelengths, rows, cols) on the
camera's sensor window (row 0 at the top, column 0 at the left, the optical axis at
``axis_pixel``). Each (depth, wavelength) plane is the fraction of the light through the coded
half-aperture wanted in each pixel, so its sum is the energy wanted in the window (at most 1).
Targets are plain objects: build them with the functions below, add them (``a + b`` or
:func:`~doedesign.targets.base.combine`) and reweight them (:meth:`Target.with_weights <doedesign.targets.base.Target.with_weights>`) in a script or notebook.

Built-in targets (positions are (row, col) offsets from the axis pixel unless stated):

- :func:`~doedesign.targets.builtin.bayer`: the colour-sorting PSF of the seed supplement, Eq. (1): red on (0, 0),
  green on (+1, 0), blue on (+1, +1) -- pixels (256, 256), (257, 256), (257, 257) of the
  512 x 512 window -- at optical infinity; ``rggb=True`` puts half the green on (0, +1) too.
- :func:`~doedesign.targets.builtin.hdr_streak`: streaks through the axis ("+" cross of 2-px arms, or one direction),
  with a peak penalty for the loss.
- :func:`~doedesign.targets.builtin.hyperspectral`: diffraction orders along the axis row, positions from the grating
  equation ``sin(theta) = m lambda / period`` and ``x = z tan(theta)``.
- :func:`~doedesign.targets.builtin.depth_ring`: a ring whose radius follows a schedule of depth (seed: 25 - 5 d px).
- :func:`~doedesign.targets.builtin.spots`: spots with given window positions and weights.
- :func:`~doedesign.targets.builtin.image`: any user image (PNG/TIFF or ``.npy``) as the intensity.

TOML schema (``doe design TARGET.toml``)
----------------------------------------
One ``[target]`` table, or several ``[[target]]`` tables whose targets are added::

    [[target]]
    kind = "bayer"                     # bayer | hdr-streak | hyperspectral | depth | spots | image
    wavelengths_nm = [656, 589, 486]   # optional, kind-specific default
    energy = 1.0                       # energy wanted in the window per wavelength and depth
    rggb = false                       # bayer only
    weight = 1.0                       # scale of this target's loss weight when combined

    [[target]]
    kind = "spots"
    positions_px = [[256, 300], [300, 256]]   # absolute (row, col) window pixels
    weights = [1.0, 2.0]
    depths_m = ["inf"]                        # numbers in metres, or "inf"

Other keys per kind: hdr-streak ``arms`` ("+", "h" or "v"), ``arm_width_px``,
``arm_length_px``, ``peak_penalty``; hyperspectral ``period_m``, ``orders``,
``order_weights``, ``spot_px``, ``wavelengths_nm`` (default 400-700 nm, 31 bands);
depth ``depths_m`` and ``radii_px`` (default 1..5 m, 25 - 5 d px), ``ring_width_px``;
image ``path`` (relative to the TOML file), ``wavelengths_nm``, ``depths_m``.
The camera (window shape, axis pixel, sensor distance) comes from the run configuration.

The package holds three rooms: :mod:`.base` (the :class:`~doedesign.targets.base.Target` container and
:func:`~doedesign.targets.base.combine`), :mod:`.builtin` (the built-in targets and each kind's optimizer defaults) and
:mod:`.files` (targets by name and from TOML).
"""

from .base import Target, combine
from .builtin import (DEFAULT_INIT, DEFAULT_LOSS, DEFAULT_OBJECTIVE, HYPERSPECTRAL_WAVELENGTHS_M, KINDS,
                      RGB_WAVELENGTHS_M, SEED_GRATING_PERIOD_M, bayer, depth_ring, grating_order_offset_px,
                      hdr_streak, hyperspectral, image, seed_ring_radius_px, spots)
from .files import build, from_dict, load_toml

__all__ = ["DEFAULT_INIT", "DEFAULT_LOSS", "DEFAULT_OBJECTIVE", "HYPERSPECTRAL_WAVELENGTHS_M", "KINDS",
           "RGB_WAVELENGTHS_M", "SEED_GRATING_PERIOD_M", "Target", "bayer", "build", "combine", "depth_ring",
           "from_dict", "grating_order_offset_px", "hdr_streak", "hyperspectral", "image", "load_toml",
           "seed_ring_radius_px", "spots"]
