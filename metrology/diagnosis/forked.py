"""Independent pieces of a fit run side by side in forked processes.

A diagnosis spends its time in model evaluations that do not depend on each other: the
screening fits of the candidates, and the columns of a finite-difference Jacobian. Forked
workers see the problem (its data, its render caches) by copy-on-write memory, so nothing
large is pickled: only the task's index goes out and its result (a column, a fitted model)
comes back. A worker never forks again. The results are the same as in one process: every
piece is computed by the same code from the same state.

Written by hand on ``os.fork`` and two pipes per worker, with no thread in the parent:
``concurrent.futures.ProcessPoolExecutor`` pickles the callable (a closure cannot go), and
with the fork context it forks its workers on demand while its own feeder and manager threads
run. That lost a task about twice in 90 diagnoses (the parent waiting for a result, the worker
waiting for a task). Here every worker is forked before any task is handed out, the parent
hands out the next index to whichever worker answers (dynamic balance, as the pool had), and a
worker that dies is an error naming it, not a wait. The other hang seen (once in 30 CSI
diagnoses) was in ``fork()`` itself, in scipy.fft's thread pool's fork handler: no FFT of the
process starts that pool (:mod:`doedesign.engine.threaded_fft`).
"""

from __future__ import annotations

import gc
import os
import pickle
import signal
from collections.abc import Callable, Iterable, Iterator
from multiprocessing.connection import Connection, Pipe, wait
from typing import Any

__all__ = ["WORKERS", "ForkedWorkerError", "forked_map"]

# Processes that share the work (the machines this runs on have two cores).
WORKERS = min(2, os.cpu_count() or 1)
_IN_WORKER = False


class ForkedWorkerError(RuntimeError):
    """A forked worker ended without answering (killed, or out of memory)."""


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

    Raises
    ------
    Exception
        The first exception a worker's ``fn`` raised, re-raised here (its type kept where it
        pickles), after the workers are stopped.
    ForkedWorkerError
        A worker ended without a result.
    """
    items = list(items)
    workers = min(int(workers), len(items))
    if workers <= 1 or _IN_WORKER:
        for item in items:
            yield fn(item)
        return
    pool = _fork(fn, items, workers)
    try:
        yield from pool.results(ordered)
    finally:
        pool.stop()


class _Pool:
    """The parent's side: per worker its pid, the task pipe's sending end, the result pipe's reading end."""

    def __init__(self, n_items: int, pids: list[int], tasks: list[Connection], results: list[Connection]):
        self.n_items = n_items
        self.pids, self.tasks, self.results_in = pids, tasks, results
        self.done = False

    def results(self, ordered: bool) -> Iterator[Any]:
        next_i, received, buffered, want = 0, 0, {}, 0
        owner = {}
        for w, conn in enumerate(self.tasks):
            conn.send(next_i)
            owner[self.results_in[w]] = w
            next_i += 1
        busy = list(self.results_in)
        while received < self.n_items:
            for conn in wait(busy):
                w = owner[conn]
                try:
                    kind, i, value = pickle.loads(conn.recv_bytes())
                except EOFError:
                    raise ForkedWorkerError(f"forked worker {self.pids[w]} ended without a result "
                                            "(killed, or out of memory?)") from None
                if kind == "error":
                    raise value
                received += 1
                # The next piece goes out before this result is used: the worker never waits on us.
                if next_i < self.n_items:
                    self.tasks[w].send(next_i)
                    next_i += 1
                else:
                    busy.remove(conn)
                if not ordered:
                    yield value
                    continue
                buffered[i] = value
                while want in buffered:
                    yield buffered.pop(want)
                    want += 1
        self.done = True

    def stop(self) -> None:
        """End every worker: a stop message after a full run, else SIGKILL (an error or an early close)."""
        for pid, conn in zip(self.pids, self.tasks):
            if self.done:
                try:
                    conn.send(None)
                except OSError:
                    pass
            else:
                try:
                    os.kill(pid, signal.SIGKILL)
                except ProcessLookupError:
                    pass
        for conn in self.tasks + self.results_in:
            conn.close()
        for pid in self.pids:
            try:
                os.waitpid(pid, 0)
            except ChildProcessError:
                pass


def _fork(fn: Callable[[Any], Any], items: list, workers: int) -> _Pool:
    """Fork ``workers`` processes serving ``fn`` over ``items``; all pipes made before the first fork."""
    pipes = [(Pipe(duplex=False), Pipe(duplex=False)) for _ in range(workers)]
    pids = []
    # The objects that exist now stay out of the collector's passes until the workers are
    # forked, and a worker never collects: a collection walks every object it tracks and writes
    # its header, which copies each page of the parent's that the worker shares.
    gc.freeze()
    try:
        for w in range(workers):
            pid = os.fork()
            if pid == 0:
                _child(fn, items, pipes, w)
            pids.append(pid)
    except BaseException:
        for pid in pids:
            os.kill(pid, signal.SIGKILL)
            os.waitpid(pid, 0)
        for (a, b), (c, d) in pipes:
            for conn in (a, b, c, d):
                conn.close()
        raise
    finally:
        gc.unfreeze()
    # The parent keeps the task pipes' sending ends and the result pipes' reading ends.
    for (task_in, _), (_, result_out) in pipes:
        task_in.close()
        result_out.close()
    return _Pool(len(items), pids, [p[0][1] for p in pipes], [p[1][0] for p in pipes])


def _child(fn: Callable[[Any], Any], items: list, pipes: list, w: int) -> None:
    """A worker's whole life: never returns into the parent's code."""
    global _IN_WORKER
    _IN_WORKER = True
    gc.disable()
    code = 0
    try:
        # Only this worker's own ends stay open, so a dead sibling's pipe reads as closed.
        for v, ((task_in, task_out), (result_in, result_out)) in enumerate(pipes):
            task_out.close()
            result_in.close()
            if v != w:
                task_in.close()
                result_out.close()
        (tasks, _), (_, results) = pipes[w]
        while (i := tasks.recv()) is not None:
            try:
                payload = pickle.dumps(("ok", i, fn(items[i])))
            except Exception as exc:  # handed to the parent, which raises it
                payload = pickle.dumps(("error", i, _portable(exc)))
            results.send_bytes(payload)
    except BaseException:  # the parent is gone or stopped us: nothing to report to
        code = 1
    finally:
        os._exit(code)


def _portable(exc: Exception) -> Exception:
    """``exc`` if it pickles, else a RuntimeError carrying its type and message."""
    try:
        pickle.loads(pickle.dumps(exc))
        return exc
    except Exception:
        return RuntimeError(f"{type(exc).__name__}: {exc}")
