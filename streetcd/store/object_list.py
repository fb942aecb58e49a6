"""The read side of change objects: :func:`list_objects` (the contract of
``docs/DECISIONS.md``, issue 17) and the names and checks it shares with the write side,
:mod:`streetcd.store.objects`, which re-exports all of them.

Kept apart so that reading pays only for SQLite and the standard library: ``streetcd
query`` imports this module, not the rebuild's numpy, geometry and configuration
(docs/BENCHMARKS.md, "streetcd query on a 10,000-view index"). It opens the index read-only.
"""

from __future__ import annotations

import json
import math
import sqlite3
from collections.abc import Callable, Sequence
from pathlib import Path

from streetcd import classes as C
from streetcd.errors import InputError
from streetcd.store.index import (
    SCHEMA_VERSION,
    ChangeIndex,
    _check_bbox,
    limit_clause,
    parse_since,
)

TYPE_CHECKING = False  # typing's, without importing typing (~18 ms here): mypy reads the name
if TYPE_CHECKING:
    from typing import Any

REVIEW_STATUSES = ("confirmed", "false_alarm", "fixed")
LIST_STATUSES = ("awaiting", "transient", *REVIEW_STATUSES)
KINDS = ("added", "removed", "unknown")


def list_objects(
    index_path: str | Path,
    *,
    status: str | None = None,
    segment: str | None = None,
    kind: str | None = None,
    bbox: Sequence[float] | None = None,
    limit: int | None = None,
    sort: str = "confidence",
    since: str | None = None,
    min_confidence: float | None = None,
    transients: bool = True,
    with_views: bool = True,
) -> list[dict]:
    """The change objects of an index, as plain dicts (see ``docs/DECISIONS.md``, issue 17).

    status : ``awaiting`` (not reviewed, not transient), ``transient``, or a review status
        (``confirmed``, ``false_alarm``, ``fixed``); None: all. segment : a segment id.
    kind : ``added``, ``removed``, ``unknown``. bbox : (min_x, min_y, max_x, max_y) in the
        index's CRS, objects whose x/y box meets it. limit : at most this many (≥ 0).
    sort : ``confidence`` (highest first, then id) or ``id``.
    since : ISO date: objects last seen on or after that night.
    min_confidence : confidence ≥ this (a finite number in [0, 1]).
    transients : False leaves out transients (before ``limit``). True by default, unlike
        ``streetcd query``: the library's readers (the review page, the evaluation) show or
        score every object, transients marked; leaving them out is the command's choice
        for people (docs/DECISIONS.md, 2026-11-25).
    with_views : False leaves each object's ``views`` list empty (its counts stay): a table
        of every object of a 10,000-view night spent two thirds of its time reading them.
        True: an object with an entry kept by the rebuild (:func:`object_entries`) is that
        entry parsed, its review added; the others are made from the tables.
    Opens the index read-only (never creates or writes a file).
    """
    sql, args = _objects_sql(
        "o.*, r.status AS r_status, r.who AS r_who, r.at AS r_at, r.note AS r_note",
        status=status,
        segment=segment,
        kind=kind,
        bbox=bbox,
        limit=limit,
        sort=sort,
        since=since,
        min_confidence=min_confidence,
        transients=transients,
    )
    with ChangeIndex(index_path, readonly=True) as idx:
        rows = idx.conn.execute(sql, args).fetchall()
        if not with_views:
            return [_as_dict(r, []) for r in rows]
        # the entries the rebuild keeps (object_entries), parsed: the views' joins were
        # most of a whole listing's time; the others' views are read from the tables
        kept = _kept_entries(idx, [r["id"] for r in rows])
        made = [r["object_id"] for r in rows if r["id"] not in kept]
        views = _views_of(idx.conn, made) if made else {}
    loads = _loads(len(kept))
    out = []
    for r in rows:
        entry = kept.get(r["id"])
        if entry is None:
            out.append(_as_dict(r, views.get(r["object_id"], [])))
        else:
            d = loads(entry)
            d["review"] = _review(r)
            out.append(d)
    return out


def object_entries(index_path: str | Path, **selection: Any) -> list[str]:
    """The objects :func:`list_objects` lists with the same arguments (``with_views`` aside),
    each as compact JSON text (the dict it gives, ``json.loads`` of an entry), in its order.

    Read from ``object_json``, where the rebuild keeps each object's entry as it is listed
    unreviewed (a review is put in here): `streetcd query --format json` of a 10,000-view
    night's 2,490 objects spent ~80 of its ~120 ms making 14,000 view dicts from joins by
    text keys. An object without a kept entry (a transient; an index of an older schema,
    read as it is; a view of it published since its rebuild) is made as list_objects
    makes it.
    """
    sql, args = _objects_sql("o.id, r.status, r.who, r.at, r.note", **selection)
    with ChangeIndex(index_path, readonly=True) as idx:
        rows = idx.conn.execute(sql, args).fetchall()
        ids = [r[0] for r in rows]
        kept = _kept_entries(idx, ids)
        missing = [i for i in ids if i not in kept]
        if missing:
            kept.update(_made_entries(idx.conn, missing))
    out = []
    for rowid, *review in rows:
        entry = kept[rowid]
        if review[0] is not None:  # the kept entry ends with the review it had: none
            reviewed = _dumps(dict(zip(REVIEW_FIELDS, review, strict=True)))
            entry = entry[: -len(NO_REVIEW)] + ',"review":' + reviewed + "}"
        out.append(entry)
    return out


def write_entries(conn: sqlite3.Connection, segment: str) -> None:
    """Keep the listing entries of segment ``segment``'s objects (just rebuilt) in
    ``object_json``: what :func:`object_entries` reads. Transients are left out: four in
    five objects of a night, they more than doubled the index (31 to 76 MB for 10,000
    views), and `streetcd query` lists them only when asked (they are then made from the
    tables, as before)."""
    ids = [
        r[0]
        for r in conn.execute(
            "SELECT id FROM objects WHERE segment_id = ? AND transient IS NULL", (segment,)
        )
    ]
    made = _made_entries(conn, ids)
    conn.executemany("INSERT OR REPLACE INTO object_json VALUES (?, ?)", made.items())


REVIEW_FIELDS = ("status", "who", "at", "note")
NO_REVIEW = ',"review":null}'  # how a kept entry ends


def _objects_sql(
    columns: str,
    *,
    status: str | None = None,
    segment: str | None = None,
    kind: str | None = None,
    bbox: Sequence[float] | None = None,
    limit: int | None = None,
    sort: str = "confidence",
    since: str | None = None,
    min_confidence: float | None = None,
    transients: bool = True,
) -> tuple[str, list[Any]]:
    """The query of :func:`list_objects` (its selecting arguments, checked, with its
    defaults), selecting ``columns`` of objects ``o`` and their reviews ``r``."""
    where, args = _filters(status, segment, kind, bbox)
    if since is not None:
        where.append("o.last_seen >= ?")
        args.append(parse_since(since)[:10])
    if min_confidence is not None:
        where.append("o.confidence >= ?")
        args.append(check_fraction("min_confidence", min_confidence))
    if not transients:
        where.append("o.transient IS NULL")
    if sort not in ("confidence", "id"):
        raise InputError(f"sort {sort!r} must be 'confidence' or 'id'")
    order = "o.confidence DESC, o.object_id" if sort == "confidence" else "o.object_id"
    sql = (
        f"SELECT {columns} FROM objects o LEFT JOIN reviews r ON r.object_id = o.object_id"
        + (" WHERE " + " AND ".join(where) if where else "")
        + f" ORDER BY {order}"
    )
    return sql + limit_clause(limit), args


def _kept_entries(idx: ChangeIndex, ids: Sequence[int]) -> dict[int, str]:
    """{objects.id: entry} of those of ``ids`` that ``object_json`` holds (none in an index
    of a schema before it, read as it is)."""
    if idx.file_version != SCHEMA_VERSION:
        return {}
    out: dict[int, str] = {}
    cur = idx.conn.cursor()
    cur.row_factory = None
    for k in range(0, len(ids), 500):
        chunk = ids[k : k + 500]
        cur.execute(
            f"SELECT id, entry FROM object_json WHERE id IN ({','.join('?' * len(chunk))})", chunk
        )
        out.update(cur)
    # an entry of another form (written by another version) is made again
    return {k: v for k, v in out.items() if v.endswith(NO_REVIEW)}


def _made_entries(conn: sqlite3.Connection, ids: Sequence[int]) -> dict[int, str]:
    """{objects.id: entry} of objects ``ids`` made from the tables as list_objects makes
    them, as if none were reviewed (each ends with :data:`NO_REVIEW`)."""
    rows = []
    for k in range(0, len(ids), 500):
        chunk = ids[k : k + 500]
        rows += conn.execute(
            "SELECT o.*, NULL AS r_status FROM objects o"
            f" WHERE o.id IN ({','.join('?' * len(chunk))})",
            chunk,
        ).fetchall()
    views = _views_of(conn, [r["object_id"] for r in rows])
    dumps = _dumps if len(rows) < ORJSON_FROM else _orjson_dumps
    return {r["id"]: dumps(_as_dict(r, views.get(r["object_id"], []))) for r in rows}


def _dumps(value: object) -> str:
    """Compact JSON, non-ASCII kept (the change index holds no NaN or infinity)."""
    return json.dumps(value, separators=(",", ":"), ensure_ascii=False, allow_nan=False)


# orjson encodes many entries ~3x faster than the standard library (the 9,660 transients of a
# 10,000-view city, made from the tables when listed) but takes ~22 ms to import
ORJSON_FROM = 500


def _loads(n_entries: int) -> Callable[[str], Any]:
    """A JSON parser for ``n_entries`` entries: orjson's from :data:`ORJSON_FROM` on (the
    same values: both read the shortest float text back to the same double)."""
    if n_entries < ORJSON_FROM:
        return json.loads
    import orjson

    return orjson.loads


def _orjson_dumps(value: object) -> str:
    """:func:`_dumps` by orjson (the same JSON; a float may be written in another form)."""
    import orjson

    return orjson.dumps(value).decode()


def _filters(
    status: str | None, segment: str | None, kind: str | None, bbox: Sequence[float] | None
) -> tuple[list[str], list[Any]]:
    where: list[str] = []
    args: list[Any] = []
    if status is not None:
        status = normalise_status(status, LIST_STATUSES)
        if status == "awaiting":
            where.append("r.status IS NULL AND o.transient IS NULL")
        elif status == "transient":
            where.append("o.transient IS NOT NULL")
        else:
            where.append("r.status = ?")
            args.append(status)
    if segment is not None:
        where.append("o.segment_id = ?")
        args.append(segment)
    if kind is not None:
        if kind not in KINDS:
            raise InputError(f"kind {kind!r} must be one of {', '.join(KINDS)}")
        where.append("o.kind = ?")
        args.append(kind)
    if bbox is not None:
        mnx, mny, mxx, mxy = _check_bbox(bbox)
        where.append(
            "o.id IN (SELECT id FROM objects_rtree WHERE max_x >= ? AND min_x <= ?"
            " AND max_y >= ? AND min_y <= ?)"
        )
        args += [mnx, mxx, mny, mxy]
    return where, args


def _views_of(conn: sqlite3.Connection, object_ids: Sequence[str]) -> dict[str, list[dict]]:
    """The views of objects ``object_ids``, by object id, those that see the change first,
    then by view: one query per 500 objects (one per object was most of a big listing's
    time). Rows come as plain tuples (``sqlite3.Row``'s lookups by name, and decoding
    each view's labels again, were most of what remained: the same few label lists, ``[1]``,
    ``[2]`` …, recur, so each text is decoded once)."""
    out: dict[str, list[dict]] = {}
    decoded: dict[str, list[int]] = {}
    cur = conn.cursor()
    cur.row_factory = None
    for k in range(0, len(object_ids), 500):
        chunk = object_ids[k : k + 500]
        cur.execute(
            "SELECT ov.object_id, ov.view, ov.sees_change, ov.labels, w.image, w.image_path,"
            " f.overlay_path, f.mask_path, f.score FROM object_views ov"
            " LEFT JOIN views w ON w.view = ov.view"
            " LEFT JOIN flagged f ON f.view = ov.view AND ov.sees_change = 1"
            f" WHERE ov.object_id IN ({','.join('?' * len(chunk))})"
            " ORDER BY ov.object_id, ov.sees_change DESC, ov.view",
            chunk,
        )
        for oid, view, sees, labels_text, image, image_path, overlay, mask, score in cur:
            labels = decoded.get(labels_text)
            if labels is None:
                labels = decoded[labels_text] = json.loads(labels_text)
            out.setdefault(oid, []).append(
                {
                    "view": view,
                    "image": image,
                    "overlay": overlay,
                    "mask": mask,
                    "image_path": image_path,
                    "sees_change": bool(sees),
                    "labels": list(labels),  # a copy: a caller may change one view's list
                    "score": score,
                }
            )
    return out


def _review(r: sqlite3.Row) -> dict | None:
    if r["r_status"] is None:
        return None
    return {"status": r["r_status"], "who": r["r_who"], "at": r["r_at"], "note": r["r_note"]}


def _as_dict(r: sqlite3.Row, views: list[dict]) -> dict:
    return {
        "id": r["object_id"],
        "kind": r["kind"],
        "class": r["class"],
        "class_name": C.NAMES.get(r["class"], "unknown"),
        "confidence": r["confidence"],
        "centroid": [r["x"], r["y"], r["z"]],
        "bbox": [r["min_x"], r["min_y"], r["min_z"], r["max_x"], r["max_y"], r["max_z"]],
        "segment": r["segment_id"],
        "pixels": r["pixels"],
        "n_views": r["n_views"],
        "n_without": r["n_without"],
        "views": views,
        "first_seen": r["first_seen"],
        "last_seen": r["last_seen"],
        "transient": r["transient"],
        "review": _review(r),  # last: object_entries puts it in the end of a kept entry
    }


def check_fraction(name: str, value: object) -> float:
    """``value`` as a float in [0, 1]; InputError naming ``name`` for NaN, inf, junk."""
    try:
        x = float(value)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        raise InputError(f"{name} {value!r} is not a number") from None
    if not (math.isfinite(x) and 0.0 <= x <= 1.0):
        raise InputError(f"{name} {value!r} must be a finite number in [0, 1]")
    return x


def normalise_status(status: str, allowed: Sequence[str] = REVIEW_STATUSES) -> str:
    """``status`` with ``-`` read as ``_`` (``false-alarm``); InputError if not allowed."""
    s = str(status).strip().lower().replace("-", "_")
    if s not in allowed:
        raise InputError(f"status {status!r} must be one of {', '.join(allowed)}")
    return s
