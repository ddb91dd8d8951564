"""`doe design`, `doe evaluate-bayer` and `doe calibrate` leave a folder that is either the complete
output of one run or says INCOMPLETE: a failure injected after the first result file is written
leaves the marker, and the next clean run removes it."""

from __future__ import annotations

import numpy as np
import pytest

from doedesign import cli
from doedesign.camera import Camera
from doedesign.design import Design
from doedesign.fileio import INCOMPLETE_MARKER


def _interrupt(*args, **kwargs):
    raise KeyboardInterrupt


def _fail_after_first_result(monkeypatch, module, name):
    """Make ``module.name`` (a writer called after the first result file) fail like a Ctrl-C."""
    monkeypatch.setattr(module, name, _interrupt)


def _results(folder):
    return sorted(p.name for p in folder.iterdir() if p.name != INCOMPLETE_MARKER and not p.name.startswith("."))


def test_design_marks_its_folder_until_design_and_report_are_written(tmp_path, monkeypatch):
    import doedesign.cli.design as design_cli

    out = tmp_path / "d" / "design.npz"
    argv = ["design", "bayer", "--size", "16", "--iterations", "2", "--anneal-iterations", "1", "--out", str(out)]
    with monkeypatch.context() as m:
        _fail_after_first_result(m, design_cli, "write_json")
        assert cli.main(argv) == 130
    # The design was written, its report was not: the folder says so.
    assert (out.parent / INCOMPLETE_MARKER).is_file() and out.is_file()
    assert not (out.parent / "report.json").exists()
    assert cli.main(argv) == 0
    assert not (out.parent / INCOMPLETE_MARKER).exists()
    assert _results(out.parent) == ["design.npz", "report.json"]


def test_evaluate_bayer_marks_its_folder_until_every_output_is_written(tmp_path, monkeypatch):
    import doedesign.bayer as bayer

    cam = Camera(aperture_diameter_m=16 * 5.4e-6)
    Design(np.zeros((16, 16)), 5.4e-6, metadata={"camera": cam.to_dict(), "name": "flat"}).save(tmp_path / "f.npz")
    out = tmp_path / "study"
    argv = ["evaluate-bayer", "--design", str(tmp_path / "f.npz"), "--front", "0", "--crop", "32",
            "--images", "astronaut", "--out", str(out)]
    with monkeypatch.context() as m:
        _fail_after_first_result(m, bayer, "figure")  # table.json is written just before the figure
        assert cli.main(argv) == 130
    assert (out / INCOMPLETE_MARKER).is_file() and (out / "table.json").is_file()
    assert cli.main(argv) == 0
    assert not (out / INCOMPLETE_MARKER).exists() and _results(out) == ["fig2.png", "table.json"]


def test_evaluate_bayer_refused_before_writing_leaves_nothing(tmp_path):
    out = tmp_path / "bad"
    assert cli.main(["evaluate-bayer", "--no-doe", "--images", "nosuchimage", "--out", str(out)]) == 2
    assert not out.exists()


@pytest.fixture
def captures(tmp_path):
    from doedesign.engine.psf import PSFEngine

    # Two narrowband captures of a small grating's PSF: the sum frame and the stored (uncoded) view.
    cam = Camera(aperture_diameter_m=48 * 5.4e-6, window_shape=(48, 48), axis_pixel=(24, 24))
    heights = -np.tile((np.arange(48) % 8 < 4) * 0.3e-6, (48, 1))
    folder = tmp_path / "caps"
    folder.mkdir()
    for wl in (450, 500):
        res = PSFEngine(cam, 5.4e-6, heights.shape, wavelengths_m=[wl * 1e-9], depths_m=[np.inf]).psf(heights)
        coded, uncoded = res.psf[0, 0, 0] * 1e6, res.psf[1, 0, 0] * 1e6
        np.save(folder / f"{wl}nm_sum.npy", coded + uncoded + 2.0)
        np.save(folder / f"{wl}nm_view.npy", uncoded + 1.0)
    return folder


def test_calibrate_psf_marks_its_folder_until_every_output_is_written(tmp_path, monkeypatch, captures):
    import metrology.calibration.psfstack as ps

    out = tmp_path / "cal"
    argv = ["calibrate", "psf", "--captures", str(captures), "--coded-view", "other", "--window", "32,32",
            "--background", "none", "--out", str(out)]
    with monkeypatch.context() as m:
        _fail_after_first_result(m, ps, "save_network_npy")  # after the figure and psf_stack.npz
        assert cli.main(argv) == 130
    assert (out / INCOMPLETE_MARKER).is_file() and (out / "psf_stack.npz").is_file()
    assert not (out / "report.json").exists()
    assert cli.main(argv) == 0
    assert not (out / INCOMPLETE_MARKER).exists()
    assert _results(out) == ["psf_network.npy", "psf_stack.npz", "psf_stack.png", "report.json"]


def test_calibrate_psf_checks_the_prediction_before_writing(tmp_path, captures, capsys):
    """A --predicted file that does not fit the captures (no 450/500 nm PSF) is refused before any output."""
    from doedesign.engine import PSFEngine

    cam = Camera(aperture_diameter_m=48 * 5.4e-6, window_shape=(48, 48), axis_pixel=(24, 24))
    predicted = PSFEngine(cam, 5.4e-6, (48, 48), wavelengths_m=[600e-9], depths_m=[np.inf]).psf(np.zeros((48, 48)))
    predicted_path = predicted.save(tmp_path / "predicted_600nm.npz")
    out = tmp_path / "cal"
    argv = ["calibrate", "psf", "--captures", str(captures), "--coded-view", "other", "--window", "32,32",
            "--background", "none", "--predicted", str(predicted_path), "--out", str(out)]
    assert cli.main(argv) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and str(predicted_path) in err and "Traceback" not in err, err
    assert not out.exists()
