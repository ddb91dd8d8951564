"""doe tolerance's samples on any array namespace: a seeded sample gives the same process render
and the same metrics on array_api_strict (CPU) and on CuPy (``gpu``) as on NumPy (the
``namespace_backend`` fixture); the Dask cluster of a GPU run has one worker per GPU."""

import math
import os

import numpy as np
import pytest

from doedesign.camera import Camera
from doedesign.errors import DoeError

PITCH = 5.4e-6
# Every effect of the process model at once, each drawn away from zero (masks.effects).
EVERY_EFFECT = {"etch_depth": {"sigma_rel": 0.02}, "mask_overlay": {"sigma_um": 0.25},
                "mask_rotation": {"sigma_urad": 200}, "linewidth_bias": {"sigma_um": 0.1, "mean_um": 0.3},
                "proximity_blur": {"sigma_um": 0.3, "mean_um": 2.5}, "sidewall_slope": {"sigma_um": 0.1, "mean_um": 0.6},
                "etch_loading": {"sigma": 0.01, "mean": 0.05}, "roughness": {"sigma_nm": 0.5, "mean_nm": 2},
                "microtrenching": {"sigma_nm": 2, "mean_nm": 10, "mean_um": 0.8},
                "etch_gradient": {"sigma_percent_per_mm": 0.5, "mean_percent_per_mm": 1.0}}


def _design(kind="bayer", n=24):
    from doedesign.design import Design
    from doedesign.levels import level_step_m

    levels = np.random.default_rng(3).integers(0, 16, (n, n)).astype(np.int16)
    cam = Camera(aperture_diameter_m=n * PITCH, focus_distance_m=math.inf, window_shape=(24, 24), axis_pixel=(12, 12))
    meta = {"camera": cam.to_dict(), "n_levels": 16,
            "target": {"kind": kind, "wavelengths_nm": [656.0, 589.0, 486.0], "depths_m": ["inf"], "rggb": False}}
    return Design(height_m=-levels * level_step_m("fused_silica", 550e-9, 16), pitch_m=PITCH, levels=levels,
                  metadata=meta)


def _same_metrics(got, ref, rel):
    assert set(got) == set(ref) and ref
    for k, v in ref.items():
        assert got[k] == pytest.approx(v, rel=rel, abs=1e-12), k


def test_seeded_tolerance_sample_same_metrics_on_either_device(namespace_backend):
    # doe tolerance's sample k (its process draw, fabricated heights, PSF and metrics) on the
    # namespace under test against NumPy: the same metrics to 1e-9.
    from masks.tolerance.analysis import build_evaluator, nominal_depths
    from masks.tolerance.spec import default_spec

    design = _design()
    spec = default_spec(nominal_depths(design))
    values, seed = spec.draw(11, 3)
    job = {"id": 3, "values": values, "seed": seed}
    ref = build_evaluator(design, spec, device="cpu")[0](job)["metrics"]
    got = build_evaluator(design, spec, device=namespace_backend)[0](job)["metrics"]
    _same_metrics(got, ref, 1e-9)


@pytest.mark.parametrize("process_upsample", [None, 4])
def test_every_process_effect_renders_the_same_on_either_device(namespace_backend, process_upsample):
    # A sample with every effect of the process model switched on (rotation, blur and threshold,
    # sidewall ramp, loading, roughness, trenches, gradient, besides depth, overlay and bias),
    # rendered on the namespace under test: the same height map as NumPy's, and the same metrics.
    # On CuPy the float32 coverage goes through cupyx's own filters (Gaussian blur, rotation),
    # which may round it differently from SciPy's by an ulp; flipping every output of those
    # filters by +-1 ulp at random on NumPy moves these heights by 1.3 pm and the metrics by
    # 5e-7 of their value, hence 10 pm and 2e-6 there.
    from masks.tolerance.analysis import build_evaluator, nominal_depths
    from masks.tolerance.spec import build_spec

    design = _design()
    spec = build_spec(EVERY_EFFECT, nominal_depths(design), "every effect")
    values, seed = spec.draw(5, 2)
    params = spec.params_for(values, build_evaluator(design, spec)[0].base, seed)
    assert params.proximity_blur > 0 and params.sidewall_slope > 0 and params.etch_loading != 0
    assert params.roughness > 0 and np.all(params.microtrenching[:, 0] > 0) and np.all(params.etch_gradient != 0)
    assert np.all(params.mask_overlay[1:, 2] != 0) and np.all(params.linewidth_bias != 0)
    job = {"id": 2, "values": values, "seed": seed}
    cpu = build_evaluator(design, spec, device="cpu", process_upsample=process_upsample)[0]
    dev = build_evaluator(design, spec, device=namespace_backend, process_upsample=process_upsample)[0]
    h_cpu = cpu.height(values, seed)
    h_dev = dev.height(values, seed)
    assert not isinstance(h_dev, np.ndarray)  # rendered on the device, not on the host
    exact = namespace_backend.device == "cpu"
    np.testing.assert_allclose(namespace_backend.to_host(h_dev), h_cpu, rtol=0, atol=0 if exact else 1e-11)
    assert np.ptp(h_cpu) > 500e-9  # a real 16-level surface, not a flat one
    _same_metrics(dev(job)["metrics"], cpu(job)["metrics"], 1e-9 if exact else 2e-6)


@pytest.mark.parametrize("kind", ["bayer", "hyperspectral", "spots", "hdr-streak", "depth", "image"])
def test_metrics_reduce_on_the_device_to_the_same_numbers(namespace_backend, kind):
    # Every target kind's figures computed from a PSF on the namespace under test, against the
    # same MetricSet on a NumPy copy of that PSF.
    from masks.tolerance.metrics import MetricSet, ring_radii_px

    rng = np.random.default_rng(7)
    shape = (2, 3, 16, 16)
    psf = rng.random(shape) * 1e-3
    target = np.zeros(shape, bool)
    target[..., 3:5, 3:5] = True
    target[..., 10:12, 9:13] = True
    ms = MetricSet(kind=kind, wavelengths_m=np.array([656e-9, 589e-9, 486e-9]), depths_m=np.array([1.0, 2.0]),
                   axis_pixel=(8, 8), target_mask=target)
    if kind == "bayer":
        ms.bayer_cells = [[(0, 0)], [(1, 0), (0, 1)], [(1, 1)]]
    if kind == "spots":
        from scipy import ndimage as ndi

        ms.spot_labels = ndi.label(target.any(axis=(0, 1)))[0]
        assert ms.spot_labels.max() == 2
    if kind == "depth":
        ms.target_radii_px = ring_radii_px(target.astype(float), (8, 8))
    ref = ms(psf)
    got = ms(namespace_backend.asarray(psf), namespace_backend)
    _same_metrics(got, ref, 1e-12)
    # Against the definitions, on the host.
    if kind == "image":
        assert ref["efficiency"] == pytest.approx(np.sum(psf * target, axis=(-2, -1)).mean(), rel=1e-12)
    if kind == "hyperspectral":
        assert ref["zero_order_leak"] == pytest.approx(psf[..., 7:10, 7:10].sum(axis=(-2, -1)).mean(), rel=1e-12)
    if kind == "bayer":
        assert ref["on_target_G"] == pytest.approx(psf[0, 1, 9, 8] + psf[0, 1, 8, 9], rel=1e-12)


def test_gpu_workers_one_per_visible_gpu(monkeypatch):
    from masks.tolerance import runner

    monkeypatch.setenv("CUDA_VISIBLE_DEVICES", "2,5")
    assert runner.visible_gpus() == ["2", "5"]
    assert runner.gpu_worker_devices() == ["2", "5"]
    assert runner.gpu_worker_devices(workers=3) == ["2", "5", "2"]
    assert runner.local_workers("processes", gpu=True) == 2
    assert runner.local_workers("threads", gpu=True) == 1
    monkeypatch.setattr(runner, "visible_gpus", lambda: ["0", "1", "2", "3"])
    assert runner.gpu_worker_devices() == ["0", "1", "2", "3"]
    monkeypatch.setattr(runner, "visible_gpus", lambda: [])
    with pytest.raises(DoeError, match="no visible CUDA device"):
        runner.gpu_worker_devices()


def test_gpu_cluster_pins_each_worker_to_its_gpu(monkeypatch):
    # Two faked GPUs: the cluster has two single-threaded worker processes, each of which sees
    # only its own GPU (a worker inherits the parent's "0,1" unless it is given its own).
    from masks.tolerance import runner

    monkeypatch.setenv("CUDA_VISIBLE_DEVICES", "0,1")
    with runner.make_client("processes", gpu=True) as client:
        assert sorted(client.nthreads().values()) == [1, 1]
        seen = client.run(lambda: (os.environ["CUDA_VISIBLE_DEVICES"], os.getpid()))
    assert sorted(v[0] for v in seen.values()) == ["0", "1"]
    assert len({v[1] for v in seen.values()} | {os.getpid()}) == 3


@pytest.mark.gpu
def test_real_gpu_workers_each_compute_on_their_own_gpu():
    # On a machine with GPUs: one worker per visible GPU, and each one's CuPy computes on a
    # different physical device (its PCI bus id).
    from doedesign.engine import backend as be
    from masks.tolerance import runner

    why = be.gpu_unavailable_reason()
    if why is not None:
        pytest.skip(f"no GPU: {why}")

    def where():
        import cupy

        be.select_backend("gpu")
        return cupy.cuda.runtime.getDeviceCount(), cupy.cuda.Device().pci_bus_id

    with runner.make_client("processes", gpu=True) as client:
        seen = list(client.run(where).values())
    assert len(seen) == len(runner.visible_gpus())
    assert all(count == 1 for count, _ in seen)
    assert len({bus for _, bus in seen}) == len(seen)
