"""What surrounds a design inside the lens aperture: one stated convention.

A design is usually smaller than the camera's clear aperture (a 1 mm element in an 8.64 mm
lens). The PSF engine needs to know what the light meets in the rest of the DOE's
half-aperture, and that choice changes the answer (an all-closed ``aperture`` on a small
design still passes most of the light when the rest is open glass):

``open`` (default, the behaviour before the choice was named)
    Unetched glass: the rest of the half-aperture passes light with no phase.
``opaque``
    Chrome: only the design's own clear region passes light.
``repeat``
    The design (its heights and its ``aperture``) tiled across the half-aperture, the
    central tile where the design sits.

The convention comes from the ``--surround`` option where a command has one, else from the
design file's metadata field ``surround``, else ``open``. It is written into every PSF file
and shown by ``doe inspect``.
"""

from __future__ import annotations

from collections.abc import Mapping

from .errors import DoeError

__all__ = ["DEFAULT_SURROUND", "SURROUNDS", "check_surround", "describe_surround", "resolve_surround"]

SURROUNDS = ("open", "opaque", "repeat")
DEFAULT_SURROUND = "open"
_TEXT = {"open": "open glass (unetched, no phase) around the design inside the lens aperture",
         "opaque": "opaque (chrome) around the design: only its own clear region passes light",
         "repeat": "the design repeated (heights and aperture tiled) across the lens aperture"}


def check_surround(value: object, where: str = "surround") -> str:
    """``value`` if it names a convention, else a one-line :class:`~doedesign.errors.DoeError`."""
    if not isinstance(value, str) or value not in SURROUNDS:
        raise DoeError(f"{where}: {value!r} is not a surround convention; use one of {', '.join(SURROUNDS)}")
    return value


def resolve_surround(option: str | None, metadata: Mapping | None = None, source: str = "design") -> tuple[str, str]:
    """The convention and where it came from (``"option"``, ``"design file"`` or ``"default"``)."""
    if option is not None:
        return check_surround(option, "--surround"), "option"
    if metadata and "surround" in metadata:
        return check_surround(metadata["surround"], f"{source}: metadata surround"), "design file"
    return DEFAULT_SURROUND, "default"


def describe_surround(value: str) -> str:
    """One sentence for reports and ``doe inspect``."""
    return _TEXT[check_surround(value)]
