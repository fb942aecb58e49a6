"""Writing a night into the change index: the plan, each batch as it ends, the run's end.

Each step is one index transaction (or one per batch), so a run killed at any moment leaves
an index that the next run completes: views already published are skipped by their hashes.
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from typing import Any

from streetcd.config import ClassMap
from streetcd.run.plan import Batch, Plan
from streetcd.run.progress import notify
from streetcd.store.index import ChangeIndex
from streetcd.store.objects import MIN_REGION_FRACTION, ground_classes, rebuild_objects
from streetcd.store.records import ViewRecord

log = logging.getLogger(__name__)


@dataclass
class RunSummary:
    """Counts and times of one run: ``detect_s`` the sum of per-view detector times,
    ``view_s`` of the time each view held its worker's detection thread (the detector and
    whatever it waited for: its images, its share of the segment's crop and of its batch's
    last writes; what the worker's I/O and crop threads did ahead is not in it), ``cpu_s``
    the worker process's CPU time meanwhile; ``plan_s`` the planning, ``wait_s`` the time
    spent waiting for the Dask cluster after planning, ``wall_s`` the whole run."""

    run_id: str
    n_views: int = 0
    n_skipped: int = 0
    n_done: int = 0
    n_failed: int = 0
    n_flagged: int = 0
    n_lost: int = 0  # views of batches that never came back (not published; next run retries)
    detect_s: float = 0.0
    view_s: float = 0.0
    cpu_s: float = 0.0
    plan_s: float = 0.0
    wait_s: float = 0.0
    wall_s: float = 0.0
    failures: list[tuple[str, str]] = field(default_factory=list)
    # The night's verdict (streetcd.run.night.judge): tonight's views that failed in an
    # earlier run and were not tried again, as (view, error, when it failed); the input
    # check's notes; the exit code of ``streetcd run`` and where the summary JSON went.
    still_failing: list[tuple[str, str, str]] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    exit_code: int = 0
    summary_path: str | None = None

    def add(self, records: Sequence[ViewRecord]) -> None:
        for r in records:
            if r.status == "done":
                self.n_done += 1
            else:
                self.n_failed += 1
                self.failures.append((r.view, r.error or ""))
            self.n_flagged += int(r.flagged)
            self.detect_s += r.detect_s or 0.0
            self.view_s += r.total_s or 0.0
            self.cpu_s += r.cpu_s or 0.0

    def merge(self, other: RunSummary) -> None:
        for name in ("n_done", "n_failed", "n_flagged", "n_lost", "detect_s", "view_s", "cpu_s"):
            setattr(self, name, getattr(self, name) + getattr(other, name))
        self.failures += other.failures

    def as_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


def open_index(index: str) -> None:
    """Create the change index, or bring an older schema up to date, before planning reads it."""
    with ChangeIndex(index):
        pass


def register_plan(plan: Plan) -> None:
    """Record the run, its CRS (CRSMismatchError when the index holds another), its segments
    and the views that failed before detection."""
    with ChangeIndex(plan.index) as idx:
        idx.set_crs(plan.crs)
        idx.begin_run(plan.run_id, plan.params_hash, dict(plan.inputs))
        idx.add_segments(list(plan.segments), plan.run_id)
        if plan.failed_at_plan:
            idx.publish(plan.run_id, plan.failed_at_plan)
    notify("planned", plan)


def new_summary(plan: Plan) -> RunSummary:
    """The summary of ``plan`` before any detection: its counts and plan-time failures."""
    return RunSummary(
        plan.run_id,
        n_views=plan.n_views,
        n_skipped=plan.n_skipped,
        n_failed=len(plan.failed_at_plan),
        failures=[(r.view, r.error or "") for r in plan.failed_at_plan],
    )


def publish_segment(plan: Plan, finished: Iterable[tuple[Any, Batch]]) -> RunSummary:
    """Publish one segment's batches in the index, each in one transaction as it ends
    (``finished``: (Dask future, batch) pairs, from
    :meth:`streetcd.run.dispatch.Dispatcher.finished`); a batch lost (its views crashed the
    workers) is logged and counted."""
    summary = RunSummary(plan.run_id)
    with ChangeIndex(plan.index) as idx:
        for future, batch in finished:
            try:
                records = future.result()
            except Exception as exc:  # e.g. KilledWorker: a view that keeps crashing workers
                log.error(
                    "batch %s lost (%s: %s); its %d views stay unpublished and are "
                    "retried by the next run",
                    batch.key,
                    type(exc).__name__,
                    exc,
                    len(batch.tasks),
                )
                summary.n_lost += len(batch.tasks)
                continue
            idx.publish(plan.run_id, records)
            summary.add(records)
            notify("batch", records)
            future.release()
    return summary


def finish_run(
    plan: Plan,
    summary: RunSummary,
    class_map: ClassMap | None = None,
    min_region_fraction: float = MIN_REGION_FRACTION,
) -> None:
    """Merge the change objects of the plan's segments (:func:`rebuild_objects`, over
    every night the index holds), then close the run's row in the index with the counts
    of ``summary`` (from new_summary): status ``finished``, or ``incomplete`` when batches
    were lost. ``class_map``: the config's ``detect.classes``, to read the store's codes;
    ``min_region_fraction``: the config's ``run.min_region_fraction`` (the flag rule)."""
    with ChangeIndex(plan.index) as idx:
        store = dict(plan.inputs).get("store")
        ground = ground_classes(store, class_map=class_map) if store else None
        rebuild_objects(idx, [s.id for s in plan.segments], ground, min_region_fraction)
        idx.finish_run(
            plan.run_id,
            "incomplete" if summary.n_lost else "finished",
            n_planned=plan.n_views,
            n_skipped=plan.n_skipped,
            n_done=summary.n_done,
            n_failed=summary.n_failed,
            n_flagged=summary.n_flagged,
        )
