"""A night's verdict and its summary JSON: the exit code of ``streetcd run`` and what a cron
job or an operator reads the morning after.

Exit codes: 0 a good night; 2 the night did not run, a whole-input error (one line names the
file and field); 3 the night ran, but more of its views failed than ``run.max_failed``
allows (failed tonight, lost with their batches, or still failing from an earlier run). 1 is
left to unexpected errors. The summary goes to ``<out>/runs/<run id>.json`` and
``<out>/runs/latest.json``, written atomically. This module imports neither Dask nor
Prefect, so that a command that fails on its inputs says so at once.
"""

from __future__ import annotations

import json
import os
import threading
from datetime import UTC, datetime
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:  # publish imports the planner and the tile store (zarr): not needed here
    from streetcd.run.publish import RunSummary

# streetcd run's exit codes (README, "Exit codes"); 1 is left to unexpected errors
EXIT_OK = 0
EXIT_INPUT = 2  # the night did not run: a whole-input error (one line names file and field)
EXIT_VIEWS_FAILED = 3  # the night ran, but more views failed than run.max_failed allows


def judge(summary: RunSummary, max_failed: float) -> None:
    """Set the night's exit code (module docstring): EXIT_VIEWS_FAILED when more views failed
    (tonight, lost, or still failing from earlier runs) than ``max_failed`` allows (a count,
    or a fraction of the night's views when < 1)."""
    summary.exit_code = (
        EXIT_VIEWS_FAILED
        if n_failing(summary) > allowed_failures(max_failed, summary.n_views)
        else EXIT_OK
    )


def n_failing(summary: RunSummary) -> int:
    """Views of the night that have no result: failed, lost, or still failing."""
    return summary.n_failed + summary.n_lost + len(summary.still_failing)


def allowed_failures(max_failed: float, n_views: int) -> float:
    """How many failing views ``run.max_failed`` allows in a night of ``n_views``."""
    return float(max_failed) if max_failed >= 1 else max_failed * n_views


def summary_json(
    summary: RunSummary, inputs: dict[str, str], started: str, max_failed: float
) -> dict[str, Any]:
    """The run summary a cron job or an operator reads (``<out>/runs/<run id>.json``):
    the views planned, already done, detected, flagged, failed (with their errors), still
    failing from earlier runs (and since when), the exit code and the times."""
    s = summary
    since = min((when for _, _, when in s.still_failing if when), default=None)
    return {
        "run_id": s.run_id,
        "exit_code": s.exit_code,
        "status": "ok" if s.exit_code == EXIT_OK else "views failed",
        "started_at": started,
        "finished_at": utc_now(),
        "views": {
            "planned": s.n_views,
            "already_done": max(0, s.n_skipped - len(s.still_failing)),
            "detected": s.n_done,
            "flagged": s.n_flagged,
            "failed": s.n_failed,
            "lost": s.n_lost,
            "still_failing": len(s.still_failing),
        },
        "failed": [{"view": v, "error": e} for v, e in s.failures],
        "still_failing": [{"view": v, "error": e, "since": w} for v, e, w in s.still_failing],
        "still_failing_since": since,
        "max_failed": max_failed,
        "allowed_failures": allowed_failures(max_failed, s.n_views),
        "notes": s.notes,
        "seconds": {
            "wall": round(s.wall_s, 3),
            "plan": round(s.plan_s, 3),
            "wait_for_cluster": round(s.wait_s, 3),
            "detector": round(s.detect_s, 3),
        },
        "inputs": inputs,
    }


def write_summary(out: str, data: dict[str, Any]) -> str:
    """Write ``data`` to ``<out>/runs/<run id>.json`` and to ``<out>/runs/latest.json`` (the
    path a cron job reads), each atomically; returns the first. A night without a run id
    (it did not run) writes ``latest.json`` alone."""
    folder = Path(out) / "runs"
    path = folder / (f"{data['run_id']}.json" if data.get("run_id") else "latest.json")
    blob = (json.dumps({**data, "summary_path": str(path)}, indent=2) + "\n").encode()
    atomic_write(path, blob)
    if path.name != "latest.json":
        atomic_write(folder / "latest.json", blob)
    return str(path)


def write_input_error(out: str, exc: BaseException, started: str) -> str | None:
    """The summary of a night that did not run (exit code 2): its one-line reason, in
    ``<out>/runs/latest.json``. None when the out folder cannot be written either (the
    error is raised all the same)."""
    data = {
        "run_id": None,
        "exit_code": EXIT_INPUT,
        "status": "input error",
        "error": f"{type(exc).__name__}: {exc}",
        "started_at": started,
        "finished_at": utc_now(),
    }
    try:
        return write_summary(out, data)
    except OSError:
        return None


def utc_now() -> str:
    """Now in the change index's format (:func:`streetcd.store.index.utc_now`)."""
    return datetime.now(UTC).strftime("%Y-%m-%dT%H:%M:%SZ")


def atomic_write(path: Path, data: bytes) -> None:
    """:func:`streetcd.io.outputs.atomic_write` (a temporary name, then a rename), written
    again here: that module imports the detector, a second of imports on the path of an
    input error that must answer at once."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.{threading.get_ident()}.tmp")
    tmp.write_bytes(data)
    os.replace(tmp, path)


def still_failing_line(summary: RunSummary) -> str:
    """ "N views still failing since <date>" and what to do about it."""
    since = min((when for _, _, when in summary.still_failing if when), default="an earlier run")
    return (
        f"{len(summary.still_failing)} views still failing since {since} "
        "(fix their inputs, or --retry-failed)"
    )
