"""Throughput of the nightly flow: views per minute with 1 and 2 Dask workers, and the
orchestration overhead (flow wall time against the per-view work it schedules).

    .venv/bin/python benchmarks/throughput.py --views 200          # the goal's setting
    .venv/bin/python benchmarks/throughput.py --views 24 --size 480x270   # a quick look

Goals: speed-up from 1 to 2 workers ≥ 1.8×; overhead ≤ 5 % at ≥ 200 views, where

    overhead = wall / (Σ per-view time / workers) − 1

``Σ per-view time`` is what the workers spend on each view (read images, crop the cloud,
detect, write the mask); ``Σ detect`` (the detector alone) is printed beside it. ``wall`` is
the flow's own wall time (ingest skipped, planning, LocalCluster start, detection,
publishing); the temporary Prefect server's start (~20 s, once per process) is outside it.
An untimed warm-up run first fills numba's on-disk cache (else each new worker process
compiles the detector's kernels, ~30 s, inside the timed run).
``cpu/core`` is the CPU time the workers got per core-second of wall time (Σ per-view
process time / (wall × workers)): near 100 % on free cores; far below it, the machine is
shared and the speed-up says more about the neighbours than about the flow.
"""

from __future__ import annotations

import argparse
import math
import shutil
import tempfile
import time
from pathlib import Path


def make_city(root: Path, views: int, size: tuple[int, int], seed: int) -> dict[str, str]:
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


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--views", type=int, default=200, help="views in the synthetic city")
    ap.add_argument("--workers", default="1,2", help="worker counts to compare")
    ap.add_argument("--size", default="960x540", help="image size WxH")
    ap.add_argument("--batch-size", type=int, default=8)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", help="work folder (kept; default a temporary one, removed)")
    ap.add_argument("--no-warmup", action="store_true", help="skip the untimed first run")
    args = ap.parse_args()
    w, h = (int(x) for x in args.size.lower().split("x"))
    from streetcd.cli.run import quiet_prefect

    quiet_prefect()
    from flows.nightly import nightly

    root = Path(args.out) if args.out else Path(tempfile.mkdtemp(prefix="streetcd-bench-"))
    try:
        paths = make_city(root, args.views, (w, h), args.seed)
        counts = [int(x) for x in args.workers.split(",")]
        if not args.no_warmup:
            # Untimed: numba compiles the detector's kernels into its on-disk cache once,
            # so that no timed worker pays for compilation (it still loads the cache).
            warm = root / "warmup"
            shutil.rmtree(warm, ignore_errors=True)
            nightly(
                **paths,
                index=str(warm / "change_index.sqlite"),
                out=str(warm),
                workers=max(counts),
                batch_size=args.batch_size,
            )
        rows = []
        for workers in counts:
            out = root / f"run-{workers}w"
            shutil.rmtree(out, ignore_errors=True)
            s = nightly(
                **paths,
                index=str(out / "change_index.sqlite"),
                out=str(out),
                workers=workers,
                batch_size=args.batch_size,
            )
            ideal = s["view_s"] / workers
            rows.append(
                (
                    workers,
                    s["n_done"],
                    s["wall_s"],
                    60 * s["n_done"] / s["wall_s"],
                    s["detect_s"],
                    s["view_s"],
                    s["wall_s"] / ideal - 1,
                    s["cpu_s"] / (s["wall_s"] * workers),
                )
            )
    finally:
        if not args.out:
            shutil.rmtree(root, ignore_errors=True)
    base = rows[0][3]
    print(
        f"\n{'workers':>7} {'views':>6} {'wall s':>8} {'views/min':>10} {'Σ detect s':>11} "
        f"{'Σ view s':>9} {'overhead':>9} {'speed-up':>9} {'cpu/core':>9}"
    )
    for workers, n, wall, vpm, det, view, over, share in rows:
        print(
            f"{workers:>7} {n:>6} {wall:>8.1f} {vpm:>10.1f} {det:>11.1f} {view:>9.1f} "
            f"{100 * over:>8.1f}% {vpm / base:>8.2f}x {100 * share:>8.0f}%"
        )


if __name__ == "__main__":
    main()
