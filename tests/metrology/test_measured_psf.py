"""PSF from measured heights against the scalar theory of a too-deep blazed grating."""

import numpy as np
import pytest

from doedesign.camera import Camera
from doedesign.design import Design
from doedesign.levels import level_step_m
from masks.process import ProcessParams
from metrology.matching.measured_psf import compare_psf, target_from_psf

PITCH = 5.4e-6
N = 16


def _grating(n_px=64):
    levels = np.tile(N - 1 - np.arange(n_px) % N, (n_px, 1)).astype(np.int16)  # phase rises with column
    cam = Camera(aperture_diameter_m=None, doe_side="full", window_shape=(32, 128), axis_pixel=(16, 32),
                 focus_distance_m=np.inf)
    step = level_step_m("fused_silica", 550e-9)
    return Design(height_m=-levels * step, pitch_m=PITCH, levels=levels,
                  metadata={"name": "blazed", "camera": cam.to_dict()}), step


def _first_order_efficiency(a, n=N):
    """eta_1 of an n-level staircase whose 2 pi step is scaled by ``a`` (optics reference)."""
    x = a - 1
    return np.sinc(1 / n) ** 2 * (1.0 if abs(x) < 1e-12 else (np.sin(np.pi * x) / (n * np.sin(np.pi * x / n))) ** 2)


def test_target_holds_the_requested_share():
    psf = np.array([[[0.5, 0.3], [0.15, 0.05]]])
    np.testing.assert_array_equal(target_from_psf(psf, 0.8)[0], [[True, True], [False, False]])
    np.testing.assert_array_equal(target_from_psf(psf, 0.81)[0], [[True, True], [True, False]])


@pytest.mark.parametrize("scale", [1.0, 1.1, 0.85])
def test_over_and_under_etch_lose_the_light_scalar_theory_predicts(scale):
    design, step = _grating()
    params = ProcessParams.ideal().copy(etch_depth=step * np.array([1, 2, 4, 8]) * scale)
    cmp = compare_psf(design, params, wavelengths_m=[550e-9], oversample=1)
    expected = _first_order_efficiency(scale) / _first_order_efficiency(1.0)
    assert cmp.measured_on_target[0] / cmp.design_on_target[0] == pytest.approx(expected, abs=0.01)
    # The first order sits about 59 px right of the axis (x = lambda z / period).
    col = np.argmax(cmp.design_psf[0].sum(axis=0))
    assert col - 32 == pytest.approx(550e-9 * 50e-3 / (N * PITCH) / PITCH, abs=1.5)


@pytest.fixture(scope="module")
def small_demo_design(tmp_path_factory):
    """The demo's design step at a 64-pixel aperture: a Bayer (RGGB) element, its report and file."""
    from metrology import pipeline

    out = tmp_path_factory.mktemp("demo_design")
    cfg = pipeline.DemoConfig(doe_px=64, iterations=4, anneal_iterations=1, window=64, rggb=True)
    run = pipeline.design_step(cfg, pipeline.demo_camera(cfg), out)
    return run, Design.load(out / "design.npz")


def test_comparison_reports_the_design_reports_figure_of_merit(small_demo_design):
    """One figure of merit per design: the comparison counts the light on the design's own Bayer
    target, at its R, G, B wavelengths, and for the same heights gets the design report's numbers
    (the demo's design section); the design PSF's core (90 % of its light) is another quantity."""
    run, design = small_demo_design
    design_section = np.array(run.report["quantized"]["energy_on_target"][0])
    res = compare_psf(design, ProcessParams.ideal(), oversample=1)
    assert res.target_source == "design_target" and res.merit_name == "light on the design's target"
    np.testing.assert_allclose(res.wavelengths_m, [656e-9, 589e-9, 486e-9])
    np.testing.assert_allclose(res.design_on_target, design_section, rtol=1e-9)
    # RGGB: green counts on two pixels, red and blue on one.
    assert res.target.sum(axis=(1, 2)).tolist() == [1, 2, 1]
    rep = res.report()
    assert rep["merit"]["name"] == "light on the design's target" and "design_in_psf_core" not in rep
    np.testing.assert_allclose(rep["design_on_target"], design_section, rtol=1e-9)
    core = target_from_psf(res.design_psf)
    assert np.all(np.array([p[t].sum() for p, t in zip(res.design_psf, core)]) > 5 * design_section)


def test_a_design_without_target_gets_the_psf_core_under_its_own_name(small_demo_design):
    _, design = small_demo_design
    bare = Design(height_m=design.height_m, pitch_m=design.pitch_m, levels=design.levels,
                  metadata={"name": "bare", "camera": design.metadata["camera"]})
    res = compare_psf(bare, ProcessParams.ideal(), oversample=1)
    assert res.target_source == "psf_core"
    rep = res.report()
    assert rep["merit"]["name"] == "light in the design PSF's core" and "design_on_target" not in rep
    # The brightest pixels holding 90 % of the window's light (to within the last pixel added).
    np.testing.assert_allclose(rep["design_in_psf_core"], 0.9 * res.design_in_window, atol=0.01)
    # Wavelengths the design's target does not have cannot be counted on it either.
    other = compare_psf(design, ProcessParams.ideal(), wavelengths_m=(550e-9,), oversample=1)
    assert other.target_source == "psf_core"
