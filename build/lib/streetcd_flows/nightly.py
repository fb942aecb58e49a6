"""The nightly Prefect flow: :func:`streetcd.run.night.run_night` with Prefect's tracking.

The sequence is streetcd's own (the CLI and the tests run the same one); this module only
makes each of its steps a Prefect task — ``check-inputs``, ``ingest-archive``,
``plan-segments`` and one ``publish-segment`` per street segment, which publishes that
segment's batches as the Dask workers finish them — and sends the run's log lines to
Prefect's run logger. A night whose failed views exceed ``run.max_failed`` (exit code 3 of
``streetcd run``) ends in a Failed state that carries the run summary as its data; a
whole-input error fails the flow with that error.

Run it with ``streetcd run`` (progress bar), ``python -m streetcd_flows.nightly --help``, or
deploy it with ``infra/prefect.yaml``. Installed as the package ``streetcd_flows`` (this
folder), so that nothing called ``flows`` lands in site-packages.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any, TypeVar

from prefect import flow, get_run_logger, task
from prefect.cache_policies import NO_CACHE
from prefect.states import Failed, State
from prefect.task_runners import ThreadPoolTaskRunner
from prefect.utilities.annotations import quote

from streetcd.config import load_config
from streetcd.run.night import SEGMENTS_IN_FLIGHT, NightInputs, run_night
from streetcd.run.publish import RunSummary
from streetcd.run.summary import n_failing, still_failing_line

T = TypeVar("T")


class PrefectTracker:
    """Each step of the night as a Prefect task run. Tasks neither cache nor persist results:
    the change index is the flow's result and makes reruns incremental. Arguments go in
    ``quote()``d: Prefect would otherwise walk every dataclass of a plan looking for futures."""

    def step(self, name: str, fn: Callable[..., T], *args: Any, **kwargs: Any) -> T:
        tracked = task(name=name, cache_policy=NO_CACHE, persist_result=False)(fn)
        return tracked(*(quote(a) for a in args), **{k: quote(v) for k, v in kwargs.items()})

    def each(self, name: str, fn: Callable[[str], T], items: Sequence[str]) -> list[T]:
        def one(item: str) -> T:
            return fn(item)

        tracked = task(
            name=name,
            cache_policy=NO_CACHE,
            persist_result=False,
            task_run_name=f"{name} {{item}}",
        )(one)
        futures = [tracked.submit(item) for item in items]
        return [f.result() for f in futures]

    def logger(self) -> Any:
        return get_run_logger()


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
    config_file: str | None = None,
    workers: int | None = None,
    batch_size: int | None = None,
    retry_failed: bool = False,
    max_failed: float | None = None,
) -> dict[str, Any] | State:
    """One nightly run; returns the run summary (counts, times, failures, exit code), or a
    Failed state carrying it when more views failed than ``run.max_failed`` allows.

    images, poses : tonight's images folder and their pose file (COLMAP or OPK CSV).
    store : the tile store of the reference MLS cloud; ``archive`` new LAS/LAZ to add first.
    index, out : the change index (SQLite) and the folder for masks and overlays.
    scheduler : a Dask scheduler address; default ``$STREETCD_SCHEDULER``, else a
    LocalCluster. config_file : the YAML config (``configs/default.yaml`` layout); workers,
    batch_size and max_failed, when given, override its ``run.workers``, ``run.batch_size``
    and ``run.max_failed``.
    """
    config = load_config(config_file).replace_run(
        workers=workers, batch_size=batch_size, max_failed=max_failed
    )
    inputs = NightInputs(images, poses, store, index, out, archive)
    summary = run_night(
        inputs,
        config,
        scheduler=scheduler,
        retry_failed=retry_failed,
        tracker=PrefectTracker(),
        holder="the streetcd-nightly flow",
    )
    if summary.exit_code:
        return Failed(message=failed_message(summary), data=summary.as_dict())
    return summary.as_dict()


def failed_message(summary: RunSummary) -> str:
    """One line on why a night failed, for its Failed state."""
    line = f"{n_failing(summary)} of {summary.n_views} views failed"
    if summary.still_failing:
        line += f" ({still_failing_line(summary)})"
    return f"{line}; summary {summary.summary_path}"


if __name__ == "__main__":
    import argparse

    ap = argparse.ArgumentParser(description=nightly.__doc__)
    for name in ("images", "poses", "store", "index", "out"):
        ap.add_argument(f"--{name}", required=True)
    ap.add_argument("--archive")
    ap.add_argument("--scheduler")
    ap.add_argument("--config-file")
    ap.add_argument("--workers", type=int)
    ap.add_argument("--batch-size", type=int)
    ap.add_argument("--retry-failed", action="store_true")
    ap.add_argument("--max-failed", type=float)
    nightly(**vars(ap.parse_args()))
