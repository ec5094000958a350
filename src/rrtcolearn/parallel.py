"""One execution layer for chunked, seeded work: serial, local processes, or a Dask cluster.

Work is a list of picklable tasks, each carrying its own seed (spawned from one
``SeedSequence``), and a top-level function applied to each. Results come back in task order
whatever the backend or the number of workers, so they are bit-identical across both.
``on_result(index, result)`` runs in the calling process as each task finishes: that is where
finished chunks are written as shards, and where progress is reported.
"""

from __future__ import annotations

import atexit
import multiprocessing
import os
from collections.abc import Callable, Sequence
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from dataclasses import dataclass
from typing import Any, Literal

from rrtcolearn.errors import ConfigError

_THREAD_VARS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS",
                "NUMEXPR_NUM_THREADS", "NUMBA_NUM_THREADS", "VECLIB_MAXIMUM_THREADS")


@dataclass(frozen=True)
class ExecutionSettings:
    """Where tasks run.

    backend : "serial", "processes" (``workers`` local processes) or "dask" (the cluster at
        ``scheduler``, e.g. ``tcp://host:8786``, or a new LocalCluster of ``workers``).
    """

    backend: Literal["serial", "processes", "dask"] = "serial"
    workers: int = 1
    scheduler: str | None = None
    retries: int = 3

    @classmethod
    def from_options(cls, workers: int | None = None, scheduler: str | None = None,
                     dask_local: int | None = None) -> ExecutionSettings:
        """The backend chosen by ``--workers``, ``--scheduler`` and ``--dask-local``."""
        if sum(x is not None for x in (scheduler, dask_local)) > 1:
            raise ConfigError("use either --scheduler or --dask-local, not both")
        if workers is not None and workers < 1:
            raise ConfigError("--workers must be at least 1")
        if dask_local is not None:
            if dask_local < 1:
                raise ConfigError("--dask-local must be at least 1")
            return cls("dask", dask_local)
        if scheduler is not None:
            return cls("dask", workers or 1, scheduler)
        n = workers if workers is not None else 1
        return cls("serial" if n == 1 else "processes", n)


def pin_threads() -> None:
    """One BLAS/OpenMP/numba thread per worker process, so workers do not oversubscribe cores."""
    for var in _THREAD_VARS:
        os.environ[var] = "1"


def map_tasks(fn: Callable[[Any], Any], tasks: Sequence[Any],
              settings: ExecutionSettings | None = None,
              on_result: Callable[[int, Any], None] | None = None) -> list[Any]:
    """``[fn(t) for t in tasks]`` on the chosen backend, in task order."""
    settings = settings or ExecutionSettings()
    results: list[Any] = [None] * len(tasks)

    def done(i: int, r: Any) -> None:
        results[i] = r
        if on_result is not None:
            on_result(i, r)

    if not tasks:
        return results
    if settings.backend == "serial":
        for i, t in enumerate(tasks):
            done(i, fn(t))
    elif settings.backend == "processes":
        _map_processes(fn, tasks, settings.workers, done)
    elif settings.backend == "dask":
        _map_dask(fn, tasks, settings, done)
    else:
        raise ConfigError(f"unknown execution backend {settings.backend!r}")
    return results


_POOLS: dict[int, ProcessPoolExecutor] = {}


def _pool(workers: int) -> ProcessPoolExecutor:
    """A pool of ``workers`` processes, kept for later calls: starting a worker (an
    interpreter, numpy, the compiled kernels) costs about a second."""
    if workers not in _POOLS:
        # spawn: workers start clean and read the pinned thread counts before numpy loads
        saved = {v: os.environ.get(v) for v in _THREAD_VARS}
        pin_threads()
        try:
            _POOLS[workers] = ProcessPoolExecutor(
                max_workers=workers, mp_context=multiprocessing.get_context("spawn"))
        finally:
            for v, value in saved.items():
                if value is None:
                    os.environ.pop(v, None)
                else:
                    os.environ[v] = value
    return _POOLS[workers]


def shutdown_pools() -> None:
    """Stop the kept worker processes."""
    while _POOLS:
        _POOLS.popitem()[1].shutdown(wait=True, cancel_futures=True)


atexit.register(shutdown_pools)


def _map_processes(fn, tasks, workers: int, done) -> None:
    pool = _pool(workers)
    pending = {pool.submit(fn, t): i for i, t in enumerate(tasks)}
    try:
        while pending:
            finished, _ = wait(pending, return_when=FIRST_COMPLETED)
            for f in finished:
                done(pending.pop(f), f.result())
    except BaseException:
        for f in pending:
            f.cancel()
        # a pool interrupted mid-task may hold broken workers: start afresh next time
        _POOLS.pop(workers, None)
        pool.shutdown(wait=False, cancel_futures=True)
        raise


def _existing_client(address: str):
    """A client of this process already connected to ``address`` (reused, never closed)."""
    from distributed import default_client

    try:
        client = default_client()
    except ValueError:
        return None
    return client if client.scheduler.address == address else None


def _map_dask(fn, tasks, settings: ExecutionSettings, done) -> None:
    try:
        from distributed import Client, LocalCluster, as_completed
    except ImportError:
        raise ConfigError("the Dask backend needs the optional extra: "
                          "pip install 'rrtcolearn[dask]'") from None
    cluster = None
    client = None if settings.scheduler is None else _existing_client(settings.scheduler)
    owned = client is None
    if settings.scheduler is None:
        cluster = LocalCluster(n_workers=settings.workers, threads_per_worker=1,
                               processes=True, dashboard_address=None,
                               env={v: "1" for v in _THREAD_VARS})
        client = Client(cluster)
    elif client is None:
        try:
            client = Client(settings.scheduler, timeout="20s")
        except OSError as exc:
            raise ConfigError(f"cannot reach the Dask scheduler {settings.scheduler}: {exc}"
                              ) from None
    try:
        # a worker lost mid-run costs only its tasks: the scheduler reruns them elsewhere
        futures = client.map(fn, list(tasks), pure=False, retries=settings.retries)
        index = {f.key: i for i, f in enumerate(futures)}
        for f, result in as_completed(futures, with_results=True):
            done(index[f.key], result)
    finally:
        if owned:
            client.close()
        if cluster is not None:
            cluster.close()
