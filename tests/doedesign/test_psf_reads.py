"""Losses of a few pixels and the window energy: the engine's few-pixel path against the full window."""

import numpy as np
import pytest

from doedesign import targets
from doedesign.camera import Camera
from doedesign.engine.psf import PSFEngine
from doedesign.optimizer.losses import LossSpec, make_loss
from doedesign.optimizer.optimize import OptimizerSettings, design_doe

PITCH = 5.4e-6


def bayer_engine(n=64, focus=np.inf, q=1):
    cam = Camera(aperture_diameter_m=n * PITCH, focus_distance_m=focus)
    target = targets.bayer(cam)
    engine = PSFEngine(cam, PITCH, (n, n), wavelengths_m=target.wavelengths_m, depths_m=target.depths_m,
                       doe_oversample=q)
    return cam, target, engine


def random_height(n, seed=1):
    return -np.random.default_rng(seed).uniform(0, 1.2e-6, (n, n))


@pytest.mark.parametrize("spec", ["l1,energy", "l1", "energy", "energy,uniformity=0.5"])
def test_bayer_loss_and_gradient_match_full_window(spec):
    _, target, engine = bayer_engine()
    loss = make_loss(target, LossSpec.parse(spec))
    assert loss.reads is not None and loss.reads.energy == ("l1" in spec)
    h = random_height(64)
    v_full, g_full = engine.value_and_grad(h, loss, full_window=True)
    v_read, g_read = engine.value_and_grad(h, loss)
    assert v_read == pytest.approx(v_full, rel=1e-9)
    assert np.abs(g_read - g_full).max() <= 1e-9 * np.abs(g_full).max()


@pytest.mark.parametrize("weights", [None, [1.0, 0.7, 1.3]])
def test_softmin_and_plane_losses_match_full_window(weights):
    # The balanced objectives read only the target pixels (no window energy): same value and
    # gradient as the whole window, to 1e-9.
    from doedesign.optimizer.objectives import _single_plane_loss, softmin_loss

    _, target, engine = bayer_engine(focus=5.0)
    h = random_height(64, seed=4)
    for loss in (softmin_loss(target, weights, tau=0.02), _single_plane_loss(target.mask, 0, 1)):
        eng = engine if loss.mask.shape[1] == 3 else PSFEngine(
            engine.camera, PITCH, (64, 64), wavelengths_m=target.wavelengths_m[1:2], depths_m=target.depths_m)
        assert loss.reads is not None and not loss.reads.energy
        v_full, g_full = eng.value_and_grad(h, loss, full_window=True)
        v_read, g_read = eng.value_and_grad(h, loss)
        assert v_read == pytest.approx(v_full, rel=1e-9)
        assert np.abs(g_read - g_full).max() <= 1e-9 * np.abs(g_full).max()


def test_spot_array_with_defocus_and_oversampling_matches_full_window():
    # Spots on 3 rows x 3 columns (not every pair is a target), a source at 2 m seen by a lens
    # focused at 5 m (defocus term), two pupil samples per DOE pixel, pixel weights on target.
    n = 48
    cam = Camera(aperture_diameter_m=n * PITCH, focus_distance_m=5.0)
    pos = [(250, 250), (250, 262), (256, 256), (262, 250), (262, 262)]
    target = targets.spots(pos, weights=[1, 2, 1, 1, 3], camera=cam, wavelengths_m=[500e-9, 600e-9], depths_m=[2.0])
    pw = np.ones(target.intensity.shape)
    pw[target.mask] = np.linspace(0.5, 2.0, int(target.mask.sum()))
    target = target.with_weights(pixel=pw, wavelengths=[1.0, 0.5])
    loss = make_loss(target, LossSpec(l1=1, energy=0.5, uniformity=0.3))
    assert loss.reads is not None and len(loss.reads.rows) == 5
    engine = PSFEngine(cam, PITCH, (n, n), wavelengths_m=target.wavelengths_m, depths_m=target.depths_m,
                       doe_oversample=2)
    h = random_height(n, seed=3)
    v_full, g_full = engine.value_and_grad(h, loss, full_window=True)
    v_read, g_read = engine.value_and_grad(h, loss)
    assert v_read == pytest.approx(v_full, rel=1e-9)
    assert np.abs(g_read - g_full).max() <= 1e-9 * np.abs(g_full).max()


def test_few_pixel_gradient_matches_finite_differences():
    _, target, engine = bayer_engine(n=40)
    loss = make_loss(target, LossSpec.parse("l1,energy"))
    h = random_height(40, seed=5)
    _, grad = engine.value_and_grad(h, loss)
    rng = np.random.default_rng(2)
    clear = np.argwhere(np.abs(grad) > 0.1 * np.abs(grad).max())
    dh = 1e-10
    for r, c in clear[rng.choice(len(clear), 6, replace=False)]:
        hp, hm = h.copy(), h.copy()
        hp[r, c] += dh
        hm[r, c] -= dh
        fd = (engine.value_and_grad(hp, loss)[0] - engine.value_and_grad(hm, loss)[0]) / (2 * dh)
        assert grad[r, c] == pytest.approx(fd, rel=1e-5)


def test_sparse_loss_equals_full_loss_on_any_psf():
    # Loss.sparse (pixels + energy) against the per-pixel terms on a whole random window.
    cam = Camera(window_shape=(32, 32), axis_pixel=(16, 16))
    target = targets.bayer(cam)
    rng = np.random.default_rng(0)
    psf = rng.uniform(0, 2e-3, target.intensity.shape)
    psf[..., 16:18, 16:18] = rng.uniform(0, 0.5, (1, 3, 2, 2))
    for spec in (LossSpec(l1=1, energy=1), LossSpec(l1=0.3, energy=0, uniformity=1)):
        loss = make_loss(target, spec)
        value, grad = loss(psf)
        rows, cols = loss.reads.rows, loss.reads.cols
        v, dv, de = loss.sparse(psf[..., rows, cols], psf.sum(axis=(-2, -1)))
        assert v == pytest.approx(value, rel=1e-12)
        rebuilt = np.broadcast_to(de[..., None, None], psf.shape).copy()
        rebuilt[..., rows, cols] += dv
        assert np.allclose(rebuilt, grad, rtol=1e-12, atol=1e-15)


def test_off_target_l1_is_the_light_there():
    cam = Camera(window_shape=(32, 32), axis_pixel=(16, 16))
    target = targets.bayer(cam)
    psf = np.random.default_rng(1).uniform(0, 1e-8, target.intensity.shape)  # far below eps
    value, _ = make_loss(target, LossSpec(l1=1, eps=1e-6))(psf)
    exact = np.mean(np.abs(psf - target.intensity).sum(axis=(-2, -1)))
    assert value == pytest.approx(exact, abs=3 * 1e-6)


def test_losses_that_read_the_window_declare_nothing():
    cam = Camera(window_shape=(32, 32), axis_pixel=(16, 16))
    target = targets.bayer(cam)
    assert make_loss(target, LossSpec(l1=1, l2=1)).reads is None
    assert make_loss(target, LossSpec(l1=1, peak=0.1)).reads is None
    pw = np.ones(target.intensity.shape)
    pw[0, 0, 0, 0] = 2.0  # one off-target pixel weighted differently: the energy cannot carry it
    assert make_loss(target.with_weights(pixel=pw), LossSpec(l1=1)).reads is None
    assert make_loss(target.with_weights(pixel=pw), LossSpec(l1=0, energy=1)).reads is not None
    streak = targets.hdr_streak(cam, arm_length_px=8)
    assert make_loss(streak, LossSpec(l1=1, peak=0)).reads is None  # many rows and columns


def test_design_is_the_same_on_both_paths():
    cam = Camera(aperture_diameter_m=48 * PITCH, focus_distance_m=np.inf, window_shape=(64, 64), axis_pixel=(32, 32))
    target = targets.bayer(cam)
    settings = OptimizerSettings(max_iter=8, anneal_iter=2, init="zeros")
    runs = [design_doe(target, cam, PITCH, (48, 48), loss=LossSpec(l1=1, energy=1), settings=settings,
                       full_window=full) for full in (True, False)]
    a, b = (r.continuous_height_m for r in runs)
    assert np.abs(a - b).max() <= 1e-9 * np.abs(a).max()
    assert runs[0].report["quantized"]["energy_on_target"][0] == pytest.approx(
        runs[1].report["quantized"]["energy_on_target"][0], rel=1e-9)
