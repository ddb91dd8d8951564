"""The forked map: same results as a plain map, errors and dead workers reported, no task lost."""

import os
import signal
import time

import numpy as np
import pytest

from doedesign.errors import DoeError
from metrology.diagnosis import forked
from metrology.diagnosis.forked import ForkedWorkerError, forked_map


def _children():
    """Live (not reaped) children of this process (other tests' helpers among them)."""
    try:
        with open(f"/proc/{os.getpid()}/task/{os.getpid()}/children") as f:
            return {int(p) for p in f.read().split()}
    except OSError:
        pytest.skip("no /proc children list here")


@pytest.fixture
def no_new_children():
    """The map's workers are all reaped when it ends, however it ends."""
    before = _children()
    yield
    assert _children() <= before


def test_closures_and_order_as_a_plain_map():
    scale = np.arange(5.0)  # reached through the closure, never pickled
    items = list(range(23))
    expect = [float(np.sum(scale * i)) for i in items]
    assert list(forked_map(lambda i: float(np.sum(scale * i)), items, workers=2)) == expect
    assert sorted(forked_map(lambda i: float(np.sum(scale * i)), items, workers=2, ordered=False)) == sorted(expect)
    assert list(forked_map(lambda i: i, [], workers=2)) == []


def test_work_is_shared_and_workers_do_not_fork_again():
    pids = list(forked_map(lambda i: (os.getpid(), forked._IN_WORKER,
                                      list(forked_map(lambda _: os.getpid(), [0, 1], workers=2))), range(8), workers=2))
    assert {p for p, _, _ in pids} - {os.getpid()}          # computed in children
    assert all(inside for _, inside, _ in pids)
    assert all(set(inner) == {p} for p, _, inner in pids)  # the nested map ran in the worker itself


def test_many_maps_lose_no_task(no_new_children):
    """The pool this replaced lost a task about once in 45 diagnoses (each a few hundred maps)."""
    for run in range(300):
        n, ordered = 1 + run % 7, run % 2 == 0
        out = list(forked_map(lambda i: i * i, range(n), workers=2, ordered=ordered))
        assert (out if ordered else sorted(out)) == [i * i for i in range(n)]


def test_a_workers_exception_arrives_with_its_type(no_new_children):
    def fn(i):
        if i == 3:
            raise DoeError("file x.datx: piece 3 is bad")
        return i

    with pytest.raises(DoeError, match="piece 3 is bad"):
        list(forked_map(fn, range(6), workers=2))


def test_an_unpicklable_exception_or_result_is_still_reported(no_new_children):
    class Local(Exception):  # a local class does not pickle
        pass

    def raises(i):
        raise Local("no pickle")

    with pytest.raises(RuntimeError, match="Local: no pickle"):
        list(forked_map(raises, range(3), workers=2))
    with pytest.raises(Exception, match="pickle"):
        list(forked_map(lambda i: (lambda: i), range(3), workers=2))


def test_a_dead_worker_is_an_error_not_a_wait(no_new_children):
    def fn(i):
        if i == 2:
            os.kill(os.getpid(), signal.SIGKILL)
        return i

    t0 = time.monotonic()
    with pytest.raises(ForkedWorkerError, match="ended without a result"):
        list(forked_map(fn, range(6), workers=2))
    assert time.monotonic() - t0 < 30


def test_an_early_close_stops_the_workers(no_new_children):
    gen = forked_map(lambda i: time.sleep(0.05 * (i > 0)) or i, range(40), workers=2)
    assert next(gen) == 0
    gen.close()


def test_registration_and_camera_maps_never_start_scipys_fft_thread_pool():
    # scipy.fft's thread pool, once started, shuts down and restarts around every fork; a fork soon
    # after a restart can hang for ever in pocketfft's prefork handler (a CSI diagnosis did, once in
    # 30; a test worker in CI did, after PSF tests). The FFTs a process may run before the diagnosis
    # forks (registration, camera maps of a large field, the PSF engine's transforms and lags) start
    # no thread in a fresh process.
    import subprocess
    import sys

    code = """
import os
import numpy as np
from masks.process import ProcessParams
from metrology.matching.instrument import InstrumentModel, Placement
from metrology.matching.register import _normalized_xcorr

before = len(os.listdir("/proc/self/task"))
rng = np.random.default_rng(0)
image = rng.standard_normal((600, 600))
_normalized_xcorr(image, image[100:400, 100:400], np.ones((300, 300), bool))
model = InstrumentModel(rng.integers(0, 16, (60, 60)), 5.4e-6, (256, 256), Placement(np.eye(2) * 0.19, np.array([5.0, 5.0])))
fine = model.fine_surface(ProcessParams.ideal())
assert fine.size >= 2 ** 22, fine.shape
model.camera_map(fine, 0.4e-6)
from doedesign.engine.backend import numpy_backend
from doedesign.engine.lags import paired_lags
backend = numpy_backend()
x = rng.standard_normal((512, 512))
backend.fftn(x), backend.rfftn(x), backend.fft(x), paired_lags(x, backend)
print(before, len(os.listdir("/proc/self/task")))
"""
    if not os.path.isdir("/proc/self/task"):
        pytest.skip("no /proc task list here")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    before, after = map(int, out.stdout.split())
    assert after == before


def test_workers_never_collect_and_the_parent_is_left_as_it_was():
    """A collection in a worker writes the header of every object it walks, copying the pages it
    shares with the parent: the workers run with the collector off, the parent's objects frozen
    only while it forks."""
    import gc

    assert gc.isenabled()
    states = list(forked_map(lambda i: (gc.isenabled(), gc.get_freeze_count() > 0), range(4), workers=2))
    assert states == [(False, True)] * 4
    assert gc.isenabled() and gc.get_freeze_count() == 0
