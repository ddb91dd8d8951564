"""One engine on any array namespace: the PSF engine on ``array_api_strict`` (a namespace that
refuses everything outside the array API standard) and on CuPy gives NumPy's answers.

The strict runs make non-portable code fail on a CPU machine; the ``gpu`` tests run the same
cases on CuPy and skip where no GPU is present (the ``namespace_backend`` fixture, tests/conftest.py). The NumPy engine is itself checked against
analytic results in test_psf.py; here each namespace is checked against it.
"""

import logging

import numpy as np
import pytest

from doedesign import targets
from doedesign.camera import Camera
from doedesign.engine import backend as be
from doedesign.engine.psf import PSFEngine
from doedesign.errors import DoeError
from doedesign.optimizer.losses import LossSpec, make_loss

PITCH = 5.4e-6


def _case(q=1, focus=np.inf, depths=None, n=40):
    cam = Camera(aperture_diameter_m=n * PITCH, focus_distance_m=focus, window_shape=(48, 40),
                 axis_pixel=(24, 21))
    target = targets.bayer(cam)
    h = -np.random.default_rng(3).uniform(0, 1.2e-6, (n, n))
    kw = dict(wavelengths_m=target.wavelengths_m, depths_m=depths, doe_oversample=q)
    return cam, target, h, kw


@pytest.mark.parametrize("q, focus, depths", [(1, np.inf, None), (2, 5.0, (2.0, 5.0))])
def test_psf_stack_equals_numpy(namespace_backend, q, focus, depths):
    cam, _, h, kw = _case(q, focus, depths)
    ref = PSFEngine(cam, PITCH, h.shape, device="cpu", **kw).psf(h)
    other = PSFEngine(cam, PITCH, h.shape, device=namespace_backend, **kw).psf(h)
    assert isinstance(other.psf, np.ndarray)
    assert np.abs(other.psf - ref.psf).max() <= 1e-10 * ref.psf.max()
    single = PSFEngine(cam, PITCH, h.shape, device=namespace_backend, precision="single", **kw).psf(h)
    assert np.abs(single.psf - ref.psf).max() <= 1e-5 * ref.psf.max()


@pytest.mark.parametrize("spec, full", [("l1,energy", False), ("l1,energy", True), ("energy", False)])
def test_value_and_grad_equals_numpy(namespace_backend, spec, full):
    cam, target, h, kw = _case(q=2, focus=5.0)
    loss = make_loss(target, LossSpec.parse(spec))
    v_ref, g_ref = PSFEngine(cam, PITCH, h.shape, device="cpu", **kw).value_and_grad(h, loss, full_window=full)
    v, g = PSFEngine(cam, PITCH, h.shape, device=namespace_backend, **kw).value_and_grad(h, loss, full_window=full)
    assert isinstance(g, np.ndarray) and g.shape == h.shape
    assert v == pytest.approx(v_ref, rel=1e-10)
    assert np.abs(g - g_ref).max() <= 1e-10 * np.abs(g_ref).max()


@pytest.mark.parametrize("full", [False, True])
def test_free_vector_gradient_and_level_penalty_equal_numpy(namespace_backend, full):
    # The design loop's path: the free heights cross as a vector, the map is assembled and the
    # gradient gathered where the engine computes, the annealing's penalty added there.
    from doedesign.optimizer.anneal import level_penalty

    cam, target, h, kw = _case(q=2, focus=5.0)
    loss = make_loss(target, LossSpec.parse("l1,energy"))
    free = np.zeros(h.shape, bool)
    free[3:-3, : h.shape[1] // 2] = True
    v_ref, g_ref = PSFEngine(cam, PITCH, h.shape, device="cpu", **kw).value_and_grad(np.where(free, h, 0.0), loss,
                                                                                      full_window=full)
    engine = PSFEngine(cam, PITCH, h.shape, device=namespace_backend, **kw)
    x = namespace_backend.asarray(h[free])
    v, g = engine.value_and_grad_free(x, free, loss, full_window=full)
    g = namespace_backend.to_host(g)
    assert g.shape == (free.sum(),)
    assert v == pytest.approx(v_ref, rel=1e-10)
    assert np.abs(g - g_ref[free]).max() <= 1e-10 * np.abs(g_ref).max()
    step = 75e-9
    p_ref, gp_ref = level_penalty(h[free], step)
    p, gp = level_penalty(x, step)
    assert p == pytest.approx(p_ref, rel=1e-12)
    assert np.abs(namespace_backend.to_host(gp) - gp_ref).max() <= 1e-12 * np.abs(gp_ref).max()


def test_strict_namespace_refuses_numpy_only_calls():
    # The guard itself: were the engine to call a NumPy-only function on its arrays, the strict
    # namespace would raise, so the tests above could not pass by accident.
    xs = be.strict_backend().xp
    a = xs.ones((2, 2))
    assert not hasattr(xs, "einsum") and not hasattr(xs, "sinc")
    with pytest.raises(IndexError):
        a[xs.asarray([1, 0]), :]


def test_device_choice(caplog, monkeypatch):
    assert be.select_backend("cpu").name == "numpy"
    with pytest.raises(DoeError, match="device must be one of"):
        be.select_backend("tpu")
    monkeypatch.setattr(be, "_CHOSEN", {})
    monkeypatch.setattr(be, "gpu_unavailable_reason", lambda: "CuPy is not installed (test)")
    with caplog.at_level(logging.INFO, logger=be.__name__):
        assert be.select_backend("auto").name == "numpy"
    assert [r.getMessage() for r in caplog.records] == ["computing on the CPU: CuPy is not installed (test)"]
    with pytest.raises(DoeError, match="--device gpu: CuPy is not installed"):
        be.select_backend("gpu")


def _tiny_design(tmp_path):
    from doedesign.design import Design

    d = Design(height_m=-np.random.default_rng(2).uniform(0, 1.1e-6, (16, 16)), pitch_m=PITCH)
    path = tmp_path / "d.npz"
    d.save(path)
    return path


@pytest.mark.skipif(be.gpu_unavailable_reason() is None, reason="a GPU is present")
def test_psf_command_device_gpu_without_one_is_refused_in_one_line(tmp_path, capsys):
    from doedesign.cli import main

    out = tmp_path / "psf.npz"
    argv = ["psf", str(_tiny_design(tmp_path)), "--aperture-mm", "0", "--out", str(out), "--device", "gpu"]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert "--device gpu:" in err and "Traceback" not in err and len(err.strip().splitlines()) == 1
    assert not out.exists()


def test_psf_command_same_stack_on_cpu_and_auto(tmp_path):
    from doedesign.cli import main
    from doedesign.engine import PSFResult

    d = _tiny_design(tmp_path)
    for device in ("cpu", "auto"):
        assert main(["psf", str(d), "--aperture-mm", "0", "--wavelengths-nm", "550", "--out",
                     str(tmp_path / f"{device}.npz"), "--device", device]) == 0
    a, b = (PSFResult.load(tmp_path / f"{k}.npz").psf for k in ("cpu", "auto"))
    assert np.abs(a - b).max() <= 1e-10 * a.max()



def test_ndimage_of_a_backend_gives_scipys_filters_on_its_arrays(namespace_backend):
    # The filters the process model uses, on the namespace under test, against SciPy's on the
    # host: a Gaussian blur, a 1-D maximum, a linear rotation and a sum per label.
    from scipy import ndimage as ndi

    # Double precision, as the process model renders (CuPy's single-precision interpolation
    # differs from SciPy's by tens of ulp).
    img = np.random.default_rng(2).random((30, 26))
    dev = namespace_backend.asarray(img)
    nd = namespace_backend.ndimage
    host = namespace_backend.to_host
    np.testing.assert_allclose(host(nd.gaussian_filter(dev, 1.7, mode="constant", cval=0.0)),
                               ndi.gaussian_filter(img, 1.7, mode="constant", cval=0.0), rtol=0, atol=1e-10)
    np.testing.assert_array_equal(host(nd.maximum_filter1d(dev, 5, axis=1, mode="constant", cval=0.0)),
                                  ndi.maximum_filter1d(img, 5, axis=1, mode="constant", cval=0.0))
    c, s = np.cos(0.01), np.sin(0.01)
    matrix = np.array([[c, s], [-s, c]])
    np.testing.assert_allclose(
        host(nd.affine_transform(dev, namespace_backend.asarray(matrix), offset=(0.3, -0.2), order=1,
                                 mode="grid-constant", cval=0.0, prefilter=False)),
        ndi.affine_transform(img, matrix, offset=(0.3, -0.2), order=1, mode="grid-constant", cval=0.0,
                             prefilter=False), rtol=0, atol=1e-10)
    labels = (np.arange(30 * 26).reshape(30, 26) % 3).astype(np.int32)
    sums = nd.sum(namespace_backend.asarray(img.astype(np.float64)), namespace_backend.asarray(labels),
                  namespace_backend.asarray(np.arange(1, 3)))
    np.testing.assert_allclose(host(sums), [img[labels == 1].sum(), img[labels == 2].sum()], rtol=1e-6)
