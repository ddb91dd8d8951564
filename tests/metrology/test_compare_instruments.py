"""`doe compare` on a perfectly printed wafer measured by the tests' own instruments
(``tests/metrology/instruments``, written apart from the model): the camera-frame fit holds
the instrument's family (blur and pixel fill factor), so what is left is the noise."""

import json

import numpy as np
import pytest

import filegen
from doedesign.cli import main
from instruments import boxcar, point


@pytest.mark.parametrize("instrument", [point, boxcar], ids=["point", "boxcar"])
def test_a_perfect_wafer_is_judged_at_the_instruments_noise(tmp_path, instrument):
    rng = np.random.default_rng(5)
    levels = filegen.random_levels((40, 40), rng)
    surface = filegen.wafer_surface(levels, {})
    height, inst = instrument.measure(surface, filegen.FINE_PER_PX, levels.shape, (130, 130), rng)
    case = filegen.FileCase(levels=levels, truth={}, instrument=inst, height_m=height, seed=5)
    design, measured = case.write(tmp_path)
    out = tmp_path / "cmp"
    assert main(["compare", "--design", str(design), str(measured), "--out", str(out), "--no-psf", "--no-render"]) == 0
    frame = json.loads((out / "report.json").read_text())["instrument_frame"]
    # Full pixels with a Gaussian blur left 2.9 nm against 1.3 nm of noise on a point-sampled file.
    assert frame["rms_residual_nm"] <= 1.1 * inst["noise_m"] * 1e9
    # Blur and fill factor trade against each other on a small field: their kernel's second
    # moment is what the edges fix.
    kernel_var = (frame["blur_sigma_um"] * 1e-6) ** 2 + frame["fill_factor"] * inst["pixel_m"] ** 2 / 12
    true_var = inst["blur_sigma_m"] ** 2 + (1.0 if instrument is boxcar else 0.0) * inst["pixel_m"] ** 2 / 12
    assert abs(kernel_var / true_var - 1) < 0.15
