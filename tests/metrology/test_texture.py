"""Surface texture figures (metrology.matching.texture) against analytic surfaces and a second
implementation: a sinusoid's Sq = A / sqrt(2), Sa = 2 A / pi, Sz = 2 A; Parseval for the bands."""

import numpy as np
import pytest

from metrology.matching.texture import band_rms, field_texture, height_parameters, residual_psd

PX = 1e-6
A = 5e-9


def _sine(period_px, amp=A, shape=(128, 128), axis=1, phase=0.3):
    r, c = np.mgrid[:shape[0], :shape[1]]
    x = c if axis == 1 else r
    return amp * np.sin(2 * np.pi * x / period_px + phase)


def test_sinusoid_height_parameters_are_analytic():
    p = height_parameters(_sine(64), PX)
    assert p["Sq_m"] == pytest.approx(A / np.sqrt(2), rel=1e-3)
    assert p["Sa_m"] == pytest.approx(2 * A / np.pi, rel=2e-3)
    assert p["Sz_m"] == pytest.approx(2 * A, rel=2e-3)


def test_sq_through_surfacetopography_matches_numpy_on_a_mask():
    rng = np.random.default_rng(1)
    h = rng.normal(0, 2e-9, (90, 70)) + 1e-7
    h[3, 4] = np.nan
    mask = rng.random(h.shape) < 0.3
    p = height_parameters(h, PX, mask)
    z = h[mask & np.isfinite(h)]
    assert p["pixels"] == z.size
    assert p["Sq_m"] == pytest.approx(np.std(z), rel=1e-9)
    assert p["Sa_m"] == pytest.approx(np.mean(np.abs(z - z.mean())), rel=1e-12)
    assert p["Sz_m"] == pytest.approx(np.ptp(z), rel=1e-12)
    assert height_parameters(h, PX, np.zeros(h.shape, bool))["Sq_m"] is None


def test_band_rms_separates_two_sinusoids_and_sums_to_the_variance():
    h = _sine(32) + _sine(4, amp=0.5 * A, axis=0)      # 32 um along x, 4 um along y
    short, long_, form = band_rms(h, PX, [(0, 8e-6), (8e-6, 1e-3), (1e-3, np.inf)])
    assert short == pytest.approx(0.5 * A / np.sqrt(2), rel=0.02)
    assert long_ == pytest.approx(A / np.sqrt(2), rel=0.02)
    assert form < 0.01 * A
    # Parseval: the bands tile every wavelength; with the Hann window normalised to unit mean square.
    total = np.sqrt(short ** 2 + long_ ** 2 + form ** 2)
    assert total == pytest.approx(np.sqrt((A ** 2 + (0.5 * A) ** 2) / 2), rel=0.02)


def test_psd_peaks_at_the_sinusoid():
    q, c = residual_psd(_sine(16, shape=(256, 256)), PX)
    assert 2 * np.pi / q[np.argmax(c)] == pytest.approx(16e-6, rel=0.15)


def test_field_texture_per_level_and_residual():
    rng = np.random.default_rng(2)
    labels = np.kron(rng.integers(0, 2, (6, 6)), np.ones((16, 16), int))
    noise = np.where(labels == 0, 1e-9, 3e-9)
    height = -100e-9 * labels + noise * rng.standard_normal(labels.shape)
    tex = field_texture(height, labels, np.ones(labels.shape, bool), height + 100e-9 * labels, PX, 5.4e-6, 2)
    assert tex.levels[0]["Sq_m"] == pytest.approx(1e-9, rel=0.05)
    assert tex.levels[1]["Sq_m"] == pytest.approx(3e-9, rel=0.05)
    rep = tex.report()
    assert rep["residual"]["Sq_nm"] == pytest.approx(np.std(height + 100e-9 * labels) * 1e9, rel=1e-9)
    assert [b["wavelength_to_um"] for b in rep["residual"]["bands"]] == pytest.approx([5.4, 54.0, None])
