"""PSF calibration of the dual-pixel camera: raw frames to coded and uncoded views
(crosstalk, demosaicking, white balance) and measured PSF stacks (background, centring,
normalization, extrapolation below 440 nm, export for a reconstruction network).

:mod:`.dualpixel` turns raw frames into views; :mod:`.psfstack` gathers the stack steps, which
live in :mod:`.stack` (container and files), :mod:`.capture` (per capture) and :mod:`.orders`.
"""

__all__: list[str] = []
