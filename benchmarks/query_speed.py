"""How long ``streetcd query`` takes on a big change index, in-process and as a command, and
where a command's time goes (Python's start, imports, the query, printing).

    nice .venv/bin/python benchmarks/query_speed.py                      # the city indexes
    nice .venv/bin/python benchmarks/query_speed.py --index A.sqlite --index B.sqlite
    nice .venv/bin/python benchmarks/query_speed.py --json out/query-speed.json

Each index is copied to a temporary folder first (``query`` opens it read-only, but a
benchmark should not even risk the original). Default indexes: the cities of
``benchmarks/city_scale.py`` (``out/city-scale/run-1000`` and ``run-10000``).

For each query form: the median of ``--repeat`` (5) runs of ``run_query`` in this process
(the query itself: SQLite, decoding, formatting) and of ``streetcd query`` in a subprocess
(what a user waits for: Python's start, the imports, the query, writing the answer to a
pipe), and the answer's size. Two baselines are timed in the same run, at the same load:
``python -c pass`` (the interpreter's start), ``streetcd query --help`` (start and the query
command's own imports, no index read) and ``streetcd --version`` (start and click, which
every other command loads and ``query`` does not: streetcd/cli/entry.py). The load average before and after is
printed: on a shared VM a subprocess time is only comparable within one run.

It also lists which heavy libraries a real ``streetcd query`` imports (numpy, zarr, numba,
pyproj, yaml ...): none should be needed for a table or JSON answer.

``--against OTHER_VENV/bin`` compares two installs instead (each ``pip install``-ed, not
editable: an editable install's import hook slows every start): each form as a command of
the other install and of this interpreter's, alternated run by run, and whether their
answers are the same bytes.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import sqlite3
import statistics
import subprocess
import sys
import tempfile
import time
from contextlib import closing
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
BIN = Path(sys.executable).parent
DEFAULT_INDEXES = [
    ROOT / "out/city-scale/run-1000/change_index.sqlite",
    ROOT / "out/city-scale/run-10000/change_index.sqlite",
]
HEAVY = ("numpy", "zarr", "numba", "pyproj", "yaml", "scipy", "dask", "prefect", "pyogrio")
# Runs one `streetcd query` in this interpreter and names the heavy modules it loaded.
PROBE = (
    "import sys\n"
    "from streetcd.cli.entry import main\n"
    "sys.argv = ['streetcd', *sys.argv[1:]]\n"
    "try:\n"
    "    main()\n"
    "except SystemExit:\n"
    "    pass\n"
    f"print(','.join(m for m in {HEAVY!r} if m in sys.modules), file=sys.stderr)\n"
)


def middle_bbox(index: Path, half_m: float = 100.0) -> tuple[float, float, float, float]:
    """A box of 2 × ``half_m`` metres around the middle street change (by id) of the index:
    the middle of the camera centres (city_scale.py's box) can fall between the city's
    copies, where the answer is empty."""
    uri = index.resolve().as_uri() + "?mode=ro"
    with closing(sqlite3.connect(uri, uri=True)) as conn:
        n = conn.execute("SELECT count(*) FROM objects WHERE transient IS NULL").fetchone()[0]
        cx, cy = conn.execute(
            "SELECT x, y FROM objects WHERE transient IS NULL ORDER BY object_id LIMIT 1 OFFSET ?",
            (n // 2,),
        ).fetchone()
    return (cx - half_m, cy - half_m, cx + half_m, cy + half_m)


def forms(index: Path) -> list[tuple[str, list[str], dict[str, Any]]]:
    """(name, command-line arguments, run_query keywords) of each query form timed."""
    box = tuple(round(v, 1) for v in middle_bbox(index))
    box_arg = ",".join(f"{v:.1f}" for v in box)
    return [
        ("objects, table", [], {}),
        ("objects, json", ["--format", "json"], {"fmt": "json"}),
        ("objects, geojson", ["--format", "geojson"], {"fmt": "geojson"}),
        ("objects --limit 100, json", ["--limit", "100", "--format", "json"],
         {"limit": 100, "fmt": "json"}),
        ("--views --limit 100", ["--views", "--limit", "100"], {"views": True, "limit": 100}),
        ("--views, json", ["--views", "--format", "json"], {"views": True, "fmt": "json"}),
        ("--bbox 200 m, json", ["--bbox", box_arg, "--format", "json"],
         {"bbox": box, "fmt": "json"}),
        ("--awaiting-review --limit 20", ["--awaiting-review", "--limit", "20"],
         {"status": "awaiting", "limit": 20}),
    ]  # fmt: skip


def median_s(fn: Any, repeat: int) -> tuple[float, float, Any]:
    """The median wall seconds of ``repeat`` calls of ``fn``, the median CPU seconds (user +
    system) of the child processes they ran (0 for none), and the last call's result. On a
    shared machine the CPU time moves less with the load than the wall time."""
    times, cpu, out = [], [], None
    for _ in range(repeat):
        before = resource.getrusage(resource.RUSAGE_CHILDREN)
        t = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t)
        after = resource.getrusage(resource.RUSAGE_CHILDREN)
        cpu.append(after.ru_utime - before.ru_utime + after.ru_stime - before.ru_stime)
    return statistics.median(times), statistics.median(cpu), out


# The commands run as an installed streetcd does, from compiled bytecode: with
# PYTHONDONTWRITEBYTECODE set (as on our development machines) every command compiled the
# modules it imports again, ~10 ms more than a user's install pays.
COMMAND_ENV = {k: v for k, v in os.environ.items() if k != "PYTHONDONTWRITEBYTECODE"}


def command(args: list[str]) -> Any:
    return lambda: subprocess.run(args, capture_output=True, text=True, check=True, env=COMMAND_ENV)


def streetcd_command() -> list[str]:
    """The installed ``streetcd`` script, or (the package on PYTHONPATH, not installed) the
    same entry point through this interpreter."""
    script = BIN / "streetcd"
    if script.is_file():
        return [str(script)]
    return [sys.executable, "-c", "from streetcd.cli.entry import main; main()"]


def time_index(index: Path, repeat: int) -> dict[str, Any]:
    """Baselines, then every query form, on ``index``."""
    from streetcd.cli.query import run_query

    base = [*streetcd_command(), "query", "--index", str(index)]
    rows: list[dict[str, Any]] = []
    for name, args in (
        ("(python -c pass)", [sys.executable, "-c", "pass"]),
        ("(streetcd query --help)", [*streetcd_command(), "query", "--help"]),
        ("(streetcd --version: click)", [*streetcd_command(), "--version"]),
    ):
        sub, cpu, _ = median_s(command(args), repeat)
        rows.append(
            {
                "query": name,
                "subprocess_s": sub,
                "subprocess_cpu_s": cpu,
                "in_process_s": None,
                "bytes": 0,
            }
        )
    for name, args, kwargs in forms(index):
        sub, cpu, done = median_s(command(base + args), repeat)
        inproc, _, text = median_s(lambda kw=kwargs: run_query(index, **kw), repeat)
        if text.strip() != done.stdout.strip():
            raise SystemExit(f"{name}: the in-process and the command's answers differ")
        rows.append(
            {
                "query": name,
                "command": " ".join(["streetcd", "query", *args]),
                "subprocess_s": sub,
                "subprocess_cpu_s": cpu,
                "in_process_s": inproc,
                "bytes": len(done.stdout.encode()),
            }
        )
    probe = subprocess.run(
        [sys.executable, "-c", PROBE, "query", "--index", str(index), "--limit", "100"],
        capture_output=True,
        text=True,
        check=True,
    )
    heavy = probe.stderr.strip().splitlines()[-1] if probe.stderr.strip() else ""
    return {"index": str(index), "queries": rows, "heavy_imports": heavy}


def compare(index: Path, other_bin: Path, repeat: int) -> str:
    """``--against``: every form as a command of the install in ``other_bin`` (``before``)
    and of this one (``after``), alternated run by run so that both see the same load;
    median ms of each, and whether their answers are the same bytes."""
    installs = {"before": other_bin, "after": BIN}
    for name, where in installs.items():
        if not (where / "python").is_file() or not (where / "streetcd").is_file():
            raise SystemExit(f"--against: no python and streetcd in {where} ({name})")
    cases = [("(python -c pass)", None)] + [(name, args) for name, args, _ in forms(index)]
    times: dict[tuple[str, str], list[float]] = {}
    answers: dict[tuple[str, str], bytes] = {}
    for _ in range(repeat):
        for name, args in cases:
            for which, where in installs.items():
                cmd = [str(where / "python"), "-c", "pass"]
                if args is not None:  # through its own python: a copied venv keeps its shebang
                    cmd = [str(where / "python"), str(where / "streetcd"), "query"]
                    cmd += ["--index", str(index), *args]
                t = time.perf_counter()
                done = subprocess.run(
                    cmd, capture_output=True, check=True, cwd=tempfile.gettempdir()
                )
                times.setdefault((name, which), []).append(time.perf_counter() - t)
                answers[name, which] = done.stdout
    lines = [f"{'query':<30} {'before ms':>9} {'after ms':>9}  same answer"]
    for name, _ in cases:
        same = answers[name, "before"] == answers[name, "after"]
        lines.append(
            f"{name:<30} {1000 * statistics.median(times[name, 'before']):>9.0f}"
            f" {1000 * statistics.median(times[name, 'after']):>9.0f}  {'yes' if same else 'NO'}"
        )
    return "\n".join(lines)


def counts(index: Path) -> dict[str, int]:
    uri = index.resolve().as_uri() + "?mode=ro"
    with closing(sqlite3.connect(uri, uri=True)) as conn:
        one = lambda sql: conn.execute(sql).fetchone()[0]  # noqa: E731
        return {
            "views": one("SELECT count(*) FROM views"),
            "objects": one("SELECT count(*) FROM objects"),
            "street objects": one("SELECT count(*) FROM objects WHERE transient IS NULL"),
            "flagged": one("SELECT count(*) FROM flagged"),
        }


def table(result: dict[str, Any]) -> str:
    c = result["counts"]
    head = (
        f"{result['index']}: {c['views']} views, {c['objects']} objects "
        f"({c['street objects']} not transient), {c['flagged']} flagged views"
    )
    lines = [
        head,
        f"{'query':<30} {'in-process ms':>13} {'command ms':>11} {'its CPU ms':>10}"
        f" {'answer bytes':>12}",
    ]
    for q in result["queries"]:
        inproc = "-" if q["in_process_s"] is None else f"{1000 * q['in_process_s']:.0f}"
        lines.append(
            f"{q['query']:<30} {inproc:>13} {1000 * q['subprocess_s']:>11.0f}"
            f" {1000 * q['subprocess_cpu_s']:>10.0f} {q['bytes']:>12,}"
        )
    lines.append(
        f"heavy libraries `streetcd query --limit 100` imported: {result['heavy_imports'] or 'none'}"
    )
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--index", action="append", type=Path, help="a change index (repeatable)")
    ap.add_argument("--repeat", type=int, default=5, help="runs per form (median)")
    ap.add_argument("--json", type=Path, help="also write the results here")
    ap.add_argument(
        "--against",
        type=Path,
        help="the bin folder of another install (e.g. a venv of an earlier commit): time its "
        "`streetcd query` and this one's, alternated, form by form (instead of the tables)",
    )
    a = ap.parse_args()
    indexes = a.index or [p for p in DEFAULT_INDEXES if p.is_file()]
    if not indexes:
        raise SystemExit("no index: run benchmarks/city_scale.py first, or give --index")
    results = []
    with tempfile.TemporaryDirectory(prefix="query-speed-") as tmp:
        for k, original in enumerate(indexes):
            copy = Path(tmp) / f"{k}-{original.name}"
            shutil.copyfile(original, copy)
            if a.against is not None:
                print(f"{original}: {a.against} (before) against {BIN} (after)")
                print(compare(copy, a.against, a.repeat) + "\n", flush=True)
                continue
            load0 = os.getloadavg()[0]
            result = time_index(copy, a.repeat)
            result.update(
                index=str(original),
                counts=counts(copy),
                load_before=load0,
                load_after=os.getloadavg()[0],
                repeat=a.repeat,
            )
            results.append(result)
            print(table(result))
            print(f"load average (1 min) {load0:.2f} -> {result['load_after']:.2f}\n", flush=True)
    if a.json:
        a.json.parent.mkdir(parents=True, exist_ok=True)
        a.json.write_text(json.dumps(results, indent=1) + "\n", encoding="utf-8")


if __name__ == "__main__":
    main()
