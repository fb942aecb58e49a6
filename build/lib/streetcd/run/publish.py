"""Writing a night into the change index: the plan, each batch as it ends, the run's end.

Each step is one index transaction (or one per batch), so a run killed at any moment leaves
an index that the next run completes: views already published are skipped by their hashes.
"""

from __future__ import annotations

import dataclasses
import logging
import threading
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from streetcd.config import ClassMap, DetectParams
from streetcd.run.plan import Batch, Plan
from streetcd.run.progress import notify
from streetcd.store.index import ChangeIndex
from streetcd.store.objects import (
    MIN_REGION_FRACTION,
    ground_classes,
    influence_m,
    rebuild_objects,
)
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


class ObjectBuilder:
    """Rebuilds each planned segment's change objects during the night, as soon as no view
    still to come can change them, so that the run's end has only the last few left.

    A segment's objects (:func:`rebuild_objects`) are made from its own flagged views'
    regions, from the other segments' regions within ``HALO_M`` of those, and from the done
    views that see their spots: all come from views whose camera centre lies within
    :func:`~streetcd.store.objects.influence_m` of its box in the index (regions lie within
    the detector's ``max_range_m`` of their camera). So segment S is ready once S and every
    segment to do tonight with a camera centre (its polyline) within that reach of S's box
    (1 m more, for rounding) have been published: rebuilding it then gives what the run's
    end would, and :meth:`finish` rebuilds only the segments not built yet (those whose
    publishing failed, the last ones). The rebuilds run one at a time, in the publishing
    thread that made the segment ready. ``class_map``, ``min_region_fraction``: as
    :func:`finish_run`'s; ``max_range_m``: the detector's (``detect.max_range_m``)."""

    def __init__(
        self,
        plan: Plan,
        class_map: ClassMap | None = None,
        min_region_fraction: float = MIN_REGION_FRACTION,
        max_range_m: float = DetectParams().max_range_m,
    ) -> None:
        self.plan, self.min_region_fraction = plan, min_region_fraction
        store = dict(plan.inputs).get("store")
        self.ground = ground_classes(store, class_map=class_map) if store else None
        self.waiting = _waiting_for(plan, influence_m(max_range_m) + 1.0)
        self.built: set[str] = set()
        self.lock = threading.Lock()  # the book-keeping
        self.building = threading.Lock()  # one rebuild at a time (the ground test's caches)

    def published(self, segment_id: str) -> None:
        """Segment ``segment_id``'s batches are all published: rebuild the segments that
        were waiting only for it."""
        with self.lock:
            ready = []
            for seg, deps in self.waiting.items():
                deps.discard(segment_id)
                if not deps and seg not in self.built:
                    self.built.add(seg)
                    ready.append(seg)
        if ready:
            self._rebuild(sorted(ready))

    def finish(self) -> None:
        """Rebuild the segments not built during the night."""
        with self.lock:
            rest = sorted(s.id for s in self.plan.segments if s.id not in self.built)
            self.built.update(rest)
        self._rebuild(rest)

    def _rebuild(self, segment_ids: list[str]) -> None:
        with self.building, ChangeIndex(self.plan.index) as idx:
            rebuild_objects(idx, segment_ids, self.ground, self.min_region_fraction)


def _waiting_for(plan: Plan, reach: float) -> dict[str, set[str]]:
    """{segment id: the segments to do tonight whose publishing can change its objects}
    (see :class:`ObjectBuilder`): those with a camera centre within ``reach`` metres (x/y) of
    its box, for every segment of the plan."""
    todo = plan.segments_todo
    by_id = {s.id: s for s in plan.segments}
    xy = [np.asarray(by_id[t].polyline, np.float64).reshape(-1, 2) for t in todo]
    points = np.concatenate(xy) if xy else np.zeros((0, 2))
    owner = np.repeat(np.arange(len(todo)), [len(p) for p in xy])
    with ChangeIndex(plan.index) as idx:
        boxes = {
            r["segment_id"]: (r["min_x"], r["min_y"], r["max_x"], r["max_y"])
            for r in idx.conn.execute("SELECT segment_id, min_x, min_y, max_x, max_y FROM segments")
        }
    x, y, tonight = points[:, 0], points[:, 1], set(todo)
    out: dict[str, set[str]] = {}
    for s in plan.segments:
        box = boxes.get(s.id)
        if box is None:  # not in the index: wait for everything
            near = np.ones(len(points), bool)
        else:
            near = (x >= box[0] - reach) & (x <= box[2] + reach)
            near &= (y >= box[1] - reach) & (y <= box[3] + reach)
        out[s.id] = {todo[k] for k in np.unique(owner[near]).tolist()} | ({s.id} & tonight)
    return out


def finish_run(
    plan: Plan,
    summary: RunSummary,
    class_map: ClassMap | None = None,
    min_region_fraction: float = MIN_REGION_FRACTION,
    objects: ObjectBuilder | None = None,
) -> None:
    """Merge the change objects of the plan's segments (:func:`rebuild_objects`, over
    every night the index holds), then close the run's row in the index with the counts
    of ``summary`` (from new_summary): status ``finished``, or ``incomplete`` when batches
    were lost. ``class_map``: the config's ``detect.classes``, to read the store's codes;
    ``min_region_fraction``: the config's ``run.min_region_fraction`` (the flag rule).
    ``objects``: the night's :class:`ObjectBuilder`, which has built some segments already
    (then ``class_map`` and ``min_region_fraction`` are its own)."""
    (objects or ObjectBuilder(plan, class_map, min_region_fraction)).finish()
    with ChangeIndex(plan.index) as idx:
        idx.finish_run(
            plan.run_id,
            "incomplete" if summary.n_lost else "finished",
            n_planned=plan.n_views,
            n_skipped=plan.n_skipped,
            n_done=summary.n_done,
            n_failed=summary.n_failed,
            n_flagged=summary.n_flagged,
        )
