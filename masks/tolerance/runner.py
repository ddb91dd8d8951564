"""Run tolerance jobs in process or on a dask.distributed cluster, resumably.

A job is a dict ``{"id", "kind", "index", "seed", "values"}``; its result adds ``metrics``.
Each finished result is written at once to ``DIR/samples/<id>.json`` (atomically, by the
client), so a rerun with the same folder skips it and a worker that dies loses only the
batch it was computing, which the scheduler runs again elsewhere. ``DIR/run.json`` holds a
key of the inputs; a folder filled by another run is refused rather than mixed.

Results never depend on the worker: every job carries its own seed (see
:func:`masks.tolerance.spec.sample_seed`) and the PSF engine is deterministic.

On GPUs (``--device gpu``) the local cluster has one single-threaded worker process per
visible GPU, each started with ``CUDA_VISIBLE_DEVICES`` naming its own GPU, so each sees one
device (its device 0) and the GPUs never share a worker (:func:`gpu_worker_devices`).
"""

from __future__ import annotations

import contextlib
import hashlib
import itertools
import json
import logging
import math
import os
from collections.abc import Iterable, Iterator, Sized
from pathlib import Path
from typing import TYPE_CHECKING

from doedesign.errors import DoeError
from doedesign.fileio import write_json
from doedesign.progress import Progress

from .evaluate import Evaluator, evaluate_batch
from .scheduler import PROBE_TIMEOUT_S, probe_scheduler

if TYPE_CHECKING:
    from distributed import Client

__all__ = ["SCHEDULERS", "batch_size", "gpu_worker_devices", "load_done", "local_workers", "make_client", "n_workers",
           "open_store", "run_jobs", "run_key", "visible_gpus"]

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
        result = _load_one(samples_dir, job_id)
        if result is not None:
            done[job_id] = result
    return done


def _load_one(samples_dir, job_id):
    path = Path(samples_dir) / f"{job_id}.json"
    if not path.is_file():
        return None
    try:
        return json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError):
        log.warning("%s: unreadable, recomputing", path)
        return None


def batch_size(seconds_per_job: float, n_jobs: int, n_workers: int) -> int:
    """Jobs per task: about ``TARGET_TASK_S`` of work, at least two tasks per worker."""
    by_time = max(1, int(TARGET_TASK_S / max(seconds_per_job, 1e-3)))
    by_spread = max(1, math.ceil(n_jobs / (2 * max(n_workers, 1))))
    return max(1, min(by_time, by_spread))


def visible_gpus() -> list[str]:
    """The CUDA devices this process may use, as ``CUDA_VISIBLE_DEVICES`` names them: that
    variable's entries when it is set, else ``0`` to ``n - 1`` for the n devices CuPy counts."""
    listed = os.environ.get("CUDA_VISIBLE_DEVICES")
    if listed is not None:
        return [d.strip() for d in listed.split(",") if d.strip()]
    try:
        import cupy

        return [str(i) for i in range(cupy.cuda.runtime.getDeviceCount())]
    except Exception:  # no CuPy or no driver: no GPU to give a worker
        return []


def gpu_worker_devices(workers: int | None = None, devices: list[str] | None = None) -> list[str]:
    """The GPU each local worker is pinned to (its ``CUDA_VISIBLE_DEVICES``): one worker per
    visible GPU, or ``workers`` of them dealt round the GPUs.

    Parameters
    ----------
    workers : int, optional
        Number of workers (default: one per GPU).
    devices : list of str, optional
        The GPUs (default :func:`visible_gpus`).
    """
    devices = visible_gpus() if devices is None else list(devices)
    if not devices:
        raise DoeError("--device gpu: no visible CUDA device to give the dask workers")
    n = len(devices) if workers is None else int(workers)
    if n < 1:
        raise DoeError(f"--workers {workers}: need at least one worker")
    return [devices[i % len(devices)] for i in range(n)]


def _gpu_cluster(devices: list[str]):
    """A local cluster of one single-threaded worker process per entry of ``devices``, each
    seeing only that GPU. LocalCluster gives every worker the same environment, so the
    workers are listed one by one (as dask-cuda's cluster does)."""
    from distributed import Nanny, Scheduler, SpecCluster
    from distributed.system import MEMORY_LIMIT

    host = "127.0.0.1"
    scheduler = {"cls": Scheduler, "options": {"host": host, "protocol": "tcp://", "dashboard": False,
                                               "dashboard_address": None}}
    workers = {f"gpu-{i}-{device}": {"cls": Nanny, "options": {
        "host": host, "protocol": "tcp://", "nthreads": 1, "memory_limit": MEMORY_LIMIT // len(devices),
        "dashboard": False, "dashboard_address": None, "silence_logs": logging.CRITICAL,
        "env": {"CUDA_VISIBLE_DEVICES": device}}} for i, device in enumerate(devices)}
    return SpecCluster(workers=workers, scheduler=scheduler, silence_logs=logging.CRITICAL)


def local_workers(scheduler: str, workers: int | None = None, gpu: bool = False) -> int:
    """Worker processes (or threads) a local cluster of :func:`make_client` will have."""
    if gpu:
        return len(gpu_worker_devices(workers)) if scheduler == "processes" else int(workers or 1)
    return int(workers or os.cpu_count() or 1)


@contextlib.contextmanager
def make_client(scheduler: str = "processes", workers: int | None = None,
                gpu: bool = False) -> Iterator[Client | None]:
    """A dask client: a LocalCluster of processes or threads, an existing cluster, or None (inline).

    ``workers`` defaults to the machine's cores, or with ``gpu`` and ``processes`` to one
    single-threaded worker per visible GPU, each pinned to its GPU (:func:`gpu_worker_devices`);
    ``threads`` on a GPU default to one (each thread holds a sample in device memory).
    ``tcp://host:port`` connects to a running dask.distributed scheduler as is (SLURM via
    dask-jobqueue, Kubernetes, ...).
    """
    if scheduler == "inline":
        yield None
        return
    from distributed import Client, LocalCluster

    n = int(workers or (1 if gpu else os.cpu_count()) or 1)
    if n < 1:
        raise DoeError(f"--workers {workers}: need at least one worker")
    if "://" in scheduler:
        probe_scheduler(scheduler)  # a bounded check first: dask itself waits on a silent peer forever
        try:
            client = Client(scheduler, timeout=f"{PROBE_TIMEOUT_S}s")
        except (OSError, TimeoutError, ValueError) as exc:
            raise DoeError(f"--scheduler {scheduler}: cannot connect: {exc}") from None
        with client:
            yield client
        return
    if scheduler not in SCHEDULERS:
        raise DoeError(f"--scheduler {scheduler!r}: use {', '.join(SCHEDULERS)} or tcp://HOST:PORT")
    processes = scheduler == "processes"
    if gpu and processes:
        devices = gpu_worker_devices(workers)
        log.info("one dask worker per GPU: CUDA_VISIBLE_DEVICES %s", ", ".join(devices))
        with _quiet_dask():
            with _gpu_cluster(devices) as cluster, Client(cluster) as client:
                yield client
        return
    with _quiet_dask():
        cluster = LocalCluster(n_workers=n if processes else 1, threads_per_worker=1 if processes else n,
                               processes=processes, dashboard_address=None, silence_logs=logging.CRITICAL)
        with cluster, Client(cluster) as client:
            yield client


@contextlib.contextmanager
def _quiet_dask():
    """Keep dask's own log lines (cluster start, worker shutdown races) off a run without ``-v``.

    A local cluster's shutdown, with workers still busy on few cores, makes the nannies kill
    them and their heartbeats log tracebacks against the closed scheduler: noise, not errors
    of the run (any failure of a task reaches :func:`run_jobs` as an exception).
    """
    dask_log = logging.getLogger("distributed")
    level = dask_log.level
    if logging.getLogger().getEffectiveLevel() > logging.INFO:
        dask_log.setLevel(logging.CRITICAL)
    try:
        yield
    finally:
        dask_log.setLevel(level)


def n_workers(client: Client | None) -> int:
    """Threads available on the client's cluster (1 inline)."""
    if client is None:
        return 1
    return max(sum(client.nthreads().values()), 1)


def run_jobs(evaluator: Evaluator, jobs: Iterable[dict], samples_dir: str | Path, client: Client | None = None,
             seconds_per_job: float = 1.0, desc: str = "tolerance", total: int | None = None) -> dict:
    """Evaluate ``jobs`` (skipping those already in ``samples_dir``); results by job id.

    Jobs are taken from the iterable as work is handed out (at most a few tasks per worker
    in flight), so a million samples start at once and are never all held as jobs.

    Parameters
    ----------
    evaluator : masks.tolerance.evaluate.Evaluator
        Scattered once to every worker.
    jobs : iterable of dict
    samples_dir : path
        One JSON file per finished job, written as it completes.
    client : distributed.Client or None
        None evaluates in this process.
    seconds_per_job : float
        Measured cost of one job, to size the batches.
    total : int, optional
        Number of jobs (default ``len(jobs)``).
    """
    if total is None:
        if not isinstance(jobs, Sized):  # a generator: its length is known once it is listed
            jobs = list(jobs)
        total = len(jobs)
    total = int(total)
    results = {}
    with Progress(total, desc=desc) as bar:

        def keep(result):
            write_json(Path(samples_dir) / f"{result['id']}.json", result)
            results[result["id"]] = result
            bar.update(1, status=result["id"])

        def todo_jobs():
            for job in jobs:
                done = _load_one(samples_dir, job["id"])
                if done is None:
                    yield job
                else:
                    results[job["id"]] = done
                    bar.update(1, status="resumed")

        todo = todo_jobs()
        if client is None:
            for job in todo:
                keep(evaluator(job))
            return results
        from distributed import as_completed

        _LOST_WORK = _lost_work_errors()
        workers = n_workers(client)
        size = batch_size(seconds_per_job, total, workers)
        remote = None
        batches = {}
        pending = as_completed()

        def submit(batch):
            nonlocal remote
            if remote is None:  # a lost worker can take the scattered evaluator with it: scatter again
                remote = client.scatter(evaluator, broadcast=True, hash=False)
            future = client.submit(evaluate_batch, remote, batch, pure=False)
            batches[future] = batch
            pending.add(future)

        def submit_next():
            batch = list(itertools.islice(todo, size))
            if batch:
                submit(batch)
            return bool(batch)

        while len(batches) < 4 * workers and submit_next():
            pass
        log.info("batches of %d jobs, at most %d tasks in flight", size, 4 * workers)
        for future in pending:
            batch = batches.pop(future)
            try:
                results_of_batch = future.result()
            except Exception as exc:
                if not isinstance(exc, _LOST_WORK):
                    raise
                log.warning("task lost (%s); resubmitting %d jobs", type(exc).__name__, len(batch))
                remote = None
                submit(batch)
                continue
            for result in results_of_batch:
                keep(result)
            submit_next()
    return results
