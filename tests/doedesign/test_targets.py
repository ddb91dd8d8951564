"""Targets: seed geometry (Eq. 1, grating equation, ring schedule), composition and bad input."""

import numpy as np
import pytest

from doedesign import targets
from doedesign.camera import Camera
from doedesign.errors import DoeError
from doedesign.optimizer.losses import LossSpec, energy_loss, make_loss, peak_loss, smooth_l1, target_metrics

CAM = Camera()


def lit(plane):
    return [tuple(int(v) for v in rc) for rc in np.argwhere(plane > 0)]


def test_bayer_positions_match_eq1():
    t = targets.bayer(CAM)
    assert t.intensity.shape == (1, 3, 512, 512)
    assert np.isinf(t.depths_m).all()
    np.testing.assert_allclose(t.wavelengths_m, [656e-9, 589e-9, 486e-9])
    assert lit(t.intensity[0, 0]) == [(256, 256)]
    assert lit(t.intensity[0, 1]) == [(257, 256)]
    assert lit(t.intensity[0, 2]) == [(257, 257)]
    rggb = targets.bayer(CAM, rggb=True)
    assert lit(rggb.intensity[0, 1]) == [(256, 257), (257, 256)]
    np.testing.assert_allclose(rggb.energy, 1.0)


def test_hyperspectral_first_order_follows_grating_equation():
    # Seed: about 42 / 58 / 74 px from the axis at 400 / 550 / 700 nm for an 86.4 um period.
    off = targets.grating_order_offset_px(np.array([400e-9, 550e-9, 700e-9]), 86.4e-6, 1, CAM)
    np.testing.assert_allclose(off, [42.87, 58.95, 75.03], atol=0.02)
    t = targets.hyperspectral(CAM)
    assert t.wavelengths_m.size == 31
    cols = [np.flatnonzero(t.intensity[0, w, 256]) for w in (0, 15, 30)]
    assert [list(c - 256) for c in cols] == [[42, 43, 44], [58, 59, 60], [74, 75, 76]]
    assert np.count_nonzero(t.intensity[0, :, :256]) == 0 and np.count_nonzero(t.intensity[0, :, 257:]) == 0
    multi = targets.hyperspectral(CAM, wavelengths_m=[550e-9], orders=(0, 1, 2), order_weights=(1, 2, 1))
    plane = multi.intensity[0, 0, 256]
    assert plane[256] == pytest.approx(0.25 / 3) and plane[256 + 59] == pytest.approx(0.5 / 3)
    assert plane[256 + 118] == pytest.approx(0.25 / 3)


def test_depth_ring_radius_schedule():
    t = targets.depth_ring(CAM)
    rr = np.hypot(*np.meshgrid(np.arange(512) - 256, np.arange(512) - 256, indexing="ij"))
    for di, d in enumerate(t.depths_m):
        radius = rr[t.intensity[di, 0] > 0]
        assert np.abs(radius - (25 - 5 * d)).max() <= 0.5
    assert lit(t.intensity[-1, 0]) == [(256, 256)]  # 5 m: radius 0
    custom = targets.depth_ring(CAM, depths_m=[2.0], radii_px=[10])
    assert np.abs(rr[custom.intensity[0, 0] > 0] - 10).max() <= 0.5


def test_hdr_streak_cross_and_peak():
    t = targets.hdr_streak(CAM, arm_length_px=20)
    plane = t.intensity[0, 0]
    assert plane[255:257, 236:277].all() and plane[236:277, 255:257].all()
    assert np.count_nonzero(plane) == 2 * 2 * 41 - 4
    h = targets.hdr_streak(CAM, arms="h", arm_length_px=20)
    assert np.count_nonzero(h.intensity[0, 0][:255]) == 0
    # The soft maximum is close to the true maximum (p-norm with p = 8 over a few bright pixels).
    psf = np.zeros((1, 1, 512, 512))
    psf[0, 0, 256, 256] = 0.5
    v, _ = peak_loss(psf, t)
    assert v == pytest.approx(0.5 / (1 / np.count_nonzero(plane)))


def test_combine_and_weights():
    a = targets.spots([(100, 100)], camera=CAM, wavelengths_m=[550e-9], energy=0.4)
    b = targets.spots([(300, 300)], camera=CAM, wavelengths_m=[550e-9], energy=0.4)
    c = targets.spots([(200, 200)], camera=CAM, wavelengths_m=[650e-9])
    ab = a + b
    assert ab.intensity.shape == (1, 1, 512, 512)
    assert lit(ab.intensity[0, 0]) == [(100, 100), (300, 300)]
    assert ab.energy[0, 0] == pytest.approx(0.8)
    with pytest.raises(DoeError, match="no target defines"):
        targets.combine(a, targets.spots([(1, 1)], camera=CAM, wavelengths_m=[650e-9], depths_m=[2.0]))
    ac = targets.combine(a, c)
    assert ac.wavelengths_m.size == 2
    w = ac.with_weights(wavelengths=[1.0, 3.0])
    np.testing.assert_allclose(w.channel_weight, [[1.0, 3.0]])
    # Channel weights enter the loss: light missing at 650 nm costs three times more.
    psf = np.zeros_like(w.intensity)
    loss1, _ = energy_loss(psf + w.intensity * [[[[1]], [[0]]]], w)
    loss2, _ = energy_loss(psf + w.intensity * [[[[0]], [[1]]]], w)
    assert loss1 == pytest.approx(0.75) and loss2 == pytest.approx(0.25)


def test_image_target(tmp_path):
    img = np.zeros((10, 20))
    img[2, 3] = 1
    np.save(tmp_path / "t.npy", img)
    t = targets.image(tmp_path / "t.npy", camera=CAM)
    assert lit(t.intensity[0, 0]) == [(256 - 5 + 2, 256 - 10 + 3)]
    with pytest.raises(DoeError, match="does not fit"):
        targets.image(np.ones((600, 10)), camera=CAM)
    with pytest.raises(DoeError, match="no such image"):
        targets.image(tmp_path / "missing.png", camera=CAM)


@pytest.mark.parametrize("make,match", [
    (lambda: targets.Target(np.zeros((1, 1, 8, 8)), [550e-9], [1.0]), "empty"),
    (lambda: targets.Target(-np.ones((1, 1, 8, 8)), [550e-9], [1.0]), "negative"),
    (lambda: targets.Target(np.ones((1, 2, 8, 8)) / 64, [550e-9], [1.0]), "must be"),
    (lambda: targets.Target(np.ones((8, 8)), [550e-9], [1.0]), "must be"),
    (lambda: targets.Target(np.ones((1, 1, 8, 8)), [550e-9], [1.0]), "at most 1"),
    (lambda: targets.spots([(10, 600)], camera=CAM), "outside"),
    (lambda: targets.spots([(-1, 6)], camera=CAM), "outside"),
    (lambda: targets.spots([], camera=CAM), "pairs"),
    (lambda: targets.depth_ring(CAM, radii_px=[300] * 5), "leaves the window"),
    (lambda: targets.bayer(CAM, wavelengths_m=[550e-9]), "three wavelengths"),
    (lambda: targets.build("rainbow"), "unknown target kind"),
])
def test_bad_targets_raise_clear_errors(make, match):
    with pytest.raises(DoeError, match=match):
        make()


def test_toml_target(tmp_path):
    path = tmp_path / "t.toml"
    path.write_text('[[target]]\nkind = "spots"\npositions_px = [[256, 300], [300, 256]]\nweights = [1.0, 3.0]\n'
                    'wavelengths_nm = [550]\ndepths_m = ["inf"]\n')
    t = targets.load_toml(path, camera=CAM)
    assert t.intensity[0, 0, 300, 256] == pytest.approx(0.75)
    assert np.isinf(t.depths_m[0])
    path.write_text('[[target]]\nkind = "spots"\npositions_px = [[256, 999]]\n')
    with pytest.raises(DoeError, match=r"t\.toml.*outside"):
        targets.load_toml(path, camera=CAM)
    path.write_text("[[target]]\nkind = \n")
    with pytest.raises(DoeError, match="not valid TOML"):
        targets.load_toml(path, camera=CAM)


def test_losses_values_and_gradients():
    rng = np.random.default_rng(1)
    t = targets.spots([(3, 3), (5, 6)], camera=Camera(window_shape=(9, 9), axis_pixel=(4, 4)),
                      wavelengths_m=[500e-9, 600e-9], energy=0.8)
    psf = rng.uniform(0, 0.02, t.intensity.shape)
    # Smooth L1 tends to L1 for eps -> 0; target_metrics reports the plain L1.
    v, _ = smooth_l1(psf, t, eps=1e-12)
    assert v == pytest.approx(target_metrics(psf, t)["l1"], rel=1e-9)
    # A perfect PSF has zero L1 and zero missing energy.
    assert smooth_l1(t.intensity, t)[0] == pytest.approx(0, abs=1e-12)
    assert energy_loss(t.intensity, t)[0] == pytest.approx(0.0, abs=1e-12)
    for spec in (LossSpec(), LossSpec(l1=0, energy=1), LossSpec(l1=0, l2=1), LossSpec(l1=1, peak=0.3)):
        fn = make_loss(t, spec)
        _, g = fn(psf)
        d = rng.normal(size=psf.shape)
        h = 1e-7
        fd = (fn(psf + h * d)[0] - fn(psf - h * d)[0]) / (2 * h)
        assert np.sum(g * d) == pytest.approx(fd, rel=1e-5)
    with pytest.raises(DoeError, match="unknown loss term"):
        LossSpec.parse("l3")
    assert LossSpec.parse("l1,energy=0.5").energy == 0.5
