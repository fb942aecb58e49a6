"""A night, start to end: the one sequence that ``streetcd run``, the tests and the Prefect
flow all run.

    lock the index → check the inputs → (ingest new MLS files) → plan → register the plan →
    hand the batches to the Dask workers → publish each segment as its batches end → close the
    run → judge the night and write its summary JSON

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

**The night's verdict.** A night is good (exit code 0) when no more of its views failed than
``run.max_failed`` allows, counting the views that failed tonight, those lost with their
batches, and those of tonight's inputs that failed in an earlier run and were skipped
("still failing since <date>": they stay counted until retried with ``--retry-failed`` or
fixed); else it exits 3, and the Prefect flow ends Failed. Inputs that no view could
succeed with raise before the cluster starts (``streetcd run`` exits 2). Every run writes its
summary as JSON to ``<out>/runs/<run id>.json`` and ``<out>/runs/latest.json``
(:mod:`streetcd.run.summary`).
"""

from __future__ import annotations

import contextlib
import dataclasses
import gc
import logging
import time
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol, TypeVar

from distributed import Client

from streetcd.config import Config
from streetcd.errors import StreetcdError
from streetcd.run.check import CheckReport, check_inputs
from streetcd.run.cluster import dask_client_soon
from streetcd.run.dispatch import Dispatcher
from streetcd.run.plan import (
    NightListing,
    Plan,
    file_hash,
    image_name,
    lasting_key,
    plan_run,
)
from streetcd.run.publish import (
    ObjectBuilder,
    RunSummary,
    finish_run,
    new_summary,
    open_index,
    publish_segment,
    register_plan,
)
from streetcd.run.summary import (
    judge,
    still_failing_line,
    summary_json,
    write_input_error,
    write_summary,
)
from streetcd.run.worker import detect_batch
from streetcd.store.index import ChangeIndex, failed_views, utc_now
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
    started = utc_now()
    try:
        summary = _night(inputs, config, scheduler, client, retry_failed, tracker, holder, log)
    except StreetcdError as exc:  # the night did not run (or not to its end): say why, stop
        write_input_error(inputs.out, exc, started)
        raise
    finally:
        gc.unfreeze()  # frozen after planning (_night)
    summary.wall_s = time.perf_counter() - t0
    judge(summary, config.run.max_failed)
    paths = {k: v and str(Path(v).resolve()) for k, v in dataclasses.asdict(inputs).items()}
    data = summary_json(summary, paths, started, config.run.max_failed)
    summary.summary_path = write_summary(inputs.out, data)
    _log_summary(log, summary)
    return summary


def _night(
    inputs: NightInputs,
    config: Config,
    scheduler: str | None,
    client: Client | None,
    retry_failed: bool,
    tracker: Tracker,
    holder: str,
    log: Logger,
) -> RunSummary:
    """:func:`run_night` up to its verdict."""
    t0 = time.perf_counter()
    with run_lock(inputs.index, holder):
        report = None
        if not inputs.archive:  # else the store may not be there before the ingest
            report = tracker.step("check-inputs", check_night, inputs, config, log)
        with _client_soon(client, scheduler, config) as starting:
            if inputs.archive:
                # files are read on the cluster (the store is on storage its workers share)
                tracker.step("ingest-archive", ingest_archive, inputs, starting.result(), log)
                report = tracker.step("check-inputs", check_night, inputs, config, log)
            assert report is not None
            plan = tracker.step(
                "plan-segments", plan_night, inputs, config, retry_failed, log, report.listing
            )
            # The plan and everything imported live all night: out of the cycle collector's
            # full passes from here on. Each pass held the GIL for up to 1.5 s on a
            # 10,000-view night and the workers ran dry meanwhile (docs/BENCHMARKS.md).
            # Undone when the night ends (run_night): in a long-lived process they become
            # collectable again.
            gc.freeze()
            summary = new_summary(plan)
            summary.notes = [*report.notes, *(f"warning: {w}" for w in report.warnings)]
            summary.plan_s = time.perf_counter() - t0
            segments = plan.segments_todo
            # change objects built as segments end, not all after the last one
            objects = ObjectBuilder(
                plan,
                config.detect.classes,
                config.run.min_region_fraction,
                config.detect.max_range_m,
            )
            if segments:
                dask = starting.result()
                summary.wait_s = time.perf_counter() - t0 - summary.plan_s
                with contextlib.closing(Dispatcher(dask, plan, detect_batch).start()) as dispatcher:
                    _log_cluster(log, dask)

                    def publish(segment_id: str) -> RunSummary:
                        part = _publish(plan, dispatcher, segment_id, log)
                        objects.published(segment_id)
                        return part

                    for part in tracker.each("publish-segment", publish, segments):
                        summary.merge(part)
            finish_run(plan, summary, objects=objects)
        summary.still_failing = still_failing(inputs, report, plan.run_id)
    return summary


def check_night(inputs: NightInputs, config: Config, log: Logger) -> CheckReport:
    """:func:`~streetcd.run.check.check_inputs` on the night's inputs (the run holds the
    index's lock, so that is not checked); its notes and warnings go to the log."""
    report = check_inputs(
        inputs.images, inputs.poses, inputs.store, inputs.index, config, check_lock=False
    )
    for note in report.notes:
        log.info("check: %s", note)
    for warning in report.warnings:
        log.warning("check: %s", warning)
    return report


def still_failing(
    inputs: NightInputs, report: CheckReport, run_id: str
) -> list[tuple[str, str, str]]:
    """(view, error, when it failed) of tonight's views that failed in an earlier run and
    were not tried again tonight. Tonight's: a view whose image name is in tonight's images
    folder or pose file, and whose index key is tonight's (a lasting key names the image's
    content: the same name with other bytes is another view, and a fixed image a new one)."""
    names = report.image_names | report.pose_names
    poses = Path(inputs.poses).resolve()
    images = Path(inputs.images)
    with ChangeIndex(inputs.index, create=False) as idx:
        rows = failed_views(idx)
    out = []
    for key, error, failed_run, when in rows:
        name = image_name(key)
        if failed_run == run_id or name not in names:
            continue
        if key != name and key not in _keys_tonight(name, images, poses):
            continue
        out.append((key, error, when or ""))
    return out


def _keys_tonight(name: str, images: Path, poses: Path) -> set[str]:
    """The index keys a view ``name`` can have tonight (:func:`~streetcd.run.plan.lasting_key`):
    by its image's content, or by the pose file where the image is missing."""
    keys = {lasting_key(name, None, poses)}
    path = images / name
    if path.is_file():
        keys.add(lasting_key(name, file_hash(path)))
    return keys


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


def plan_night(
    inputs: NightInputs,
    config: Config,
    retry_failed: bool,
    log: Logger,
    listing: NightListing | None = None,
) -> Plan:
    """Plan the night (:func:`~streetcd.run.plan.plan_run`, from the input check's
    ``listing`` where given) and record the plan in the index."""
    open_index(inputs.index)
    plan = plan_run(
        inputs.images,
        inputs.poses,
        inputs.store,
        inputs.index,
        inputs.out,
        config,
        retry_failed=retry_failed,
        listing=listing,
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
    if summary.still_failing:
        log.warning("%s", still_failing_line(summary))
    log.info("summary: %s (exit code %d)", summary.summary_path, summary.exit_code)
