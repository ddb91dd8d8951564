"""`doe demo --quick` runs the whole chain and names the hidden process error."""

import json

from doedesign.cli import main


def test_quick_demo_runs_end_to_end_and_finds_the_hidden_error(tmp_path):
    out = tmp_path / "demo"
    assert main(["demo", "--quick", "--out", str(out)]) == 0
    report = json.loads((out / "report.json").read_text())
    steps = [s["step"] for s in report["timings"]]
    assert len(steps) == 6 and all(s["seconds"] > 0 for s in report["timings"])
    assert report["masks"]["verification"]["passed"]
    assert (out / "masks" / "bayer_demo.gds").stat().st_size > 0
    assert (out / "measurement.datx").exists()
    # The hidden 0.4 um x-overlay of the 600 nm mask is measured and named.
    overlay = report["comparison"]["overlay_um"][3]
    assert abs(overlay[0] - 0.4) < 0.15 and abs(overlay[1]) < 0.15
    named = [s["effect"] for s in report["diagnosis"]["steps"]]
    assert named and named[0] == "mask_overlay"
    text = (out / "report.md").read_text()
    assert "psf.png" in text and "Diagnosis" in text
