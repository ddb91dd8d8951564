"""Errors a user can cause, reported by the CLI as one clear line (no traceback)."""

__all__ = ["DesignFileError", "DoeError", "MaterialError", "SamplingError"]


class DoeError(Exception):
    """Base class of every user-facing error of the tool (bad file, bad input, bad option)."""


class DesignFileError(DoeError):
    """A design file is missing, foreign or broken; the message names the file and the field."""


class SamplingError(DoeError):
    """A propagation configuration would alias; the message gives the numbers."""


class MaterialError(DoeError):
    """Unknown material, or a wavelength outside its valid range."""
