"""The design file, materials and the `doe inspect` / `doe psf` commands."""

import json

import numpy as np
import pytest

from doedesign import materials
from doedesign.cli import main
from doedesign.design import Design
from doedesign.engine.psf import PSFResult
from doedesign.errors import DesignFileError, DoeError, MaterialError
from doedesign.spectra import bandpass, gaussian_band, rgb_response


@pytest.mark.parametrize("nm,n", [(400, 1.47012), (500, 1.46233), (550, 1.45991), (600, 1.45804), (700, 1.45529)])
def test_fused_silica_malitson(nm, n):
    assert materials.FUSED_SILICA.n(nm * 1e-9) == pytest.approx(n, abs=5e-6)


def test_two_pi_height_and_level_step():
    h2pi = materials.FUSED_SILICA.height_2pi_m(550e-9)
    assert h2pi * 1e9 == pytest.approx(1195.9, abs=0.05)
    assert h2pi / 16 * 1e9 == pytest.approx(74.74, abs=0.01)


def test_phase_from_heights_not_wrapped_phase():
    # A height of 1.5 two-pi steps at 550 nm keeps its full phase at 450 nm (no wrapping loss).
    h = -1.5 * materials.FUSED_SILICA.height_2pi_m(550e-9)
    phi = materials.FUSED_SILICA.phase(h, 450e-9)
    expected = 2 * np.pi * (materials.FUSED_SILICA.n(450e-9) - 1) * h / 450e-9
    assert phi == pytest.approx(expected)
    assert abs(phi) > 2 * np.pi * 1.5


def test_user_materials():
    m = materials.cauchy("test_cauchy", (1.5, 0.004), 400e-9, 800e-9)
    assert m.n(500e-9) == pytest.approx(1.5 + 0.004 / 0.25)
    t = materials.table("test_table", [400e-9, 700e-9], [1.6, 1.5])
    assert t.n(550e-9) == pytest.approx(1.55)
    s = materials.sellmeier("test_sellmeier", (1.0,), (0.1,), 300e-9, 1e-6)
    assert s.n(500e-9) == pytest.approx(np.sqrt(1 + 0.25 / (0.25 - 0.01)))
    assert materials.get_material("test_table") is t
    with pytest.raises(MaterialError, match="already registered"):
        materials.table("test_table", [400e-9, 700e-9], [1.6, 1.5])
    with pytest.raises(MaterialError, match="outside the valid range"):
        t.n(900e-9)
    with pytest.raises(MaterialError, match="unknown material"):
        materials.get_material("unobtainium")


def test_design_round_trip(tmp_path):
    rng = np.random.default_rng(0)
    levels = rng.integers(0, 16, (20, 30)).astype(np.int16)
    d = Design(-levels * 74.74e-9, 5.4e-6, levels=levels, aperture=np.ones((20, 30), bool),
               metadata={"name": "t", "target": "bayer"})
    path = d.save(tmp_path / "d.npz")
    back = Design.load(path)
    np.testing.assert_array_equal(back.height_m, d.height_m)
    np.testing.assert_array_equal(back.levels, levels)
    assert back.metadata["format_version"] == 1 and back.metadata["target"] == "bayer"
    # numpy alone reads it
    with np.load(path) as raw:
        assert raw["height_m"].dtype == np.float64 and float(raw["pitch_m"]) == 5.4e-6


@pytest.mark.parametrize("change,message", [
    (dict(height_m=np.full((4, 4), np.nan)), "NaN"),
    (dict(pitch_m=0.0), "pitch_m"),
    (dict(pitch_m=5.4), "metres"),
    (dict(material="unobtainium"), "material"),
    (dict(levels=np.zeros((3, 3), int)), "levels has shape"),
    (dict(levels=np.full((4, 4), 1.5)), "levels must be integers"),
])
def test_design_validation(change, message):
    kwargs = dict(height_m=np.zeros((4, 4)), pitch_m=5.4e-6)
    kwargs.update(change)
    with pytest.raises(DesignFileError, match=message):
        Design(**kwargs)


def test_broken_and_foreign_files(tmp_path):
    (tmp_path / "junk.npz").write_bytes(b"not a zip")
    with pytest.raises(DesignFileError, match="junk.npz"):
        Design.load(tmp_path / "junk.npz")
    np.savez(tmp_path / "foreign.npz", image=np.zeros(3))
    with pytest.raises(DesignFileError, match="missing field"):
        Design.load(tmp_path / "foreign.npz")
    np.savez(tmp_path / "meta.npz", height_m=np.zeros((2, 2)), pitch_m=5.4e-6, material="fused_silica",
             design_wavelength_m=550e-9, metadata="{not json")
    with pytest.raises(DesignFileError, match="metadata"):
        Design.load(tmp_path / "meta.npz")


def test_cli_inspect_design(tmp_path, capsys):
    step = Design(np.zeros((1, 1)), 5.4e-6).height_2pi_m() / 16
    d = Design(-np.arange(12.0).reshape(3, 4) * step, 5.4e-6, levels=np.arange(12).reshape(3, 4),
               metadata={"name": "ramp"})
    d.save(tmp_path / "ramp.npz")
    assert main(["inspect", str(tmp_path / "ramp.npz"), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["shape"] == [3, 4] and out["pitch_m"] == 5.4e-6
    assert out["height_min_m"] == pytest.approx(-11 * step) and out["height_max_m"] == 0.0
    assert out["levels"]["used"] == list(range(12))


def test_cli_psf_writes_documented_file(tmp_path, capsys):
    n = 32
    d = Design(np.zeros((n, n)), 5.4e-6, metadata={"name": "flat"})
    d.save(tmp_path / "flat.npz")
    rc = main(["psf", str(tmp_path / "flat.npz"), "--wavelengths-nm", "450:650:100", "--aperture-mm", "0",
               "--side", "full", "--window", "64", "--out", str(tmp_path / "psf.npz"), "--png", str(tmp_path / "psf.png")])
    assert rc == 0
    res = PSFResult.load(tmp_path / "psf.npz")
    assert res.psf.shape == (2, 1, 3, 64, 64)
    assert res.views == ("coded", "uncoded")
    np.testing.assert_allclose(res.wavelengths_m, [450e-9, 550e-9, 650e-9])
    # A flat full-aperture DOE: coded and uncoded views are identical and peak on the axis.
    np.testing.assert_allclose(res.psf[0], res.psf[1], atol=1e-15)
    assert np.unravel_index(res.psf[0, 0, 1].argmax(), (64, 64)) == (32, 32)
    assert (tmp_path / "psf.png").stat().st_size > 1000


def test_cli_errors_are_one_line(tmp_path, capsys):
    assert main(["psf", str(tmp_path / "missing.npz"), "--out", str(tmp_path / "o.npz")]) == 2
    err = capsys.readouterr().err
    assert "missing.npz" in err and "Traceback" not in err
    d = Design(np.zeros((8, 8)), 5.4e-6)
    d.save(tmp_path / "d.npz")
    assert main(["psf", str(tmp_path / "d.npz"), "--wavelengths-nm", "5000", "--out", str(tmp_path / "o.npz")]) == 2
    assert "outside the valid range" in capsys.readouterr().err
    assert not (tmp_path / "o.npz").exists()


def test_spectra_and_polychromatic():
    wl = np.linspace(400e-9, 700e-9, 31)
    g = gaussian_band(wl, 550e-9, 20e-9)
    assert g.max() == 1 and wl[g.argmax()] == pytest.approx(550e-9)
    # FWHM: the half-maximum points are 20 nm apart.
    fine = np.linspace(500e-9, 600e-9, 10001)
    above = fine[gaussian_band(fine, 550e-9, 20e-9) >= 0.5]
    assert above[-1] - above[0] == pytest.approx(20e-9, rel=1e-3)
    assert bandpass(wl, 450e-9, 500e-9).sum() == 6
    rgb = rgb_response(wl)
    assert [wl[i] * 1e9 for i in rgb.argmax(axis=1)] == [600, 530, 460]
    res = PSFResult(psf=np.arange(2 * 1 * 3 * 2 * 2, dtype=float).reshape(2, 1, 3, 2, 2), views=("coded", "uncoded"),
                    wavelengths_m=np.array([1, 2, 3]) * 1e-7, depths_m=np.array([5.0]), pixel_pitch_m=5.4e-6)
    poly = res.polychromatic([1, 0, 1])
    np.testing.assert_allclose(poly, 0.5 * (res.psf[:, :, 0] + res.psf[:, :, 2]))
    with pytest.raises(DoeError):
        res.polychromatic([1, -1, 0])
