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


def make_city(root: Path, views: int, size: tuple[int, int], seed: int) -> dict[str, str]:
    """The synthetic city (reused when ``root`` already has it) and its tile store."""
    from streetcd.synth import generate_city
    from streetcd.tiles import ingest

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
    from streetcd import pipeline

    shutil.rmtree(folder, ignore_errors=True)
    plan = pipeline.plan_run(**paths, index=folder / "index.sqlite", out=folder)
    first = plan.batches[0]
    pipeline.detect_batch(dataclasses.replace(first, tasks=first.tasks[:2]))


def load() -> str:
    return "/".join(f"{x:.2f}" for x in os.getloadavg())


def measure(paths: dict[str, str], out: Path, workers: int, batch_size: int) -> dict[str, Any]:
    from flows.nightly import nightly

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
    ap.add_argument("--batch-size", type=int, default=4)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument(
        "--out", help="work folder (kept, and its city reused; default a temporary one)"
    )
    ap.add_argument("--no-warmup", action="store_true", help="skip the untimed warm-up")
    args = ap.parse_args()
    w, h = (int(x) for x in args.size.lower().split("x"))
    from streetcd.cli.run import quiet_prefect

    quiet_prefect()
    root = Path(args.out) if args.out else Path(tempfile.mkdtemp(prefix="streetcd-bench-"))
    rows = []
    try:
        paths = make_city(root, args.views, (w, h), args.seed)
        if not args.no_warmup:
            warm_up(paths, root / "warmup")
        for workers in (int(x) for x in args.workers.split(",")):
            rows.append(measure(paths, root / f"run-{workers}w", workers, args.batch_size))
            print(f"{workers} worker(s): {rows[-1]['wall_s']:.1f} s", flush=True)
    finally:
        if not args.out:
            shutil.rmtree(root, ignore_errors=True)
    print(f"\n{args.views} views of {w}x{h}, batch size {args.batch_size}, {os.cpu_count()} cores")
    print(table(rows))


if __name__ == "__main__":
    main()
