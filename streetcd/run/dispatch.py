"""Handing a run's batches to the Dask workers: one queue per worker, topped up as batches end.

Each worker gets a share of the run: whole segments, about the same number of views per
worker (:func:`plan_workers`), in plan order. The client keeps each share
in a queue of its own and gives a worker only ``threads + 1`` batches at a time: the one it
runs and the next, so it never waits for the client. Each batch is told the batch after it
on its worker (``ahead``: its images are decoded during this batch's last view) and the
first batch of the worker's next segment (``next_segment``: its cloud is cropped while this
segment runs, not only during its last batch).

The end of each queue, ``tail_views`` views, is cut into single-view batches. A worker that
has run out of its own queue takes the last batch of the longest queue, so the workers end
within about one view of each other. A view taken so is detected on its segment's crop, as
its owner would have: the detector estimates the cloud's point spacing from the crop it is
given (:mod:`streetcd.detect.spacing`), and a crop of the view alone (~15 ms against ~250 ms
for the segment) gave 938 pixels more or less on the quick tour's street (docs/DECISIONS.md,
"The crop a view is detected on", 2026-11-29). A queue whose worker is gone is served by the
others from its front (Dask itself moves the batches that worker held); a worker that joins
mid-run takes from the back of the longest queue.

Why not submit every batch at once and let Dask balance (what the flow did before): Dask
places a task that prefers a worker when it is submitted, and only work stealing moves it
later; stealing leaves a ~2 s batch where it is unless the victim has ~3 s more queued than
the thief, and when it does move one early in a run, the thief crops a whole segment for it.
The workers then ended seconds apart (docs/BENCHMARKS.md).
"""

from __future__ import annotations

import dataclasses
import logging
import queue
import threading
from collections import Counter, deque
from collections.abc import Callable, Collection, Iterator, Mapping, Sequence
from functools import partial
from itertools import islice
from typing import Any

from distributed import Client

from streetcd.run.plan import Batch, Plan

log = logging.getLogger(__name__)


def segment_workers(
    client: Client, segment_ids: Sequence[str], sizes: Sequence[int] | None = None
) -> dict[str, str | None]:
    """Assign segments to the workers alive now (each worker's share of the run, see
    :class:`Dispatcher`), largest first to the least loaded worker, so
    that workers get about the same number of views (``sizes``, default one per segment)
    and finish together."""
    workers = sorted(client.scheduler_info(n_workers=-1)["workers"])
    if not workers:
        return {s: None for s in segment_ids}
    sizes = [1] * len(segment_ids) if sizes is None else list(sizes)
    load = dict.fromkeys(workers, 0)
    out: dict[str, str | None] = {}
    for k in sorted(range(len(segment_ids)), key=lambda k: (-sizes[k], k)):
        worker = min(workers, key=lambda w: (load[w], w))
        out[segment_ids[k]] = worker
        load[worker] += sizes[k]
    return out


def plan_workers(client: Client, plan: Plan) -> dict[str, str | None]:
    """:func:`segment_workers` for the segments of ``plan`` still to do, by views to do."""
    segs = plan.segments_todo
    sizes = {s: 0 for s in segs}
    for b in plan.batches:
        sizes[b.segment_id] += len(b.tasks)
    return segment_workers(client, segs, [sizes[s] for s in segs])


def split_tail(batches: Sequence[Batch], tail_views: int) -> list[Batch]:
    """``batches`` with the last ones cut into single-view batches (``part`` 0, 1, …) until
    at least ``tail_views`` views at the end are single; order and views unchanged."""
    out: list[Batch] = []
    single = 0
    for b in reversed(batches):
        if single < tail_views and len(b.tasks) > 1:
            parts = [dataclasses.replace(b, tasks=(t,), part=k) for k, t in enumerate(b.tasks)]
            out += reversed(parts)
        else:
            out.append(b)
        single += len(b.tasks)
    return out[::-1]


class WorkQueues:
    """Which batch each worker runs next (see the module docstring): pure bookkeeping.

    shares : {worker address (None: no worker known): its batches in run order}.
    tail_views : views at the end of each share cut into single-view batches.
    """

    def __init__(self, shares: Mapping[str | None, Sequence[Batch]], tail_views: int):
        self.queues = {w: deque(split_tail(bs, tail_views)) for w, bs in shares.items() if bs}
        # views queued per worker, kept up to date: the longest queue is asked for often
        self.views = Counter({w: sum(len(b.tasks) for b in q) for w, q in self.queues.items()})

    def __len__(self) -> int:
        return sum(len(q) for q in self.queues.values())

    def take(self, worker: str | None, live: Collection[str]) -> Batch | None:
        """The next batch for ``worker``, None when every queue is empty. ``live``: the
        workers the scheduler knows now; a queue of any other worker is an orphan."""
        own = self.queues.get(worker)
        if own:
            return self._pop(worker, own.popleft())
        for w, q in self.queues.items():
            if q and w not in live:
                return self._pop(w, q.popleft())
        victim = max(
            (w for w, q in self.queues.items() if q and w != worker),
            key=lambda w: (self.views[w], str(w)),
            default=None,
        )
        if victim is None:
            return None
        return self._pop(victim, self.queues[victim].pop())

    def ahead(self, worker: str | None, after: Batch) -> tuple[Batch | None, Batch | None]:
        """What ``worker`` runs after ``after``, from its own queue: (its next batch, the
        first batch of another segment than ``after``'s); None where unknown."""
        q = self.queues.get(worker)
        if not q:
            return None, None
        seg = next((b for b in islice(q, 0, 64) if b.segment_id != after.segment_id), None)
        return q[0], seg

    def _pop(self, worker: str | None, batch: Batch) -> Batch:
        self.views[worker] -= len(batch.tasks)
        return batch


# The Dask task a batch runs as: task(batch, ahead, next_segment) -> its records.
BatchTask = Callable[[Batch, Batch | None, Batch | None], Any]


class Dispatcher:
    """Runs ``plan`` on the Dask cluster of ``client`` through :class:`WorkQueues`, each
    batch as ``task(batch, ahead, next_segment)`` on a worker
    (:func:`streetcd.run.worker.detect_batch` in a night).

    :meth:`start` hands each worker its first batches; every batch that ends (its Dask
    future's done-callback) is queued for its segment's publisher (:meth:`finished`) and
    tops the workers up. ``shares`` (default :func:`plan_workers` on the workers alive now)
    and ``tail_views`` (default two batches) as in :class:`WorkQueues`.
    """

    def __init__(
        self,
        client: Client,
        plan: Plan,
        task: BatchTask,
        shares: Mapping[str | None, Sequence[Batch]] | None = None,
        tail_views: int | None = None,
    ):
        if shares is None:
            hints = plan_workers(client, plan)
            owned: dict[str | None, list[Batch]] = {}
            for b in plan.batches:
                owned.setdefault(hints.get(b.segment_id), []).append(b)
            shares = owned
        if tail_views is None:
            tail_views = 2 * max((len(b.tasks) for b in plan.batches), default=1)
        self.client, self.plan, self.task = client, plan, task
        self.work = WorkQueues(shares, tail_views)
        self.running: Counter[str | None] = Counter()  # batches in Dask by intended worker
        self.results: dict[str, queue.Queue] = {s: queue.Queue() for s in plan.segments_todo}
        self.lock = threading.RLock()
        self.closed = False

    def start(self) -> Dispatcher:
        self._top_up()
        return self

    def close(self) -> None:
        """Hand out nothing more (the run is over or failed)."""
        with self.lock:
            self.closed = True

    def finished(self, segment_id: str) -> Iterator[tuple[Any, Batch]]:
        """(Dask future, batch) of each of the segment's batches as it ends, until the
        segment's views are all accounted for; raises what stopped the dispatcher."""
        left = sum(len(b.tasks) for b in self.plan.batches_of(segment_id))
        results = self.results[segment_id]
        while left > 0:
            item = results.get()
            if isinstance(item, BaseException):
                raise item
            left -= len(item[1].tasks)
            yield item

    def _top_up(self) -> None:
        with self.lock:
            if self.closed:
                return
            try:
                threads = self.client.nthreads()
                for w in sorted(threads):
                    while self.running[w] < threads[w] + 1:
                        b = self.work.take(w, threads)
                        if b is None:
                            break
                        self._submit(b, w)
                if not threads and not any(n > 0 for n in self.running.values()):
                    # No worker at all: one batch without a place, which Dask holds until a
                    # worker joins; its end tops the newcomer up.
                    b = self.work.take(None, ())
                    if b is not None:
                        self._submit(b, None)
            except Exception as exc:  # the client is gone: stop the publishers, not hang them
                log.error("dispatcher stopped: %s: %s", type(exc).__name__, exc)
                self.closed = True
                for results in self.results.values():
                    results.put(exc)

    def _submit(self, batch: Batch, worker: str | None) -> None:
        ahead, next_segment = self.work.ahead(worker, batch)
        future = self.client.submit(
            self.task,
            batch,
            ahead,
            next_segment,
            key=f"{batch.key}-{self.plan.run_id}",
            pure=False,
            workers=[worker] if worker else None,
            # a preference, not a restriction: Dask moves the batch if its worker dies
            allow_other_workers=bool(worker),
            # in run order when a worker holds two (Dask's order among equals is not)
            priority=-self.plan.order(batch),
        )
        self.running[worker] += 1
        future.add_done_callback(partial(self._done, worker, batch))

    def _done(self, worker: str | None, batch: Batch, future: Any) -> None:
        """Dask's callback thread: ``future`` of ``batch`` ended (result, error or cancel)."""
        self.results[batch.segment_id].put((future, batch))
        with self.lock:
            self.running[worker] -= 1
            self._top_up()
