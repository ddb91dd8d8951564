"""Independent pieces of a fit run side by side in forked processes.

A diagnosis spends its time in model evaluations that do not depend on each other: the
screening fits of the candidates, and the columns of a finite-difference Jacobian. Forked
workers see the problem (its data, its render caches) by copy-on-write memory, so nothing
large is pickled: only the task's index goes out and its result (a column, a fitted model)
comes back. A worker never forks again. The results are the same as in one process: every
piece is computed by the same code from the same state.

``concurrent.futures`` does the process management; this module only hands a closure to
forked workers, which the library cannot do by itself (it pickles the callable).
"""

from __future__ import annotations

import multiprocessing
import os
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import ProcessPoolExecutor, as_completed
from typing import Any

__all__ = ["WORKERS", "forked_map"]

# Processes that share the work (the machines this runs on have two cores).
WORKERS = min(2, os.cpu_count() or 1)
# The task a forked worker reads (set in the parent just before the fork).
_TASK: dict[str, Any] = {}
_IN_WORKER = False


def _mark_worker() -> None:
    global _IN_WORKER
    _IN_WORKER = True


def _run(i: int) -> Any:
    return _TASK["fn"](_TASK["items"][i])


def forked_map(fn: Callable[[Any], Any], items: Iterable[Any], workers: int = WORKERS,
               ordered: bool = True) -> Iterator[Any]:
    """Yield ``fn(item)`` for every item, computed in up to ``workers`` forked processes.

    Parameters
    ----------
    fn : callable
        Any callable, closures included (the workers inherit it; it is not pickled). Its
        results must pickle.
    items : iterable
    workers : int
        1, or inside a worker, or a single item: computed here, in order.
    ordered : bool
        Yield in the items' order (else as they finish).
    """
    items = list(items)
    workers = min(int(workers), len(items))
    if workers <= 1 or _IN_WORKER:
        for item in items:
            yield fn(item)
        return
    _TASK.update(fn=fn, items=items)
    try:
        with ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("fork"),
                                 initializer=_mark_worker) as pool:
            futures = [pool.submit(_run, i) for i in range(len(items))]
            for fut in (futures if ordered else as_completed(futures)):
                yield fut.result()
    finally:
        _TASK.clear()
