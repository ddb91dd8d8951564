"""Dual-pixel splitting, crosstalk calibration and compensation, demosaicing, white balance."""

import numpy as np
import pytest
import tifffile

from doedesign.errors import DoeError
from metrology.calibration import dualpixel as dp

ROWS, COLS = 64, 96
RNG_SEED = 3


def true_ratios():
    """Column-varying crosstalk, different per channel and per view: (2, 4, COLS)."""
    x = np.arange(COLS) / (COLS - 1)
    base = np.array([[0.06, 0.09, 0.10, 0.13], [0.05, 0.08, 0.07, 0.11]])
    slope = np.array([[0.04, -0.03, 0.02, -0.05], [-0.02, 0.03, 0.04, 0.02]])
    bow = np.array([[0.02, 0.01, -0.015, 0.01], [0.01, -0.02, 0.01, 0.015]])
    return base[..., None] + slope[..., None] * x + bow[..., None] * np.sin(np.pi * x)


def mix(stored_true, other_true, ratio, pattern="RGGB"):
    ch = dp.cfa_channels(stored_true.shape, pattern)
    cols = np.arange(stored_true.shape[1])
    c_s, c_o = ratio[0][ch, cols], ratio[1][ch, cols]
    return (1 - c_s) * stored_true + c_o * other_true, c_s * stored_true + (1 - c_o) * other_true


def frames(stored_true, other_true, ratio, rng, pattern="RGGB"):
    """Sum and stored-view raw frames with shot noise on each photodiode."""
    ms, mo = mix(stored_true, other_true, ratio, pattern)
    ns, no = rng.poisson(ms).astype(float), rng.poisson(mo).astype(float)
    return ns + no, ns


def wall():
    r, c = np.mgrid[:ROWS, :COLS]
    vignette = 1 - 0.3 * (((r - ROWS / 2) / ROWS) ** 2 + ((c - COLS / 2) / COLS) ** 2)
    return 40000.0 * vignette


@pytest.fixture(scope="module")
def calibration():
    rng = np.random.default_rng(RNG_SEED)
    ratio = true_ratios()
    # The stored photodiode sees the right half: left blocked lights only the stored view.
    left = frames(wall(), np.zeros((ROWS, COLS)), ratio, rng)
    right = frames(np.zeros((ROWS, COLS)), wall(), ratio, rng)
    return dp.calibrate_crosstalk(left, right), ratio


def test_calibration_recovers_column_varying_crosstalk_per_channel(calibration):
    cal, ratio = calibration
    ch = dp.cfa_channels((2, COLS))
    for view in range(2):
        for c in range(4):
            cols = np.flatnonzero((ch == c).any(axis=0))
            rel = np.abs(cal.ratio[view, c, cols] / ratio[view, c, cols] - 1)
            assert rel.max() < 0.01, (view, c, rel.max())
    assert cal.stored_view_half == "right"
    # The channels really differ: one ratio for all channels would be off by far more than 1 %.
    means = cal.ratio[0].mean(axis=1)
    assert means.max() / means.min() - 1 > 0.2


def test_compensation_restores_views_to_noise_level(calibration):
    cal, ratio = calibration
    rng = np.random.default_rng(7)
    r, c = np.mgrid[:ROWS, :COLS]
    coded = 5000 + 20000 * np.exp(-((r - 30) ** 2 + (c - 60) ** 2) / 50.0)
    uncoded = 8000 + 3000 * np.sin(c / 5.0) ** 2
    s_frame, v_frame = frames(coded, uncoded, ratio, rng)
    stored, other, sat = dp.split_views(s_frame, v_frame, saturation=1e9)
    fixed_s, fixed_o = dp.compensate_crosstalk(stored, other, cal, saturated=sat)
    # Noise level of a compensated capture: shot noise of each photodiode, amplified by 1/det ~ 1.25.
    noise = np.sqrt((coded + uncoded) / 2).mean() * 1.3
    before = np.sqrt(np.mean((stored - coded) ** 2))
    after_s = np.sqrt(np.mean((fixed_s - coded) ** 2))
    after_o = np.sqrt(np.mean((fixed_o - uncoded) ** 2))
    assert before > 4 * noise
    assert after_s < noise and after_o < noise
    # Mean bias well under the noise: the calibration error does not leave a faint copy.
    assert abs(np.mean(fixed_s - coded)) < 0.1 * noise


def test_calibration_roundtrip(tmp_path, calibration):
    cal, _ = calibration
    path = cal.save(tmp_path / "calib.npz")
    back = dp.CrosstalkCalibration.load(path)
    np.testing.assert_array_equal(back.ratio, cal.ratio)
    assert back.stored_view_half == "right" and back.cfa_pattern == "RGGB"


def test_split_views_and_saturation():
    s = np.array([[100.0, 4095.0], [4095.0, 50.0], [4095.0, 4095.0]])
    v = np.array([[30.0, 2000.0], [4095.0, 20.0], [1000.0, 3000.0]])
    stored, other, sat = dp.split_views(s, v)  # 4 pixels pile at 4095: read as saturation
    assert sat.sum() == 4
    np.testing.assert_array_equal(stored[~sat], [30.0, 20.0])
    np.testing.assert_array_equal(other[~sat], [70.0, 30.0])
    np.testing.assert_array_equal(stored[sat], other[sat])
    np.testing.assert_array_equal((stored + other), s)
    stored, other, sat = dp.split_views(s, v, saturation=5000, black_level=10)
    assert not sat.any()
    assert other[0, 0] == 70.0 and stored[0, 0] == 20.0


def test_bad_frames_raise():
    with pytest.raises(DoeError, match="same size"):
        dp.split_views(np.ones((4, 6)), np.ones((4, 5)), name="a.tif")
    with pytest.raises(DoeError, match="brighter than the sum"):
        dp.split_views(np.full((8, 8), 100.0), np.full((8, 8), 150.0), saturation=1e6, name="a.tif")
    with pytest.raises(DoeError, match="unknown CFA"):
        dp.cfa_channels((4, 4), "RGBW")


def test_calibration_rejects_same_half_twice():
    rng = np.random.default_rng(0)
    left = frames(wall(), np.zeros((ROWS, COLS)), true_ratios(), rng)
    with pytest.raises(DoeError, match="one half of the aperture"):
        dp.calibrate_crosstalk(left, left)


def test_load_frame_formats(tmp_path):
    a = np.arange(12, dtype=np.uint16).reshape(3, 4)
    tifffile.imwrite(tmp_path / "f.tif", a)
    np.save(tmp_path / "f.npy", a)
    np.testing.assert_array_equal(dp.load_frame(tmp_path / "f.tif"), a)
    np.testing.assert_array_equal(dp.load_frame(tmp_path / "f.npy"), a)
    with pytest.raises(DoeError, match="no such file"):
        dp.load_frame(tmp_path / "missing.tif")
    np.save(tmp_path / "cube.npy", np.zeros((2, 3, 4)))
    with pytest.raises(DoeError, match="2-D"):
        dp.load_frame(tmp_path / "cube.npy")


def test_raw_file_without_rawpy_says_install(tmp_path, monkeypatch):
    import builtins

    real_import = builtins.__import__

    def no_rawpy(name, *args, **kwargs):
        if name == "rawpy":
            raise ImportError("no rawpy")
        return real_import(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", no_rawpy)
    (tmp_path / "x.CR2").write_bytes(b"\0" * 16)
    with pytest.raises(DoeError, match="install it"):
        dp.load_frame(tmp_path / "x.CR2")


@pytest.mark.parametrize("pattern", ["RGGB", "BGGR", "GRBG"])
def test_bilinear_demosaic_exact_on_linear_ramps(pattern):
    # Bilinear interpolation reproduces any planar intensity exactly away from the border.
    r, c = np.mgrid[:16, :20].astype(float)
    planes = [1 + 0.5 * r + 0.2 * c, 3 + 0.1 * r - 0.05 * c, 2 + 0.3 * c]
    ch = dp.cfa_channels(r.shape, pattern)
    colour = np.array([0, 1, 1, 2])[ch]
    mosaic = np.choose(colour, planes)
    rgb = dp.demosaic_bilinear(mosaic, pattern)
    for k in range(3):
        np.testing.assert_allclose(rgb[1:-1, 1:-1, k], planes[k][1:-1, 1:-1], atol=1e-12)


def test_grey_world_white_balance_from_uncoded_view():
    rng = np.random.default_rng(1)
    scene = rng.uniform(0.2, 1.0, (10, 12))[..., None] * np.ones(3)
    tint = np.array([0.5, 1.0, 0.8])
    coded, uncoded, gains = dp.white_balance(scene * tint * 0.7, scene * tint)
    np.testing.assert_allclose(gains, 1 / tint)
    np.testing.assert_allclose(uncoded, scene, rtol=1e-12)
    np.testing.assert_allclose(coded, 0.7 * scene, rtol=1e-12)


def test_mosaic_channel_gains_flatten_a_narrowband_capture():
    ch = dp.cfa_channels((8, 8), "RGGB")
    response = np.array([0.1, 0.6, 0.62, 0.9])
    irradiance = np.linspace(1, 2, 64).reshape(8, 8)
    mono = dp.apply_channel_gains(irradiance * response[ch], dp.mosaic_channel_gains(irradiance * response[ch]))
    # Flat to within the irradiance variation between the channels' sites (a smooth ramp).
    assert np.abs(mono / irradiance / np.mean(mono / irradiance) - 1).max() < 0.05


def test_cli_crosstalk(tmp_path, capsys):
    from doedesign.cli import main

    rng = np.random.default_rng(5)
    ratio = true_ratios()
    paths = []
    for tag, (s_true, o_true) in {"left": (wall(), np.zeros((ROWS, COLS))),
                                  "right": (np.zeros((ROWS, COLS)), wall())}.items():
        s, v = frames(s_true, o_true, ratio, rng)
        tifffile.imwrite(tmp_path / f"{tag}_sum.tif", s.astype(np.float32))
        tifffile.imwrite(tmp_path / f"{tag}_view.tif", v.astype(np.float32))
        paths.append([str(tmp_path / f"{tag}_sum.tif"), str(tmp_path / f"{tag}_view.tif")])
    out = tmp_path / "calib.npz"
    code = main(["calibrate", "crosstalk", "--left-blocked", *paths[0], "--right-blocked", *paths[1],
                 "--out", str(out), "--png", str(tmp_path / "calib.png")])
    assert code == 0 and (tmp_path / "calib.png").stat().st_size > 0
    cal = dp.CrosstalkCalibration.load(out)
    ch = dp.cfa_channels((2, COLS))
    cols = np.flatnonzero((ch == 3).any(axis=0))
    np.testing.assert_allclose(cal.ratio[1, 3, cols], ratio[1, 3, cols], rtol=0.01)
    # Frames of different sizes: one clean line, exit 2, no output file.
    np.save(tmp_path / "small.npy", np.ones((ROWS, COLS - 2)))
    bad = tmp_path / "bad.npz"
    code = main(["calibrate", "crosstalk", "--left-blocked", paths[0][0], str(tmp_path / "small.npy"),
                 "--right-blocked", *paths[1], "--out", str(bad)])
    err = capsys.readouterr().err
    assert code == 2 and "same size" in err and "Traceback" not in err and not bad.exists()
