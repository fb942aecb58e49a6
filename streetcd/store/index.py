"""The change index: one SQLite file that lists the flagged views, by segment, with their
changed regions located in 3D (DESIGN.md, data flow steps 5–6).

Tables
------
``meta``      key/value: ``schema_version``, ``crs`` (the CRS every coordinate is in).
``runs``      one row per run: when, its parameter hash, counts, status.
``segments``  planned street segments: stable id, polyline (JSON), bbox in the CRS.
``views``     every processed view, keyed by name: the input hash and parameter hash it was
              processed with, ``done`` or ``failed`` (with the error), whether flagged. A view
              whose hashes match is not processed again; this is what makes runs incremental.
``flagged``   flagged views only: segment, score, changed fraction, region count, mask path.
``regions``   change regions of flagged views: centroid and box in the CRS, dominant class of
              the old cloud there.
``segments_rtree``, ``regions_rtree``  R*Trees over the x/y boxes of segments and regions.
``objects``, ``object_views``, ``objects_rtree``, ``reviews``  the change objects and their
              reviews (:mod:`streetcd.store.objects`); ``object_json`` each object's listing
              entry, kept with it (:mod:`streetcd.store.object_list`).

The index holds the current state: one row per view name, its latest result. Writes are one
transaction per batch (:meth:`ChangeIndex.publish`), so a run killed at any moment leaves
whole batches or nothing, and publishing the same outcome twice changes nothing.

The database runs in WAL mode, so queries read while a run writes. Timestamps are UTC ISO
8601 strings (``2026-11-22T10:00:00Z``), which compare correctly as text. A view's
``captured_at`` is when its image was taken (EXIF ``DateTimeOriginal``), NULL when the
image does not say; ``detected_at`` is when the run published it.

One run at a time writes an index: :func:`streetcd.store.locks.run_lock` holds
``<index>.lock`` for the whole run, and a second run fails at once with an
:class:`~streetcd.errors.IndexBusyError` that names the holder. The records it stores and
returns are :mod:`streetcd.store.records`; its GeoJSON export is :mod:`streetcd.store.geojson`.
"""

from __future__ import annotations

import json
import math
import sqlite3
from collections.abc import Callable, Iterable, Sequence
from datetime import UTC, datetime
from pathlib import Path

from streetcd.errors import CRSMismatchError, InputError, MissingInputError

# The records (dataclasses, and inspect under them) load where a row is made, typing not at
# all (typing's TYPE_CHECKING without the import; mypy reads the name): `streetcd query`
# lists change objects without either, ~35 ms of a ~100 ms command (docs/BENCHMARKS.md).
TYPE_CHECKING = False
if TYPE_CHECKING:
    from typing import Any

    from streetcd.store.records import FlaggedRow, RegionRecord, SegmentRow, ViewRecord

SCHEMA_VERSION = "6"
# Each change object as `streetcd query --format json` lists it before any review (a review
# is written apart, by the review page, and put in when listed): made by the objects' rebuild
# (transients left out, store/object_list.py::write_entries), dropped with its object
# and when a view it lists is published again, so an entry always reads what the joins of
# objects, object_views, views and flagged would give. The whole listing of a 10,000-view
# night joined 14,000 object views by their text keys, most of its time (docs/BENCHMARKS.md).
_OBJECT_JSON = (
    "CREATE TABLE IF NOT EXISTS object_json (id INTEGER PRIMARY KEY, entry TEXT NOT NULL)",
    "CREATE INDEX IF NOT EXISTS object_views_view ON object_views(view)",
)
# Older schemas this one reads as they are and migrates when opened for writing: each adds
# what a reader of the older file can do without (version 5: regions.depth_fraction;
# version 6: object_json, which a reader of an older file does without, and the index that
# finds the objects listing a view).
MIGRATIONS = {
    "4": ("ALTER TABLE regions ADD COLUMN depth_fraction REAL",),
    "5": _OBJECT_JSON,
}
# ... and the columns of :class:`RegionRecord` a query reads, in its order (after the row
# id), with what stands in for a column such a file lacks when it is read as it is
_REGION_COLUMNS = {
    "": "flagged_id, label, pixels, score, x, y, z, min_x, min_y, min_z, max_x, max_y, max_z,"
    " dominant_class, foot_class, depth_fraction",
}
_REGION_COLUMNS["4"] = _REGION_COLUMNS[""].replace("depth_fraction", "NULL AS depth_fraction")
# ChangeIndex.query's orders, by its ``sort``: time is the capture's (else the detection's)
QUERY_ORDER = {
    None: "f.segment_id, f.view",
    "score": "f.score DESC, f.view",
    "time": "coalesce(f.captured_at, f.detected_at) DESC, f.score DESC, f.view",
}

_SCHEMA = """
CREATE TABLE IF NOT EXISTS meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE TABLE IF NOT EXISTS runs (
    run_id TEXT PRIMARY KEY,
    started_at TEXT NOT NULL,
    finished_at TEXT,
    status TEXT NOT NULL,
    params_hash TEXT,
    n_planned INTEGER, n_skipped INTEGER, n_done INTEGER, n_failed INTEGER, n_flagged INTEGER,
    config TEXT
);
CREATE TABLE IF NOT EXISTS segments (
    id INTEGER PRIMARY KEY,
    segment_id TEXT NOT NULL UNIQUE,
    n_views INTEGER NOT NULL,
    length_m REAL NOT NULL,
    min_x REAL NOT NULL, min_y REAL NOT NULL, max_x REAL NOT NULL, max_y REAL NOT NULL,
    polyline TEXT NOT NULL,
    views TEXT NOT NULL,
    first_run TEXT
);
CREATE VIRTUAL TABLE IF NOT EXISTS segments_rtree USING rtree(id, min_x, max_x, min_y, max_y);
CREATE TABLE IF NOT EXISTS views (
    view TEXT PRIMARY KEY,
    input_hash TEXT NOT NULL,
    params_hash TEXT NOT NULL,
    segment_id TEXT,
    status TEXT NOT NULL CHECK (status IN ('done', 'failed')),
    error TEXT,
    flagged INTEGER NOT NULL DEFAULT 0,
    center_x REAL, center_y REAL, center_z REAL,
    detect_s REAL, total_s REAL, cpu_s REAL,  -- seconds: detector, whole view, its CPU
    run_id TEXT, processed_at TEXT,
    captured_at TEXT,  -- when the image was taken (EXIF), NULL if unknown
    image TEXT,  -- the image's name (views are keyed by name#content hash)
    image_path TEXT,
    camera TEXT  -- JSON pose and intrinsics (records.camera_json), NULL if unknown
);
CREATE INDEX IF NOT EXISTS views_center ON views(center_x, center_y);
CREATE TABLE IF NOT EXISTS flagged (
    id INTEGER PRIMARY KEY,
    view TEXT NOT NULL UNIQUE REFERENCES views(view),
    segment_id TEXT,
    score REAL NOT NULL,
    changed_fraction REAL NOT NULL,
    n_regions INTEGER NOT NULL,
    mask_path TEXT,
    overlay_path TEXT,
    run_id TEXT,
    detected_at TEXT NOT NULL,
    captured_at TEXT
);
CREATE INDEX IF NOT EXISTS flagged_segment ON flagged(segment_id);
CREATE INDEX IF NOT EXISTS flagged_score ON flagged(score);
CREATE INDEX IF NOT EXISTS flagged_detected ON flagged(detected_at);
CREATE INDEX IF NOT EXISTS flagged_when ON flagged(coalesce(captured_at, detected_at));
CREATE TABLE IF NOT EXISTS regions (
    id INTEGER PRIMARY KEY,
    flagged_id INTEGER NOT NULL REFERENCES flagged(id),
    label INTEGER NOT NULL,
    pixels INTEGER NOT NULL,
    score REAL NOT NULL,
    x REAL, y REAL, z REAL,  -- NULL: no pixel of the region has a surface behind it
    min_x REAL, min_y REAL, min_z REAL,
    max_x REAL, max_y REAL, max_z REAL,
    dominant_class INTEGER NOT NULL,
    foot_class INTEGER NOT NULL DEFAULT 0,  -- old cloud's class behind the lowest pixels
    depth_fraction REAL,  -- where the change stands, a fraction of the old surface's depth (NULL: unknown)
    UNIQUE (flagged_id, label)
);
CREATE INDEX IF NOT EXISTS regions_flagged ON regions(flagged_id);
CREATE VIRTUAL TABLE IF NOT EXISTS regions_rtree USING rtree(id, min_x, max_x, min_y, max_y);
CREATE TABLE IF NOT EXISTS objects (
    id INTEGER PRIMARY KEY,
    object_id TEXT NOT NULL UNIQUE,
    segment_id TEXT NOT NULL,
    kind TEXT NOT NULL CHECK (kind IN ('added', 'removed', 'unknown')),
    class INTEGER NOT NULL,
    confidence REAL NOT NULL,
    x REAL NOT NULL, y REAL NOT NULL, z REAL NOT NULL,
    min_x REAL NOT NULL, min_y REAL NOT NULL, min_z REAL NOT NULL,
    max_x REAL NOT NULL, max_y REAL NOT NULL, max_z REAL NOT NULL,
    pixels INTEGER NOT NULL,
    n_views INTEGER NOT NULL,  -- views that see the change
    n_without INTEGER NOT NULL,  -- views that see the spot without a change
    first_seen TEXT NOT NULL, last_seen TEXT NOT NULL,  -- nights (YYYY-MM-DD)
    transient TEXT  -- why it is not a change of the street (NULL: it is one)
);
CREATE INDEX IF NOT EXISTS objects_segment ON objects(segment_id);
CREATE VIRTUAL TABLE IF NOT EXISTS objects_rtree USING rtree(id, min_x, max_x, min_y, max_y);
CREATE TABLE IF NOT EXISTS object_views (
    object_id TEXT NOT NULL,
    view TEXT NOT NULL,
    sees_change INTEGER NOT NULL,
    labels TEXT NOT NULL,  -- JSON list of the view's region labels in the object
    PRIMARY KEY (object_id, view)
);
CREATE TABLE IF NOT EXISTS reviews (
    object_id TEXT PRIMARY KEY,
    segment_id TEXT NOT NULL,
    status TEXT NOT NULL CHECK (status IN ('confirmed', 'false_alarm', 'fixed')),
    who TEXT, at TEXT NOT NULL, note TEXT,
    min_x REAL NOT NULL, min_y REAL NOT NULL, min_z REAL NOT NULL,  -- the box reviewed
    max_x REAL NOT NULL, max_y REAL NOT NULL, max_z REAL NOT NULL
);
"""


def _old_schema_message(path: Path, version: str | None) -> str:
    """Why an index of another schema is refused, and what to do."""
    if version in ("2", "3"):
        return (
            f"{path}: schema_version {version} keys views by bare file name, which cannot tell"
            f" one night's IMG_0001 from another's, and has no change objects; it is left"
            f" untouched: run into a new index (schema {SCHEMA_VERSION}), or keep reading this"
            " one with the streetcd version that wrote it"
        )
    return f"{path}: schema_version {version!r}, expected {SCHEMA_VERSION}"


def utc_now() -> str:
    """Now as ``YYYY-MM-DDTHH:MM:SSZ`` (UTC, seconds), the index's timestamp format."""
    return datetime.now(UTC).strftime("%Y-%m-%dT%H:%M:%SZ")


def parse_since(text: str) -> str:
    """A user's date or date-time (ISO 8601; no zone means UTC) in the index's format."""
    try:
        when = datetime.fromisoformat(text.strip().replace("Z", "+00:00"))
    except ValueError:
        raise InputError(f"--since {text!r} is not an ISO date (YYYY-MM-DD[THH:MM[:SS]])") from None
    if when.tzinfo is None:
        when = when.replace(tzinfo=UTC)
    return when.astimezone(UTC).strftime("%Y-%m-%dT%H:%M:%SZ")


# --- the index ----------------------------------------------------------------------------


class ChangeIndex:
    """An open change index (a SQLite file). Use as a context manager, or call close().

    ``readonly``: open with SQLite's ``mode=ro`` (implies ``create=False``): nothing is
    created or written, not even the WAL setting, and a read-only file works.
    """

    def __init__(
        self,
        path: str | Path,
        *,
        create: bool = True,
        timeout_s: float = 60.0,
        readonly: bool = False,
    ):
        self.path = Path(path)
        create = create and not readonly
        if not create and not self.path.is_file():
            raise MissingInputError(f"change index not found: {self.path}")
        if readonly:
            uri = self.path.resolve().as_uri() + "?mode=ro"
            self.conn = sqlite3.connect(
                uri, uri=True, timeout=timeout_s, isolation_level=None, check_same_thread=False
            )
        else:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            # isolation_level=None: we open transactions ourselves, one per unit of work.
            self.conn = sqlite3.connect(
                self.path, timeout=timeout_s, isolation_level=None, check_same_thread=False
            )
        self.conn.row_factory = sqlite3.Row
        try:
            version = self._version()
            if version is not None and version != SCHEMA_VERSION and version not in MIGRATIONS:
                raise InputError(_old_schema_message(self.path, version))
            if not readonly:
                self.conn.execute("PRAGMA journal_mode=WAL")
                self.conn.execute("PRAGMA synchronous=NORMAL")  # WAL + NORMAL: durable per commit
                if version in MIGRATIONS:
                    self._migrate()
            if create:
                with self.transaction():
                    self._create()
            version = self._meta("schema_version")
            self.file_version = version or ""  # what the file holds (an older one read as it is)
            if readonly and version in MIGRATIONS:
                version = SCHEMA_VERSION  # read as it is (module comment at MIGRATIONS)
        except sqlite3.DatabaseError as exc:
            self.conn.close()
            raise InputError(f"{self.path}: not a streetcd change index ({exc})") from None
        except InputError:
            self.conn.close()
            raise
        if version != SCHEMA_VERSION:
            self.conn.close()
            raise InputError(_old_schema_message(self.path, version))

    def _version(self) -> str | None:
        """The schema version the file holds, None for a new (empty) database."""
        has_meta = self.conn.execute(
            "SELECT 1 FROM sqlite_master WHERE type = 'table' AND name = 'meta'"
        ).fetchone()
        return self._meta("schema_version") if has_meta else None

    def _migrate(self) -> None:
        """Bring an index of an older schema in :data:`MIGRATIONS` to this one, in one
        transaction (another writer that migrated first leaves nothing to do)."""
        with self.transaction():
            version = self._meta("schema_version")
            while version in MIGRATIONS:
                for statement in MIGRATIONS[version]:
                    if not self._column_there(statement):
                        self.conn.execute(statement)
                version = str(int(version) + 1)
            self.conn.execute("UPDATE meta SET value = ? WHERE key = 'schema_version'", (version,))

    def _column_there(self, statement: str) -> bool:
        """Whether ``statement`` adds a column (``ALTER TABLE t ADD COLUMN c …``) that the
        table has already: a file whose version was set back by hand, or copied from a
        half-upgraded one, failed with "duplicate column name"."""
        words = statement.split()
        if [w.upper() for w in words[:2] + words[3:5]] != ["ALTER", "TABLE", "ADD", "COLUMN"]:
            return False
        table, column = words[2], words[5]
        return any(r[1] == column for r in self.conn.execute(f"PRAGMA table_info({table})"))

    def _create(self) -> None:
        for statement in (*_SCHEMA.split(";"), *_OBJECT_JSON):
            if statement.strip():
                self.conn.execute(statement)
        self.conn.execute(
            "INSERT OR IGNORE INTO meta VALUES ('schema_version', ?)", (SCHEMA_VERSION,)
        )

    def __enter__(self) -> ChangeIndex:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        self.conn.close()

    def transaction(self) -> _Transaction:
        return _Transaction(self.conn)

    def _meta(self, key: str) -> str | None:
        row = self.conn.execute("SELECT value FROM meta WHERE key = ?", (key,)).fetchone()
        return None if row is None else row[0]

    @property
    def crs(self) -> str | None:
        """The CRS of every coordinate in the index, or None for a local frame."""
        return self._meta("crs")

    def set_crs(self, crs: str | None) -> None:
        """Record the CRS; CRSMismatchError if the index already holds another one."""
        if crs is None:
            return
        with self.transaction():
            have = self._meta("crs")
            if have is not None and have != crs:
                raise CRSMismatchError(f"{self.path}: index is in {have}, the new views in {crs}")
            self.conn.execute("INSERT OR IGNORE INTO meta VALUES ('crs', ?)", (crs,))

    # --- runs -----------------------------------------------------------------------------

    def begin_run(self, run_id: str, params_hash: str, config: dict | None = None) -> None:
        with self.transaction():
            self.conn.execute(
                "INSERT INTO runs (run_id, started_at, status, params_hash, config) "
                "VALUES (?, ?, 'running', ?, ?)",
                (run_id, utc_now(), params_hash, json.dumps(config or {}, sort_keys=True)),
            )

    def finish_run(self, run_id: str, status: str = "finished", **counts: int) -> None:
        cols = ("n_planned", "n_skipped", "n_done", "n_failed", "n_flagged")
        unknown = set(counts) - set(cols)
        if unknown:
            raise InputError(f"finish_run: unknown count(s) {sorted(unknown)}")
        with self.transaction():
            self.conn.execute(
                "UPDATE runs SET finished_at = ?, status = ?, "
                + ", ".join(f"{c} = ?" for c in cols)
                + " WHERE run_id = ?",
                (utc_now(), status, *(counts.get(c) for c in cols), run_id),
            )

    # --- segments -------------------------------------------------------------------------

    def add_segments(self, segments: Iterable, run_id: str | None = None) -> None:
        """Insert planned segments (:class:`streetcd.run.segments.Segment`); a known id keeps
        its row (ids name fixed pieces of the street: the first night's views and trajectory
        describe it as well as a later night's)."""
        with self.transaction():
            for s in segments:
                cur = self.conn.execute(
                    "INSERT OR IGNORE INTO segments (segment_id, n_views, length_m, min_x, min_y,"
                    " max_x, max_y, polyline, views, first_run) VALUES (?,?,?,?,?,?,?,?,?,?)",
                    (
                        s.id,
                        len(s.views),
                        float(s.length_m),
                        *map(float, s.bbox),
                        json.dumps([[round(float(x), 4) for x in p] for p in s.polyline]),
                        json.dumps(list(s.views)),
                        run_id,
                    ),
                )
                if cur.rowcount:
                    mnx, mny, mxx, mxy = map(float, s.bbox)
                    self.conn.execute(
                        "INSERT INTO segments_rtree VALUES (?, ?, ?, ?, ?)",
                        (cur.lastrowid, mnx, mxx, mny, mxy),
                    )

    # --- views ----------------------------------------------------------------------------

    def processed(self) -> dict[str, tuple[str, str, str]]:
        """{view: (input_hash, params_hash, status)} for every view the index knows."""
        rows = self.conn.execute("SELECT view, input_hash, params_hash, status FROM views")
        return {r[0]: (r[1], r[2], r[3]) for r in rows}

    def publish(self, run_id: str, records: Sequence[ViewRecord]) -> None:
        """Write the outcomes of one batch in one transaction (idempotent per view)."""
        now = utc_now()
        with self.transaction():
            for r in records:
                self._drop_flagged(r.view)
                c = r.center or (None, None, None)
                self.conn.execute(
                    "INSERT OR REPLACE INTO views VALUES (?,?,?,?,?,?,?,?,?,?,?,?,?,?,?,?,?,?,?)",
                    (
                        r.view,
                        r.input_hash,
                        r.params_hash,
                        r.segment_id,
                        r.status,
                        r.error,
                        int(r.flagged),
                        *c,
                        r.detect_s,
                        r.total_s,
                        r.cpu_s,
                        run_id,
                        now,
                        r.captured_at,
                        r.image or r.view.rsplit("#", 1)[0],
                        r.image_path,
                        r.camera,
                    ),
                )
                if r.flagged:
                    self._add_flagged(run_id, now, r)
                self.conn.execute(
                    "DELETE FROM object_json WHERE id IN (SELECT o.id FROM object_views ov"
                    " JOIN objects o ON o.object_id = ov.object_id WHERE ov.view = ?)",
                    (r.view,),
                )

    def _drop_flagged(self, view: str) -> None:
        row = self.conn.execute("SELECT id FROM flagged WHERE view = ?", (view,)).fetchone()
        if row is None:
            return
        self.conn.execute(
            "DELETE FROM regions_rtree WHERE id IN (SELECT id FROM regions WHERE flagged_id = ?)",
            (row[0],),
        )
        self.conn.execute("DELETE FROM regions WHERE flagged_id = ?", (row[0],))
        self.conn.execute("DELETE FROM flagged WHERE id = ?", (row[0],))

    def _add_flagged(self, run_id: str, now: str, r: ViewRecord) -> None:
        cur = self.conn.execute(
            "INSERT INTO flagged (view, segment_id, score, changed_fraction, n_regions, mask_path,"
            " overlay_path, run_id, detected_at, captured_at) VALUES (?,?,?,?,?,?,?,?,?,?)",
            (
                r.view,
                r.segment_id,
                float(r.score),
                float(r.changed_fraction),
                len(r.regions),
                r.mask_path,
                r.overlay_path,
                run_id,
                now,
                r.captured_at,
            ),
        )
        flagged_id = cur.lastrowid
        for g in r.regions:
            coords: list[float | None] = [None] * 9
            if g.centroid is not None and g.bbox_min is not None and g.bbox_max is not None:
                coords = [*g.centroid, *g.bbox_min, *g.bbox_max]
            cur = self.conn.execute(
                "INSERT INTO regions (flagged_id, label, pixels, score, x, y, z, min_x, min_y,"
                " min_z, max_x, max_y, max_z, dominant_class, foot_class, depth_fraction)"
                " VALUES (?,?,?,?,?,?,?,?,?,?,?,?,?,?,?,?)",
                (
                    flagged_id,
                    int(g.label),
                    int(g.pixels),
                    float(g.score),
                    *(None if c is None else float(c) for c in coords),
                    int(g.dominant_class),
                    int(g.foot_class),
                    g.depth_fraction,
                ),
            )
            if g.bbox_min is not None and g.bbox_max is not None:
                lo, hi = g.bbox_min, g.bbox_max
                self.conn.execute(
                    "INSERT INTO regions_rtree VALUES (?, ?, ?, ?, ?)",
                    (cur.lastrowid, lo[0], hi[0], lo[1], hi[1]),
                )

    # --- queries --------------------------------------------------------------------------

    def query(
        self,
        *,
        segment: str | None = None,
        bbox: tuple[float, float, float, float] | None = None,
        since: str | None = None,
        min_score: float | None = None,
        detected_since: str | None = None,
        sort: str | None = None,
        limit: int | None = None,
        records: tuple[Callable[..., Any], Callable[..., Any]] | None = None,
    ) -> list[FlaggedRow]:
        """Flagged views matching every filter given, ordered by segment then view.

        segment : a segment id. bbox : (min_x, min_y, max_x, max_y) in the index's CRS; a
        view matches when one of its located regions' x/y boxes intersects it. A view with
        no located region matches the box when its camera centre lies inside.
        since : ISO date or date-time; views whose image was taken at or after it. Where the
        capture time is unknown (no EXIF date), the detection time stands in: an image is
        detected after it is taken, so such a view may be listed though taken earlier, but a
        change since the date is never left out.
        detected_since : views detected (published) at or after it.
        min_score : score ≥ this.
        sort : ``score`` (best first, then view) or ``time`` (latest capture, else detection,
        first; then as ``score``) instead of segment and view. limit : at most this many
        (≥ 0). Both are done by SQLite, so that the first rows of a big index come fast.
        records : the (row, region) types to make, called with the fields of
        :class:`FlaggedRow` and :class:`RegionRecord` in their order; default those two.
        ``streetcd query`` passes named tuples, which need no import of the dataclasses
        module (docs/BENCHMARKS.md).
        """
        if sort not in QUERY_ORDER:
            raise InputError(f"sort {sort!r} must be one of {', '.join(map(str, QUERY_ORDER))}")
        where: list[str] = []
        args: list[Any] = []
        if segment is not None:
            where.append("f.segment_id = ?")
            args.append(segment)
        if since is not None:
            where.append("coalesce(f.captured_at, f.detected_at) >= ?")
            args.append(parse_since(since))
        if detected_since is not None:
            where.append("f.detected_at >= ?")
            args.append(parse_since(detected_since))
        if min_score is not None:
            where.append("f.score >= ?")
            args.append(float(min_score))
        if bbox is not None:
            mnx, mny, mxx, mxy = _check_bbox(bbox)
            where.append(
                "(f.id IN (SELECT g.flagged_id FROM regions g JOIN regions_rtree t ON t.id = g.id"
                " WHERE t.max_x >= ? AND t.min_x <= ? AND t.max_y >= ? AND t.min_y <= ?)"
                " OR (NOT EXISTS (SELECT 1 FROM regions g WHERE g.flagged_id = f.id AND g.x IS NOT NULL)"
                " AND v.center_x BETWEEN ? AND ? AND v.center_y BETWEEN ? AND ?))"
            )
            args += [mnx, mxx, mny, mxy, mnx, mxx, mny, mxy]
        sql = (
            "SELECT f.*, v.center_x, v.center_y, v.center_z, v.image FROM flagged f "
            "JOIN views v ON v.view = f.view"
            + (" WHERE " + " AND ".join(where) if where else "")
            + f" ORDER BY {QUERY_ORDER[sort]}"
        )
        sql += limit_clause(limit)
        rows = self.conn.execute(sql, args).fetchall()
        if records is None:  # once a query, not once a row
            from streetcd.store.records import FlaggedRow, RegionRecord

            records = (FlaggedRow, RegionRecord)
        regions = self._regions_of([r["id"] for r in rows], records[1])
        return [_flagged_row(records[0], r, regions.get(r["id"], ())) for r in rows]

    def _regions_of(
        self, ids: Sequence[int], record: Callable[..., Any]
    ) -> dict[int, tuple[RegionRecord, ...]]:
        """The regions of flagged rows ``ids`` as ``record``, by row id, each in label
        order: one query per 500 rows (one per row was most of a big query's time), rows as
        plain tuples (looking 16 columns up by name was most of what remained: 31,900
        regions of a 10,000-view city)."""
        out: dict[int, list[RegionRecord]] = {}
        cur = self.conn.cursor()
        cur.row_factory = None
        for k in range(0, len(ids), 500):
            chunk = ids[k : k + 500]
            cur.execute(
                f"SELECT {_REGION_COLUMNS.get(self.file_version, _REGION_COLUMNS[''])} FROM regions"
                f" WHERE flagged_id IN ({','.join('?' * len(chunk))})"
                " ORDER BY flagged_id, label",
                chunk,
            )
            for fid, label, px, score, x, y, z, x0, y0, z0, x1, y1, z1, *rest in cur:
                out.setdefault(fid, []).append(
                    record(
                        label,
                        px,
                        score,
                        None if x is None else (x, y, z),
                        None if x0 is None else (x0, y0, z0),
                        None if x1 is None else (x1, y1, z1),
                        *rest,  # dominant_class, foot_class, depth_fraction
                    )
                )
        return {k: tuple(v) for k, v in out.items()}

    def segments(
        self,
        ids: Iterable[str] | None = None,
        bbox: tuple[float, float, float, float] | None = None,
        record: Callable[..., Any] | None = None,
    ) -> list[SegmentRow]:
        """Segments by id and/or whose box intersects ``bbox`` (R*Tree), ordered by id;
        ``record`` the type to make, called with :class:`SegmentRow`'s fields in their order
        (default that class; see :meth:`query`)."""
        where: list[str] = []
        args: list[Any] = []
        if ids is not None:
            ids = list(ids)
            where.append(f"s.segment_id IN ({','.join('?' * len(ids))})")
            args += ids
        if bbox is not None:
            mnx, mny, mxx, mxy = _check_bbox(bbox)
            where.append(
                "s.id IN (SELECT id FROM segments_rtree WHERE max_x >= ? AND min_x <= ?"
                " AND max_y >= ? AND min_y <= ?)"
            )
            args += [mnx, mxx, mny, mxy]
        sql = "SELECT * FROM segments s" + (" WHERE " + " AND ".join(where) if where else "")
        rows = self.conn.execute(sql + " ORDER BY s.segment_id", args).fetchall()
        if record is None:
            from streetcd.store.records import SegmentRow

            record = SegmentRow
        return [
            record(
                r["segment_id"],
                r["n_views"],
                r["length_m"],
                (r["min_x"], r["min_y"], r["max_x"], r["max_y"]),
                json.loads(r["polyline"]),
            )
            for r in rows
        ]

    def failures(self) -> list[tuple[str, str]]:
        """(view, error) of every failed view, by name."""
        rows = self.conn.execute(
            "SELECT view, error FROM views WHERE status = 'failed' ORDER BY view"
        )
        return [(r[0], r[1]) for r in rows]

    def counts(self) -> dict[str, int]:
        one = self.conn.execute
        return {
            "views": one("SELECT count(*) FROM views").fetchone()[0],
            "done": one("SELECT count(*) FROM views WHERE status = 'done'").fetchone()[0],
            "failed": one("SELECT count(*) FROM views WHERE status = 'failed'").fetchone()[0],
            "flagged": one("SELECT count(*) FROM flagged").fetchone()[0],
            "regions": one("SELECT count(*) FROM regions").fetchone()[0],
            "segments": one("SELECT count(*) FROM segments").fetchone()[0],
        }


def _flagged_row(
    record: Callable[..., Any], r: sqlite3.Row, regions: tuple[RegionRecord, ...]
) -> FlaggedRow:
    """A ``flagged`` ⋈ ``views`` row as ``record`` (:class:`FlaggedRow`, passed in: the
    records load with the first query, not with this module)."""
    center = None if r["center_x"] is None else (r["center_x"], r["center_y"], r["center_z"])
    return record(
        r["view"],
        r["segment_id"],
        r["score"],
        r["changed_fraction"],
        r["n_regions"],
        r["mask_path"],
        r["overlay_path"],
        r["detected_at"],
        center,
        regions,
        r["captured_at"],
        r["image"],
    )


class _Transaction:
    """``BEGIN IMMEDIATE`` … ``COMMIT`` (``ROLLBACK`` on error): one writer at a time, and a
    killed process leaves either the whole unit or none of it."""

    def __init__(self, conn: sqlite3.Connection):
        self.conn = conn

    def __enter__(self) -> sqlite3.Connection:
        self.conn.execute("BEGIN IMMEDIATE")
        return self.conn

    def __exit__(self, exc_type: object, *rest: object) -> None:
        self.conn.execute("ROLLBACK" if exc_type is not None else "COMMIT")


def limit_clause(limit: int | None) -> str:
    """SQL's `` LIMIT n`` for a query's ``limit`` ("" for None); InputError for anything but a
    whole number >= 0 (it is written into the SQL, so it must be one)."""
    if limit is None:
        return ""
    if isinstance(limit, bool) or not isinstance(limit, int) or limit < 0:
        raise InputError(f"limit {limit!r} must be a whole number >= 0")
    return f" LIMIT {int(limit)}"


def _check_bbox(bbox: Sequence[float]) -> tuple[float, float, float, float]:
    if len(bbox) != 4 or not all(math.isfinite(float(x)) for x in bbox):
        raise InputError(f"bbox {bbox!r} must be four finite numbers min_x,min_y,max_x,max_y")
    mnx, mny, mxx, mxy = (float(x) for x in bbox)
    if mnx > mxx or mny > mxy:
        raise InputError(f"bbox {bbox!r}: min_x must be <= max_x and min_y <= max_y")
    return mnx, mny, mxx, mxy


# --- comparing indexes --------------------------------------------------------------------


def _canon(value: object) -> str:
    if isinstance(value, float):
        return f"{value:.9g}"
    return repr(value)


def canonical_dump(path: str | Path) -> list[str]:
    """The index's content as sorted text lines, without what differs between equivalent
    runs: run ids, timestamps (objects' first and last nights too), durations, integer row
    ids, the runs table, and the folder of mask paths (only the file name is kept). Floats
    are printed to 9 significant digits.

    Two runs over the same inputs, one interrupted and resumed, give equal dumps.
    """
    with ChangeIndex(path, create=False) as idx:
        q = idx.conn.execute
        lines = [f"meta {k} {v}" for k, v in q("SELECT key, value FROM meta")]
        for r in q(
            "SELECT s.segment_id, s.n_views, s.length_m, s.min_x, s.min_y, s.max_x, "
            "s.max_y, s.polyline, s.views, t.min_x, t.max_x, t.min_y, t.max_y "
            "FROM segments s LEFT JOIN segments_rtree t ON t.id = s.id"
        ):
            lines.append("segment " + " ".join(_canon(x) for x in r))
        for r in q(
            "SELECT view, input_hash, params_hash, segment_id, status, error, flagged, "
            "center_x, center_y, center_z, captured_at FROM views"
        ):
            lines.append("view " + " ".join(_canon(x) for x in r))
        for r in q(
            "SELECT view, segment_id, score, changed_fraction, n_regions, mask_path, "
            "overlay_path, captured_at FROM flagged"
        ):
            vals = list(r)
            vals[5:7] = [None if p is None else Path(p).name for p in vals[5:7]]
            lines.append("flagged " + " ".join(_canon(x) for x in vals))
        for r in q(
            "SELECT f.view, g.label, g.pixels, g.score, g.x, g.y, g.z, g.min_x, g.min_y, "
            "g.min_z, g.max_x, g.max_y, g.max_z, g.dominant_class, t.min_x, t.max_x, "
            "t.min_y, t.max_y FROM regions g JOIN flagged f ON f.id = g.flagged_id "
            "LEFT JOIN regions_rtree t ON t.id = g.id"
        ):
            lines.append("region " + " ".join(_canon(x) for x in r))
        for r in q(
            "SELECT object_id, segment_id, kind, class, confidence, x, y, z, min_x, min_y, min_z,"
            " max_x, max_y, max_z, pixels, n_views, n_without, transient FROM objects"
        ):
            lines.append("object " + " ".join(_canon(x) for x in r))
        for r in q("SELECT object_id, view, sees_change, labels FROM object_views"):
            lines.append("object_view " + " ".join(_canon(x) for x in r))
        n_rtree = q(
            "SELECT (SELECT count(*) FROM segments_rtree), (SELECT count(*) FROM regions_rtree)"
        ).fetchone()
        lines.append(f"rtree_rows {n_rtree[0]} {n_rtree[1]}")
    return sorted(lines)


# --- failed views, for the night's verdict (streetcd.run.night) ---------------------------
# Kept apart at the end of the module: the run's "N views still failing since <date>".


def failed_views(idx: ChangeIndex) -> list[tuple[str, str, str | None, str | None]]:
    """(view, error, run id, processed at) of every failed view in ``idx``, by view: the
    run that last tried it and when (UTC, the index's format)."""
    rows = idx.conn.execute(
        "SELECT view, error, run_id, processed_at FROM views WHERE status = 'failed' ORDER BY view"
    )
    return [(r[0], r[1] or "", r[2], r[3]) for r in rows]
