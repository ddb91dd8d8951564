"""Measured PSF stacks: from separated views to calibrated, comparable, exportable PSFs.

Pipeline per narrowband capture (one wavelength): background subtraction, centring on the
uncoded view's peak (or a given axis), normalization, cropping to the sensor window around the
axis; then extrapolation to wavelengths the source cannot reach, comparison with predicted
PSFs, and export for reconstruction networks and the diagnosis stage.

Energy bookkeeping (default ``normalization="uncoded"``): both views of a wavelength are divided
by the uncoded view's total over the whole background-subtracted frame, before cropping. Both
halves of the aperture pass the same light, so the numbers are directly the engine's quantity
(fraction of the light through a view's half-aperture per pixel): the uncoded window sum is the
share the window holds, the coded window sum is the coded efficiency relative to the uncoded
half, and light leaving the window is not hidden by renormalizing after the crop.

Arrays are row-major, row 0 at the top; a stack's axis sits at ``axis_pixel`` (row, col).
The steps live in three modules, re-exported here so ``psfstack.NAME`` keeps working:
:mod:`.stack` (the container and its files), :mod:`.capture` (per-capture calibration) and
:mod:`.orders` (orders, extrapolation, comparison).
"""

from .capture import build_stack, calibrate_capture, centroid, crop_to_window, estimate_background, find_peak
from .orders import compare_stacks, extrapolate_orders, locate_orders, order_energies
from .stack import (BACKGROUNDS, NORMALIZATIONS, PSFStack, VIEWS, WAVELENGTH_TOLERANCE_M, as_stack,
                    band_centroid_fwhm, check_wavelengths, load_stack, network_array, read_stack, save_network_npy,
                    save_stack)

__all__ = ["BACKGROUNDS", "NORMALIZATIONS", "PSFStack", "VIEWS", "WAVELENGTH_TOLERANCE_M", "as_stack",
           "band_centroid_fwhm", "build_stack", "calibrate_capture", "centroid", "check_wavelengths",
           "compare_stacks", "crop_to_window", "estimate_background", "extrapolate_orders", "find_peak",
           "load_stack", "locate_orders", "network_array", "order_energies", "read_stack",
           "save_network_npy", "save_stack"]
