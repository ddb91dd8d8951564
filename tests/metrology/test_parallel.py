"""The threaded map: same results as a plain map, errors reported, no task lost, no thread left
behind; the diagnosis's shared caches give the same fits in threads as in one thread."""

import os
import threading
import time

import numpy as np
import pytest

import filegen
from doedesign.errors import DoeError
from masks.process import ProcessParams
from metrology.diagnosis import fitting, parallel
from metrology.diagnosis.camera import CAMERA, CameraHeightProblem
from metrology.diagnosis.effects import effects_for
from metrology.diagnosis.parallel import in_worker, parallel_map
from metrology.matching.instrument import ArrayCache, Placement


def _fit_threads():
    return [t for t in threading.enumerate() if t.name.startswith("doe-fit")]


@pytest.fixture
def no_thread_left():
    """The map's threads are all joined when it ends, however it ends."""
    yield
    assert _fit_threads() == []


def test_closures_and_order_as_a_plain_map(no_thread_left):
    scale = np.arange(5.0)
    items = list(range(23))
    expect = [float(np.sum(scale * i)) for i in items]
    assert list(parallel_map(lambda i: float(np.sum(scale * i)), items, workers=2)) == expect
    assert sorted(parallel_map(lambda i: float(np.sum(scale * i)), items, workers=2, ordered=False)) == sorted(expect)
    assert list(parallel_map(lambda i: i, [], workers=2)) == []


def test_work_is_shared_and_a_nested_map_runs_in_its_worker(no_thread_left):
    def piece(i):
        time.sleep(0.01)
        inner = list(parallel_map(lambda _: threading.get_ident(), [0, 1, 2], workers=2))
        return threading.get_ident(), in_worker(), inner

    out = list(parallel_map(piece, range(8), workers=2))
    idents = {t for t, _, _ in out}
    assert threading.get_ident() not in idents and len(idents) == 2  # two worker threads shared it
    assert all(inside for _, inside, _ in out)
    assert all(set(inner) == {t} for t, _, inner in out)             # the nested map ran in place
    assert not in_worker()


def test_many_maps_lose_no_task(no_thread_left):
    for run in range(300):
        n, ordered = 1 + run % 7, run % 2 == 0
        out = list(parallel_map(lambda i: i * i, range(n), workers=2, ordered=ordered))
        assert (out if ordered else sorted(out)) == [i * i for i in range(n)]


@pytest.mark.parametrize("ordered", [True, False])
def test_an_exception_arrives_with_its_type_and_stops_the_rest(no_thread_left, ordered):
    started = []

    def fn(i):
        started.append(i)
        if i == 1:
            raise DoeError("file x.datx: piece 1 is bad")
        time.sleep(0.02)
        return i

    with pytest.raises(DoeError, match="piece 1 is bad"):
        list(parallel_map(fn, range(40), workers=2, ordered=ordered))
    assert len(started) < 40  # the pieces not started by then never start


def test_an_early_close_joins_the_threads(no_thread_left):
    gen = parallel_map(lambda i: time.sleep(0.02 * (i > 0)) or i, range(40), workers=2)
    assert next(gen) == 0
    gen.close()


def test_a_shared_cache_survives_threads_that_fill_and_evict_it():
    cache = ArrayCache(max_bytes=10 * 800, max_items=6)

    def hammer(seed):
        rng = np.random.default_rng(seed)
        for _ in range(3000):
            key = int(rng.integers(0, 20))
            got = cache.get(key)
            if got is not None:
                assert got[0] == key  # never another key's array
            else:
                cache.put(key, np.full(100, float(key)))
        return True

    assert all(parallel_map(hammer, range(4), workers=4))
    assert len(cache._items) <= 6


@pytest.mark.skipif((os.cpu_count() or 1) < 2, reason="one CPU: the map runs in place")
def test_a_camera_fit_is_the_same_in_threads_as_in_one_thread(monkeypatch):
    # The Jacobian's columns share the problem's render caches (fine surfaces, spectra, camera
    # maps, Fourier factors of a batwing): computed side by side they must give the very numbers
    # one thread gives, column by column.
    case = filegen.make_case(["mask_overlay"], 11, design_px=32, field_px=80)
    inst = case.instrument
    pl = Placement(np.array(inst["matrix"]), np.array(inst["offset"]))
    names = ["mask_overlay", "linewidth_bias", "batwing"]

    def fit():
        problem = CameraHeightProblem(case.levels, filegen.PITCH_M, case.height_m, pl, ProcessParams.ideal(),
                                      effects_for("height", names))
        start = {CAMERA.name: problem.effects[CAMERA.name].start_values(),
                 **{n: problem.effects[n].start_values() for n in names}}
        return fitting.fit_effects(problem, start, [CAMERA.name, *names], max_iter=3)

    monkeypatch.setattr(parallel, "WORKERS", 2)
    threaded = fit()
    monkeypatch.setattr(parallel, "WORKERS", 1)
    alone = fit()
    assert threaded[1] == alone[1]
    for name in threaded[0]:
        np.testing.assert_array_equal(threaded[0][name], alone[0][name])


@pytest.mark.skipif((os.cpu_count() or 1) < 2, reason="one CPU: the map runs in place")
def test_a_comparison_is_the_same_in_threads_as_in_one_thread(monkeypatch, tmp_path):
    # The camera-frame fits' Jacobian columns and the instrument stage's fits run side by side:
    # each piece computed alone, so the comparison a diagnosis starts from must be the one one
    # thread gives; without its surface texture (a diagnosis's) it is the same comparison.
    from doedesign.design import Design
    from metrology.formats.readers import read_measurement
    from metrology.matching.compare import compare_measurement

    case = filegen.make_case(["mask_overlay", "linewidth_bias"], 5, design_px=40, field_px=110)
    d_path, m_path = case.write(tmp_path)
    design, measurement = Design.load(d_path), read_measurement(m_path).square_pixels()

    def compare(texture):
        comp = compare_measurement(measurement, design, texture=texture)
        fit = comp.instrument_fit
        return comp, [comp.edge_fit.shift_m, comp.edge_fit.bias_m, comp.edge_fit.depths_m, fit.depths_m, fit.overlay_m,
                      fit.bias_m, fit.placement.matrix, fit.placement.offset, fit.residual_m]

    monkeypatch.setattr(parallel, "WORKERS", 2)
    threaded, numbers = compare(texture=True)
    monkeypatch.setattr(parallel, "WORKERS", 1)
    alone, same = compare(texture=False)
    for a, b in zip(numbers, same):
        np.testing.assert_array_equal(a, b)
    assert threaded.texture is not None and alone.texture is None
    assert alone.report()["texture"] is None


def test_registration_and_camera_maps_never_start_scipys_fft_thread_pool():
    # scipy.fft's thread pool, once started, shuts down and restarts around every fork; a fork soon
    # after a restart can hang for ever in pocketfft's prefork handler (a CSI diagnosis did, once in
    # 30, when its workers were forked; a test worker in CI did, after PSF tests). The FFTs a process
    # runs (registration, camera maps of a large field, the PSF engine's transforms and lags) start
    # no thread that outlives them in a fresh process.
    import subprocess
    import sys

    code = """
import os
import time
import numpy as np
from masks.process import ProcessParams
from metrology.matching.instrument import InstrumentModel, Placement
from metrology.matching.register import _normalized_xcorr

before = len(os.listdir("/proc/self/task"))
rng = np.random.default_rng(0)
image = rng.standard_normal((600, 600))
_normalized_xcorr(image, image[100:400, 100:400], np.ones((300, 300), bool))
model = InstrumentModel(rng.integers(0, 16, (90, 90)), 5.4e-6, (400, 400), Placement(np.eye(2) * 0.19, np.array([5.0, 5.0])))
fine = model.fine_surface(ProcessParams.ideal())
assert fine.size >= 2 ** 22, fine.shape
model.camera_map(fine, 0.4e-6)
from doedesign.engine.backend import numpy_backend
from doedesign.engine.lags import paired_lags
backend = numpy_backend()
x = rng.standard_normal((512, 512))
backend.fftn(x), backend.rfftn(x), backend.fft(x), paired_lags(x, backend)
# A joined thread's task can stay listed for a moment while the kernel ends it (seen in CI: one
# run in a few); a pool's threads stay for ever. Wait up to 5 s for the count to come back.
deadline = time.monotonic() + 5.0
while len(os.listdir("/proc/self/task")) > before and time.monotonic() < deadline:
    time.sleep(0.01)
print(before, len(os.listdir("/proc/self/task")))
"""
    if not os.path.isdir("/proc/self/task"):
        pytest.skip("no /proc task list here")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    before, after = map(int, out.stdout.split())
    assert after == before


def test_one_thread_limits_blas_and_restores_it_after_the_last_block():
    from threadpoolctl import threadpool_info

    from metrology.diagnosis.parallel import one_thread

    def blas():
        return {d["filepath"]: d["num_threads"] for d in threadpool_info() if d["user_api"] == "blas"}

    before = blas()
    inside = threading.Event()
    leave = threading.Event()

    def other():
        with one_thread():
            inside.set()
            leave.wait(10)

    t = threading.Thread(target=other)
    t.start()
    inside.wait(10)
    with one_thread():
        assert set(blas().values()) <= {1}
    assert set(blas().values()) <= {1}  # the other block still holds the limit
    leave.set()
    t.join()
    assert blas() == before
    # A thread after the main thread's block, and after a limit the main thread set without a
    # ``with`` (threadpoolctl would then ignore every other thread's): limited all the same.
    from threadpoolctl import threadpool_limits

    with one_thread():
        pass
    held = threadpool_limits(limits=2)
    seen = []

    def later():
        with one_thread():
            seen.append(blas())

    t = threading.Thread(target=later)
    t.start()
    t.join()
    held.restore_original_limits()
    assert set(seen[0].values()) == {1}
    assert blas() == before
