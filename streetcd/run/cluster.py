"""The Dask cluster a night runs on: a scheduler given by address, or a LocalCluster.

The settings here are the ones every streetcd worker runs with; ``infra/dask.yaml`` carries
the same for workers started by hand (``tests/test_flow.py`` checks that the two agree).
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from typing import Any

import dask
from distributed import Client, LocalCluster

from streetcd.errors import InputError
from streetcd.run.worker import warm_worker

SCHEDULER_ENV = "STREETCD_SCHEDULER"

# glibc settings for worker processes. Dask's nanny sets MALLOC_TRIM_THRESHOLD_=65536 to
# hand memory back to the OS early; setting any of these variables also freezes glibc's
# mmap threshold at 128 KiB, so every raster of a view (4-24 MB each) is mmapped, faulted
# in page by page and unmapped again (docs/BENCHMARKS.md, "Worker memory"). A worker that
# keeps its last view's memory for the next one is what we want; 32 MiB is glibc's largest
# mmap threshold.
WORKER_MALLOC_ENV = {
    "MALLOC_TRIM_THRESHOLD_": str(1 << 30),
    "MALLOC_MMAP_THRESHOLD_": str(32 << 20),
}

# Dask's periodic housekeeping, slowed down: with the defaults (an event-loop tick every
# 20 ms and a memory check every 100 ms in every process, a system monitor every 0.5 s) an
# idle cluster takes a share of a core that, on a 2-core machine, comes out of the
# detectors'. The tick only measures how long the event loop was blocked, and the system
# monitor only feeds the dashboard. The worker's statistical profiler (the dashboard's
# "Profile" page) is off: it wakes the worker's event loop every 10 ms to walk the running
# task's stack under the GIL (docs/BENCHMARKS.md, "Dask housekeeping"). Turn it back on to
# profile a worker.
QUIET_DASK = {
    "distributed.admin.tick.interval": "1s",
    "distributed.admin.system-monitor.interval": "5s",
    "distributed.worker.memory.monitor-interval": "1s",
    "distributed.worker.profile.enabled": False,
    # The scheduler keeps the last N messages it sent each worker (and the client the last N
    # it sent the scheduler), for debugging. At the default 1,000 those held ~2,000 batches'
    # tasks (each with its views and their neighbours) in the flow process: 290,000 objects
    # at 1,000 views that every full pass of Python's cycle collector walked, with the GIL
    # held, while the workers waited for their next batch (docs/BENCHMARKS.md).
    "distributed.admin.low-level-log-length": 50,
}


def local_worker_config() -> dict[str, Any]:
    """Dask settings for our LocalCluster: the malloc environment of
    :data:`WORKER_MALLOC_ENV` and :data:`QUIET_DASK`."""
    env = {f"distributed.nanny.pre-spawn-environ.{k}": v for k, v in WORKER_MALLOC_ENV.items()}
    return {**env, **QUIET_DASK}


@contextlib.contextmanager
def dask_client(
    scheduler: str | None = None, workers: int = 2, threads_per_worker: int = 1
) -> Iterator[Client]:
    """A ``distributed.Client``: to ``scheduler`` (or ``$STREETCD_SCHEDULER``) when given,
    else to a new LocalCluster of ``workers`` processes that is closed afterwards."""
    address = scheduler or os.environ.get(SCHEDULER_ENV) or None
    if address:
        with Client(address, set_as_default=False) as client:
            yield client
        return
    if workers < 1:
        raise InputError(f"workers = {workers} must be >= 1")
    # dashboard on a free port: ``None`` would still bind 8787 and warn when it is taken.
    with (
        dask.config.set(local_worker_config()),
        LocalCluster(
            n_workers=workers,
            threads_per_worker=threads_per_worker,
            processes=True,
            dashboard_address=":0",
        ) as cluster,
        Client(cluster, set_as_default=False) as client,
    ):
        yield client


@contextlib.contextmanager
def dask_client_soon(
    scheduler: str | None = None, workers: int = 2, threads_per_worker: int = 1
) -> Iterator[Future]:
    """:func:`dask_client` started in a background thread, its workers warmed up
    (:func:`~streetcd.run.worker.warm_worker`): yields a Future of the client, closed on
    leaving.

    Starting a LocalCluster and importing the detector in its workers takes seconds of
    CPU in other processes; the caller plans the run meanwhile. A run with nothing to do
    pays for a cluster it does not use, which is cheaper than making every run wait.
    """
    with contextlib.ExitStack() as stack:

        def start() -> Client:
            client = stack.enter_context(dask_client(scheduler, workers, threads_per_worker))
            client.run(warm_worker)
            return client

        # The pool is left first: it waits for a start in progress before the stack closes it.
        with ThreadPoolExecutor(1, thread_name_prefix="streetcd-dask-start") as pool:
            yield pool.submit(start)
