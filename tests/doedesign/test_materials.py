"""Fused silica against Malitson (1965) and the 2 pi height against the phase formula."""

import numpy as np
import pytest

from doedesign.errors import MaterialError
from doedesign.materials import FUSED_SILICA, Material, cauchy, get_material, table

# optics-and-fabrication.md: Malitson 1965, 20 C
MALITSON = {400: 1.47012, 500: 1.46233, 550: 1.45991, 600: 1.45804, 700: 1.45529}


@pytest.mark.parametrize("nm, n", sorted(MALITSON.items()))
def test_fused_silica_matches_malitson(nm, n):
    assert FUSED_SILICA.n(nm * 1e-9) == pytest.approx(n, abs=2e-5)


def test_dispersion_is_normal_and_two_pi_height_published():
    wl = np.linspace(400e-9, 700e-9, 31)
    assert np.all(np.diff(FUSED_SILICA.n(wl)) < 0)
    assert FUSED_SILICA.height_2pi_m(550e-9) == pytest.approx(1195.9e-9, abs=0.1e-9)
    # phase = 2 pi (n - 1) h / lambda: the 2 pi height gives 2 pi at every wavelength
    for w in (450e-9, 550e-9, 650e-9):
        assert FUSED_SILICA.phase(FUSED_SILICA.height_2pi_m(w), w) == pytest.approx(2 * np.pi, rel=1e-12)


def test_cauchy_and_table_materials():
    c = cauchy("test_cauchy_h15", (1.5, 0.004), 400e-9, 700e-9)
    assert c.n(500e-9) == pytest.approx(1.5 + 0.004 / 0.25)
    t = table("test_table_h15", [400e-9, 600e-9], [1.6, 1.5])
    assert t.n(500e-9) == pytest.approx(1.55)
    assert get_material("test_table_h15") is t


def test_material_errors():
    with pytest.raises(MaterialError, match="outside the valid range"):
        FUSED_SILICA.n(5e-6)
    with pytest.raises(MaterialError, match="unknown material"):
        get_material("unobtainium")
    with pytest.raises(MaterialError, match="positive"):
        FUSED_SILICA.n(-1.0)
    with pytest.raises(MaterialError, match="increasing"):
        table("bad_table_h15", [600e-9, 400e-9], [1.5, 1.6])
    assert isinstance(get_material(FUSED_SILICA), Material)
