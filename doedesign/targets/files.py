"""Targets by name and from a TOML file (schema in :mod:`doedesign.targets`)."""

from __future__ import annotations

import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from ..camera import Camera
from ..errors import DoeError
from ..fileio import parse_toml
from .base import Target, _camera, combine
from .builtin import KINDS, bayer, depth_ring, hdr_streak, hyperspectral, image, spots

__all__ = ["build", "from_dict", "load_toml"]


def build(kind: str, camera: Camera | None = None, **options: Any) -> Target:
    """Build a built-in target by its name (see :data:`~doedesign.targets.builtin.KINDS`) with keyword options."""
    builders: dict[str, Callable[..., Target]] = {"bayer": bayer, "hdr-streak": hdr_streak, "hyperspectral": hyperspectral,
                "depth": depth_ring, "spots": spots, "image": image}
    if kind not in builders:
        raise DoeError(f"unknown target kind {kind!r}; choose from {', '.join(KINDS)}")
    if kind == "spots" and "positions_px" not in options:
        cam = _camera(camera)
        r0, c0 = cam.axis_pixel
        # A default 3 x 3 spot array 20 px apart around the axis, for quick trials.
        options["positions_px"] = [(r0 + 20 * i, c0 + 20 * j) for i in (-1, 0, 1) for j in (-1, 0, 1)]
    try:
        return builders[kind](camera=camera, **options)
    except TypeError as exc:
        raise DoeError(f"target {kind!r}: {exc}") from None


_TOML_KEYS = {
    "wavelengths_nm": ("wavelengths_m", lambda v: np.asarray(v, dtype=float) * 1e-9),
    "depths_m": ("depths_m", lambda v: [math.inf if str(x).lower() == "inf" else float(x) for x in v]),
}


def from_dict(spec: dict, camera: Camera | None = None, base_dir: str | Path = ".",
              source: str = "target") -> Target:
    """Build a (combined) target from a parsed TOML document (see the module docstring)."""
    tables = spec.get("target")
    if tables is None:
        raise DoeError(f"{source}: no [target] or [[target]] table")
    if isinstance(tables, dict):
        tables = [tables]
    if not tables:
        raise DoeError(f"{source}: the target list is empty")
    built = []
    for i, table in enumerate(tables):
        table = dict(table)
        kind = table.pop("kind", None)
        if kind is None:
            raise DoeError(f"{source}: target {i + 1} has no 'kind' (one of {', '.join(KINDS)})")
        weight = float(table.pop("weight", 1.0))
        options = {}
        for key, value in table.items():
            name, conv = _TOML_KEYS.get(key, (key, lambda v: v))
            options[name] = conv(value)
        if kind == "image" and "path" in options:
            options["source"] = Path(base_dir) / options.pop("path")
        try:
            target = build(kind, camera=camera, **options)
        except DoeError as exc:
            raise DoeError(f"{source}: target {i + 1}: {exc}") from None
        built.append(target.with_weights(wavelengths=np.full(target.wavelengths_m.size, weight)))
    return built[0] if len(built) == 1 else combine(*built)


def load_toml(path: str | Path, camera: Camera | None = None) -> Target:
    """Read a target TOML file (schema in the module docstring)."""
    path = Path(path)
    if not path.is_file():
        raise DoeError(f"{path}: no such target file")
    try:
        text = path.read_text()
    except UnicodeDecodeError as exc:
        raise DoeError(f"{path}: not valid TOML: {exc}") from None
    spec = parse_toml(text, str(path))
    return from_dict(spec, camera=camera, base_dir=path.parent, source=str(path))
