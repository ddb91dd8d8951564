"""What a map's models ask of the fab (``doe correct --map``): aligner settings, mask scale, warnings.

Per mask (relative to mask 0, x right, y up, counter-clockwise): the aligner offset and rotation to
dial in (the negative of the named translation and rotation); a named magnification as the scale
the mask must be redrawn at (``1 - M``: a contact aligner cannot change it; the mask writer can);
an orthogonality error as a warning (no knob); a named radial depth term as a warning with its
centre-to-edge size (the etch tool's uniformity, no mask can take it out). Terms not named are left.
"""

from __future__ import annotations

import json
from pathlib import Path

from doedesign.errors import DoeError

__all__ = ["map_corrections", "read_map_report"]


def read_map_report(path: str | Path) -> dict:
    """A ``doe map`` report.json; a one-line error when it is not one."""
    from doedesign.fileio import check_input_file

    path = check_input_file(path, DoeError)
    try:
        report = json.loads(Path(path).read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise DoeError(f"{path}: not a doe map report ({exc})") from None
    if not isinstance(report, dict) or "models" not in report or "n_tiles" not in report:
        raise DoeError(f"{path}: not a doe map report (no models or n_tiles)")
    return report


def map_corrections(report: dict) -> dict:
    """Aligner settings, mask scale corrections and warnings from a map report's models."""
    models = report.get("models", {})
    masks, warnings = [], []
    for j in (1, 2, 3):
        fit = models.get(f"overlay_mask{j}")
        if fit is None:
            continue
        t = fit["terms"]
        named = lambda k: t[k]["named"]  # noqa: E731
        entry = {"mask": j,
                 "aligner_offset_m": [-t["translation_x_m"]["value"] if named("translation_x_m") else 0.0,
                                      -t["translation_y_m"]["value"] if named("translation_y_m") else 0.0],
                 "aligner_rotation_rad": -t["rotation_urad"]["value"] * 1e-6 if named("rotation_urad") else 0.0,
                 "mask_scale": 1.0 - t["magnification_ppm"]["value"] * 1e-6 if named("magnification_ppm") else 1.0}
        if named("magnification_ppm"):
            warnings.append(f"mask {j}: printed {t['magnification_ppm']['value']:.2f} +- "
                            f"{t['magnification_ppm']['error']:.2f} ppm large against mask 0; the aligner cannot "
                            f"change it: redraw the mask at scale {entry['mask_scale']:.8f} (or match the mask "
                            "and wafer temperatures)")
        if named("orthogonality_urad"):
            warnings.append(f"mask {j}: orthogonality error {t['orthogonality_urad']['value']:.2f} urad "
                            "(no aligner knob; the mask writer's axes)")
        masks.append(entry)
    depth = models.get("depth_all", {}).get("terms", {})
    radial = depth.get("radial_centre_to_edge")
    if radial and radial["named"]:
        warnings.append(f"etch depth {radial['value'] * 100:+.2f} +- {radial['error'] * 100:.2f} % from the centre "
                        "to the edge of the element (radial non-uniformity of the etch; no mask takes it out)")
    return {"masks": masks, "warnings": warnings}
