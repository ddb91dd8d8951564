"""``doe calibrate instrument`` on an artefact of known geometry (issue 25, cf. ISO 25178-600): a
profilometer simulated apart from the model (``tests/metrology/instruments``) with a known
lateral transfer and a height scale off by 2 % measures the artefact; the calibration recovers
the transfer and the scale within their uncertainties, and refuses certified step heights
that the measurement contradicts."""

import json

import numpy as np
import pytest

import filegen
from doedesign.cli import main
from instruments import boxcar

BLUR_M, GAIN = 0.4e-6, 1.02


@pytest.fixture(scope="module")
def artefact(tmp_path_factory):
    """A test structure on the die (a random 16-level field, 4 masks of 75-600 nm), measured
    by a pixel-integrating camera (fill factor 1) behind a 0.4 um Gaussian blur, its heights
    read 2 % high."""
    rng = np.random.default_rng(41)
    levels = filegen.random_levels((32, 32), rng)
    height, inst = boxcar.measure(filegen.wafer_surface(levels, {}), filegen.FINE_PER_PX, levels.shape, (100, 100),
                                  rng, blur_sigma_m=BLUR_M, rotation_deg=0.4, n_spikes=3)
    case = filegen.FileCase(levels=levels, truth={}, instrument=inst, height_m=GAIN * height, seed=41)
    return case.write(tmp_path_factory.mktemp("artefact"))


def _calibrate(artefact, out, *extra):
    design, measured = artefact
    return main(["calibrate", "instrument", str(measured), "--design", str(design), "--out", str(out),
                 "--window-px", "72", *extra])


@pytest.mark.slow
def test_the_transfer_and_the_height_scale_are_recovered_within_their_uncertainty(artefact, tmp_path):
    out = tmp_path / "instrument.json"
    assert _calibrate(artefact, out, "--step-height-nm", "75,150,300,600") == 0
    cal = json.loads(out.read_text())
    lateral, scale = cal["lateral_transfer"], cal["height_scale"]
    assert abs(lateral["blur_sigma_m"] - BLUR_M) < 3 * lateral["blur_sigma_uncertainty_m"] + 2e-9
    assert abs(lateral["fill_factor"] - 1.0) < 3 * lateral["fill_factor_uncertainty"] + 0.01
    assert lateral["na"] == 0.0
    assert abs(scale["value"] - GAIN) < 3 * scale["uncertainty"] + 1e-4 and scale["uncertainty"] < 0.002
    assert scale["certified_step_heights_m"] == pytest.approx(filegen.DEPTHS_M)
    # The pixel the calibration holds for (the file's, as the next measurement's will read).
    from metrology.formats.readers import read_measurement

    assert lateral["camera_pixel_m"] == read_measurement(artefact[1]).pixel_size_m


@pytest.mark.slow
@pytest.mark.parametrize("heights, why", [("75,150,300,660", "mask 3"), ("85,170,340,680", "beyond the 5%")])
def test_a_wrong_certified_step_height_is_refused(artefact, tmp_path, capsys, heights, why):
    # One mask's height wrong by 10 % (the others agree on one scale), or every height 13 % off
    # (no profilometer's height scale is that far out): one line, status 2, nothing written.
    out = tmp_path / "instrument.json"
    assert _calibrate(artefact, out, "--step-height-nm", heights) == 2
    err = capsys.readouterr().err.strip()
    assert "measured.datx" in err and "--step-height-nm" in err and why in err and "Traceback" not in err
    assert not out.exists()


@pytest.mark.slow
def test_without_certified_heights_the_scale_is_not_calibrated(artefact, tmp_path):
    out = tmp_path / "instrument.json"
    assert _calibrate(artefact, out) == 0
    cal = json.loads(out.read_text())
    assert cal["height_scale"]["value"] == 1.0 and cal["height_scale"]["uncertainty"] is None


def test_the_height_scale_is_the_masks_common_ratio_and_a_stray_mask_is_named():
    from doedesign.errors import DoeError
    from metrology.calibration.instrument import height_scale

    cert = np.array(filegen.DEPTHS_M)
    err = np.full(4, 0.05e-9)
    value, sd = height_scale(1.01 * cert, err, cert)
    assert value == pytest.approx(1.01) and 0 < sd < 1e-3
    # A mask absent from the window (its step undetermined) does not count.
    steps = 1.01 * cert
    steps[0] = 0.5 * cert[0]
    assert height_scale(steps, [np.inf, *err[1:]], cert)[0] == pytest.approx(1.01)
    steps[0] = 1.06 * cert[0]
    with pytest.raises(DoeError, match="mask 0 measures"):
        height_scale(steps, err, cert)
    assert height_scale(steps, err, cert, force=True)[0] > 1.01
    with pytest.raises(DoeError, match="beyond the 5%"):
        height_scale(0.93 * cert, err, cert)


def test_compare_and_diagnose_take_true_heights_and_refuse_another_magnification(tmp_path):
    from doedesign.errors import DoeError
    from metrology.calibration.instrument import FORMAT, apply_calibration, read_calibration
    from metrology.formats.measurement import Measurement

    path = tmp_path / "instrument.json"
    path.write_text(json.dumps({"format": FORMAT, "lateral_transfer": {
        "blur_sigma_m": 0.3e-6, "fill_factor": 0.5, "na": 0.0, "wavelength_m": 0.57e-6, "camera_pixel_m": 1.0e-6},
        "height_scale": {"value": 1.02}}))
    cal = read_calibration(path)
    assert cal.transfer.fill_factor == 0.5 and cal.height_scale == 1.02 and cal.pixel_m == 1.0e-6
    measured = Measurement(np.full((4, 4), -102e-9), 1.004e-6)
    assert np.allclose(apply_calibration(measured, cal).height_m, -100e-9)
    with pytest.raises(DoeError, match="another objective or zoom"):
        apply_calibration(Measurement(np.zeros((4, 4)), 1.1e-6), cal, "field.datx")
