"""What the review page shows, read from a change index: the change objects, the segments,
the run and its numbers. Plain dicts and lists, ready for JSON.

Coordinates are metres in the index's CRS (``crs``; None for a local frame). Timestamps are
the index's UTC ISO strings.
"""

from __future__ import annotations

import json
import re
from collections import Counter
from pathlib import Path
from typing import Any

from streetcd.classes import NAMES
from streetcd.errors import InputError
from streetcd.store.index import ChangeIndex
from streetcd.store.objects import REVIEW_STATUSES, list_objects, record_review


def load_changes(index_path: str | Path) -> list[dict[str, Any]]:
    """Every change object of the index, best confidence first, as
    :func:`streetcd.store.objects.list_objects` gives them: ``id, kind, class, confidence,
    centroid [x, y, z], bbox [xmin, ymin, zmin, xmax, ymax, zmax], segment, views [{view,
    image, image_path, overlay, mask, sees_change}], first_seen, last_seen, review,
    transient``. The one place the page reads change objects."""
    return list_objects(index_path, sort="confidence")


def record_decision(
    index_path: str | Path, change_id: str, status: str, *, who: str, note: str | None = None
) -> dict[str, Any]:
    """Record an operator's decision on a change (``status`` one of :data:`REVIEW_STATUSES`)
    through :func:`streetcd.store.objects.record_review`; the review as stored. InputError
    for an unknown status, MissingInputError for an unknown change."""
    if status not in REVIEW_STATUSES:
        raise InputError(f"review status {status!r} must be one of {', '.join(REVIEW_STATUSES)}")
    return record_review(index_path, change_id, status, who=who, note=note)


def pick_run(idx: ChangeIndex, run_id: str | None) -> dict[str, Any] | None:
    """The row of run ``run_id`` (InputError naming the index if it has none), or of the
    latest run when None; None when the index has no run at all."""
    if run_id is None:
        row = idx.conn.execute("SELECT * FROM runs ORDER BY started_at DESC LIMIT 1").fetchone()
    else:
        row = idx.conn.execute("SELECT * FROM runs WHERE run_id = ?", (run_id,)).fetchone()
        if row is None:
            raise InputError(f"{idx.path}: no run {run_id!r} in this index (--run)")
    if row is None:
        return None
    run = dict(row)
    try:
        run["inputs"] = json.loads(run.pop("config") or "{}")
    except json.JSONDecodeError:
        run["inputs"] = {}
    return run


_PATH = re.compile(r"(?:[A-Za-z]:)?[/\\][^\s:,;'\"()]+")
_QUOTED = re.compile(r"'[^']*'|\"[^\"]*\"")
_NUMBER = re.compile(r"\d+(?:\.\d+)?")


def failure_reason(error: str | None) -> str:
    """The reason of a failed view's error, without the names that make each one unique
    (paths, quoted names, numbers), so failures group: ``"InputError: <path>: image is <n>x<n>,
    the pose says <n>x<n>"``."""
    text = (error or "unknown error").strip().splitlines()[0]
    text = _PATH.sub("<path>", text)
    text = _QUOTED.sub("<name>", text)
    return _NUMBER.sub("<n>", text)[:200]


def night_numbers(idx: ChangeIndex, run: dict[str, Any] | None) -> dict[str, Any]:
    """The night's numbers: views in the index and in the run (done, failed, flagged), and the
    failed views grouped by reason (most frequent first, with up to 5 example views each)."""
    counts = idx.counts()
    failed = idx.failures()
    by_reason: dict[str, list[str]] = {}
    for view, error in failed:
        by_reason.setdefault(failure_reason(error), []).append(view)
    order = Counter({k: len(v) for k, v in by_reason.items()}).most_common()
    numbers: dict[str, Any] = {
        "views": counts["views"],
        "done": counts["done"],
        "failed": counts["failed"],
        "flagged": counts["flagged"],
        "segments": counts["segments"],
        "failures": [
            {"reason": reason, "count": n, "views": by_reason[reason][:5]} for reason, n in order
        ],
    }
    if run is not None:
        numbers["run"] = {
            k: run.get(k)
            for k in (
                "run_id",
                "started_at",
                "finished_at",
                "status",
                "n_planned",
                "n_skipped",
                "n_done",
                "n_failed",
                "n_flagged",
            )
        }
    return numbers


def segments(idx: ChangeIndex) -> list[dict[str, Any]]:
    """Every segment: ``{id, n_views, length_m, polyline [[x, y], ...]}`` (CRS metres)."""
    return [
        {
            "id": s.segment_id,
            "n_views": s.n_views,
            "length_m": round(s.length_m, 2),
            "polyline": [[round(p[0], 3), round(p[1], 3)] for p in s.polyline],
        }
        for s in idx.segments()
    ]


def view_files(idx: ChangeIndex, keys: list[str]) -> list[tuple[str, str | None, str | None]]:
    """``(key, image_path, camera JSON)`` of the views ``keys`` where the index records them
    (schema 4 and later; an older index gives nothing). Parameterised, 500 keys a query."""
    columns = {r[1] for r in idx.conn.execute("PRAGMA table_info(views)")}
    if not {"image_path", "camera"} <= columns:
        return []
    out = []
    for i in range(0, len(keys), 500):
        part = keys[i : i + 500]
        rows = idx.conn.execute(
            "SELECT view, image_path, camera FROM views"
            f" WHERE view IN ({','.join('?' * len(part))})",
            part,
        )
        out += [(r[0], r[1], r[2]) for r in rows]
    return out


def class_name(code: int) -> str:
    return NAMES.get(int(code), f"class {int(code)}")
