"""The PSF engine: the split-aperture camera's pixel-integrated PSF of a height map, and the
gradient of a loss on it.

Public:

- :class:`~doedesign.engine.psf.PSFEngine` (``.psf``, ``.value_and_grad``, ``.value_and_grad_free`` for a design loop's
  free heights) and :func:`~doedesign.engine.psf.compute_psf` (one call);
- :class:`~doedesign.engine.result.PSFResult`, the PSF file (``.save`` / ``.load``), :data:`~doedesign.engine.result.VIEWS`;
- :func:`~doedesign.engine.result.parse_wavelengths_nm`, the CLI's wavelength lists.

Inside: ``psf`` (the engine), ``lags`` (pupil autocorrelation lags and the pixel kernels),
``reads`` (reading a few pixels and their adjoint), ``result`` (the result and its file),
``backend`` (NumPy, CuPy or array_api_strict arrays and their FFTs), ``threaded_fft`` (CPU FFTs
split over threads that end with the call).
"""

from .psf import MAX_WAVELENGTHS, VIEWS, PSFEngine, PSFResult, compute_psf, parse_wavelengths_nm

__all__ = ["MAX_WAVELENGTHS", "VIEWS", "PSFEngine", "PSFResult", "compute_psf", "parse_wavelengths_nm"]
