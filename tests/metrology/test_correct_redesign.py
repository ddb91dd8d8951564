"""`doe correct --redesign`: the design loop with the fitted process as its nominal process.

The element is a 16-level blazed grating (period 16 px) whose first order is the target of a
one-wavelength hyperspectral design, so the damage of an etch-depth error and what a level
remapping gives back follow from the grating's phase errors: the first-order amplitude is the
mean of ``exp(i phi_k)`` over the 16 levels' phase errors ``phi_k`` (equal widths), its
efficiency that amplitude squared times the ideal staircase's.
"""

import json
import math

import numpy as np
import pytest

from doedesign import targets
from doedesign.camera import Camera
from doedesign.cli import main
from doedesign.design import Design
from doedesign.levels import level_step_m
from doedesign.targets.builtin import grating_order_offset_px
from metrology.correction.diagnoses import design_fingerprint
from metrology.correction.redesign import remap_levels

PITCH = 5.4e-6
STEP = level_step_m("fused_silica", 550e-9, 16)
DEPTHS = [STEP * 2 ** j for j in range(4)]
N, WINDOW, ORDER_PX = 48, 24, 6


def _blaze(tmp_path, with_target=True):
    """A blazed grating, its first order ORDER_PX pixels off the axis; without its target the merit
    is the light on the pixels holding 90 % of its ideal PSF."""
    probe = Camera(aperture_diameter_m=N * PITCH, focus_distance_m=math.inf, sensor_distance_m=1e-3,
                   window_shape=(WINDOW, WINDOW), axis_pixel=(WINDOW // 2, WINDOW // 2))
    distance = 1e-3 * ORDER_PX / grating_order_offset_px(550e-9, 16 * PITCH, 1, probe)
    cam = Camera(aperture_diameter_m=N * PITCH, focus_distance_m=math.inf, sensor_distance_m=distance,
                 window_shape=(WINDOW, WINDOW), axis_pixel=(WINDOW // 2, WINDOW // 2))
    levels = np.broadcast_to(15 - np.arange(N) % 16, (N, N)).astype(np.int16)
    meta = {"camera": cam.to_dict(), "name": "blaze"}
    if with_target:
        meta["target"] = targets.hyperspectral(cam, wavelengths_m=[550e-9], period_m=16 * PITCH).summary()
    design = Design(height_m=-levels * STEP, pitch_m=PITCH, levels=levels, metadata=meta)
    path = tmp_path / "blaze.npz"
    design.save(path)
    return design, path


def _fields(tmp_path, design, path, depth_error_mask3, bias_m=0.0):
    """Three diagnosed fields: mask 3 etched ``depth_error_mask3`` too deep, +-0.2 % between fields;
    with ``bias_m``, that linewidth bias on every mask (+-10 nm between fields)."""
    args = []
    for i, e in enumerate((depth_error_mask3 - 0.002, depth_error_mask3, depth_error_mask3 + 0.002)):
        folder = tmp_path / f"field{i}"
        folder.mkdir()
        steps = [{"effect": "etch_depth", "kind": "fabrication",
                  "params": {f"depth_error_mask{j}": e if j == 3 else 0.0 for j in range(4)},
                  "uncertainties": {f"depth_error_mask{j}": 5e-4 for j in range(4)}}]
        if bias_m:
            steps.append({"effect": "linewidth_bias", "kind": "fabrication",
                          "params": {f"bias_mask{j}_m": bias_m + (i - 1) * 10e-9 for j in range(4)},
                          "uncertainties": {f"bias_mask{j}_m": 5e-9 for j in range(4)}})
        report = {"domain": "height", "steps": steps, "unexplained": False, "noise_floor": 1e-9,
                  "measurement_artefacts": [], "inputs": {"nominal_depths_m": DEPTHS, **design_fingerprint(design, path)}}
        (folder / "report.json").write_text(json.dumps(report))
        args += ["--diagnosis", str(folder)]
    return args


def _correct(tmp_path, depth_error, with_target=True, extra=(), bias_m=0.0):
    design, path = _blaze(tmp_path, with_target)
    out = tmp_path / "out"
    code = main(["correct", "--design", str(path), *_fields(tmp_path, design, path, depth_error, bias_m), "--out", str(out),
                 "--samples", "4", "--redesign", "--redesign-iterations", "12", *extra])
    assert code == 0
    return json.loads((out / "job.json").read_text()), out


def _first_order_factor(phase_errors_rad):
    """First-order efficiency against the ideal staircase: |mean exp(i phi_k)|^2."""
    return abs(np.mean(np.exp(1j * np.asarray(phase_errors_rad)))) ** 2


def test_remap_sends_each_level_to_the_nearest_phase_as_etched():
    # Mask 3 etched 15 % deep: levels 8..15 are 1.2 steps too deep. Wanted 8 steps: level 7 (1 step
    # short) beats level 8 (1.2 deep); wanted 9..15: the level below, 0.2 steps deep.
    actual = np.array([(k & 7) + (k >> 3) * 8 * 1.15 for k in range(16)]) * STEP
    mapped, table = remap_levels(np.arange(16), actual, STEP, 16)
    assert table == [0, 1, 2, 3, 4, 5, 6, 7, 7, 8, 9, 10, 11, 12, 13, 14]
    assert mapped.tolist() == table
    # Wrapping: every level one step deep; wanted 0 is level 15, 16 steps = one 2 pi height deep.
    _, table = remap_levels(np.arange(16), (np.arange(16) + 1.0) * STEP, STEP, 16)
    assert table == [15] + list(range(15))
    ideal = np.arange(16) * STEP
    assert remap_levels(np.arange(16), ideal, STEP, 16)[1] == list(range(16))


def test_redesign_takes_back_a_deep_etch_the_fab_keeps(tmp_path):
    """Mask 3 etched 15 % deep, the etch not adjusted: the measured wafer loses the grating's
    first order as the phase errors say, and the re-design, made with the same process, wins
    most of it back (its remap alone: the factor of the phase errors left)."""
    sheet, out = _correct(tmp_path, 0.15)
    merit = sheet["merit"]
    p = merit["primary_metric"]
    assert p == "first_order_efficiency"
    design, measured, redesigned = (merit[k]["central"][p] for k in ("design", "measured_wafer", "redesigned_wafer"))
    # Independent: the phase errors of the levels as etched (the upper half 1.2 steps deep).
    delta = 0.15 * 8 * 2 * math.pi / 16
    as_etched = _first_order_factor([0.0] * 8 + [delta] * 8)
    assert measured / design == pytest.approx(as_etched, abs=0.01)
    remapped = _first_order_factor([0.0] * 8 + [-2 * math.pi / 16] + [0.2 * 2 * math.pi / 16] * 7)
    assert redesigned / design == pytest.approx(remapped, abs=0.01)
    assert redesigned >= sheet["redesign"]["remap_only_central"][p]
    # Better than the uncorrected wafer far beyond the Monte Carlo spread of either.
    sd = max(merit[k]["draws"][p]["std"] for k in ("measured_wafer", "redesigned_wafer"))
    assert redesigned - measured > 10 * sd
    assert merit["redesigned_wafer"]["draws"][p]["mean"] > merit["measured_wafer"]["draws"][p]["mean"] + 10 * sd
    assert merit["redesigned_wafer"]["samples"] == merit["measured_wafer"]["samples"] == 4
    assert merit["measured_wafer"]["primary_change_percent"] < merit["redesigned_wafer"]["primary_change_percent"] < 0
    # The files: a design, its masks as doe masks writes them (verified), the run's report.
    rd = sheet["redesign"]
    assert rd["level_remap"] == [0, 1, 2, 3, 4, 5, 6, 7, 7, 8, 9, 10, 11, 12, 13, 14]
    assert rd["notes"] == [] and rd["masks_verification"]["passed"]
    new = Design.load(out / "redesign" / "design.npz")
    assert new.levels.shape == (N, N) and new.metadata["redesign"]["level_remap"] == rd["level_remap"]
    assert (out / "redesign" / rd["masks_file"]).is_file() and (out / "redesign" / "masks" / "masks.png").is_file()
    full = json.loads((out / "redesign" / "redesign.json").read_text())
    assert full["merit"]["central"][p] == redesigned
    page = (out / "report.md").read_text()
    assert "re-designed for the process as measured" in page and "8->7" in page


def test_redesign_without_a_built_in_target_scores_the_merits_pixels(tmp_path):
    """A design naming no target: the loop aims at its ideal PSF on the merit's pixels."""
    sheet, _ = _correct(tmp_path, 0.15, with_target=False)
    merit = sheet["merit"]
    p = merit["primary_metric"]
    assert p == "efficiency" and sheet["redesign"]["target"] == "image"
    sd = max(merit[k]["draws"][p]["std"] for k in ("measured_wafer", "redesigned_wafer"))
    assert merit["redesigned_wafer"]["central"][p] - merit["measured_wafer"]["central"][p] > 10 * sd
    # Here the loop adds to the remap (its ideal-PSF target is the light on the same pixels).
    assert sheet["redesign"]["kept"] == "design loop"
    assert merit["redesigned_wafer"]["central"][p] - sheet["redesign"]["remap_only_central"][p] > 5 * sd


@pytest.mark.parametrize("with_target", [True, False])
def test_null_process_gives_a_redesign_no_better_than_the_design(tmp_path, with_target):
    """Nothing systematic (the fields scatter +-0.2 % about zero): the design is already the best
    for its process, so the re-design may not be predicted better, within the draws' error."""
    sheet, _ = _correct(tmp_path, 0.0, with_target, extra=("--redesign-samples", "2"))
    merit = sheet["merit"]
    p = merit["primary_metric"]
    assert sheet["redesign"]["level_remap"] == list(range(16))
    assert sheet["redesign"]["process_samples"] == 3
    measured, redesigned = merit["measured_wafer"], merit["redesigned_wafer"]
    error = math.hypot(measured["draws"][p]["std"], redesigned["draws"][p]["std"]) / math.sqrt(measured["samples"])
    assert redesigned["draws"][p]["mean"] <= measured["draws"][p]["mean"] + 3 * error + 1e-12
    assert redesigned["central"][p] <= merit["design"]["central"][p] + 3 * error + 1e-12


def test_redesign_for_the_corrected_process_has_nothing_left_to_take(tmp_path):
    """Deep etch and linewidth bias, both corrected by the job sheet: the corrected process is
    nominal, so the re-design for it keeps the levels (no remap) and is no better than the
    corrected wafer; its masks are drawn with the sheet's edge offsets."""
    sheet, out = _correct(tmp_path, 0.15, bias_m=0.3e-6, extra=("--redesign-for", "corrected"))
    merit = sheet["merit"]
    p = merit["primary_metric"]
    rd = sheet["redesign"]
    assert rd["process_of"] == "corrected_wafer" and rd["level_remap"] == list(range(16))
    corrected, redesigned = merit["corrected_wafer"], merit["redesigned_wafer"]
    error = math.hypot(corrected["draws"][p]["std"], redesigned["draws"][p]["std"]) / math.sqrt(corrected["samples"])
    assert redesigned["central"][p] <= corrected["central"][p] + 3 * error + 1e-12
    assert merit["measured_wafer"]["central"][p] < redesigned["central"][p]
    masks = json.loads((out / "redesign" / "masks" / "report.json").read_text())
    assert [m["edge_offset_um"] for m in masks["layers"]] == pytest.approx([-0.3] * 4)
    assert masks["verification"]["passed"]
    assert "re-designed for the corrected process" in (out / "report.md").read_text()


def test_redesign_options_without_redesign_are_refused(tmp_path, capsys):
    design, path = _blaze(tmp_path)
    out = tmp_path / "out"
    code = main(["correct", "--design", str(path), *_fields(tmp_path, design, path, 0.1), "--out", str(out),
                 "--redesign-iterations", "5"])
    err = capsys.readouterr().err.strip()
    assert code == 2 and "--redesign" in err and len(err.splitlines()) == 1 and not out.exists()
