"""The effect registry: built-in names, user registration, and each effect against physics."""

import numpy as np
import pytest
from scipy.special import erf

from metrology.diagnosis import effects as fx
from metrology.diagnosis import psf_effects
from metrology.diagnosis.effects import Effect, EffectError, Parameter, get_effect, register_effect

BUILTIN = {"etch_depth", "mask_overlay", "linewidth_bias", "proximity_blur", "proximity_print", "sidewall_slope", "etch_loading",
           "mask_rotation", "microtrenching", "etch_gradient", "instrument_blur", "batwing", "dual_pixel_crosstalk", "source_bandwidth", "defocus", "depth_scale",
           "background"}


def test_builtin_names_domains_and_artefacts():
    assert BUILTIN <= set(fx.REGISTRY)
    assert {e.name for e in fx.effects_for("height")} >= {"etch_depth", "mask_overlay", "linewidth_bias",
                                                          "proximity_blur", "sidewall_slope", "etch_loading",
                                                          "mask_rotation", "microtrenching", "etch_gradient",
                                                          "instrument_blur", "batwing"}
    assert {e.name for e in fx.effects_for("psf")} >= {"dual_pixel_crosstalk", "source_bandwidth", "defocus",
                                                       "depth_scale", "background"}
    artefacts = {n for n in BUILTIN if get_effect(n).kind == "artefact"}
    assert artefacts == {"instrument_blur", "batwing"}
    for name in BUILTIN:
        e = get_effect(name)
        assert e.description.endswith(".") and len(e.description) > 30
        lo, hi = e.bounds()
        assert np.all(lo <= e.null_values()) and np.all(e.null_values() <= hi)
        assert np.all(lo <= e.start_values()) and np.all(e.start_values() <= hi)


def test_rivals_are_registered_symmetric_and_of_one_domain():
    # The backward pass swaps a named effect for its rivals (another form of the same cause);
    # a one-sided or misspelt rival would leave the wrong form's first pick standing.
    rivals = {n: get_effect(n).rivals for n in BUILTIN if get_effect(n).rivals}
    assert rivals["proximity_blur"] == ("proximity_print",)
    for name, others in rivals.items():
        for other in others:
            assert name in get_effect(other).rivals, (name, other)
            assert get_effect(other).domain == get_effect(name).domain


def test_user_registration_decorator_and_object():
    @register_effect(name="test_piston_tilt", domain="height", stage="surface",
                     params=[Parameter("slope", "rad", -1e-3, 1e-3, 1e-4)],
                     description="A residual slope the levelling missed.")
    def tilt(height_m, values, step_m):
        return height_m + values[0] * step_m * np.arange(height_m.shape[1])[None, :]

    try:
        e = get_effect("test_piston_tilt")
        out = e.apply(np.zeros((2, 3)), e.check([1e-4]), 1e-6)
        assert np.allclose(out[1], [0, 1e-10, 2e-10])
        with pytest.raises(EffectError, match="already registered"):
            register_effect(e)
        assert "test_piston_tilt" in {x.name for x in fx.effects_for("height")}
    finally:
        fx.unregister_effect("test_piston_tilt")
    with pytest.raises(EffectError, match="unknown effect"):
        get_effect("test_piston_tilt")
    with pytest.raises(EffectError, match="stage"):
        Effect("bad", "height", "sensor", [Parameter("a", "1", 0, 1, 0.1)], lambda *a: None, "Bad.")
    with pytest.raises(EffectError, match="takes 4 values"):
        get_effect("etch_depth").check([0.1])


def test_instrument_blur_of_a_step_is_an_erf():
    step_m, sigma = 0.02e-6, 0.8e-6
    x = (np.arange(800) - 399.5) * step_m
    h = np.tile(np.where(x > 0, 1.0, 0.0), (8, 1))
    out = fx.gaussian_blur(h, sigma, step_m)[4]
    expect = 0.5 * (1 + erf(x / (sigma * np.sqrt(2))))
    centre = np.abs(x) < 4e-6
    assert np.max(np.abs(out[centre] - expect[centre])) < 2e-3


def test_batwing_is_signed_edge_overshoot_proportional_to_step():
    step_m, sigma, amp = 0.02e-6, 0.6e-6, 0.2
    x = (np.arange(1000) - 499.5) * step_m
    for height in (100e-9, 600e-9):
        h = np.tile(np.where(x > 0, height, 0.0), (4, 1))
        b = fx.batwing_profile(h, amp, sigma, step_m)[2]
        # Overshoot of amp * H on the high side at x = sigma, undershoot as deep on the low side.
        assert b.max() == pytest.approx(amp * height, rel=0.01)
        assert x[np.argmax(b)] == pytest.approx(sigma, abs=2 * step_m)
        assert b.min() == pytest.approx(-amp * height, rel=0.01)
        assert np.max(np.abs(b[np.abs(x) > 6 * sigma])) < 1e-4 * height


def test_process_effects_change_the_right_parameters():
    from masks.process import ProcessParams, simulate_surface

    p = ProcessParams.ideal()
    q = get_effect("etch_depth").apply(p, np.array([0, 0, 0, 0.06]))
    assert np.allclose(q.etch_depth, [75e-9, 150e-9, 300e-9, 600e-9 * 1.06])
    levels = np.full((12, 12), 8)
    h = simulate_surface(levels, 5.4e-6, q, step_m=1.08e-6).height_m
    assert h[30, 30] == pytest.approx(-636e-9, rel=1e-9)
    q = get_effect("mask_overlay").apply(p, np.array([0, 0, 0, 0, 0.4e-6, -0.1e-6]))
    assert np.allclose(q.mask_overlay[3, :2], [0.4e-6, -0.1e-6]) and not np.any(q.mask_overlay[:3])
    q = get_effect("linewidth_bias").apply(p, np.full(4, 0.3e-6))
    assert np.allclose(q.linewidth_bias, 0.3e-6)


def test_new_process_effects_in_physical_units():
    """mask_rotation (deg, masks 1-3), microtrenching (depth and width per mask, m) and
    etch_gradient (1/m, x toward +column, y up) reach the process model with their units."""
    from masks.effects import effect_spec
    from masks.process import ProcessParams, simulate_surface

    p = ProcessParams.ideal()
    rot = get_effect("mask_rotation")
    assert [x.unit for x in rot.params] == ["deg"] * 3
    assert np.allclose(rot.apply(p, np.array([0.0, 0.03, 0.0])).mask_rotation, [0, 0, 0.03, 0])
    trench = get_effect("microtrenching")
    assert [x.name for x in trench.params][:2] == ["depth_mask0_m", "width_mask0_m"]
    values = np.array([0, 0.4e-6, 0, 0.4e-6, 0, 0.4e-6, 40e-9, 0.5e-6])
    assert np.allclose(trench.apply(p, values).microtrenching[3], [40e-9, 0.5e-6])
    # The null values print the ideal surface (a trench of zero depth has any width).
    levels = np.kron(np.array([[0, 8], [8, 0]]), np.ones((4, 4), int))
    ideal = simulate_surface(levels, 5.4e-6).height_m
    null = simulate_surface(levels, 5.4e-6, trench.apply(p, trench.null_values())).height_m
    np.testing.assert_array_equal(ideal, null)
    grad = get_effect("etch_gradient").apply(p, np.array([20.0, -10.0]))
    assert np.allclose(grad.etch_gradient, [20.0, -10.0])
    # A uniform level-8 field 64.8 um wide: the 600 nm etch changes by 20 /m * 64.8 um * 600 nm
    # from the left column to the right one.
    h = simulate_surface(np.full((12, 12), 8), 5.4e-6, grad, step_m=5.4e-6).height_m
    assert h[6, -1] - h[6, 0] == pytest.approx(-20.0 * 11 * 5.4e-6 * 600e-9, rel=1e-6)
    # Bounds inside the process table's plausible range.
    for name in ("mask_rotation", "microtrenching", "etch_gradient"):
        table = effect_spec(name)
        lo, hi = get_effect(name).bounds()
        assert lo.min() >= min(t.lower for t in table.params)
        assert hi.max() <= max(t.upper for t in table.params)


def test_psf_sensor_effects_closed_form():
    full = np.stack([np.full((2, 3, 3), 1.0), np.full((2, 3, 3), 3.0)])  # coded 1, uncoded 3
    info = {"views": ("coded",), "full": full, "full_views": ("coded", "uncoded")}
    out = get_effect("dual_pixel_crosstalk").apply(full[:1], np.array([0.12]), info)
    assert np.allclose(out, 0.88 * 1 + 0.12 * 3)
    bg = get_effect("background").for_channels(["a", "b"])
    assert bg.n_params == 2 and bg.params[1].name == "offset_b"
    out = bg.apply(full[:1], np.array([1e-3, 2e-3]), info)
    assert np.allclose(out[0, 1] - full[0, 1], 2e-3)


def test_defocus_and_bandwidth_wrap_the_renderer():
    seen = {}

    def render(h, wl, depth):
        seen["depth"] = depth
        wl = np.asarray(wl)
        # Linear in wavelength per channel: a symmetric band averages to the centre value.
        return np.broadcast_to((wl * 1e9)[None, :, None, None], (2, wl.size, 2, 2)).copy()

    get_effect("defocus").apply(render, np.array([0.1]), {"depth_m": 5.0})(None, [550e-9], 5.0)
    assert seen["depth"] == pytest.approx(1 / 0.3)
    get_effect("defocus").apply(render, np.array([-0.2]), {"depth_m": 5.0})(None, [550e-9], 5.0)
    assert seen["depth"] == np.inf
    avg = get_effect("source_bandwidth").apply(render, np.array([20e-9]), {})(None, [500e-9, 600e-9], 5.0)
    assert np.allclose(avg[0, :, 0, 0], [500, 600])
    # The Gauss-Hermite rule has the variance of the Gaussian spectrum: sigma = FWHM / 2.355.
    var = np.sum(psf_effects._GH_WEIGHTS * (psf_effects._GH_NODES * 20e-9 / fx.FWHM_PER_SIGMA) ** 2)
    assert np.sqrt(var) == pytest.approx(20e-9 / 2.3548, rel=1e-3)
    h = np.ones((3, 3))
    assert np.allclose(get_effect("depth_scale").apply(h, np.array([0.05])), 1.05)


def test_batwing_transfer_is_the_profile_in_fourier():
    # h + batwing_profile(h) (taps correlated in space, edges extended) against the factor
    # multiplying the spectrum of h padded with its edge values, away from the padding.
    rng = np.random.default_rng(3)
    h = np.kron(rng.integers(0, 4, (12, 10)).astype(float), np.ones((9, 9))) * 1e-7
    step, values, pad = 0.1e-6, (0.3, 0.35e-6), 24
    padded = np.pad(h, pad, mode="edge")
    wr = 2 * np.pi * np.fft.fftfreq(padded.shape[0])
    wc = 2 * np.pi * np.fft.rfftfreq(padded.shape[1])
    factor = fx.batwing_transfer(values, step, wr, wc, pad)
    got = np.fft.irfft2(np.fft.rfft2(padded) * factor, s=padded.shape)[pad:-pad, pad:-pad]
    want = h + fx.batwing_profile(h, values[0], values[1], step)
    assert np.abs(want - h).max() > 5e-9
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-7 * np.abs(h).max())
    # Taps reaching beyond the padding: the caller must use the fine grid.
    assert fx.batwing_transfer((0.3, 3e-6), step, wr, wc, pad) is None
    assert np.all(fx.batwing_transfer((0.0, 0.35e-6), step, wr, wc, pad) == 1)
