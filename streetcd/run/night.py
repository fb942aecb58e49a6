"""A night, start to end: the one sequence that ``streetcd run``, the tests and the Prefect
flow all run.

    lock the index → (ingest new MLS files) → plan → register the plan → hand the batches to
    the Dask workers → publish each segment as its batches end → close the run

:func:`run_night` does it. How each step is run and reported is the :class:`Tracker`'s: the
plain one here calls the steps and logs to ``streetcd.run``; the Prefect flow
(``flows/nightly.py``) passes one that makes each step a Prefect task, and adds nothing else.
The per-view work goes to Dask directly (one Dask task per batch of consecutive views,
:class:`~streetcd.run.dispatch.Dispatcher`), so a city's thousands of images never become
thousands of tracked task runs.

One run at a time per index: the run holds the index's run lock (``<index>.lock``) from start
to end, and a second run on the same index fails at once, naming the holder. The Dask cluster
(a LocalCluster of ``run.workers`` processes, or the scheduler given) starts while the run is
planned.
"""

from __future__ import annotations

import contextlib
import logging
import time
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any, Protocol, TypeVar

from distributed import Client

from streetcd.config import Config
from streetcd.run.cluster import dask_client_soon
from streetcd.run.dispatch import Dispatcher
from streetcd.run.plan import Plan, plan_run
from streetcd.run.publish import (
    RunSummary,
    finish_run,
    new_summary,
    open_index,
    publish_segment,
    register_plan,
)
from streetcd.run.worker import detect_batch
from streetcd.store.ingest import ingest
from streetcd.store.locks import run_lock

T = TypeVar("T")
Logger = logging.Logger | logging.LoggerAdapter  # Prefect's run logger is an adapter

# Each segment's publisher mostly waits for its batches, so threads, not cores, bound how
# many segments are in flight; 32 keeps a few dozen workers busy with whole segments.
SEGMENTS_IN_FLIGHT = 32


@dataclass(frozen=True)
class NightInputs:
    """What a night reads and writes. images, poses : tonight's images folder and their pose
    file. store : the tile store of the reference cloud; ``archive`` new LAS/LAZ files to add
    to it first. index, out : the change index (SQLite) and the folder for masks and
    overlays."""

    images: str
    poses: str
    store: str
    index: str
    out: str
    archive: str | None = None


class Tracker(Protocol):
    """How the steps of a night are run and reported."""

    def step(self, name: str, fn: Callable[..., T], *args: Any, **kwargs: Any) -> T:
        """``fn(*args, **kwargs)``, run as the step called ``name``."""
        ...

    def each(self, name: str, fn: Callable[[str], T], items: Sequence[str]) -> list[T]:
        """``fn(item)`` for every item at once (threads), as steps called ``name``; results in
        the order of ``items``."""
        ...

    def logger(self) -> Logger:
        """Where the night's progress lines go."""
        ...


class PlainTracker:
    """Runs the steps as plain calls and logs to the ``streetcd.run`` logger."""

    def step(self, name: str, fn: Callable[..., T], *args: Any, **kwargs: Any) -> T:
        return fn(*args, **kwargs)

    def each(self, name: str, fn: Callable[[str], T], items: Sequence[str]) -> list[T]:
        with ThreadPoolExecutor(max(1, min(SEGMENTS_IN_FLIGHT, len(items))), name) as pool:
            return list(pool.map(fn, items))

    def logger(self) -> logging.Logger:
        return logging.getLogger("streetcd.run")


def run_night(
    inputs: NightInputs,
    config: Config = Config(),
    *,
    scheduler: str | None = None,
    client: Client | None = None,
    retry_failed: bool = False,
    tracker: Tracker | None = None,
    holder: str = "a streetcd run",
) -> RunSummary:
    """One night (see the module docstring); returns its summary.

    scheduler : a Dask scheduler address; default ``$STREETCD_SCHEDULER``, else a LocalCluster
    of ``config.run.workers`` processes. client : an open ``distributed.Client`` to use
    instead (the tests' own cluster). retry_failed : detect again the views that failed
    before with the same inputs. holder : how the run lock names this run to a second one.
    """
    tracker = tracker or PlainTracker()
    log = tracker.logger()
    t0 = time.perf_counter()
    with run_lock(inputs.index, holder), _client_soon(client, scheduler, config) as starting:
        if inputs.archive:
            # files are read on the cluster (the store is on storage its workers share)
            tracker.step("ingest-archive", ingest_archive, inputs, starting.result(), log)
        plan = tracker.step("plan-segments", plan_night, inputs, config, retry_failed, log)
        summary = new_summary(plan)
        summary.plan_s = time.perf_counter() - t0
        segments = plan.segments_todo
        if segments:
            dask = starting.result()
            summary.wait_s = time.perf_counter() - t0 - summary.plan_s
            with contextlib.closing(Dispatcher(dask, plan, detect_batch).start()) as dispatcher:
                _log_cluster(log, dask)

                def publish(segment_id: str) -> RunSummary:
                    return _publish(plan, dispatcher, segment_id, log)

                for part in tracker.each("publish-segment", publish, segments):
                    summary.merge(part)
        finish_run(plan, summary)
        summary.wall_s = time.perf_counter() - t0
    _log_summary(log, summary)
    return summary


@contextlib.contextmanager
def _client_soon(client: Client | None, scheduler: str | None, config: Config) -> Iterator[Future]:
    """A Future of the run's Dask client: ``client`` itself, or one being started."""
    if client is not None:
        ready: Future = Future()
        ready.set_result(client)
        yield ready
        return
    with dask_client_soon(scheduler, config.run.workers) as starting:
        yield starting


def ingest_archive(inputs: NightInputs, client: Client, log: Logger) -> dict[str, int]:
    """Add the new or changed LAS/LAZ files of ``inputs.archive`` to the tile store, one file
    per task on the run's Dask cluster; files that fail are logged and the night goes on."""
    assert inputs.archive is not None
    result = ingest(inputs.archive, inputs.store, client=client)
    log.info(
        "ingest: %d new file(s), %d unchanged, %d failed, %d points, %d tiles",
        len(result.ingested),
        len(result.skipped),
        len(result.failed),
        result.points,
        result.tiles,
    )
    for path, error in sorted(result.failed.items()):
        log.warning("ingest failed for %s: %s", path, error)
    return {
        "ingested": len(result.ingested),
        "skipped": len(result.skipped),
        "failed": len(result.failed),
    }


def plan_night(inputs: NightInputs, config: Config, retry_failed: bool, log: Logger) -> Plan:
    """Plan the night (:func:`~streetcd.run.plan.plan_run`) and record the plan in the index."""
    open_index(inputs.index)
    plan = plan_run(
        inputs.images,
        inputs.poses,
        inputs.store,
        inputs.index,
        inputs.out,
        config,
        retry_failed=retry_failed,
    )
    register_plan(plan)
    log.info(
        "run %s: %d views in %d segments; %d already in the index, %d to detect in %d batches,"
        " %d failed before detection",
        plan.run_id,
        plan.n_views,
        len(plan.segments),
        plan.n_skipped,
        plan.n_todo,
        len(plan.batches),
        len(plan.failed_at_plan),
    )
    return plan


def _publish(plan: Plan, dispatcher: Dispatcher, segment_id: str, log: Logger) -> RunSummary:
    """Publish one segment's batches as they end (:func:`~streetcd.run.publish.publish_segment`)."""
    t0 = time.perf_counter()
    s = publish_segment(plan, dispatcher.finished(segment_id))
    log.info(
        "segment %s: %d views done, %d flagged, %d failed in %.1f s",
        segment_id,
        s.n_done,
        s.n_flagged,
        s.n_failed,
        time.perf_counter() - t0,
    )
    return s


def _log_cluster(log: Logger, client: Client) -> None:
    log.info(
        "dask: %s with %d worker(s), dashboard %s",
        client.scheduler.address,
        len(client.scheduler_info(n_workers=-1)["workers"]),
        client.dashboard_link,
    )


def _log_summary(log: Logger, summary: RunSummary) -> None:
    log.info(
        "run %s finished in %.1f s: %d views, %d skipped, %d done, %d flagged, %d failed",
        summary.run_id,
        summary.wall_s,
        summary.n_views,
        summary.n_skipped,
        summary.n_done,
        summary.n_flagged,
        summary.n_failed,
    )
    for view, error in summary.failures:
        log.warning("failed: %s: %s", view, error)
    if summary.n_lost:
        log.warning(
            "%d views were lost with their batches (see the log above); the next run retries them",
            summary.n_lost,
        )
