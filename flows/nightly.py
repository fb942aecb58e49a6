"""The nightly Prefect flow: ingest new MLS files → plan segments → detect on Dask → publish.

Every task is a thin call into :mod:`streetcd.pipeline` (or :mod:`streetcd.tiles`). Prefect
tracks the run, its plan and one task run per street segment; the per-view work goes to
Dask directly (one Dask task per batch of consecutive views), so a city's thousands of
images do not become thousands of Prefect task runs.

Dask: a LocalCluster of ``workers`` processes, or the cluster at ``scheduler`` /
``$STREETCD_SCHEDULER``, started (or connected to) while the run is planned. The workers'
first batches are submitted as soon as the plan and the cluster are ready, before the
per-segment Prefect task runs that publish them exist; the client hands out the rest as
batches end (:class:`streetcd.dispatch.Dispatcher`). Workers crop their segment's cloud
from the tile store once (the next segment's while they work on this one) and read their
own images; only small records travel back.

One run at a time per index: the flow holds the index's run lock (``<index>.lock``) from
start to end, and a second run on the same index fails at once, naming the holder.

Run it with ``streetcd run`` (progress bar), ``python -m flows.nightly --help``, or deploy it
with ``infra/prefect.yaml``.
"""

from __future__ import annotations

import time
from contextlib import ExitStack, closing
from typing import Any

from prefect import flow, get_run_logger, task
from prefect.cache_policies import NO_CACHE
from prefect.task_runners import ThreadPoolTaskRunner
from prefect.utilities.annotations import quote

from streetcd import pipeline
from streetcd.dispatch import Dispatcher
from streetcd.params import load_params

# Tasks neither cache nor persist results: the change index is the flow's result and makes
# reruns incremental; Prefect keeping pickled plans under ~/.prefect would only cost space.
#
# Each segment task mostly waits on Dask futures, so threads, not cores, bound how many
# segments are in flight; 32 keeps a few dozen workers busy with whole segments.
SEGMENTS_IN_FLIGHT = 32


@task(name="ingest-archive", cache_policy=NO_CACHE, persist_result=False)
def ingest_archive(archive: str, store: str, client: Any = None) -> dict[str, Any]:
    """Add new or changed LAS/LAZ files of ``archive`` to the tile store (others skipped),
    one file per task on the run's Dask cluster (``client``), else in this process."""
    from streetcd.tiles import ingest

    result = ingest(archive, store, client=client)
    logger = get_run_logger()
    logger.info(
        "ingest: %d new file(s), %d unchanged, %d failed, %d points, %d tiles",
        len(result.ingested),
        len(result.skipped),
        len(result.failed),
        result.points,
        result.tiles,
    )
    for path, error in sorted(result.failed.items()):
        logger.warning("ingest failed for %s: %s", path, error)
    return {
        "ingested": len(result.ingested),
        "skipped": len(result.skipped),
        "failed": len(result.failed),
    }


@task(name="plan-segments", cache_policy=NO_CACHE, persist_result=False)
def plan(
    images: str,
    poses: str,
    store: str,
    index: str,
    out: str,
    params: pipeline.PipelineParams,
    retry_failed: bool,
) -> pipeline.Plan:
    result = pipeline.plan_run(images, poses, store, index, out, params, retry_failed=retry_failed)
    get_run_logger().info(
        "run %s: %d views in %d segments; %d already in the index, %d to detect in %d batches,"
        " %d failed before detection",
        result.run_id,
        result.n_views,
        len(result.segments),
        result.n_skipped,
        result.n_todo,
        len(result.batches),
        len(result.failed_at_plan),
    )
    return result


@task(
    name="detect-segment",
    cache_policy=NO_CACHE,
    persist_result=False,
    task_run_name="segment {segment_id}",
)
def detect_segment(
    plan: pipeline.Plan, segment_id: str, dispatcher: Dispatcher
) -> pipeline.RunSummary:
    """Publish one segment's batches, handed to Dask by ``dispatcher``, as they end."""
    t0 = time.perf_counter()
    s = pipeline.publish_segment(plan, dispatcher.finished(segment_id))
    get_run_logger().info(
        "segment %s: %d views done, %d flagged, %d failed in %.1f s",
        segment_id,
        s.n_done,
        s.n_flagged,
        s.n_failed,
        time.perf_counter() - t0,
    )
    return s


@flow(
    name="streetcd-nightly",
    persist_result=False,
    task_runner=ThreadPoolTaskRunner(max_workers=SEGMENTS_IN_FLIGHT),  # type: ignore[arg-type]
)
def nightly(
    images: str,
    poses: str,
    store: str,
    index: str,
    out: str,
    archive: str | None = None,
    scheduler: str | None = None,
    workers: int = 2,
    params_file: str | None = None,
    batch_size: int = 4,
    segment_length_m: float = 100.0,
    retry_failed: bool = False,
) -> dict[str, Any]:
    """One nightly run; returns the run summary (counts, times, failures).

    images, poses : tonight's images folder and their pose file (COLMAP or OPK CSV).
    store : the tile store of the reference MLS cloud; ``archive`` new LAS/LAZ to add first.
    index, out : the change index (SQLite) and the folder for masks and overlays.
    scheduler : a Dask scheduler address; default ``$STREETCD_SCHEDULER``, else a
    LocalCluster of ``workers`` processes.
    """
    from dataclasses import replace

    logger = get_run_logger()
    t0 = time.perf_counter()
    params = pipeline.PipelineParams(
        detect=load_params(params_file),
        batch_size=batch_size,
        segments=replace(pipeline.SegmentParams(), length_m=segment_length_m),
    )
    with (
        pipeline.run_lock(index, "the streetcd-nightly flow"),
        pipeline.dask_client_soon(scheduler, workers) as starting,
        ExitStack() as stack,
    ):
        if archive:
            # files are read on the cluster (the store is on storage its workers share)
            ingest_archive(archive, store, quote(starting.result()))
        the_plan = plan(images, poses, store, index, out, params, retry_failed)
        summary = pipeline.new_summary(the_plan)
        summary.plan_s = time.perf_counter() - t0
        segments = the_plan.segments_todo
        if segments:
            client = starting.result()
            summary.wait_s = time.perf_counter() - t0 - summary.plan_s
            # Each worker's first batches go to Dask now, before Prefect creates the segment
            # task runs that publish them: the workers start at once.
            dispatcher = stack.enter_context(closing(Dispatcher(client, the_plan).start()))
            logger.info(
                "dask: %s with %d worker(s), dashboard %s",
                client.scheduler.address,
                len(client.scheduler_info(n_workers=-1)["workers"]),
                client.dashboard_link,
            )
            # quote(): hand the plan and the dispatcher over as they are; Prefect would
            # otherwise walk every dataclass in them looking for futures.
            futures = [
                detect_segment.submit(quote(the_plan), s, quote(dispatcher))  # type: ignore[call-overload]
                for s in segments
            ]
            for f in futures:
                summary.merge(f.result())
        pipeline.finish_run(the_plan, summary)
        summary.wall_s = time.perf_counter() - t0
    logger.info(
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
        logger.warning("failed: %s: %s", view, error)
    if summary.n_lost:
        logger.warning(
            "%d views were lost with their batches (see the log above); the next run retries them",
            summary.n_lost,
        )
    return summary.as_dict()


if __name__ == "__main__":
    import argparse

    ap = argparse.ArgumentParser(description=nightly.__doc__)
    for name in ("images", "poses", "store", "index", "out"):
        ap.add_argument(f"--{name}", required=True)
    ap.add_argument("--archive")
    ap.add_argument("--scheduler")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--params-file")
    a = ap.parse_args()
    nightly(**vars(a))
