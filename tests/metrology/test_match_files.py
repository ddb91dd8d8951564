"""`doe compare` and `doe diagnose` judge whether a field shows its design by the registration,
never by how far the heights are from nominal (profilometer files from tests/metrology/filegen.py).

A bad wafer (strong etch loading, a depth error on every mask, a large linewidth bias) is
compared and diagnosed; another design, a field turned by a quarter turn and a field off the
element are refused with one line that says which (exit 2).
"""

import json

import numpy as np
import pytest

import filegen
from doedesign.cli import main

FINE = 40  # super-fine cells per design pixel: plenty for a yes/no on the match, 4x faster
ALTERNATING_12 = np.array([0.12, -0.12, 0.12, -0.12])


def _compare(case, tmp, levels=None, height=None):
    """Write the case (optionally with another design or height map) and run doe compare."""
    if levels is not None or height is not None:
        case = filegen.FileCase(levels=case.levels if levels is None else levels, truth=case.truth,
                                instrument=case.instrument, height_m=case.height_m if height is None else height)
    design, measured = case.write(tmp)
    code = main(["compare", str(measured), "--design", str(design), "--out", str(tmp / "cmp"), "--no-psf",
                 "--no-render"])
    return code, design, measured


def _diagnose(design, measured, out, extra=()):
    return main(["diagnose", "--measured", str(measured), "--design", str(design), "--out", str(out), *extra])


@pytest.fixture(scope="module")
def loading_case():
    """30 % etch loading on a design whose mask density changes across the field: the interior
    heights of a level spread by ~100 nm, and the rule this replaces refused the file (71 % of
    feature interiors within a quarter step of their level; it needed 80 %)."""
    rng = np.random.default_rng(3)
    levels = filegen.density_split_levels((56, 56), rng)
    return filegen.make_case([], 3, levels=levels, field_px=220, fine=FINE, truth={"etch_loading": {"loading": 0.3}})


def test_strong_etch_loading_is_compared(loading_case, tmp_path):
    code, _, _ = _compare(loading_case, tmp_path)
    assert code == 0
    match = json.loads((tmp_path / "cmp" / "report.json").read_text())["match"]
    assert match["confidence"] == "high" and match["problem"] is None
    assert match["readout_correlation"] > 0.98 and match["edges_found"] > 0.95


@pytest.mark.slow
def test_strong_etch_loading_is_diagnosed(loading_case, tmp_path):
    _, design, measured = _compare(loading_case, tmp_path)
    assert _diagnose(design, measured, tmp_path / "diag") == 0
    assert "etch_loading" in json.loads((tmp_path / "diag" / "report.json").read_text())["effects_found"]


BAD_WAFERS = {
    "depth_12_percent_every_mask": {"etch_depth": {"error": ALTERNATING_12}},
    "depth_minus_12_percent": {"etch_depth": {"error": np.full(4, -0.12)}},
    "bias_half_micron": {"linewidth_bias": {"bias_m": np.full(4, 0.5e-6)}},
}


@pytest.mark.parametrize("name", [pytest.param(n, marks=[] if n == "depth_12_percent_every_mask" else pytest.mark.slow)
                                  for n in sorted(BAD_WAFERS)])
def test_bad_wafer_is_compared(name, tmp_path):
    """+-12 % on alternating masks flips the one-step 7 -> 8 edges (4 % of them); still compared."""
    case = filegen.make_case([], 5, design_px=36, field_px=120, fine=FINE, truth=BAD_WAFERS[name])
    code, _, _ = _compare(case, tmp_path)
    assert code == 0
    assert json.loads((tmp_path / "cmp" / "report.json").read_text())["match"]["confidence"] == "high"


@pytest.mark.slow
@pytest.mark.parametrize("name", sorted(BAD_WAFERS))
def test_bad_wafer_is_diagnosed(name, tmp_path):
    case = filegen.make_case([], 5, design_px=36, field_px=120, fine=FINE, truth=BAD_WAFERS[name])
    design, measured = case.write(tmp_path)
    assert _diagnose(design, measured, tmp_path / "diag") == 0
    found = json.loads((tmp_path / "diag" / "report.json").read_text())["effects_found"]
    assert next(iter(BAD_WAFERS[name])) in found


@pytest.fixture(scope="module")
def good_case():
    return filegen.make_case([], 1, fine=FINE)


def _outside_case():
    """The wafer holds a larger pattern; the design file is its top-left corner, the field
    lies in the middle: outside the design."""
    big = filegen.make_case([], 202, design_px=64, field_px=120, fine=FINE)
    return big, big.levels[:16, :16]


def _wrong(kind, good_case):
    """(case, levels, height) of a field that does not show its design."""
    if kind == "another design":
        return good_case, filegen.random_levels(good_case.levels.shape, np.random.default_rng(101)), None
    if kind == "quarter turn":
        return good_case, None, np.rot90(good_case.height_m).copy()
    if kind == "flat":
        rng = np.random.default_rng(0)
        rows = np.arange(good_case.height_m.shape[0])[:, None] * np.ones(good_case.height_m.shape[1])
        return good_case, None, 1e-9 * rng.standard_normal(rows.shape) + 1e-7 * rows / rows.shape[0]
    big, levels = _outside_case()
    return big, levels, None


WRONG = {"another design": "another design", "quarter turn": "quarter turn",
         "flat": "off the element: it is flat", "outside": "region outside this one"}


@pytest.mark.parametrize("kind", sorted(WRONG))
def test_wrong_field_is_refused_in_one_line(kind, good_case, tmp_path, capsys):
    case, levels, height = _wrong(kind, good_case)
    code, design, measured = _compare(case, tmp_path, levels, height)
    err = capsys.readouterr().err.strip()
    assert code == 2
    assert WRONG[kind] in err and "measured.datx" in err and "\n" not in err
    assert not (tmp_path / "cmp" / "report.json").exists()
    assert _diagnose(design, measured, tmp_path / "diag") == 2
    err = capsys.readouterr().err.strip()
    assert WRONG[kind] in err and "\n" not in err
    assert not (tmp_path / "diag" / "report.json").exists()


@pytest.mark.slow
def test_quarter_turn_is_compared_when_forced(good_case, tmp_path):
    """--force goes on; the report keeps why the match was poor."""
    case = filegen.FileCase(levels=good_case.levels, truth={}, instrument=good_case.instrument,
                            height_m=np.rot90(good_case.height_m).copy())
    design, measured = case.write(tmp_path)
    assert main(["compare", str(measured), "--design", str(design), "--out", str(tmp_path / "cmp"), "--no-psf",
                 "--no-render", "--force"]) == 0
    match = json.loads((tmp_path / "cmp" / "report.json").read_text())["match"]
    assert match["confidence"] == "low" and match["forced"] and "quarter turn" in match["problem"]
    assert match["quarter_turn"] and match["readout_correlation"] > 0.99

