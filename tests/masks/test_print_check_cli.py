"""`doe masks --gap-um`: what a proximity gap and dose print, before a run, through the command.

The in-place threshold is checked against Fresnel's half-plane (a quarter of the open field at
the geometric edge, for one coherent line) and by printing a long edge with it."""

import json

import numpy as np
import pytest

from doedesign.cli import main
from doedesign.design import Design
from masks.print_check import in_place_threshold
from masks.proximity import ProximityOptics, print_coverage

PITCH = 5.4e-6


def _design(tmp_path, px=32, seed=5):
    rng = np.random.default_rng(seed)
    levels = rng.integers(0, 16, (px, px))
    probe = Design(height_m=np.zeros((px, px)), pitch_m=PITCH)
    d = Design(height_m=-levels * probe.level_step_m(), pitch_m=PITCH)
    path = tmp_path / "fine.npz"
    d.save(path)
    return path


def test_in_place_threshold_of_one_coherent_line_is_fresnels_quarter():
    # |U|^2 at a half-plane's geometric edge is exactly 1/4 of the open field (Fresnel integrals at 0).
    optics = ProximityOptics(30e-6, wavelengths_m=(436e-9,), weights=(1.0,), collimation_half_angle_rad=0.0,
                             resist_blur_m=0.0)
    assert in_place_threshold(optics, 0.1e-6) == pytest.approx(0.25, abs=0.01)


def test_the_in_place_threshold_prints_a_long_edge_where_it_is_drawn():
    optics = ProximityOptics(30e-6)  # g/h/i lines, 2 deg collimation, 0.1 um resist blur
    step = 0.25e-6
    t = in_place_threshold(optics, step)
    assert 0.2 < t < 0.35
    cov = np.zeros((8, 1024), dtype=np.float32)
    cov[:, 512:] = 1.0
    printed = np.asarray(print_coverage(cov, step, optics, t, periodic=True))  # endless along the edge
    # The printed opening's edge, from its area within 400 cells of the drawn edge: in place to a step.
    shift_cells = printed[4, 112:912].sum() - cov[4, 112:912].sum()
    assert abs(shift_cells) < 1.0


def test_masks_gap_writes_the_print_check_and_a_wider_gap_prints_worse(tmp_path, capsys):
    design = _design(tmp_path)
    out = {}
    for gap in (10, 30):
        assert main(["masks", str(design), "--out", str(tmp_path / f"g{gap}"), "--gap-um", str(gap)]) == 0
        summary = json.loads(capsys.readouterr().out)
        check = json.loads((tmp_path / f"g{gap}" / "print_check.json").read_text())
        report = json.loads((tmp_path / f"g{gap}" / "report.json").read_text())
        assert report["print_check"]["field_overlap"] == check["field_overlap"] == summary["print_check"]["field_overlap"]
        assert check["threshold_from"] == "in place for a long edge" and len(check["masks"]) == 4
        assert check["region_px"] == [0, 32, 0, 32]  # smaller than the default window: the whole design
        page = (tmp_path / f"g{gap}" / "print_check.md").read_text()
        assert f"What a {gap} um gap prints" in page and "| 3 |" in page
        out[gap] = check
    # One edge per pixel at 5.4 um: a 30 um gap loses more of the designed field than 10 um.
    assert out[30]["field_overlap"] < out[10]["field_overlap"] < 1.0
    assert list((tmp_path / "g30").glob("*.gds"))  # the masks themselves, as without a gap


def test_a_dose_sets_the_threshold(tmp_path, capsys):
    design = _design(tmp_path, px=16)
    assert main(["masks", str(design), "--out", str(tmp_path / "d"), "--gap-um", "30", "--dose", "9",
                 "--dose-to-clear", "2.5"]) == 0
    check = json.loads((tmp_path / "d" / "print_check.json").read_text())
    assert check["resist_threshold"] == pytest.approx(2.5 / 9) and check["dose_mj_cm2"] == 9


def test_masks_opc_corrects_for_the_stated_dose(tmp_path, capsys):
    # About 15 s of CPU: the density stage and 2 polishing steps at the dose's threshold (2.5 / 9 = 0.278).
    design = _design(tmp_path, px=16)
    assert main(["masks", str(design), "--out", str(tmp_path / "d"), "--gap-um", "30", "--dose", "9",
                 "--dose-to-clear", "2.5", "--opc", "--opc-iterations", "2"]) == 0
    capsys.readouterr()
    check = json.loads((tmp_path / "d" / "print_check.json").read_text())
    assert check["resist_threshold"] == check["uncorrected"]["resist_threshold"] == pytest.approx(2.5 / 9)
    assert check["opc"]["method"].startswith("density") and check["opc"]["iterations"] == 2
    assert check["field_overlap"] > check["uncorrected"]["field_overlap"] + 0.1


@pytest.mark.parametrize("argv, message", [
    (["--gap-um", "30", "--dose", "9"], "go together"),
    (["--resist-threshold", "0.3"], "need --gap-um"),
    (["--gap-um", "30", "--dose", "9", "--dose-to-clear", "2", "--resist-threshold", "0.3"], "not both"),
    (["--gap-um", "30", "--print-window", "10,10,40,4"], "--print-window"),
    (["--gap-um", "30", "--dose", "2", "--dose-to-clear", "9"], "does not clear"),
    (["--gap-um", "30", "--opc-method", "level-set"], "need --opc"),
])
def test_bad_print_options_are_one_line_and_leave_nothing(tmp_path, capsys, argv, message):
    design = _design(tmp_path, px=16)
    out = tmp_path / "o"
    with _returns(2) as code:
        code.value = main(["masks", str(design), "--out", str(out), *argv])
    err = capsys.readouterr().err.strip()
    assert message in err and "Traceback" not in err and len(err.splitlines()) == 1
    assert not out.exists() or not any(out.iterdir())


class _returns:
    """Context that checks the exit status a block stores in ``.value``."""

    def __init__(self, status):
        self.status, self.value = status, None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        assert exc[0] is None and self.value == self.status
        return False


def test_masks_opc_prints_closer_and_its_gds_verifies(tmp_path, capsys):
    design = _design(tmp_path, px=16)
    runs = {}
    for name, extra in (("drawn", []), ("opc", ["--opc", "--opc-iterations", "6"])):
        out = tmp_path / name
        assert main(["masks", str(design), "--out", str(out), "--gap-um", "30", *extra]) == 0
        capsys.readouterr()
        runs[name] = (json.loads((out / "report.json").read_text()), json.loads((out / "print_check.json").read_text()),
                      (out / "design.gds").read_bytes())
    report, check, gds = runs["opc"]
    # The written layers hold the corrected edges on their sub-pixel grid, verified against it.
    assert report["verification"]["passed"] and report["verification"]["mismatched_pixels"] == 0
    assert report["opc_mask_grid_um"] == pytest.approx(5.4 / 24)
    assert gds != runs["drawn"][2]
    # The same print model on both: the uncorrected figure is the plain run's on the OPC's whole-nanometre
    # print grid (its aerial image on the sampling rule's grid, interpolated: 0.554 against 0.548), the
    # corrected one better (measured 0.554 -> 0.824 on this 16 px element of one edge per pixel on every
    # mask, with the density stage; 0.650 by the level set alone).
    assert check["uncorrected"]["field_overlap"] == pytest.approx(runs["drawn"][1]["field_overlap"], rel=0.03)
    assert check["field_overlap"] > check["uncorrected"]["field_overlap"] + 0.2
    for m in check["opc"]["masks"]:
        assert m["printed_area_error_um2_corrected"] <= m["printed_area_error_um2_drawn"]
        assert m["narrowest_opening_um"] >= check["opc"]["min_feature_um"] - 1e-9
