"""The ideal DOE and its optics: materials, the design file, the camera, PSFs, targets,
optimization and evaluation, plus the ``doe`` command-line program."""

__version__ = "0.1.0"

__all__ = ["__version__"]
