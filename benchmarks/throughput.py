"""Throughput of the nightly flow: views per minute with 1 and 2 Dask workers, and the
orchestration overhead (flow wall time against the per-view work it schedules).

    .venv/bin/python benchmarks/throughput.py                      # 200 views of 960x540
    .venv/bin/python benchmarks/throughput.py --views 24 --size 480x270   # a quick look
    .venv/bin/python benchmarks/throughput.py --views 200 --size 1920x1080 --out /tmp/b
                                                          # 2 MP views, the realistic case

Goals: speed-up from 1 to 2 workers ≥ 1.8×; overhead ≤ 5 % at ≥ 200 views, where

    overhead = wall / (Σ per-view time / workers) − 1

with two readings of ``Σ per-view time``: ``Σ detect`` (the detector alone: the issue's
definition, which counts reading images, cropping the cloud and writing masks as overhead)
and ``Σ view`` (the time each view held its worker's detection thread: the detector and what
it waited for, its images, its share of the segment's crop, its batch's last writes; the
worker decodes the next images, reads their EXIF, writes masks and overlays and crops the
next segment in other threads, ahead, and that is in neither sum). ``wall`` is the flow's
own wall time: planning, the LocalCluster's start (overlapped with planning; ``wait`` is
what was left of it after planning), detection, publishing. The temporary Prefect server's start (~20 s, once
per process) is outside it. An untimed warm-up first detects two views in this process to
fill numba's on-disk cache (else each new worker process compiles the detector's kernels,
~30 s, inside the timed run).

``cpu/core`` is the CPU time the workers got per core-second of wall time (Σ per-view
process time / (wall × workers)): near 100 % on free cores; far below it, the machine is
shared and the speed-up says more about the neighbours than about the flow. The load
average (``os.getloadavg``) is printed before and after each run for the same reason.

``ceiling`` (``--ceiling-views``, default 48): what this machine allows, without Dask or
Prefect. That many views of the city's first segments are split in two halves; one bare
process detects each half alone, then two processes detect both halves at once (same
worker settings: one OpenCV thread, :data:`streetcd.run.cluster.WORKER_MALLOC_ENV`). Two over
a half's mean slowdown is the speed-up two detectors get from two cores when nothing else
runs. Most of that slowdown is the workers' own helper threads: a lone worker has the
second core free for its image decoding, crops and writes, which two workers must fit
between their detections. The detector itself barely notices the other core
(docs/BENCHMARKS.md, "The ceiling of two workers").
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import os
import shutil
import tempfile
import time
from pathlib import Path
from typing import Any

from streetcd.config import RunParams


def make_city(root: Path, views: int, size: tuple[int, int], seed: int) -> dict[str, str]:
    """The synthetic city (reused when ``root`` already has it) and its tile store."""
    from streetcd.store.ingest import ingest
    from streetcd.synth import generate_city

    streets = max(1, math.ceil(views / 25))
    per_street = math.ceil(views / streets)
    manifest = root / "city" / "manifest.json"
    if not manifest.exists():
        t0 = time.perf_counter()
        manifest = Path(
            generate_city(
                root / "city", seed=seed, n_streets=streets, images_per_street=per_street, size=size
            )
        )
        print(
            f"city: {streets} streets x {per_street} images {size[0]}x{size[1]} "
            f"in {time.perf_counter() - t0:.1f} s"
        )
    ingest(manifest.parent / "cloud", root / "store.zarr")
    return {
        "images": str(manifest.parent / "images"),
        "poses": str(manifest.parent / "poses" / "poses_opk.csv"),
        "store": str(root / "store.zarr"),
    }


def warm_up(paths: dict[str, str], folder: Path) -> None:
    """Detect two views in this process, untimed: numba compiles the detector's kernels
    into its on-disk cache once, so that no timed worker pays for compilation (it still
    loads the cache, and that is counted)."""
    from streetcd.run.plan import plan_run
    from streetcd.run.worker import detect_batch

    shutil.rmtree(folder, ignore_errors=True)
    plan = plan_run(**paths, index=folder / "index.sqlite", out=folder)
    first = plan.batches[0]
    detect_batch(dataclasses.replace(first, tasks=first.tasks[:2]))


def _bare_detect(batches: list[Any]) -> float:
    """Detect ``batches`` in this (spawned) process, one view untimed first: wall seconds."""
    import cv2

    from streetcd.run.worker import detect_batch

    cv2.setNumThreads(1)
    first = batches[0]
    detect_batch(dataclasses.replace(first, tasks=first.tasks[:1]))
    t0 = time.perf_counter()
    for k, b in enumerate(batches):
        detect_batch(b, batches[k + 1] if k + 1 < len(batches) else None)
    return time.perf_counter() - t0


def ceiling(paths: dict[str, str], folder: Path, n_views: int) -> dict[str, float]:
    """Speed-up two bare detector processes get from two cores (module docstring): each half
    of ``n_views`` views is detected alone, then both halves at once; the ceiling is 2 over
    the mean slowdown of a half, so that halves of unequal cost do not count."""
    from concurrent.futures import ProcessPoolExecutor
    from multiprocessing import get_context

    from streetcd.run.cluster import WORKER_MALLOC_ENV
    from streetcd.run.plan import plan_run

    shutil.rmtree(folder, ignore_errors=True)
    plan = plan_run(**paths, index=folder / "index.sqlite", out=folder)
    batches, n = [], 0
    for b in plan.batches:
        if n >= n_views:
            break
        batches.append(b)
        n += len(b.tasks)
    halves = (batches[: len(batches) // 2], batches[len(batches) // 2 :])
    saved = {k: os.environ.get(k) for k in WORKER_MALLOC_ENV}
    os.environ.update(WORKER_MALLOC_ENV)  # read by glibc when a child starts
    try:
        ctx = get_context("spawn")
        with ProcessPoolExecutor(1, mp_context=ctx) as pool:
            alone = [pool.submit(_bare_detect, h).result() for h in halves]
        with ProcessPoolExecutor(2, mp_context=ctx) as pool:
            together = [f.result() for f in [pool.submit(_bare_detect, h) for h in halves]]
    finally:
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v
    slowdown = sum(t / a for t, a in zip(together, alone, strict=True)) / 2
    return {"views": n, "alone_s": sum(alone), "slowdown": slowdown, "speedup": 2 / slowdown}


def load() -> str:
    return "/".join(f"{x:.2f}" for x in os.getloadavg())


def measure(paths: dict[str, str], out: Path, workers: int, batch_size: int) -> dict[str, Any]:
    from streetcd_flows.nightly import nightly

    shutil.rmtree(out, ignore_errors=True)
    before = load()
    s = nightly(
        **paths,
        index=str(out / "change_index.sqlite"),
        out=str(out),
        workers=workers,
        batch_size=batch_size,
    )
    s["load"] = f"{before} → {load()}"
    s["workers"] = workers
    return s


def table(rows: list[dict[str, Any]]) -> str:
    head = (
        f"{'workers':>7} {'views':>5} {'wall s':>7} {'plan s':>6} {'wait s':>6} "
        f"{'views/min':>9} {'Σ detect s':>10} {'Σ view s':>8} {'overhead':>17} "
        f"{'speed-up':>8} {'cpu/core':>8}  load 1/5/15 min before → after"
    )
    lines = [head, f"{'':>64}{'vs detect':>9} {'vs view':>7}"]
    base = 60 * rows[0]["n_done"] / rows[0]["wall_s"]
    for s in rows:
        w, wall = s["workers"], s["wall_s"]
        vpm = 60 * s["n_done"] / wall
        lines.append(
            f"{w:>7} {s['n_done']:>5} {wall:>7.1f} {s['plan_s']:>6.1f} {s['wait_s']:>6.1f} "
            f"{vpm:>9.1f} {s['detect_s']:>10.1f} {s['view_s']:>8.1f} "
            f"{100 * (wall / (s['detect_s'] / w) - 1):>8.1f}% "
            f"{100 * (wall / (s['view_s'] / w) - 1):>7.1f}% "
            f"{vpm / base:>7.2f}x {100 * s['cpu_s'] / (wall * w):>7.0f}%  {s['load']}"
        )
    for s in rows:
        w, n = s["workers"], max(s["n_done"], 1)
        lines.append(
            f"{w} worker(s): per view {1000 * s['detect_s'] / n:.0f} ms detect + "
            f"{1000 * (s['view_s'] - s['detect_s']) / n:.1f} ms waiting on the detection thread;"
            f" before detection {s['plan_s'] + s['wait_s']:.1f} s; the rest "
            f"{s['wall_s'] - s['plan_s'] - s['wait_s'] - s['view_s'] / w:.1f} s"
        )
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--views", type=int, default=200, help="views in the synthetic city")
    ap.add_argument("--workers", default="1,2", help="worker counts to compare, in order")
    ap.add_argument("--size", default="960x540", help="image size WxH")
    ap.add_argument(
        "--batch-size", type=int, default=RunParams().batch_size, help="views per task [config's]"
    )
    ap.add_argument(
        "--repeat",
        type=int,
        default=3,
        help="runs of each worker count, interleaved (1, 2, 1, 2, ...); the median is reported",
    )
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument(
        "--out", help="work folder (kept, and its city reused; default a temporary one)"
    )
    ap.add_argument("--no-warmup", action="store_true", help="skip the untimed warm-up")
    ap.add_argument(
        "--ceiling-views",
        type=int,
        default=48,
        help="views for the bare-process ceiling (0: skip it)",
    )
    args = ap.parse_args()
    w, h = (int(x) for x in args.size.lower().split("x"))
    from streetcd.cli.run import quiet_prefect

    quiet_prefect()
    root = Path(args.out) if args.out else Path(tempfile.mkdtemp(prefix="streetcd-bench-"))
    counts = [int(x) for x in args.workers.split(",")]
    runs: dict[int, list[dict[str, Any]]] = {n: [] for n in counts}
    bare: dict[str, float] | None = None
    try:
        paths = make_city(root, args.views, (w, h), args.seed)
        if not args.no_warmup:
            warm_up(paths, root / "warmup")
        if args.ceiling_views > 0:
            bare = ceiling(paths, root / "ceiling", args.ceiling_views)
        # Interleaved, so that a slow spell of the machine falls on both counts alike.
        for k in range(args.repeat):
            for workers in counts:
                runs[workers].append(
                    measure(paths, root / f"run-{workers}w", workers, args.batch_size)
                )
                print(
                    f"run {k + 1}/{args.repeat}, {workers} worker(s): "
                    f"{runs[workers][-1]['wall_s']:.1f} s",
                    flush=True,
                )
    finally:
        if not args.out:
            shutil.rmtree(root, ignore_errors=True)
    rows = [median_run(runs[n]) for n in counts if runs[n]]
    if not rows:
        print(ceiling_line(bare) if bare else "nothing measured (--repeat 0, --ceiling-views 0)")
        return
    print(
        f"\n{args.views} views of {w}x{h}, batch size {args.batch_size}, {os.cpu_count()} cores, "
        f"median of {args.repeat} run(s) by wall time"
    )
    print(table(rows))
    for n in counts:
        walls = ", ".join(f"{s['wall_s']:.1f}" for s in runs[n])
        print(f"{n} worker(s): wall of each run {walls} s")
    if bare is not None:
        print(ceiling_line(bare))


def ceiling_line(bare: dict[str, float]) -> str:
    return (
        f"ceiling: {bare['views']:.0f} views, two halves detected by bare processes alone "
        f"({bare['alone_s']:.1f} s) and at once: each {100 * (bare['slowdown'] - 1):.1f} % "
        f"slower, {bare['speedup']:.2f}x without Dask or Prefect"
    )


def median_run(runs: list[dict[str, Any]]) -> dict[str, Any]:
    """The run with the median wall time (the lower middle one of an even count)."""
    ordered = sorted(runs, key=lambda s: s["wall_s"])
    return ordered[(len(ordered) - 1) // 2]


if __name__ == "__main__":
    main()
