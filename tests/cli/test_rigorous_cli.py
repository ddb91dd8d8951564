"""``doe rigorous`` end to end: a design file in, report.json and report.md out, bad input one line."""

import json
import subprocess
import sys

import numpy as np
import pytest

from doedesign.design import Design
from doedesign.materials import get_material

pytest.importorskip("fmmax")


def _doe(*args):
    return subprocess.run([sys.executable, "-c", "import sys; from doedesign.cli import main; sys.exit(main())",
                           *args], capture_output=True, text=True)


@pytest.fixture
def binary_design(tmp_path):
    # A binary (pi) grating of 12 px at 2 um (24 um period, 44 wavelengths at 550 nm), 12 rows.
    step = get_material("fused_silica").height_2pi_m(550e-9) / 2
    h = np.zeros((12, 12))
    h[:, 6:] = -step
    path = tmp_path / "d.npz"
    Design(h, 2e-6, metadata={"name": "binary"}).save(path)
    return path


def test_rigorous_command_writes_reports_beside_thin_element(binary_design, tmp_path):
    out = tmp_path / "rig"
    r = _doe("rigorous", str(binary_design), "--out", str(out), "--patch", "0,0,1,12", "--terms", "61",
             "--polarization", "te")
    assert r.returncode == 0, r.stderr
    rep = json.loads((out / "report.json").read_text())
    w = rep["comparison"]["wavelengths"][0]
    first = {tuple(o["order"]): o for o in w["orders"]}
    # thin element: a 50 % pi square wave puts (2/pi)^2 into each first order (its Fourier series;
    # pixels of flat phase make the pixelated one exact) and none into order 0
    assert first[(1, 0)]["thin_element"] == pytest.approx((2 / np.pi) ** 2, rel=1e-9)
    assert (0, 0) not in first or first[(0, 0)]["thin_element"] < 1e-12
    assert first[(1, 0)]["rigorous_relative"] == pytest.approx(first[(1, 0)]["thin_element"], abs=0.02)
    assert 0.9 < w["transmitted"] < 1.0  # a glass-air interface reflects a few percent
    assert rep["validity"]["holds"] is True  # 12 um features, 0.6 um deep
    assert "## Where the thin-element model holds" in (out / "report.md").read_text()


def test_rigorous_command_refuses_bad_input_in_one_line(binary_design, tmp_path):
    r = _doe("rigorous", str(binary_design), "--out", str(tmp_path / "o"), "--patch", "0,0,40,40")
    assert r.returncode == 2 and "does not fit" in r.stderr and "Traceback" not in r.stderr
    assert not (tmp_path / "o" / "report.json").exists()
    r = _doe("rigorous", str(tmp_path / "missing.npz"), "--out", str(tmp_path / "o2"))
    assert r.returncode == 2 and "Traceback" not in r.stderr


def test_design_report_states_where_the_thin_element_model_holds(tmp_path):
    out = tmp_path / "d.npz"
    r = subprocess.run([sys.executable, "-c", "import sys; from doedesign.cli import main; sys.exit(main())",
                        "design", "bayer", "--size", "32", "--iterations", "3", "--out", str(out)],
                       capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    thin = json.loads((tmp_path / "report.json").read_text())["thin_element_validity"]
    # 5.4 um pixels at the longest Bayer wavelength, etched at most 1.1 um: inside the limits
    assert thin["holds"] is True
    assert thin["feature_over_wavelength"] == pytest.approx(5.4e-6 / 656e-9, rel=0.05)
    assert json.loads(r.stdout)["thin_element_model"] == thin["statement"]
