"""The CPU FFTs split over short-lived threads (doedesign.engine.threaded_fft) give scipy.fft's
transforms, in its result types, and leave no thread behind (scipy.fft's own pool is not
fork-safe: the reason the module exists)."""

import threading

import numpy as np
import pytest
import scipy.fft as sfft

from doedesign.engine import threaded_fft as tf
from doedesign.engine.backend import numpy_backend

RNG = np.random.default_rng(5)
# Above MIN_SPLIT_ELEMENTS, with line counts that are not multiples of the block.
Z = RNG.normal(size=(610, 530)) + 1j * RNG.normal(size=(610, 530))
R3 = RNG.normal(size=(300, 470, 3))


def _close(a, b):
    assert a.shape == b.shape and a.dtype == b.dtype
    assert np.abs(a - b).max() <= 1e-13 * np.abs(b).max()


@pytest.mark.parametrize("threads", [2, 3])
def test_every_transform_equals_scipy(threads):
    assert Z.size >= tf.MIN_SPLIT_ELEMENTS
    before = threading.active_count()
    _close(tf.fft(Z, 700, 1, threads), sfft.fft(Z, 700, axis=1))
    _close(tf.fft(Z, None, 0, threads), sfft.fft(Z, axis=0))
    _close(tf.ifft(Z, 640, 0, threads), sfft.ifft(Z, 640, axis=0))
    _close(tf.fftn(Z, (700, 600), (0, 1), threads), sfft.fftn(Z, (700, 600), axes=(0, 1)))
    _close(tf.ifftn(Z, None, (0, 1), threads), sfft.ifftn(Z, axes=(0, 1)))
    _close(tf.rfftn(R3, None, (0, 1), threads), sfft.rfftn(R3, axes=(0, 1)))
    _close(tf.rfftn(R3[..., 0], (320, 480), None, threads), sfft.rfftn(R3[..., 0], (320, 480)))
    _close(tf.power_fft(Z, 700, 0, threads), np.abs(sfft.fft(Z, 700, axis=0)) ** 2)
    # Every thread ended with its call: a fork now finds none.
    assert threading.active_count() == before


def test_single_precision_stays_single():
    z32 = Z.astype(np.complex64)
    out = tf.fft(z32, None, 0, 2)
    assert out.dtype == np.complex64
    assert np.abs(out - sfft.fft(z32, axis=0)).max() <= 1e-5 * np.abs(out).max()
    assert tf.rfftn(R3.astype(np.float32), None, (0, 1), 2).dtype == np.complex64


def test_thread_count_follows_the_cpus_and_omp_num_threads(monkeypatch):
    monkeypatch.setenv("OMP_NUM_THREADS", "1")
    assert tf.cpu_threads() == 1
    monkeypatch.delenv("OMP_NUM_THREADS")
    assert tf.cpu_threads() >= 1
    assert numpy_backend().fft_threads == tf.cpu_threads()
