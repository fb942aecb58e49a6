"""The nightly Prefect flow: :func:`streetcd.run.night.run_night` with Prefect's tracking.

The sequence is streetcd's own (the CLI and the tests run the same one); this module only
makes each of its steps a Prefect task — ``ingest-archive``, ``plan-segments`` and one
``publish-segment`` per street segment, which publishes that segment's batches as the Dask
workers finish them — and sends the run's log lines to Prefect's run logger.

Run it with ``streetcd run`` (progress bar), ``python -m streetcd_flows.nightly --help``, or
deploy it with ``infra/prefect.yaml``. Installed as the package ``streetcd_flows`` (this
folder), so that nothing called ``flows`` lands in site-packages.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any, TypeVar

from prefect import flow, get_run_logger, task
from prefect.cache_policies import NO_CACHE
from prefect.task_runners import ThreadPoolTaskRunner
from prefect.utilities.annotations import quote

from streetcd.config import load_config
from streetcd.run.night import SEGMENTS_IN_FLIGHT, NightInputs, run_night

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
) -> dict[str, Any]:
    """One nightly run; returns the run summary (counts, times, failures).

    images, poses : tonight's images folder and their pose file (COLMAP or OPK CSV).
    store : the tile store of the reference MLS cloud; ``archive`` new LAS/LAZ to add first.
    index, out : the change index (SQLite) and the folder for masks and overlays.
    scheduler : a Dask scheduler address; default ``$STREETCD_SCHEDULER``, else a
    LocalCluster. config_file : the YAML config (``configs/default.yaml`` layout); workers and
    batch_size, when given, override its ``run.workers`` and ``run.batch_size``.
    """
    config = load_config(config_file).replace_run(workers=workers, batch_size=batch_size)
    inputs = NightInputs(images, poses, store, index, out, archive)
    summary = run_night(
        inputs,
        config,
        scheduler=scheduler,
        retry_failed=retry_failed,
        tracker=PrefectTracker(),
        holder="the streetcd-nightly flow",
    )
    return summary.as_dict()


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
    nightly(**vars(ap.parse_args()))
