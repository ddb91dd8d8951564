"""The surround convention (issue 51): what lies around a design inside the lens aperture.

The light a flat design passes is, by energy conservation, the open area of the coded
half-pupil over its whole area. Those areas are computed here from the circle itself (the
integral of its chord over the open rows, in closed form), not from the engine's samples;
the light is read from the PSFs on a window wide enough to hold all of it.
"""

import json

import numpy as np
import pytest

from doedesign.camera import Camera
from doedesign.cli import main
from doedesign.design import Design
from doedesign.engine.psf import PSFEngine, PSFResult

PITCH = 5.4e-6
N = 128                 # design pixels per side (0.69 mm)
DIAMETER = 2.0e-3       # lens aperture: the design is far smaller
STRIPE = 32             # closed and open bands of 32 rows in the "stripes" aperture
# 50 um sensor pixels, 256 of them: a 12.8 mm window holding every order of the 173 um bands.
CAMERA = Camera(aperture_diameter_m=DIAMETER, pixel_pitch_m=50e-6, window_shape=(256, 256), axis_pixel=(128, 128),
                focus_distance_m=np.inf)
WL = 550e-9


def _chord_area(y0, y1, r):
    """Area of the left half-disc of radius ``r`` between heights y0 < y1 (closed form)."""
    def f(y):
        y = np.clip(y, -r, r)
        return 0.5 * (y * np.sqrt(r * r - y * y) + r * r * np.arcsin(y / r))
    return f(y1) - f(y0)


def _grid():
    n_ap = DIAMETER / PITCH
    g = int(np.ceil(n_ap))
    return g, (g - N) // 2


def _closed_rows(kind):
    """Closed pupil-grid rows (a row's centre band) of the aperture ``kind`` under each convention."""
    g, off = _grid()
    rows = np.arange(g)
    design_row = rows - off
    inside = (design_row >= 0) & (design_row < N)
    closed_in_design = np.ones(g, bool) if kind == "closed" else (np.mod(design_row, 2 * STRIPE) < STRIPE)
    return g, inside, closed_in_design


def _expected(kind, surround):
    """Open fraction of the coded (left) half-pupil: integrals of the circle over open row bands."""
    r = DIAMETER / 2
    g, inside, closed = _closed_rows(kind)
    y = (np.arange(g) - (g - 1) / 2) * PITCH
    half_disc = np.pi * r * r / 2
    # The design covers columns [off, off + N), half of them left of the axis: N/2 px wide.
    design_w = N / 2 * PITCH
    blocked = 0.0
    for i in range(g):
        band = _chord_area(y[i] - PITCH / 2, y[i] + PITCH / 2, r)
        strip = min(band, design_w * PITCH)  # the design's part of this row (wholly inside the disc)
        if surround == "open":
            blocked += strip if (inside[i] and closed[i]) else 0.0
        elif surround == "opaque":
            blocked += band - (strip if inside[i] and not closed[i] else 0.0)
        else:  # repeat: the row pattern continues over the whole row of the half-disc
            blocked += band if closed[i] else 0.0
    return 1.0 - blocked / half_disc


def _aperture(kind):
    ap = np.ones((N, N), bool)
    if kind == "closed":
        ap[:] = False
    else:
        ap[np.mod(np.arange(N), 2 * STRIPE) < STRIPE, :] = False
    return ap


@pytest.mark.parametrize("kind", ["closed", "stripes"])
@pytest.mark.parametrize("surround", ["open", "opaque", "repeat"])
def test_passed_light_is_the_open_area_of_the_half_pupil(kind, surround):
    engine = PSFEngine(CAMERA, PITCH, (N, N), wavelengths_m=[WL], aperture=_aperture(kind), surround=surround)
    expected = _expected(kind, surround)
    if kind == "stripes" and surround == "repeat":
        assert _expected("stripes", "repeat") == pytest.approx(0.5, abs=0.05)  # the bands' duty cycle
    if surround == "open":
        # The 1 mm design's closed part: (N px)^2 / 2 against the half-disc of 2 mm.
        closed = 1.0 if kind == "closed" else 0.5
        assert expected == pytest.approx(1 - closed * (N * PITCH) ** 2 / 2 / (np.pi * (DIAMETER / 2) ** 2 / 2),
                                         abs=2e-3)
    result = engine.psf(np.zeros((N, N)), views=("coded",))
    passed = float(result.energy_in_window[0, 0, 0])
    assert passed == pytest.approx(expected, abs=5e-3)
    assert engine.clear_fraction == pytest.approx(expected, abs=2e-3)
    assert result.surround == surround and result.coded_clear_fraction == pytest.approx(engine.clear_fraction)


def test_all_closed_design_filling_the_aperture_passes_no_light():
    """A design that fills the pupil (square pupil on its grid) has no surround: closed is dark."""
    cam = Camera(aperture_diameter_m=None, window_shape=(64, 64), axis_pixel=(32, 32))
    for surround in ("open", "opaque", "repeat"):
        engine = PSFEngine(cam, PITCH, (32, 32), wavelengths_m=[WL], aperture=np.zeros((32, 32), bool),
                           surround=surround)
        assert engine.clear_fraction == 0.0
        assert np.all(engine.psf(np.zeros((32, 32)), views=("coded",)).psf == 0)


def test_repeat_tiles_the_heights_the_gradient_folds_back():
    """A repeated design equals the same design tiled by hand on the full grid (open surround),
    and its gradient is the tiled one summed over the tiles."""
    g, off = _grid()
    cam = Camera(aperture_diameter_m=DIAMETER, window_shape=(48, 48), axis_pixel=(24, 24))
    rng = np.random.default_rng(0)
    n = 40
    h = -rng.integers(0, 16, (n, n)) * 76e-9
    off = (g - n) // 2
    idx = np.mod(np.arange(g) - off, n)
    full = h[np.ix_(idx, idx)]
    rep = PSFEngine(cam, PITCH, (n, n), wavelengths_m=[WL], surround="repeat")
    big = PSFEngine(cam, PITCH, (g, g), wavelengths_m=[WL])
    np.testing.assert_allclose(rep.psf(h, views=("coded",)).psf, big.psf(full, views=("coded",)).psf, atol=1e-12)

    def loss(psf):
        w = np.linspace(0, 1, psf.size).reshape(psf.shape)
        return float(np.sum(w * psf)), w

    _, g_rep = rep.value_and_grad(h, loss, full_window=True)
    _, g_big = big.value_and_grad(full, loss, full_window=True)
    folded = np.zeros((n, n))
    np.add.at(folded, (idx[:, None], idx[None, :]), g_big)
    np.testing.assert_allclose(g_rep, folded, rtol=1e-9, atol=1e-9 * np.abs(folded).max())


def test_psf_command_writes_and_inspect_shows_the_surround(tmp_path, capsys):
    cam = Camera(aperture_diameter_m=DIAMETER, window_shape=(64, 64), axis_pixel=(32, 32))
    design = tmp_path / "d.npz"
    Design(np.zeros((N, N)), PITCH, aperture=np.zeros((N, N), bool),
           metadata={"name": "closed", "camera": cam.to_dict(), "surround": "opaque"}).save(design)
    # The design file's convention, then the option over it, then the default when neither says.
    assert main(["psf", str(design), "--out", str(tmp_path / "a.npz"), "--wavelengths-nm", "550", "--window", "64",
                 "--aperture-mm", "2"]) == 0
    a = PSFResult.load(tmp_path / "a.npz")
    assert a.surround == "opaque" and a.coded_clear_fraction == 0 and a.psf[0].sum() == 0
    assert main(["psf", str(design), "--out", str(tmp_path / "b.npz"), "--wavelengths-nm", "550", "--window", "64",
                 "--aperture-mm", "2", "--surround", "open"]) == 0
    b = PSFResult.load(tmp_path / "b.npz")
    assert b.surround == "open" and b.coded_clear_fraction == pytest.approx(_expected("closed", "open"), abs=2e-3)
    capsys.readouterr()
    assert main(["inspect", str(tmp_path / "b.npz"), "--json"]) == 0
    shown = json.loads(capsys.readouterr().out)
    assert shown["kind"] == "psf" and shown["surround"] == "open" and "open glass" in shown["surround_means"]
    assert shown["coded_clear_fraction"] == pytest.approx(b.coded_clear_fraction)
    assert main(["inspect", str(design), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["surround"] == "opaque"


def test_a_design_file_with_an_unknown_surround_is_refused(tmp_path, capsys):
    design = tmp_path / "d.npz"
    Design(np.zeros((8, 8)), PITCH, metadata={"name": "x", "surround": "mirror"}).save(design)
    assert main(["inspect", str(design)]) == 2
    err = capsys.readouterr().err.strip()
    assert "metadata surround" in err and "mirror" in err and "\n" not in err
