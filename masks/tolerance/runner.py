"""Run tolerance jobs in process or on a dask.distributed cluster, resumably.

A job is a dict ``{"id", "kind", "index", "seed", "values"}``; its result adds ``metrics``.
Each finished result is written at once to ``DIR/samples/<id>.json`` (atomically, by the
client), so a rerun with the same folder skips it and a worker that dies loses only the
batch it was computing, which the scheduler runs again elsewhere. ``DIR/run.json`` holds a
key of the inputs; a folder filled by another run is refused rather than mixed.

Results never depend on the worker: every job carries its own seed (see
:func:`masks.tolerance.spec.sample_seed`) and the PSF engine is deterministic.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import logging
import math
import os
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import TYPE_CHECKING

from doedesign.errors import DoeError
from doedesign.fileio import write_json
from doedesign.progress import Progress

from .evaluate import Evaluator, evaluate_batch

if TYPE_CHECKING:
    from distributed import Client

__all__ = ["SCHEDULERS", "batch_size", "load_done", "make_client", "n_workers", "open_store", "run_jobs",
           "run_key"]

log = logging.getLogger(__name__)

# A task should take seconds: batches hold about this much work.
TARGET_TASK_S = 2.0
SCHEDULERS = ("processes", "threads", "inline")


def _lost_work_errors():
    """The exceptions dask.distributed raises when a task's worker or inputs were lost."""
    from distributed.client import FutureCancelledError
    from distributed.scheduler import KilledWorker

    return (FutureCancelledError, KilledWorker)


def run_key(parts: dict) -> str:
    """Short hash of the run's inputs (design, spec, seed, sampling)."""
    text = json.dumps(parts, sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def open_store(out_dir: str | Path, key: str, description: dict) -> Path:
    """Create or reopen ``out_dir``; refuse one that holds another run's samples."""
    out = Path(out_dir)
    (out / "samples").mkdir(parents=True, exist_ok=True)
    marker = out / "run.json"
    if marker.is_file():
        try:
            old = json.loads(marker.read_text()).get("key")
        except (json.JSONDecodeError, UnicodeDecodeError):
            old = None
        if old != key:
            raise DoeError(f"{out}: holds samples of another run (different design, spec, seed or sampling); "
                           "use a new --out folder")
    else:
        write_json(marker, {"key": key, **description})
    return out / "samples"


def load_done(samples_dir: str | Path, ids: Iterable[str]) -> dict:
    """Results already written for these job ids."""
    done = {}
    for job_id in ids:
        path = Path(samples_dir) / f"{job_id}.json"
        if path.is_file():
            try:
                done[job_id] = json.loads(path.read_text())
            except (json.JSONDecodeError, UnicodeDecodeError):
                log.warning("%s: unreadable, recomputing", path)
    return done


def batch_size(seconds_per_job: float, n_jobs: int, n_workers: int) -> int:
    """Jobs per task: about :data:`TARGET_TASK_S` of work, at least two tasks per worker."""
    by_time = max(1, int(TARGET_TASK_S / max(seconds_per_job, 1e-3)))
    by_spread = max(1, math.ceil(n_jobs / (2 * max(n_workers, 1))))
    return max(1, min(by_time, by_spread))


@contextlib.contextmanager
def make_client(scheduler: str = "processes", workers: int | None = None) -> Iterator[Client | None]:
    """A dask client: a LocalCluster of processes or threads, an existing cluster, or None (inline).

    ``workers`` defaults to the machine's cores. ``tcp://host:port`` connects to a running
    dask.distributed scheduler as is (SLURM via dask-jobqueue, Kubernetes, ...).
    """
    if scheduler == "inline":
        yield None
        return
    from distributed import Client, LocalCluster

    n = int(workers or os.cpu_count() or 1)
    if n < 1:
        raise DoeError(f"--workers {workers}: need at least one worker")
    if scheduler.startswith("tcp://") or scheduler.startswith("tls://"):
        try:
            client = Client(scheduler, timeout="20s")
        except (OSError, TimeoutError) as exc:
            raise DoeError(f"--scheduler {scheduler}: cannot connect: {exc}") from None
        with client:
            yield client
        return
    if scheduler not in SCHEDULERS:
        raise DoeError(f"--scheduler {scheduler!r}: use {', '.join(SCHEDULERS)} or tcp://HOST:PORT")
    processes = scheduler == "processes"
    cluster = LocalCluster(n_workers=n if processes else 1, threads_per_worker=1 if processes else n,
                           processes=processes, dashboard_address=None, silence_logs=logging.ERROR)
    with cluster, Client(cluster) as client:
        yield client


def n_workers(client: Client | None) -> int:
    """Threads available on the client's cluster (1 inline)."""
    if client is None:
        return 1
    return max(sum(client.nthreads().values()), 1)


def run_jobs(evaluator: Evaluator, jobs: list[dict], samples_dir: str | Path, client: Client | None = None,
             seconds_per_job: float = 1.0, desc: str = "tolerance") -> dict:
    """Evaluate ``jobs`` (skipping those already in ``samples_dir``); results by job id.

    Parameters
    ----------
    evaluator : masks.tolerance.evaluate.Evaluator
        Scattered once to every worker.
    jobs : list of dict
    samples_dir : path
        One JSON file per finished job, written as it completes.
    client : distributed.Client or None
        None evaluates in this process.
    seconds_per_job : float
        Measured cost of one job, to size the batches.
    """
    results = load_done(samples_dir, [j["id"] for j in jobs])
    todo = [j for j in jobs if j["id"] not in results]
    if results:
        log.info("resuming: %d of %d jobs already done", len(results), len(jobs))
    with Progress(len(jobs), desc=desc) as bar:
        bar.update(len(results), status="resumed")

        def keep(result):
            write_json(Path(samples_dir) / f"{result['id']}.json", result)
            results[result["id"]] = result
            bar.update(1, status=result["id"])

        if client is None:
            for job in todo:
                keep(evaluator(job))
        elif todo:
            from distributed import as_completed

            _LOST_WORK = _lost_work_errors()

            size = batch_size(seconds_per_job, len(todo), n_workers(client))
            remote = client.scatter(evaluator, broadcast=True, hash=False)
            batches = {}
            for i in range(0, len(todo), size):
                batches[client.submit(evaluate_batch, remote, todo[i:i + size], pure=False)] = todo[i:i + size]
            log.info("%d jobs in %d tasks of %d", len(todo), len(batches), size)
            pending = as_completed(list(batches))
            for future in pending:
                batch = batches.pop(future)
                try:
                    results_of_batch = future.result()
                except Exception as exc:  # a lost worker can take the scattered evaluator with it
                    if not isinstance(exc, _LOST_WORK):
                        raise
                    log.warning("task lost (%s); resubmitting %d jobs", type(exc).__name__, len(batch))
                    remote = client.scatter(evaluator, broadcast=True, hash=False)
                    again = client.submit(evaluate_batch, remote, batch, pure=False)
                    batches[again] = batch
                    pending.add(again)
                    continue
                for result in results_of_batch:
                    keep(result)
    return results
