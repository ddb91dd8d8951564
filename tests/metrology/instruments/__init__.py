"""The tests' own profilometer simulators, three instruments written apart from each other.

Each module turns a wafer surface on the super-fine grid of ``filegen.wafer_surface`` into the
camera image a profilometer would write, by different physics:

- :mod:`instruments.point`: Gaussian blur, then point samples at the camera pixels' centres.
- :mod:`instruments.boxcar`: Gaussian blur, then the mean over each pixel's whole footprint.
- :mod:`instruments.csi`: a coherence-scanning interferometer (circular-pupil OTF, camera fill
  factor, batwing, dropouts at steep edges).

All expose ``measure(surface_m, fine, design_shape, out_shape, rng, **overrides) ->
(height_m, inst)``. None imports the model code (``masks``, ``metrology``); the modules share
no instrument code with each other, so each is a separate check of the diagnosis.
"""
