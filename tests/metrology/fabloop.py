"""The fab loop on files: a hidden process makes wafers of one design with the independent
generator (:mod:`filegen`), ``doe diagnose`` reads their fields, ``doe correct`` writes the
job sheet, and the same hidden process makes the next wafer with the job sheet applied.

Only files pass between the steps (profilometer ``.datx``, diagnosis folders, ``job.json``).
The fab's side of the loop lives here, written apart from the model code like the generator:
the hidden process is a :mod:`filegen` truth, and the job sheet changes what the fab draws and
sets (:func:`apply_job_sheet`): the drawn edges move by ``drawn_edge_offset_um`` (the printed
opening is the drawn one grown by the process bias, so the biases add: the generator's
coverage is a Chebyshev distance, which is what an edge offset of Manhattan polygons is), the
aligner adds its dials to the hidden overlay and rotation, and the etch aimed at the target
removes ``(1 + hidden error) target``. Etch loading is physics the fab cannot switch off: the
next wafer carries the same loading (the generator's own rule, the depth of mask j falling as
``1 - L rho_j`` with ``rho_j`` the local open fraction of the printed mask, a 50 um Gaussian);
only its mean loss can be aimed at through the target.
"""

from __future__ import annotations

import contextlib
import copy
import io
import json
from pathlib import Path

import numpy as np

import filegen

# The hidden systematic process of wafer 1: overlay on two masks, one mask rotated, a bias on
# every mask, one deep etch, etch loading (issue 27).
SYSTEMATIC = {
    "mask_overlay": {"mask": [1, 3], "shift_m": [[0.40e-6, -0.25e-6], [-0.30e-6, 0.35e-6]]},
    "mask_rotation": {"mask": [2], "angle_deg": [0.03]},
    "linewidth_bias": {"bias_m": [0.25e-6, 0.25e-6, 0.25e-6, 0.25e-6]},
    "etch_depth": {"error": [0.0, 0.0, 0.0, 0.05]},
    "etch_loading": {"loading": 0.08},
}
# Field-to-field spread (standard deviations) drawn afresh on every field.
SPREAD = {"overlay_m": 0.02e-6, "rotation_deg": 0.001, "bias_m": 0.008e-6, "depth": 0.002, "loading": 0.004}
# The candidates the fields are diagnosed with: the hidden ones and the generator's instrument needs no
# artefact beyond the blur every camera-frame fit holds (a shorter list is a faster diagnosis).
EFFECTS = "etch_depth,mask_overlay,linewidth_bias,mask_rotation,etch_loading"


def design_metadata():
    """A camera for the generator's small design: a square pupil filling it, focused at infinity,
    the whole element coded (its figure of merit is the light on the ideal PSF's brightest pixels)."""
    from doedesign.camera import Camera

    cam = Camera(aperture_diameter_m=None, focus_distance_m=np.inf, window_shape=(256, 256), axis_pixel=(128, 128),
                 doe_side="full")
    return {"camera": cam.to_dict()}


def field_truth(systematic, rng, spread=SPREAD):
    """One field's process: the systematic one plus this field's random departures (on every
    mask, for each effect the systematic process has)."""
    t = copy.deepcopy(systematic)
    if "mask_overlay" in t:
        full = np.zeros((4, 2))
        full[list(t["mask_overlay"]["mask"])] = np.array(t["mask_overlay"]["shift_m"], float).reshape(-1, 2)
        full[1:] += rng.normal(0, spread["overlay_m"], (3, 2))
        t["mask_overlay"] = {"mask": [1, 2, 3], "shift_m": full[1:]}
    if "mask_rotation" in t:
        angles = np.zeros(4)
        angles[list(t["mask_rotation"]["mask"])] = t["mask_rotation"]["angle_deg"]
        angles[1:] += rng.normal(0, spread["rotation_deg"], 3)
        t["mask_rotation"] = {"mask": [1, 2, 3], "angle_deg": angles[1:]}
    if "linewidth_bias" in t:
        t["linewidth_bias"] = {"bias_m": np.array(t["linewidth_bias"]["bias_m"], float)
                               + rng.normal(0, spread["bias_m"], 4)}
    if "etch_depth" in t:
        t["etch_depth"] = {"error": np.array(t["etch_depth"]["error"], float) + rng.normal(0, spread["depth"], 4)}
    if "etch_loading" in t:
        t["etch_loading"] = {"loading": float(t["etch_loading"]["loading"] + rng.normal(0, spread["loading"]))}
    return t


def apply_job_sheet(systematic, job):
    """The hidden process of the next wafer when the fab follows ``job`` (a job.json dict); its
    etch loading, if any, unchanged."""
    t = copy.deepcopy(systematic)
    shift, angles = np.zeros((4, 2)), np.zeros(4)
    if "mask_overlay" in t:
        shift[list(t["mask_overlay"]["mask"])] = np.array(t["mask_overlay"]["shift_m"], float).reshape(-1, 2)
    if "mask_rotation" in t:
        angles[list(t["mask_rotation"]["mask"])] = t["mask_rotation"]["angle_deg"]
    bias = np.array(t.get("linewidth_bias", {}).get("bias_m", np.zeros(4)), float)
    err = np.array(t.get("etch_depth", {}).get("error", np.zeros(4)), float)
    for m in job["masks"]:
        j = m["mask"]
        shift[j] += np.array(m["align_offset_um"]) * 1e-6
        angles[j] += m["align_rotation_deg"]
        bias[j] += m["drawn_edge_offset_um"] * 1e-6
        err[j] = (1 + err[j]) * m["etch_depth_target_nm"] / m["etch_depth_nm"] - 1
    if shift.any() or "mask_overlay" in t:
        t["mask_overlay"] = {"mask": [1, 2, 3], "shift_m": shift[1:]}
    if angles.any() or "mask_rotation" in t:
        t["mask_rotation"] = {"mask": [1, 2, 3], "angle_deg": angles[1:]}
    t["linewidth_bias"] = {"bias_m": bias}
    t["etch_depth"] = {"error": err}
    return t


def make_wafer(folder, levels, systematic, n_fields, seed, design_px, field_px, metadata=None, fine=80):
    """``n_fields`` measured fields of one wafer: ``folder/field<k>/measured.datx`` (and the
    design, once, as ``folder/design.npz``); returns the design path and the field paths."""
    folder = Path(folder)
    rng = np.random.default_rng(seed)
    paths = []
    design = None
    for k in range(n_fields):
        truth = field_truth(systematic, rng)
        case = filegen.make_case([], seed * 100 + k, design_px=design_px, field_px=field_px, truth=truth,
                                 levels=levels, fine=fine)
        d, m = case.write(folder / f"field{k}", metadata=metadata, design=False)
        paths.append(m)
        if design is None:
            design = folder / "design.npz"
            case.write(folder, metadata=metadata)
            (folder / "measured.datx").unlink()
    return design, paths


def diagnose(main, design, measured, out, window_px=72, effects=EFFECTS):
    """``doe diagnose --frame camera`` of one field (its printed summary kept quiet); its report."""
    with contextlib.redirect_stdout(io.StringIO()):
        code = main(["diagnose", "--design", str(design), "--measured", str(measured), "--frame", "camera",
                     "--window-px", str(window_px), "--effects", effects, "--out", str(out)])
    assert code == 0
    return json.loads((Path(out) / "report.json").read_text())


def named_params(report):
    """Fabrication effect -> {param: (value, uncertainty)} of a diagnosis report."""
    return {s["effect"]: {k: (v, s["uncertainties"][k]) for k, v in s["params"].items()}
            for s in report["steps"] if not s["measurement_artefact"]}
