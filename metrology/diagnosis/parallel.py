"""Independent pieces of a fit run side by side in threads.

A diagnosis spends its time in model evaluations that do not depend on each other: the
screening fits of the candidates, the columns of a finite-difference Jacobian, the blocks of a
large field's render. Their heavy parts (FFTs, spline sampling, filters, array arithmetic) run
in compiled code that releases the GIL, so threads share them out, with the problem and its
render caches (:class:`~metrology.matching.array_cache.ArrayCache`, locked) in common: nothing
is copied or pickled, and a column another thread needs is rendered once.

Threads, not forked processes (measured on 2 cores, one run each way, same fits and results):
a forked worker first touches its working set in pages it shares with the parent, and each
copy-on-write fault costs more than the GIL holds back. On a coherence-scanning
interferometer's file with a 0.4 um linewidth bias the whole selection took 96 s wall and
142 CPU s in threads against 157 s and 247 CPU s forked (a third of that CPU in the kernel);
the 512 x 512 benchmark row 21.6 s against 26.5 s.

Built on ``concurrent.futures.ThreadPoolExecutor``, one pool per call that is shut down before
the call returns: no thread outlives the map, so a fork elsewhere in the process (a test
runner's, Dask's) finds none. A piece that maps again (a screening fit's Jacobian) runs its own
pieces in its thread, in order: the workers are already busy.
"""

from __future__ import annotations

import contextlib
import threading
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import FIRST_COMPLETED, ThreadPoolExecutor, wait
from typing import Any

from doedesign.engine.threaded_fft import cpu_threads

__all__ = ["WORKERS", "fit_workers", "in_worker", "one_thread", "parallel_map"]

#: Threads that share the work: beyond two the Python-level part of each evaluation, which holds
#: the GIL, leaves little to gain (and the machines this is measured on have two cores).
WORKERS = min(2, cpu_threads())
_local = threading.local()


_one_lock = threading.Lock()
_one_state: dict[str, Any] = {"depth": 0, "limits": None}


@contextlib.contextmanager
def one_thread() -> Iterator[None]:
    """BLAS and OpenMP limited to one thread inside the block, as in a Dask worker.

    A Dask nanny starts its workers with ``OMP_NUM_THREADS``, ``MKL_NUM_THREADS`` and
    ``OPENBLAS_NUM_THREADS`` at 1; a computation run here (``--scheduler inline``, the
    ``threads`` scheduler, a benchmark, a test) would otherwise get the machine's BLAS threads,
    which split a factorization's work in another order (an SVD in a least-squares step: results
    differ in the last bits, and a fit's path with them) and spin beside the caller.

    The limit is the process's (OpenBLAS's pool is shared), so blocks entered from several
    threads at once share it: the first sets it, the last to leave restores what was there.
    threadpoolctl lets only one thread (the first to set a limit, until its ``with`` ends) set
    OpenBLAS's count and silently ignores the others; a thread that set one without a ``with``
    would keep that right for good. Here any thread may: the right is taken for the set and the
    restore and released at once. SciPy's FFTs run on one thread unless asked (``workers``), and
    :mod:`doedesign.engine.threaded_fft` splits only transforms far larger than a map tile's.
    """
    from threadpoolctl import OpenBLASController, threadpool_limits

    with _one_lock:
        if _one_state["depth"] == 0:
            OpenBLASController.clear_controlling_thread(force=True)
            _one_state["limits"] = threadpool_limits(limits=1)
            OpenBLASController.clear_controlling_thread(force=True)
        _one_state["depth"] += 1
    try:
        yield
    finally:
        with _one_lock:
            _one_state["depth"] -= 1
            if _one_state["depth"] == 0:
                OpenBLASController.clear_controlling_thread(force=True)
                _one_state["limits"].restore_original_limits()
                OpenBLASController.clear_controlling_thread(force=True)
                _one_state["limits"] = None


def fit_workers(problem: Any) -> int:
    """Threads for ``problem``'s independent fits and Jacobian columns: :data:`WORKERS` where its
    renders are safe to share between threads (``parallel_fits``), else 1."""
    return WORKERS if getattr(problem, "parallel_fits", False) else 1


def in_worker() -> bool:
    """Whether the calling thread is one of a :func:`parallel_map`'s workers."""
    return getattr(_local, "inside", False)


def parallel_map(fn: Callable[[Any], Any], items: Iterable[Any], workers: int | None = None,
                 ordered: bool = True) -> Iterator[Any]:
    """Yield ``fn(item)`` for every item, computed in up to ``workers`` threads.

    Parameters
    ----------
    fn : callable
        Any callable (closures included); it must be safe to call from several threads at once
        on the objects it shares (the diagnosis's caches are locked).
    items : iterable
    workers : int, optional
        Default :data:`WORKERS` (read at the call). 1, or called from a worker, or a single item:
        computed here, in order. The results do not depend on it (each piece is computed alone).
    ordered : bool
        Yield in the items' order (else as they finish).

    Raises
    ------
    Exception
        The first exception an ``fn`` raised, once the pieces already running have ended (the
        others are not started).
    """
    items = list(items)
    workers = min(int(WORKERS if workers is None else workers), len(items))
    if workers <= 1 or in_worker():
        for item in items:
            yield fn(item)
        return

    def run(item):
        _local.inside = True
        try:
            return fn(item)
        finally:
            _local.inside = False

    pool = ThreadPoolExecutor(workers, thread_name_prefix="doe-fit")
    try:
        futures = [pool.submit(run, item) for item in items]
        if ordered:
            for future in futures:
                yield future.result()
            return
        pending = set(futures)
        while pending:
            done, pending = wait(pending, return_when=FIRST_COMPLETED)
            for future in done:
                yield future.result()
    finally:
        # Reached on success, on an error and on an early close alike: what has not started never
        # will, and the threads are joined before the call returns.
        pool.shutdown(wait=True, cancel_futures=True)
