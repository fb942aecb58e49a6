"""A synthetic city of 1,000 and 10,000 views of small images through ``streetcd run``: wall
time, orchestration overhead, peak memory per worker, index size and ``streetcd query`` times.

    nice .venv/bin/python benchmarks/city_scale.py --views 1000,10000     # out/city-scale/
    nice .venv/bin/python benchmarks/city_scale.py --views 1000 --generate-only

The city: one synthetic city of 1,000 views (40 streets of 25 views, ``--size``, default
320x180) is rendered once; a city of N views is ``N / 1,000`` copies of it, each moved by a
whole number of kilometres north (its images hard-linked under new names, its poses moved,
its LAZ files with their header's offset and bounds moved: the points' stored integers are
the same). Rendering 1,000 views took 19 min on the shared 2-core VM; the copies are distinct
views, tiles and segments to the store, the planner, the cluster and the index, and each
copy's detector work is the first one's, so that 1,000 and 10,000 views compare like with
like. Each city is ingested once (untimed) and cached under ``--out``.

Each run is the real command, ``streetcd run --workers 2`` in a subprocess (its LocalCluster,
its temporary Prefect server), on a fresh index, after an untimed warm-up that fills numba's
on-disk cache (:func:`throughput.warm_up`). A thread samples the resident set size (RSS,
psutil) of the run's Dask worker processes (its ``multiprocessing`` spawn children) every
0.5 s: ``peak RSS`` is each worker's highest sample. From the run's summary and its index:

    overhead = wall / (Σ detect / workers) − 1     (benchmarks/throughput.py's definition)

with ``wall`` the flow's own wall time (``seconds.wall`` of ``runs/latest.json``: planning,
the cluster's start, detection, publishing; the Prefect server's start and the process's
imports are outside it, and printed as ``process s``). ``cpu/core`` is the workers' CPU time
per core-second of wall (Σ per-view CPU / (wall × workers)): far below 100 %, the machine was
shared and the overhead says more about the neighbours (load averages are printed too).
A second table gives the CPU seconds of the run's processes by kind (psutil, every 0.5 s):
the Dask workers, the flow process (planning, the LocalCluster's scheduler and the client,
Prefect's task engine, publishing, the change objects), Prefect's temporary server, the
``streetcd run`` command itself, the rest; against the command's time × the cores. On a
machine with as many cores as workers, the flow and the server run on the workers' cores.

``streetcd query`` is timed on the run's index, median of 5, as a subprocess (what a user
waits for, Python's start and imports included) and in-process (``run_query``, the query
itself): all objects as JSON, the first 100 objects, flagged views ``--views --limit 100``,
and a ``--bbox`` of 200 m around the middle change of the city (query_speed.middle_bbox).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shutil
import sqlite3
import statistics
import struct
import subprocess
import sys
import threading
import time
from contextlib import closing
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))
from query_speed import COMMAND_ENV, middle_bbox  # noqa: E402  (a box around a change, not between copies)
from throughput import load, warm_up  # noqa: E402  (the sibling benchmark's helpers)

from streetcd.config import RunParams  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
BIN = Path(sys.executable).parent
BASE_VIEWS = 1000  # views of the rendered city; bigger cities are copies of it
PER_STREET = 25
# LAS header (1.2-1.4): x, y offsets (doubles) at bytes 155, 163; max x, min x, max y, min y
# at 179, 187, 195, 203.
LAS_OFFSET_XY = (155, 163)
LAS_BOUNDS = {"max_x": 179, "min_x": 187, "max_y": 195, "min_y": 203}


# --- the city ------------------------------------------------------------------------------


def base_city(root: Path, size: tuple[int, int], seed: int) -> Path:
    """The rendered 1,000-view city (reused when there): its folder (generate_city's)."""
    from streetcd.synth import generate_city

    folder = root / f"base-{size[0]}x{size[1]}-seed{seed}"
    if not (folder / "manifest.json").exists():
        t0 = time.perf_counter()
        shutil.rmtree(folder, ignore_errors=True)
        generate_city(
            folder,
            seed=seed,
            n_streets=BASE_VIEWS // PER_STREET,
            images_per_street=PER_STREET,
            size=size,
        )
        print(
            f"rendered {BASE_VIEWS} views {size[0]}x{size[1]} in {time.perf_counter() - t0:.0f} s"
        )
    return folder


def _cloud_span_y(cloud: Path) -> float:
    """North-south extent of the base city's cloud, metres (from the LAS headers)."""
    lo, hi = math.inf, -math.inf
    for laz in sorted(cloud.glob("*.la[sz]")):
        with open(laz, "rb") as f:
            head = f.read(227)
        hi = max(hi, struct.unpack_from("<d", head, LAS_BOUNDS["max_y"])[0])
        lo = min(lo, struct.unpack_from("<d", head, LAS_BOUNDS["min_y"])[0])
    return hi - lo


def _moved_las(src: Path, dst: Path, dy: float) -> None:
    """``src`` with its points moved ``dy`` metres north: the header's y offset and bounds
    change, the (compressed) point records are copied as they are."""
    head = bytearray(src.read_bytes())
    for at in (LAS_OFFSET_XY[1], LAS_BOUNDS["max_y"], LAS_BOUNDS["min_y"]):
        (v,) = struct.unpack_from("<d", head, at)
        struct.pack_into("<d", head, at, v + dy)
    dst.write_bytes(bytes(head))


def _moved_poses(src: Path, dst: Path, copies: int, dy: float) -> None:
    """The OPK CSV with ``copies`` copies of every row, copy ``j`` renamed ``C{j}_<name>``,
    moved ``j·dy`` metres north and driven after copy ``j - 1`` (its ``time`` shifted)."""
    lines = src.read_text().splitlines()
    head = [ln for ln in lines if ln.startswith("#")]
    header, *rows = [ln for ln in lines if ln and not ln.startswith("#")]
    cols = header.split(",")
    i_name, i_y, i_t = cols.index("name"), cols.index("y"), cols.index("time")
    times = [float(r.split(",")[i_t]) for r in rows]
    dt = max(times) - min(times) + 1.0
    out = [*head, header]
    for j in range(copies):
        for row in rows:
            f = row.split(",")
            f[i_name] = f"C{j}_{f[i_name]}"
            f[i_y] = repr(float(f[i_y]) + j * dy)
            f[i_t] = repr(float(f[i_t]) + j * dt)
            out.append(",".join(f))
    dst.write_text("\n".join(out) + "\n")


def city(root: Path, views: int, size: tuple[int, int], seed: int) -> dict[str, str]:
    """The ``views``-view city (``views / 1,000`` moved copies of the base city), ingested
    into its tile store; reused when there. Returns ``images``, ``poses``, ``store``."""
    from streetcd.store.ingest import ingest

    if views % BASE_VIEWS:
        raise SystemExit(f"--views {views}: must be a multiple of {BASE_VIEWS}")
    copies = views // BASE_VIEWS
    folder = root / f"city-{views}-{size[0]}x{size[1]}-seed{seed}"
    paths = {
        "images": str(folder / "images"),
        "poses": str(folder / "poses_opk.csv"),
        "store": str(folder / "store.zarr"),
    }
    done = folder / "ingested"
    if done.exists():
        return paths
    base = base_city(root, size, seed)
    t0 = time.perf_counter()
    shutil.rmtree(folder, ignore_errors=True)
    for sub in ("images", "cloud"):
        (folder / sub).mkdir(parents=True)
    dy = 1000.0 * math.ceil((_cloud_span_y(base / "cloud") + 500.0) / 1000.0)
    images = sorted((base / "images").iterdir())
    for j in range(copies):
        for img in images:
            os.link(img, folder / "images" / f"C{j}_{img.name}")
        for laz in sorted((base / "cloud").glob("*.la[sz]")):
            _moved_las(laz, folder / "cloud" / f"C{j}_{laz.name}", j * dy)
    _moved_poses(base / "poses" / "poses_opk.csv", folder / "poses_opk.csv", copies, dy)
    t1 = time.perf_counter()
    ingest(folder / "cloud", folder / "store.zarr")
    done.write_text(f"{copies} copies, {dy:.0f} m apart\n")
    print(
        f"city of {views} views: {copies} copies {dy:.0f} m apart in {t1 - t0:.0f} s, "
        f"ingested in {time.perf_counter() - t1:.0f} s",
        flush=True,
    )
    return paths


# --- one run -------------------------------------------------------------------------------


class RssSampler(threading.Thread):
    """Samples, every ``every_s`` seconds, the RSS of ``streetcd run``'s Dask worker processes
    (its descendants started by ``multiprocessing``'s spawn) and of its flow process (the
    supervised ``streetcd.cli.run`` child: planning, the client, publishing); keeps each
    one's peak, bytes; every 10 s it writes them to ``dump`` (JSON, for a run cut short).
    Every ``trace_s`` seconds it adds a line to ``trace`` (a text file): the time, the views
    the index holds (``index``, read-only), each worker's and the flow's RSS now, the load.

    It also keeps each process's CPU time (user + system) at its last sample, by kind
    (:func:`process_kind`): where the two cores went. A process's last 0.5 s before it
    exits are not counted."""

    def __init__(
        self,
        pid: int,
        dump: Path,
        every_s: float = 0.5,
        trace: Path | None = None,
        index: Path | None = None,
        trace_s: float = 20.0,
    ) -> None:
        super().__init__(daemon=True)
        self.pid, self.dump, self.every_s = pid, dump, every_s
        self.trace, self.index, self.trace_s = trace, index, trace_s
        self.workers: dict[int, int] = {}
        self.now: dict[int, int] = {}
        self.main = 0
        self.main_now = 0
        self.cpu: dict[int, tuple[str, float]] = {}  # pid → (kind, CPU s at the last sample)
        self.stopped = threading.Event()

    def cpu_by_kind(self) -> dict[str, float]:
        """CPU seconds of the run's processes, summed by kind."""
        out: dict[str, float] = {}
        for kind, cpu in self.cpu.values():
            out[kind] = out.get(kind, 0.0) + cpu
        return out

    def _trace_line(self) -> None:
        if self.trace is None:
            return
        views = "-"
        if self.index is not None and self.index.exists():
            try:
                with closing(sqlite3.connect(f"file:{self.index}?mode=ro", uri=True)) as db:
                    views = str(db.execute("SELECT count(*) FROM views").fetchone()[0])
            except sqlite3.Error:
                pass
        mib = " ".join(f"{v / 2**20:.0f}" for _, v in sorted(self.now.items()))
        with open(self.trace, "a") as f:
            f.write(
                f"{time.strftime('%H:%M:%S', time.gmtime())} views={views} "
                f"workers_MiB={mib} flow_MiB={self.main_now / 2**20:.0f} load={load()}\n"
            )

    def run(self) -> None:
        import psutil

        root = psutil.Process(self.pid)
        last = last_trace = time.monotonic()
        while not self.stopped.wait(self.every_s):
            if time.monotonic() - last > 10:
                last = time.monotonic()
                peaks = {"main": self.main, "workers": self.workers, "load": load()}
                self.dump.write_text(json.dumps(peaks) + "\n")
            if time.monotonic() - last_trace > self.trace_s:
                last_trace = time.monotonic()
                self._trace_line()
            try:
                self.main = max(self.main, root.memory_info().rss)
                children = root.children(recursive=True)
                self.cpu[root.pid] = ("command", _cpu_s(root))
            except psutil.Error:
                return
            for p in children:
                try:
                    kind = process_kind(" ".join(p.cmdline()))
                    self.cpu[p.pid] = (kind, _cpu_s(p))
                    if kind == "workers":
                        self.now[p.pid] = p.memory_info().rss
                        self.workers[p.pid] = max(self.workers.get(p.pid, 0), self.now[p.pid])
                    elif kind == "flow":
                        self.main_now = p.memory_info().rss
                        self.main = max(self.main, self.main_now)
                except psutil.Error:
                    pass


def process_kind(cmdline: str) -> str:
    """Which part of a night a process of ``streetcd run`` is, from its command line."""
    if "spawn_main" in cmdline:  # multiprocessing's spawned children: the Dask workers
        return "workers"
    if "streetcd.cli.run" in cmdline:
        return "flow"  # planning, the Dask scheduler and client, Prefect's engine, publishing
    if "prefect.server" in cmdline:
        return "prefect server"
    return "other"


def _cpu_s(p: Any) -> float:
    t = p.cpu_times()
    return float(t.user + t.system)


def night(paths: dict[str, str], out: Path, workers: int, batch_size: int) -> dict[str, Any]:
    """``streetcd run`` on a fresh index in ``out``: its summary, the index's per-view sums,
    the RSS peaks and the load average before and after."""
    shutil.rmtree(out, ignore_errors=True)
    out.mkdir(parents=True)
    index = out / "change_index.sqlite"
    cmd = [
        str(BIN / "streetcd"), "run", "--images", paths["images"], "--poses", paths["poses"],
        "--store", paths["store"], "--index", str(index), "--out", str(out / "results"),
        "--workers", str(workers), "--batch-size", str(batch_size),
    ]  # fmt: skip
    env = {
        k: v for k, v in os.environ.items() if k not in ("PREFECT_API_URL", "STREETCD_SCHEDULER")
    }
    before = load()
    t0 = time.perf_counter()
    with open(out / "run.log", "wb") as log:
        proc = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, env=env, cwd=ROOT)
        sampler = RssSampler(proc.pid, out / "rss.json", trace=out / "rss-trace.txt", index=index)
        sampler.start()
        code = proc.wait()
        sampler.stopped.set()
        sampler.join()
    process_s = time.perf_counter() - t0
    summary = json.loads((out / "results" / "runs" / "latest.json").read_text())
    with closing(sqlite3.connect(f"file:{index}?mode=ro", uri=True)) as db:
        n, detect_s, view_s, cpu_s = db.execute(
            "SELECT count(*), sum(detect_s), sum(total_s), sum(cpu_s) FROM views "
            "WHERE status = 'done'"
        ).fetchone()
        # the run's end after its last view was published (1 s timestamps): the objects'
        # rebuild and the run's close
        (tail_s,) = db.execute(
            "SELECT (julianday(r.finished_at) - julianday(max(v.processed_at))) * 86400"
            " FROM runs r JOIN views v ON v.run_id = r.run_id"
        ).fetchone()
    return {
        "command": " ".join(cmd),
        "exit_code": code,
        "process_s": process_s,
        "wall_s": summary["seconds"]["wall"],
        "plan_s": summary["seconds"]["plan"],
        "tail_s": tail_s,
        "n_done": n,
        "n_failed": summary["views"]["failed"],
        "detect_s": detect_s or 0.0,
        "view_s": view_s or 0.0,
        "cpu_s": cpu_s or 0.0,
        "workers": workers,
        "worker_rss": sorted(sampler.workers.values(), reverse=True),
        "main_rss": sampler.main,
        "cpu_by_process": sampler.cpu_by_kind(),
        "index": index,
        "index_bytes": sum(
            p.stat().st_size for p in out.glob("change_index.sqlite*") if p.is_file()
        ),
        "load": f"{before} → {load()}",
    }


# --- queries -------------------------------------------------------------------------------


def query_times(index: Path, repeat: int = 5) -> list[dict[str, Any]]:
    """Median seconds of each typical query, as ``streetcd query`` in a subprocess and as
    ``run_query`` in this process, with the size of its answer."""
    from streetcd.cli.query import run_query

    box = middle_bbox(index)
    queries: list[tuple[str, list[str], dict[str, Any]]] = [
        ("all objects, json", ["--format", "json"], {"fmt": "json"}),
        (
            "objects --limit 100, json",
            ["--limit", "100", "--format", "json"],
            {"limit": 100, "fmt": "json"},
        ),
        ("--views --limit 100", ["--views", "--limit", "100"], {"views": True, "limit": 100}),
        (
            "--bbox 200 m, json",
            ["--bbox", ",".join(f"{v:.1f}" for v in box), "--format", "json"],
            {"bbox": tuple(round(v, 1) for v in box), "fmt": "json"},
        ),
    ]
    rows = []
    for name, args, kwargs in queries:
        cmd = [str(BIN / "streetcd"), "query", "--index", str(index), *args]
        sub, inproc = [], []
        for _ in range(repeat):
            t = time.perf_counter()
            done = subprocess.run(cmd, capture_output=True, text=True, check=True, env=COMMAND_ENV)
            sub.append(time.perf_counter() - t)
            t = time.perf_counter()
            text = run_query(index, **kwargs)
            inproc.append(time.perf_counter() - t)
        assert text.strip() == done.stdout.strip(), f"{name}: in-process and CLI answers differ"
        rows.append(
            {
                "query": name,
                "command": " ".join(cmd[1:]),
                "subprocess_s": statistics.median(sub),
                "in_process_s": statistics.median(inproc),
                "answer_bytes": len(done.stdout.encode()),
            }
        )
    # the floor of any `streetcd query`: Python's start and the CLI's imports, no index read
    floor = [str(BIN / "streetcd"), "query", "--help"]
    times = []
    for _ in range(repeat):
        t = time.perf_counter()
        subprocess.run(floor, capture_output=True, check=True, env=COMMAND_ENV)
        times.append(time.perf_counter() - t)
    rows.append(
        {
            "query": "(start only: --help)",
            "command": " ".join(floor[1:]),
            "subprocess_s": statistics.median(times),
            "in_process_s": 0.0,
            "answer_bytes": 0,
        }
    )
    return rows


# --- report --------------------------------------------------------------------------------


def table(rows: list[dict[str, Any]]) -> str:
    mib = 1 / 2**20
    lines = [
        f"{'views':>6} {'wall s':>7} {'process s':>9} {'plan s':>6} {'tail s':>6} {'views/min':>9} "
        f"{'Σ detect s':>10} {'overhead':>8} {'vs view':>7} {'cpu/core':>8} "
        f"{'worker peak RSS MiB':>19} {'flow MiB':>8} {'index MB':>8} {'failed':>6}  load"
    ]
    for s in rows:
        w, wall = s["workers"], s["wall_s"]
        rss = "/".join(f"{r * mib:.0f}" for r in s["worker_rss"]) or "-"
        lines.append(
            f"{s['n_done']:>6} {wall:>7.1f} {s['process_s']:>9.1f} {s['plan_s']:>6.1f} "
            f"{s.get('tail_s') or 0:>6.0f} "
            f"{60 * s['n_done'] / wall:>9.1f} {s['detect_s']:>10.1f} "
            f"{100 * (wall / (s['detect_s'] / w) - 1):>7.1f}% "
            f"{100 * (wall / (s['view_s'] / w) - 1):>6.1f}% "
            f"{100 * s['cpu_s'] / (wall * w):>7.0f}% {rss:>19} {s['main_rss'] * mib:>8.0f} "
            f"{s['index_bytes'] / 1e6:>8.2f} {s['n_failed']:>6}  {s['load']}"
        )
    lines.append("")
    kinds = ("workers", "flow", "prefect server", "command", "other")
    lines.append(f"{'views':>6} " + " ".join(f"{k + ' CPU s':>18}" for k in kinds) + "  of")
    for s in rows:
        cpu = s.get("cpu_by_process") or {}
        lines.append(
            f"{s['n_done']:>6} "
            + " ".join(f"{cpu.get(k, 0.0):>18.1f}" for k in kinds)
            + f"  {s['process_s'] * (os.cpu_count() or 1):.0f} core-s (the command's time × cores)"
        )
    lines.append("")
    lines.append(
        f"{'views':>6} {'query':<26} {'subprocess ms':>13} {'in-process ms':>13} {'bytes':>9}"
    )
    for s in rows:
        for q in s["queries"]:
            lines.append(
                f"{s['n_done']:>6} {q['query']:<26} {1000 * q['subprocess_s']:>13.0f} "
                f"{1000 * q['in_process_s']:>13.1f} {q['answer_bytes']:>9}"
            )
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--views", default="1000,10000", help="city sizes, multiples of 1,000")
    ap.add_argument("--size", default="320x180", help="image size WxH")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument(
        "--batch-size", type=int, default=RunParams().batch_size, help="views per task [config's]"
    )
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default=str(ROOT / "out" / "city-scale"), help="work folder")
    ap.add_argument("--generate-only", action="store_true", help="make the cities, run nothing")
    ap.add_argument(
        "--queries-only",
        action="store_true",
        help="time the queries again on the indexes of earlier runs (their result.json)",
    )
    args = ap.parse_args()
    size = tuple(int(x) for x in args.size.lower().split("x"))
    assert len(size) == 2
    root = Path(args.out)
    sizes = [int(v) for v in args.views.split(",")]
    if args.queries_only:
        for n in sizes:
            s = json.loads((root / f"run-{n}" / "result.json").read_text())
            s["queries"] = query_times(Path(s["index"]))
            (root / f"run-{n}" / "result.json").write_text(json.dumps(s, indent=2) + "\n")
            print(f"{n} views: queries on {s['index']} ({s['index_bytes'] / 1e6:.2f} MB)")
            print("\n".join(table([s]).splitlines()[3:]))
        return
    cities = {n: city(root, n, (size[0], size[1]), args.seed) for n in sizes}
    if args.generate_only:
        return
    # numba's on-disk cache, filled once on the smallest city (planning 10,000 views to
    # detect two would be a waste)
    warm_up(city(root, BASE_VIEWS, (size[0], size[1]), args.seed), root / "warmup")
    rows = []
    for n in sizes:
        run_dir = root / f"run-{n}"
        s = night(cities[n], run_dir, args.workers, args.batch_size)
        s["queries"] = query_times(s["index"])
        rows.append(s)
        print(f"{n} views: exit {s['exit_code']}, wall {s['wall_s']:.0f} s", flush=True)
        (run_dir / "result.json").write_text(json.dumps(s, indent=2, default=str) + "\n")
    print(
        f"\ncity of {size[0]}x{size[1]} views, {args.workers} workers, batch size "
        f"{args.batch_size}, {os.cpu_count()} cores; worker RSS sampled every 0.5 s (psutil)"
    )
    for s in rows:
        print(f"{s['n_done']} views: {s['command']}")
    print(table(rows))


if __name__ == "__main__":
    main()
