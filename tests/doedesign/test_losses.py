"""Loss values against closed forms and their gradients against finite differences."""

import numpy as np
import pytest

from doedesign.optimizer import losses
from doedesign.optimizer.losses import LossSpec, make_loss
from doedesign.targets import Target


def _target(intensity, **kw):
    return Target(intensity=np.asarray(intensity, float)[None, None], wavelengths_m=[550e-9], depths_m=[np.inf],
                  axis_pixel=(2, 2), **kw)


def test_energy_loss_is_one_minus_efficiency():
    t = _target(np.pad([[1.0]], 2))
    psf = np.zeros((1, 1, 5, 5))
    psf[0, 0, 2, 2] = 0.37
    psf[0, 0, 0, 0] = 0.2
    assert losses.energy_loss(psf, t)[0] == pytest.approx(1 - 0.37)
    assert losses.target_metrics(psf, t)["efficiency"] == pytest.approx(0.37)


def test_uniformity_is_squared_coefficient_of_variation():
    tgt = np.zeros((5, 5))
    tgt[1, 1] = tgt[1, 3] = tgt[3, 1] = tgt[3, 3] = 0.25
    t = _target(tgt)
    psf = np.zeros((1, 1, 5, 5))
    a = np.array([0.8, 1.0, 1.2, 1.0])
    for (r, c), ai in zip([(1, 1), (1, 3), (3, 1), (3, 3)], a):
        psf[0, 0, r, c] = 0.25 * ai
    assert losses.uniformity_loss(psf, t)[0] == pytest.approx(np.var(a) / np.mean(a) ** 2)


def test_l1_tends_to_plain_l1_and_l2_is_relative():
    rng = np.random.default_rng(0)
    t = _target(rng.random((5, 5)) / 30)
    psf = rng.random((1, 1, 5, 5)) / 30
    l1 = np.abs(psf - t.intensity).sum()
    assert losses.smooth_l1(psf, t, eps=1e-9)[0] == pytest.approx(l1, rel=1e-6)
    assert losses.l2_loss(psf, t)[0] == pytest.approx(((psf - t.intensity) ** 2).sum() / (t.intensity ** 2).sum())


@pytest.mark.parametrize("spec", ["l1", "energy", "l2", "uniformity", "peak=0.5", "l1=1,energy=0.5,uniformity=2"])
def test_gradients_match_finite_differences(spec):
    rng = np.random.default_rng(1)
    tgt = np.zeros((6, 6))
    tgt[1:5:2, 1:5:2] = rng.uniform(0.1, 0.3, (2, 2))
    t = _target(tgt)
    loss = make_loss(t, LossSpec.parse(spec))
    psf = rng.uniform(0.01, 0.2, (1, 1, 6, 6))
    _, grad = loss(psf)
    for idx in [(0, 0, 1, 1), (0, 0, 3, 3), (0, 0, 0, 5), (0, 0, 2, 4)]:
        h = 1e-7
        up, down = psf.copy(), psf.copy()
        up[idx] += h
        down[idx] -= h
        numeric = (loss(up)[0] - loss(down)[0]) / (2 * h)
        assert grad[idx] == pytest.approx(numeric, rel=1e-4, abs=1e-7)


def test_reweighting_favours_dark_spots():
    tgt = np.zeros((4, 4))
    tgt[1, 1] = tgt[1, 2] = 0.5
    t = _target(tgt)
    psf = np.zeros((1, 1, 4, 4))
    psf[0, 0, 1, 1], psf[0, 0, 1, 2] = 0.1, 0.3
    w = np.broadcast_to(losses.reweight_target(t, psf).pixel_weight, psf.shape)
    # (mean / a_i) scaled to mean 1: ratios 0.2 and 0.6, mean 0.4 -> 2 and 2/3 -> 1.5 and 0.5
    assert w[0, 0, 1, 1] == pytest.approx(1.5) and w[0, 0, 1, 2] == pytest.approx(0.5)
    assert w[0, 0, 0, 0] == pytest.approx(1.0)
