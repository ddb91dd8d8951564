"""PSF calibration of the dual-pixel camera: raw frames to coded and uncoded views
(crosstalk, demosaicking, white balance) and measured PSF stacks (background, centring,
normalization, extrapolation below 440 nm, export for a reconstruction network).
"""
