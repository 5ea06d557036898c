"""Where a batch's tasks run: Dask (local cluster or a cluster's address) or a process pool.

Every engine is a ``concurrent.futures.Executor``, so the batch and the sweep have one code
path: ``submit`` a task per log, collect with ``as_completed``.

* ``dask`` - ``distributed.Client``: with ``address=None`` on Dask's own ``LocalCluster``
  (no set-up), else on the scheduler at ``address`` (``tcp://host:8786``; the workers need
  decod installed and the logs on a shared path). Installed by the ``batch`` extra
  (``pip install 'decod-rs[batch]'``) and imported only here, only when used.
* ``processes`` - a local ``ProcessPoolExecutor`` (spawned workers): the fallback when Dask
  is not installed.
* ``serial`` - the tasks in this process, one after another (debugging, ``--workers 1``).
* ``auto`` - ``dask`` if it is installed, else ``processes``.

Memory: a worker runs one log at a time (one thread per Dask worker, one task per pool
process), and a run's memory is bounded by the submaps in flight (the Rust ``LogProcessor``),
so a worker needs what one ``decod run`` needs. Dask also enforces ``memory_per_worker``
(its nanny pauses a worker at 80 % and restarts it at 95 %). Each local worker's Rust
(rayon) pool gets ``cores // workers`` threads so that the workers do not oversubscribe
the cores.
"""

from __future__ import annotations

import importlib
import importlib.util
import logging
import multiprocessing
import os
from collections.abc import Callable, Iterator
from concurrent.futures import Executor, Future, ProcessPoolExecutor
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any, ParamSpec, TypeVar

ENGINES = ("auto", "dask", "processes", "serial")
INSTALL_HINT = "pip install 'decod-rs[batch]'"

P = ParamSpec("P")
T = TypeVar("T")

__all__ = ["ENGINES", "Engine", "SerialExecutor", "dask_available", "open_engine"]


@dataclass
class Engine:
    """An open engine: its executor, which kind it is, and how many tasks run at once."""

    executor: Executor
    kind: str
    workers: int
    description: str


class SerialExecutor(Executor):
    """Runs each task at ``submit``, in this process; the future is already done."""

    def submit(self, fn: Callable[P, T], /, *args: P.args, **kwargs: P.kwargs) -> Future[T]:
        future: Future[T] = Future()
        try:
            future.set_result(fn(*args, **kwargs))
        except BaseException as exc:
            future.set_exception(exc)
        return future


def dask_available() -> bool:
    """Whether ``dask.distributed`` can be imported (the ``batch`` extra)."""
    return importlib.util.find_spec("distributed") is not None


def cores() -> int:
    """The cores this process may use."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1


def worker_env(workers: int) -> dict[str, str]:
    """Thread counts for local workers: the cores shared out, unless the user set them."""
    threads = str(max(1, cores() // max(1, workers)))
    env = {"RAYON_NUM_THREADS": threads, "OMP_NUM_THREADS": threads}
    return {k: os.environ.get(k, v) for k, v in env.items()}


def _set_env(env: dict[str, str]) -> None:
    os.environ.update(env)


@contextmanager
def _dask(address: str | None, workers: int, memory: str | None) -> Iterator[Engine]:
    # Imported here, only when used; typed Any (distributed ships no complete stubs).
    distributed: Any = importlib.import_module("distributed")
    Client, LocalCluster = distributed.Client, distributed.LocalCluster
    if address is not None:
        client = Client(address)
        try:
            n = len(client.scheduler_info().get("workers", {}))
            yield Engine(client.get_executor(pure=False), "dask", n, f"dask cluster {address}")
        finally:
            client.close()
        return
    cluster = LocalCluster(
        n_workers=workers,
        threads_per_worker=1,
        processes=True,
        memory_limit=memory or "auto",
        dashboard_address=None,
        silence_logs=logging.ERROR,
        env=worker_env(workers),
    )
    client = Client(cluster)
    try:
        limit = f", {memory} each" if memory else ""
        description = f"dask local cluster, {workers} workers{limit}"
        yield Engine(client.get_executor(pure=False), "dask", workers, description)
    finally:
        client.close()
        cluster.close()


@contextmanager
def open_engine(
    kind: str = "auto",
    *,
    address: str | None = None,
    workers: int | None = None,
    memory_per_worker: str | None = None,
) -> Iterator[Engine]:
    """Open the engine ``kind`` (module doc) for the duration of the ``with`` block.

    ``workers`` defaults to the cores of this machine (local engines only);
    ``memory_per_worker`` (``"4GiB"``) is Dask's per-worker limit (default: the machine's
    memory shared out). An ``address`` needs Dask. Raises ``ImportError`` naming the extra
    when Dask is asked for but not installed, ``ValueError`` for a bad argument.
    """
    if kind not in ENGINES:
        raise ValueError(f"engine: {kind!r} is not one of {ENGINES}")
    if workers is not None and workers < 1:
        raise ValueError(f"workers: expected >= 1, got {workers}")
    n = workers or cores()
    if kind == "auto":
        kind = "dask" if dask_available() or address is not None else "processes"
    if kind != "dask" and address is not None:
        raise ValueError(f"--address needs the dask engine, not {kind!r}")
    if kind == "dask":
        if not dask_available():
            raise ImportError(f"the dask engine needs dask.distributed: {INSTALL_HINT}")
        with _dask(address, n, memory_per_worker) as engine:
            yield engine
        return
    if kind == "serial":
        yield Engine(SerialExecutor(), "serial", 1, "serial, in this process")
        return
    pool = ProcessPoolExecutor(
        max_workers=n,
        mp_context=multiprocessing.get_context("spawn"),
        initializer=_set_env,
        initargs=(worker_env(n),),
    )
    note = f" ({memory_per_worker} per worker not enforced: dask only)" if memory_per_worker else ""
    with pool:
        yield Engine(pool, "processes", n, f"local process pool, {n} workers{note}")
