"""Ingest throughput and memory against a plain laspy read, store build time and crop latency
per view against the number of tiles in the store.

    .venv/bin/python benchmarks/ingest.py                      # full size: 50 M points, 10 files
    .venv/bin/python benchmarks/ingest.py --repeats 3          # medians of 3 (≈ 3× as long)
    .venv/bin/python benchmarks/ingest.py --points 2000000 --crop-tiles 10,100,1000

Goals: ingest ≥ 0.5× the points/s of a plain laspy read of the same files (chunked, one
process, the same chunk size); ingest peak RSS independent of archive size; store build
linear in points, not in tiles; crop ≤ 100 ms per view from a warm tile cache, flat from 10
to 10,000 tiles. The default run takes about 7–10 minutes on 2 cores.

The archive is synthetic MLS: a scanner on a car drives along a street and sweeps profiles
across it (road, verges, façades), written as LAZ with write_las. Every timed step runs in its
own subprocess (clean peak RSS) after one warm-up run (page cache, imports); medians over
``--repeats``, taken round-robin over the rows. On a shared machine the wall-clock ratio moves
with other processes' load; the CPU-time ratio (process + workers, user + system) does not. The crop stores have a dense core of tiles around the views (``--core-points``
per tile) and sparse tiles (100 points) elsewhere, so every store size costs the views the
same points and the table shows what the index lookup adds as the store grows. Store build is
timed in-process (2 workers) against a plain laspy read of the same files; its ``build ×
plain read`` and crop's ``warm × smallest store`` are the same-run baselines.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ORIGIN = np.array([500_000.0, 5_400_000.0, 0.0])  # CRS metres (UTM-sized)
CRS = "EPSG:32632"


# --- synthetic archive -------------------------------------------------------------------


def street_strip(
    rng: np.random.Generator, n: int, x0: float, length: float, t0: float
) -> dict[str, np.ndarray]:
    """n points of a 2D profile scanner (2.5 m high, 100 profiles/s) driving along +x from
    x0 over ``length`` metres: road |y| < 4, verges to ±12 m, façades at y = ±12 up to 15 m.
    Local metres (add ORIGIN for the CRS); scan order, like a real MLS file."""
    per_profile = 2000
    profiles = math.ceil(n * 1.6 / per_profile)  # some rays hit the sky
    x = x0 + np.repeat(np.linspace(0.0, length, profiles, endpoint=False), per_profile)
    theta = np.tile(np.linspace(0.0, 2 * np.pi, per_profile, endpoint=False), profiles)
    dy, dz = np.cos(theta), np.sin(theta)
    with np.errstate(divide="ignore"):
        t_ground = np.where(dz < -1e-6, 2.5 / -dz, np.inf)
        t_wall = np.where(np.abs(dy) > 1e-6, 12.0 / np.abs(dy), np.inf)
    t = np.minimum(t_ground, t_wall)
    z = 2.5 + t * dz
    hit = np.isfinite(t) & (z <= 15.0)
    x, y, z, t = x[hit][:n], (t * dy)[hit][:n], z[hit][:n], t[hit][:n]
    if len(x) < n:
        raise RuntimeError("strip generator made too few points")
    xyz = np.column_stack([x, y, z]) + rng.normal(0.0, 0.005, (n, 3))
    wall = np.abs(np.abs(y) - 12.0) < 0.05
    cls = np.where(wall, 6, np.where(np.abs(y) < 4.0, 11, 2)).astype(np.uint8)
    shade = (0.5 + 0.25 * np.sin(x / 3.0) + 0.25 * np.cos(z)) * 60000
    rgb = np.clip(shade[:, None] + rng.normal(0, 800, (n, 3)), 0, 65535).astype(np.uint16)
    return {
        "xyz": xyz,
        "classification": cls,
        "rgb": rgb,
        "intensity": np.clip(4000 / (1 + t), 0, 65535).astype(np.uint16),
        "gps_time": t0 + np.arange(n) / (100.0 * per_profile),
    }


def make_archive(root: Path, points: int, files: int, seed: int = 0) -> list[Path]:
    rng = np.random.default_rng(seed)
    per_file = points // files
    length = max(20.0, per_file / 20_000)  # ≈ 20 000 points per metre of street
    out = []
    for k in range(files):
        s = street_strip(rng, per_file, k * length, length, t0=k * 1000.0)
        out.append(_write(root / f"strip_{k:03d}.laz", s))
    return out


def _write(path: Path, s: dict[str, np.ndarray]) -> Path:
    from streetcd.io.las import write_las

    return write_las(
        path,
        s["xyz"],
        s["classification"],
        origin=ORIGIN,
        intensity=s["intensity"],
        rgb=s["rgb"],
        gps_time=s["gps_time"],
        crs=CRS,
    )


# --- timed children ----------------------------------------------------------------------


def _hwm_mb(pid: int | str) -> float:
    """Peak resident memory (VmHWM) of a process since its exec, MiB; 0 if it has gone.
    (ru_maxrss would also count the parent's pages the process had between fork and exec.)"""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    return 0.0


class _WorkerPeak:
    """Samples VmHWM of this process's children (the ingest workers) every 0.1 s."""

    def __init__(self) -> None:
        import threading

        self.peak = 0.0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.wait(0.1):
            for task in Path("/proc/self/task").iterdir():
                kids = (task / "children").read_text().split()
                self.peak = max([self.peak, *(_hwm_mb(k) for k in kids)])

    def stop(self) -> float:
        self._stop.set()
        self._thread.join()
        return self.peak


def child(args: argparse.Namespace) -> None:
    """Run one timed step in this (fresh) process; print JSON with seconds and peak RSS."""
    files = json.loads(args.child_files)
    workers_peak = _WorkerPeak()
    t0 = time.perf_counter()
    if args.child == "read":
        import laspy

        points = 0
        for f in files:
            with laspy.open(f) as reader:
                for chunk in reader.chunk_iterator(args.chunk_points):
                    points += len(chunk.X)
    else:
        from streetcd.store.ingest import ingest

        r = ingest(
            files,
            args.child_store,
            tile_size_m=args.tile_size,
            workers=args.workers,
            chunk_points=args.chunk_points,
        )
        if r.failed:
            raise SystemExit(f"ingest failed: {r.failed}")
        points = r.points
    seconds = time.perf_counter() - t0
    cpu = os.times()  # this process and its joined workers: load from others does not count
    print(
        json.dumps(
            {
                "seconds": seconds,
                "cpu_s": cpu.user + cpu.system + cpu.children_user + cpu.children_system,
                "points": points,
                "rss_mb": _hwm_mb("self"),
                "workers_rss_mb": workers_peak.stop(),
            }
        )
    )


def run_child(
    kind: str,
    files: list[Path],
    args: argparse.Namespace,
    store: Path | None = None,
    workers: int = 1,
) -> dict[str, float]:
    if store is not None:
        shutil.rmtree(store, ignore_errors=True)
    cmd = [
        sys.executable,
        __file__,
        "--child",
        kind,
        "--child-files",
        json.dumps([str(f) for f in files]),
        "--child-store",
        str(store or ""),
        "--workers",
        str(workers),
        "--tile-size",
        str(args.tile_size),
        "--chunk-points",
        str(args.chunk_points),
    ]
    out = subprocess.run(cmd, check=True, capture_output=True, text=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def ingest_table(files: list[Path], args: argparse.Namespace, work: Path) -> list[str]:
    subset = files[: max(1, len(files) // 5)]
    runs = [
        ("plain laspy read", "read", files, 1),
        ("ingest, 1 worker", "ingest", files, 1),
        ("ingest, 1 worker, 1/5 archive", "ingest", subset, 1),
        (f"ingest, {args.workers} workers", "ingest", files, args.workers),
        (f"ingest, {args.workers} workers, 1/5 archive", "ingest", subset, args.workers),
    ]
    keep = [int(k) for k in args.rows.split(",")] if args.rows else range(len(runs))
    runs = [runs[k] for k in keep]
    run_child("read", files, args)  # warm-up: imports, page cache
    # Round-robin over the rows, so that load from other processes drifts over all of them.
    results: list[list[dict[str, float]]] = [[] for _ in runs]
    for _ in range(args.repeats):
        for k, (_, kind, fs, w) in enumerate(runs):
            store = work / "bench.zarr" if kind == "ingest" else None
            results[k].append(run_child(kind, fs, args, store, w))
    rows, plain, plain_cpu = [], None, None
    for (label, kind, fs, _), res in zip(runs, results, strict=True):
        sec = statistics.median(r["seconds"] for r in res)
        cpu = statistics.median(r["cpu_s"] for r in res)
        pts = res[0]["points"]
        rate, cpu_rate = pts / sec, pts / cpu
        plain = plain or (rate if kind == "read" else float("nan"))
        plain_cpu = plain_cpu or (cpu_rate if kind == "read" else float("nan"))
        rss = max(r["rss_mb"] for r in res)
        wrss = max(r["workers_rss_mb"] for r in res)
        rows.append(
            f"| {label} | {len(fs)} | {pts:,} | {sec:.1f} | {rate / 1e6:.2f} | "
            f"{rate / plain:.2f} | {cpu:.1f} | {cpu_rate / plain_cpu:.2f} | "
            f"{rss:.0f} | {wrss:.0f} |"
        )
    head = [
        "| run | files | points | s (median) | Mpts/s | × plain read | CPU s | "
        "× plain read, per CPU s | peak RSS MB | peak RSS workers MB |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    return head + rows


# --- coordinates: int32 against float64 --------------------------------------------------


def coords_table(files: list[Path], work: Path) -> list[str]:
    """Bytes per point and write/read time of one tile's xyz as int32 (tile-local, 1 mm)
    against local float64, same Blosc-zstd compressor."""
    import zarr

    from streetcd.io.las import read_las
    from streetcd.store.ingest import _COMPRESSOR

    cloud = read_las(files[0], origin=ORIGIN)
    xyz = cloud.xyz[:2_000_000]
    variants = {
        "int32, 1 mm, tile-local": np.rint(xyz / 0.001).astype(np.int32),
        "float64, local": xyz,
    }
    rows = ["| xyz storage | bytes/point | write ms/Mpt | read ms/Mpt |", "|---|---|---|---|"]
    for label, arr in variants.items():
        w, r = [], []
        for k in range(4):
            path = work / f"coords_{k}.zarr"
            shutil.rmtree(path, ignore_errors=True)
            t0 = time.perf_counter()
            zarr.create_array(str(path), data=arr, chunks=(262_144, 3), compressors=_COMPRESSOR)
            w.append(time.perf_counter() - t0)
            t0 = time.perf_counter()
            zarr.open_array(str(path), mode="r")[:]
            r.append(time.perf_counter() - t0)
        size = sum(p.stat().st_size for p in path.rglob("*") if p.is_file())
        mpts = len(arr) / 1e6
        rows.append(
            f"| {label} | {size / len(arr):.2f} | "
            f"{statistics.median(w[1:]) * 1000 / mpts:.0f} | "
            f"{statistics.median(r[1:]) * 1000 / mpts:.0f} |"
        )
    return rows


# --- store build and crop latency against store size -------------------------------------


def crop_store(
    root: Path, n_tiles: int, core_points: int, tile: float, rng: np.random.Generator
) -> tuple[Path, dict[str, float]]:
    """A store of ``n_tiles`` tiles (≥ 10) in a square-ish grid: the 5 × 2 core that holds
    every view's frustum dense, every other tile 100 points (written in ≤ 10 files). Also
    times its build against a plain laspy read of the same files (the baseline)."""
    import laspy

    from streetcd.store.ingest import ingest

    cols = max(5, math.ceil(math.sqrt(n_tiles)))
    rows = math.ceil(n_tiles / cols)
    ij = np.array([(i, j) for j in range(rows) for i in range(cols)])[:n_tiles]
    core = (ij[:, 0] < 5) & (ij[:, 1] < 2)
    counts = np.where(core, core_points, 100)
    start = np.repeat(ij * tile, counts, axis=0)
    # Keep 1 cm off the tile edges: the 1 mm LAS grid would round a few points across them.
    xy = start + rng.uniform(0.01, tile - 0.01, (len(start), 2))
    z = rng.uniform(0.0, 15.0, len(start))
    xyz = np.column_stack([xy, z])
    n = len(xyz)
    s = {
        "xyz": xyz,
        "classification": rng.integers(1, 12, n).astype(np.uint8),
        "rgb": rng.integers(0, 65535, (n, 3)).astype(np.uint16),
        "intensity": rng.integers(0, 4000, n).astype(np.uint16),
        "gps_time": np.arange(n, dtype=np.float64),
    }
    arch = root / f"crop_archive_{n_tiles}"
    parts = np.array_split(np.arange(n), min(10, max(1, n_tiles // 10)))
    files = [
        _write(arch / f"part_{k}.laz", {key: v[idx] for key, v in s.items()})
        for k, idx in enumerate(parts)
    ]
    t0 = time.perf_counter()
    for f in files:
        with laspy.open(f) as reader:
            for _ in reader.chunk_iterator(1_000_000):
                pass
    read_s = time.perf_counter() - t0
    store = root / f"crop_{n_tiles}.zarr"
    shutil.rmtree(store, ignore_errors=True)
    t0 = time.perf_counter()
    ingest(arch, store, tile_size_m=tile, workers=2)
    build_s = time.perf_counter() - t0
    shutil.rmtree(arch)
    return store, {"files": len(files), "points": n, "read_s": read_s, "build_s": build_s}


def crop_table(args: argparse.Namespace, work: Path) -> list[str]:
    """Two tables: store build time per tile count (baseline: a plain laspy read of the same
    files), and crop latency per view (baseline: the smallest store, same views)."""
    from streetcd.geometry.camera import look_at
    from streetcd.store.crop import crop_for_view
    from streetcd.store.tiles import TileStore, tile_cache
    from streetcd.types import Intrinsics, View

    rng = np.random.default_rng(1)
    tile = args.tile_size
    intr = Intrinsics(width=1600, height=1200, fx=1500.0, fy=1500.0, cx=799.5, cy=599.5)
    views = []
    for _ in range(args.views):  # frustum (60 m, ±28° wide, ± 5° yaw) inside the 5 × 2 core
        c = np.array([rng.uniform(0.5, 2.5) * tile, rng.uniform(0.9, 1.1) * tile, 2.5])
        yaw = np.radians(rng.uniform(-5, 5))
        target = c + np.array([np.cos(yaw), np.sin(yaw), -0.05])
        views.append(View("v", intr, look_at(c + ORIGIN, target + ORIGIN)))
    build = [
        "| tiles in store | points | files | plain read s | build s | build ms/tile | "
        "build µs/point | build × plain read |",
        "|---|---|---|---|---|---|---|---|",
    ]
    crop = [
        "| tiles in store | open index ms | bbox lookup µs | crop warm ms (median) | "
        "warm p90 ms | warm × smallest store | crop cold ms (median) | points/view |",
        "|---|---|---|---|---|---|---|---|",
    ]
    base = None
    for n_tiles in [int(x) for x in args.crop_tiles.split(",")]:
        path, b = crop_store(work, n_tiles, args.core_points, tile, rng)
        t0 = time.perf_counter()
        store = TileStore.open(path)
        open_ms = (time.perf_counter() - t0) * 1000
        build.append(
            f"| {len(store):,} | {store.point_count:,} | {b['files']} | {b['read_s']:.2f} | "
            f"{b['build_s']:.2f} | {b['build_s'] * 1000 / len(store):.2f} | "
            f"{b['build_s'] * 1e6 / b['points']:.2f} | {b['build_s'] / b['read_s']:.1f} |"
        )
        t0 = time.perf_counter()
        for _ in range(1000):
            store.tiles_in_bbox(ORIGIN[0] + 10, ORIGIN[1] + 10, ORIGIN[0] + 130, ORIGIN[1] + 90)
        lookup_us = (time.perf_counter() - t0) * 1000
        cold = []
        for v in views[:10]:
            tile_cache().clear()
            t0 = time.perf_counter()
            crop_for_view(store, v)
            cold.append(time.perf_counter() - t0)
        tile_cache().clear()
        for v in views:  # warm-up pass fills the cache
            crop_for_view(store, v)
        warm, sizes = [], []
        for v in views:
            t0 = time.perf_counter()
            sizes.append(len(crop_for_view(store, v)))
            warm.append(time.perf_counter() - t0)
        med = statistics.median(warm)
        base = base or med
        crop.append(
            f"| {len(store):,} | {open_ms:.1f} | {lookup_us:.1f} | {med * 1000:.1f} | "
            f"{np.percentile(warm, 90) * 1000:.1f} | {med / base:.2f} | "
            f"{statistics.median(cold) * 1000:.1f} | {int(np.median(sizes)):,} |"
        )
        print(f"  store of {len(store):,} tiles built in {b['build_s']:.1f} s", file=sys.stderr)
        shutil.rmtree(path)
    return [*build, "", *crop]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--points", type=int, default=50_000_000, help="archive size (points)")
    ap.add_argument("--files", type=int, default=10)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--tile-size", type=float, default=50.0)
    ap.add_argument("--chunk-points", type=int, default=1_000_000)
    ap.add_argument("--repeats", type=int, default=1, help="timed runs per row (median)")
    ap.add_argument("--crop-tiles", default="10,100,1000,10000")
    ap.add_argument("--core-points", type=int, default=100_000, help="points per core tile")
    ap.add_argument("--views", type=int, default=40)
    ap.add_argument("--out", help="work folder (kept); default a temporary one (removed)")
    ap.add_argument("--skip", default="", help="comma list of sections to skip: ingest,coords,crop")
    ap.add_argument(
        "--rows",
        help="ingest-table rows to run, e.g. 0,3 (default all; '× plain read' needs row 0)",
    )
    ap.add_argument("--child", help=argparse.SUPPRESS)
    ap.add_argument("--child-files", help=argparse.SUPPRESS)
    ap.add_argument("--child-store", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        child(args)
        return
    work = Path(args.out) if args.out else Path(tempfile.mkdtemp(prefix="streetcd-bench-"))
    skip = set(args.skip.split(","))
    try:
        t0 = time.perf_counter()
        files = sorted((work / "archive").glob("*.laz"))
        if len(files) != args.files and {"ingest", "coords"} - skip:
            shutil.rmtree(work / "archive", ignore_errors=True)
            files = make_archive(work / "archive", args.points, args.files)
        print(
            f"archive: {args.files} LAZ files, {args.points:,} points "
            f"({sum(f.stat().st_size for f in files) / 2**20:.0f} MiB) "
            f"in {time.perf_counter() - t0:.0f} s; chunk {args.chunk_points:,} points, "
            f"{args.tile_size:g} m tiles",
            file=sys.stderr,
        )
        if "ingest" not in skip:
            print("\n".join(ingest_table(files, args, work)))
            print()
        if "coords" not in skip:
            print("\n".join(coords_table(files, work)))
            print()
        if "crop" not in skip:
            print("\n".join(crop_table(args, work)))
    finally:
        if not args.out:
            shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
