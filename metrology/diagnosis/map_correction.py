"""What a map's models ask of the fab (``doe correct --map``): aligner settings, mask scale, warnings.

Per mask (relative to mask 0, x right, y up, counter-clockwise): the aligner offset and rotation to
dial in (the negative of the named translation and rotation); a named magnification as the scale
the mask must be redrawn at (``1 - M``: a contact aligner cannot change it; the mask writer can);
an orthogonality error as a warning (no knob); a named radial depth term as a warning with its
centre-to-edge size (the etch tool's uniformity, no mask can take it out). Terms not named are left.

:func:`apply_to_jobs` puts them into ``doe correct``'s job sheet: where the map names a mask's
translation or rotation, its whole-element fit sets that mask's aligner dial (a few diagnosed
windows measure the same overlay less well and cannot see a rotation about the element's centre
apart from a translation); the fields' own dial is kept beside it.
"""

from __future__ import annotations

import json
import math
import re
from pathlib import Path

from doedesign.errors import DoeError

__all__ = ["apply_to_jobs", "map_corrections", "read_map_report"]


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
    overlay = sorted(int(m.group(1)) for k in models if (m := re.fullmatch(r"overlay_mask(\d+)", k)))
    for j in overlay:
        fit = models[f"overlay_mask{j}"]
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


def apply_to_jobs(jobs: list[dict], from_map: dict, source: str) -> list[str]:
    """Set the aligner dials of ``doe correct``'s per-mask ``jobs`` from a map's named terms.

    Parameters
    ----------
    jobs : list of dict
        :func:`metrology.correction.jobsheet.job_entries` (changed in place: ``align_offset_um``,
        ``align_rotation_deg`` where the map names them, ``mask_scale``, ``align_source``,
        the fields' dials as ``align_offset_um_fields`` / ``align_rotation_deg_fields``).
    from_map : dict
        :func:`map_corrections` of the map report.
    source : str
        The map report's file name (the sheet's notes).

    Returns
    -------
    list of str
        One line per mask whose dial the map set, for the job sheet's warnings.
    """
    by_mask = {m["mask"]: m for m in from_map["masks"]}
    notes = []
    for job in jobs:
        job.setdefault("mask_scale", 1.0)
        job.setdefault("align_source", "fields")
        entry = by_mask.get(job["mask"])
        if entry is None:
            continue
        offset_um = [v * 1e6 for v in entry["aligner_offset_m"]]
        rotation_deg = math.degrees(entry["aligner_rotation_rad"])
        job["mask_scale"] = entry["mask_scale"]
        if not any(offset_um) and not rotation_deg:
            continue
        job["align_offset_um_fields"] = job["align_offset_um"]
        job["align_rotation_deg_fields"] = job["align_rotation_deg"]
        job["align_offset_um"] = [offset_um[c] if offset_um[c] else job["align_offset_um"][c] for c in range(2)]
        if rotation_deg:
            job["align_rotation_deg"] = rotation_deg
        job["align_source"] = "map"
        done = (f"aligner {job['align_offset_um'][0]:+.3f},{job['align_offset_um'][1]:+.3f} um "
                f"{job['align_rotation_deg']:+.5f} deg from the map {source}")
        job["corrections"] = [c for c in job["corrections"] if not c.startswith(("aligner", "none:"))] + [done]
        notes.append(f"mask {job['mask']}: {done} (the diagnosed fields gave "
                     f"{job['align_offset_um_fields'][0]:+.3f},{job['align_offset_um_fields'][1]:+.3f} um "
                     f"{job['align_rotation_deg_fields']:+.5f} deg; the predicted merit uses the fields')")
    return notes
