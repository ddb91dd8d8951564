"""The instrument benchmark's field fits its design, and its scoring reads a report right."""

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
from benchmarks import bench_instruments as bench  # noqa: E402


@pytest.mark.parametrize("name", list(bench.INSTRUMENTS))
@pytest.mark.parametrize("rotation", [-1.0, pytest.param(1.0, marks=pytest.mark.slow)])  # one sense in make test
@pytest.mark.parametrize("design_px", [bench.DESIGN_PX, 130])
def test_field_fits_the_design_at_the_largest_pixel_rotation_and_offset(name, rotation, design_px):
    # 130 design pixels: the --design-px of the 512 x 512 runs, whose field must fit as well.
    fine, n = 2, bench.field_px(design_px)
    assert design_px != 130 or n >= 512
    surface = np.zeros((design_px * fine, design_px * fine))
    centre = (design_px - 1) / 2 + np.array([0.5, -0.5])
    bench.INSTRUMENTS[name].measure(surface, fine, (design_px,) * 2, (n, n), np.random.default_rng(0),
                                    pixel_m=1.3e-6, rotation_deg=rotation, centre_px=centre)
    with pytest.raises(ValueError):   # and it is the largest such field
        bench.INSTRUMENTS[name].measure(surface, fine, (design_px,) * 2, (n + 2, n + 2),
                                        np.random.default_rng(0), pixel_m=1.3e-6, rotation_deg=rotation,
                                        centre_px=centre)


def test_score_counts_names_errors_and_the_floor():
    truth = {"mask_overlay": {"mask": 2, "shift_m": np.array([0.3e-6, 0.4e-6])}}
    params = {f"d{a}_mask{j}_m": 0.0 for a in "xy" for j in range(1, 4)}
    params.update(dx_mask2_m=0.33e-6, dy_mask2_m=0.4e-6)
    report = {"steps": [{"effect": "mask_overlay", "measurement_artefact": False, "params": params},
                        {"effect": "etch_loading", "measurement_artefact": False, "params": {"loading": 0.01}},
                        {"effect": "batwing", "measurement_artefact": True, "params": {}}],
              "final_residual_rms": 1.2e-9, "noise_floor": 1.0e-9, "measurement_artefacts": ["batwing"]}
    got = bench.score(["mask_overlay"], truth, report)
    assert got["named_right"] == ["mask_overlay"] and got["false_names"] == ["etch_loading"]
    assert got["parameter_error"]["mask_overlay"] == pytest.approx(0.06)
    assert got["final_over_floor"] == pytest.approx(1.2) and not got["all_right"]
    report["steps"].pop(1)
    assert bench.score(["mask_overlay"], truth, report)["all_right"]


@pytest.mark.parametrize("name", list(bench.INSTRUMENTS))
def test_a_calibration_artefact_is_measured_with_the_cases_pixel_and_transfer(name):
    # What --calibrated carries from a case's instrument to its artefact: draws the simulator
    # takes back as they were (an unknown name would be refused with a KeyError).
    fine, shape = 2, (bench.ARTEFACT_DESIGN_PX,) * 2
    surface = np.zeros((shape[0] * fine, shape[1] * fine))
    _, case = bench.INSTRUMENTS[name].measure(surface, fine, shape, (40, 40), np.random.default_rng(1))
    held = {k: case[k] for k in bench.TRANSFER_KEYS[name]}
    _, artefact = bench.INSTRUMENTS[name].measure(surface, fine, shape, (40, 40), np.random.default_rng(2), **held)
    assert {k: artefact[k] for k in held} == held
    assert artefact["rotation_deg"] != case["rotation_deg"]   # mounted afresh


# The CSI simulator integrates 256 nodes per pixel: 160 M points at 800 px, seconds and gigabytes.
@pytest.mark.parametrize("name", ["point", "boxcar", pytest.param("csi", marks=pytest.mark.slow)])
def test_a_drawn_field_of_400_800_px_fits_its_design_and_follows_its_seed(name):
    # --field-px 400-800 over the 108 px design of the large tables: each case's side and pixel
    # come from its seed alone, in range, and fit at the largest rotation and centre offset.
    design_px, fine = 108, 1
    surface = np.zeros((design_px * fine,) * 2)
    centre = (design_px - 1) / 2 + np.array([-0.5, 0.5])
    sides = []
    for seed in (3, 518677876, 9942083):
        side, pixel, header = bench.draw_field((400, 800), seed, design_px)
        assert (side, pixel, header) == bench.draw_field((400, 800), seed, design_px)
        assert 400 <= side <= 800 and 0.7e-6 <= pixel <= 1.3e-6 and abs(header / pixel - 1) <= 0.005
        for rotation in (-1.0, 1.0):
            bench.INSTRUMENTS[name].measure(surface, fine, (design_px,) * 2, (side, side), np.random.default_rng(0),
                                            pixel_m=pixel, rotation_deg=rotation, centre_px=centre)
        sides.append(side)
    assert len(set(sides)) == 3
    assert bench.draw_field(512, 3, design_px) == (512, None, None)   # a single side: the instrument's pixel
    assert bench.parse_field("400-800") == (400, 800) and bench.parse_field("512") == 512
    with pytest.raises(ValueError, match="--design-px 107"):
        bench.check_field((400, 800), 100)
