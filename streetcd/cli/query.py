"""``streetcd query``: list the change objects of a change index (or, with ``--views``, its
flagged views), as a table, JSON or GeoJSON.

GeoJSON is written in WGS84 longitude/latitude (RFC 7946; reprojected with pyproj from the
index's CRS), which QGIS and web maps read directly; ``--native-crs`` keeps the index's CRS
and names it in the legacy ``crs`` member instead (QGIS honours it too).

The index is opened read-only (SQLite ``mode=ro``): a query never creates or changes a file,
and works on a read-only one. Numbers are checked before anything is read (a NaN, an
infinity, a score outside [0, 1] is a one-line error).

The command parses its arguments with argparse, not click, and ``streetcd`` hands it
``query`` before importing click (:func:`streetcd.cli.entry.main`): click's import was 45 of
the ~150 ms a short query took as a process, and a GIS script polls the index with it.

JSON is written compact, one entry (object or view) a line (the standard library's encoder
with an indent took 3.7 of the 4.6 s that all 2,570 objects of a 10,000-view index took):
by orjson for long answers, by the standard library's C encoder for short ones
(:data:`ORJSON_FROM`). Only the command's own modules and SQLite load for a table or JSON
(no numpy: it was half of a small query's time as a command); pyproj loads for GeoJSON in
WGS 84 or a box in another CRS, pyogrio and numpy for a GeoPackage (docs/BENCHMARKS.md).
"""

from __future__ import annotations

import argparse
import math
import os
import sys
from collections import namedtuple
from collections.abc import Callable, Sequence
from pathlib import Path

from streetcd.cli import INDEX_HELP
from streetcd.errors import InputError, StreetcdError

TYPE_CHECKING = False  # typing's, without importing typing (~18 ms here): mypy reads the name
if TYPE_CHECKING:
    from typing import Any

    from streetcd.store.records import FlaggedRow


# A listing's rows as named tuples with the fields of the index's records (FlaggedRow,
# RegionRecord, SegmentRow), in their order (tests/test_query_output.py checks that they
# agree): the records are dataclasses, and importing the dataclasses module (inspect under
# it) was a good part of a short `streetcd query --views` (docs/BENCHMARKS.md).
ViewRow = namedtuple(
    "ViewRow",
    "view segment_id score changed_fraction n_regions mask_path overlay_path detected_at "
    "center regions captured_at image",
)
RegionRow = namedtuple(
    "RegionRow",
    "label pixels score centroid bbox_min bbox_max dominant_class foot_class depth_fraction",
)
SegmentTuple = namedtuple("SegmentTuple", "segment_id n_views length_m bbox polyline")


def _bbox(text: str | None) -> tuple[float, float, float, float] | None:
    """``minx,miny,maxx,maxy`` as four finite numbers (min ≤ max); InputError otherwise."""
    if text is None:
        return None
    parts = text.split(",")
    try:
        values: tuple[float, ...] = tuple(float(p) for p in parts)
    except ValueError:
        values = ()
    if len(values) != 4 or not all(math.isfinite(v) for v in values):
        raise InputError(f"--bbox {text!r}: expected minx,miny,maxx,maxy (four finite numbers)")
    if values[0] > values[2] or values[1] > values[3]:
        raise InputError(f"--bbox {text!r}: minx must be <= maxx and miny <= maxy")
    return values[0], values[1], values[2], values[3]


def _fraction(name: str, value: float | None) -> float | None:
    if value is not None and not (math.isfinite(value) and 0.0 <= value <= 1.0):
        raise InputError(f"{name} {value!r} must be a finite number in [0, 1]")
    return value


def rows_as_json(rows: Sequence[FlaggedRow | ViewRow]) -> list[dict]:
    """Query rows (flagged views, :class:`ViewRow` or
    :class:`~streetcd.store.records.FlaggedRow`) as plain dicts (coordinates in the index's
    CRS): ``id`` the view's lasting key, ``image`` its file name, ``segment``, ``score``, and
    every field of the row, its regions as dicts of every field of
    :class:`~streetcd.store.records.RegionRecord` (what ``dataclasses.asdict`` gives, which
    copied every value and took most of the 8,280 views' 9 s)."""
    row_fields, region_fields = ViewRow._fields, RegionRow._fields
    out = []
    for r in rows:
        d: dict[str, Any] = {
            "id": r.view,
            "image": r.image,
            "segment": r.segment_id,
            "score": r.score,
        }
        if isinstance(r, tuple):  # a ViewRow and its RegionRows: zip, not 12 lookups
            d.update(zip(row_fields, r, strict=True))
            d["regions"] = [dict(zip(region_fields, g, strict=True)) for g in r.regions]
        else:
            d.update((name, getattr(r, name)) for name in row_fields)
            d["regions"] = [{name: getattr(g, name) for name in region_fields} for g in r.regions]
        out.append(d)
    return out


# orjson writes a long answer ~3.5x faster than the standard library's C encoder (54 against
# 190 ms for the 7 MB of a 10,000-view city's 2,450 objects) but takes ~22 ms to import (it
# loads dataclasses and uuid): more than the standard library spends on a few hundred entries.
ORJSON_FROM = 500


def _json_encoder(n_entries: int) -> Callable[[object], bytes]:
    """Compact JSON as bytes, non-ASCII kept: orjson for ``ORJSON_FROM`` entries or more,
    the standard library below (orjson too for a value it refuses, a NaN: orjson writes
    null where the standard library would write the invalid ``NaN``)."""
    if n_entries >= ORJSON_FROM:
        import orjson

        return orjson.dumps
    import json

    def dumps(value: object) -> bytes:
        try:
            text = json.dumps(value, separators=(",", ":"), ensure_ascii=False, allow_nan=False)
        except ValueError:
            import orjson

            return orjson.dumps(value)
        return text.encode()

    return dumps


def json_document(head: dict, key: str, entries: Sequence[dict]) -> str:
    """``{**head, key: entries}`` as compact JSON, each entry on a line of its own (so that
    ``head`` and ``grep`` work on it, and a line is one entry). ``key`` must not be in ``head``."""
    dumps = _json_encoder(len(entries))
    return "".join(json_pieces(head, key, [dumps(e).decode() for e in entries]))


def json_pieces(head: dict, key: str, lines: Sequence[str]) -> list[str]:
    """:func:`json_document` of entries given as JSON texts, in pieces to be written one
    after the other (the entries themselves among them, not copied)."""
    import json

    opening = json.dumps(head, separators=(",", ":"), ensure_ascii=False)[:-1]
    opening += ("," if head else "") + json.dumps(key) + ":["
    if not lines:
        return [opening + "]}"]
    pieces = [opening]
    for line in lines:
        pieces += ("\n", line, ",")
    pieces[-1] = "\n]}"
    return pieces


def _geojson_text(collection: dict) -> str:
    import orjson

    return orjson.dumps(collection).decode()


def rows_as_table(rows: Sequence, title: str = "flagged views") -> str:
    """A fixed-width text table of query rows, one line per flagged view."""
    header = f"{'segment':<28} {'view':<24} {'score':>6} {'changed':>8} {'regions':>7}  mask"
    lines = [f"{title}: {len(rows)}", header, "-" * len(header)]
    for r in rows:
        lines.append(
            f"{(r.segment_id or '-'):<28} {r.view:<24} {r.score:>6.3f} "
            f"{100 * r.changed_fraction:>7.2f}% {r.n_regions:>7}  {r.mask_path or '-'}"
        )
    return "\n".join(lines)


def segments_table(rows: Sequence, segments: Sequence) -> str:
    """One line per segment that has flagged views: how many, the best score, its length."""
    header = f"{'segment':<28} {'flagged':>9} {'max score':>9} {'length m':>9}"
    lines = [f"flagged segments: {len(segments)}", header, "-" * len(header)]
    by_segment: dict[str | None, list] = {}
    for r in rows:
        by_segment.setdefault(r.segment_id, []).append(r)
    for s in segments:
        mine = by_segment.get(s.segment_id, [])
        lines.append(
            f"{s.segment_id:<28} {len(mine):>4} / {s.n_views:<2} "
            f"{max(r.score for r in mine):>9.3f} {s.length_m:>9.1f}"
        )
    return "\n".join(lines)


def objects_table(objects: Sequence[dict]) -> str:
    """One line per change object: id, kind, class, confidence, views, nights, review."""
    header = (
        f"{'object':<16} {'segment':<24} {'kind':<8} {'class':<11} {'conf':>5} "
        f"{'views':>7} {'first':<10} {'last':<10} review / transient"
    )
    lines = [f"change objects: {len(objects)}", header, "-" * len(header)]
    for o in objects:
        review = o["review"]["status"] if o["review"] else (o["transient"] or "awaiting")
        lines.append(
            f"{o['id']:<16} {o['segment']:<24} {o['kind']:<8} {o['class_name']:<11} "
            f"{o['confidence']:>5.2f} {o['n_views']:>3}/{o['n_views'] + o['n_without']:<3} "
            f"{o['first_seen']:<10} {o['last_seen']:<10} {review}"
        )
    return "\n".join(lines)


def run_query(index: str | Path, **kwargs: Any) -> str:
    """The text ``streetcd query`` prints: :func:`answer`'s pieces (its keywords), joined."""
    return "".join(answer(index, **kwargs))


def answer(
    index: str | Path,
    *,
    segment: str | None = None,
    bbox: tuple[float, float, float, float] | None = None,
    since: str | None = None,
    min_score: float | None = None,
    fmt: str = "table",
    native_crs: bool = False,
    detected_since: str | None = None,
    views: bool = False,
    status: str | None = None,
    kind: str | None = None,
    transients: bool = False,
    limit: int | None = None,
    sort: str | None = None,
    bbox_crs: str | None = None,
    output: str | None = None,
) -> list[str]:
    """The text ``streetcd query`` prints, in pieces to be written one after the other
    (a whole JSON export's entries as the index keeps them: joining and encoding 7 MB
    again took a sixth of the command's time): change objects, or flagged views with ``views``.

    For objects, ``min_score`` is the least confidence, ``since`` the last night seen;
    ``status`` a :func:`~streetcd.store.objects.list_objects` status (``awaiting`` …);
    transients are left out unless ``transients`` or ``status="transient"``.
    """
    from streetcd.store.index import ChangeIndex
    from streetcd.store.object_list import list_objects, object_entries

    _fraction("--min-score", min_score)
    # issue 18: --sort, --bbox-crs, csv / gpkg, GeoJSON only with a CRS (streetcd.report.export,
    # loaded only where one of them is asked for: a plain query pays for SQLite alone)
    with ChangeIndex(index, readonly=True) as idx:
        crs = idx.crs
    if bbox is not None and bbox_crs is not None:
        from streetcd.report.export import bbox_in_index_crs

        bbox = bbox_in_index_crs(bbox, bbox_crs, crs)
    if fmt == "geojson":
        from streetcd.report.export import check_geojson_crs

        check_geojson_crs(crs, native_crs)
    if views and fmt in ("csv", "gpkg"):
        raise InputError(f"--format {fmt} lists change objects: leave out --views")
    if limit is not None and limit < 0:
        raise InputError(f"--limit {limit} must be >= 0")
    if not views:
        if detected_since is not None:
            raise InputError("--detected-since lists flagged views: add --views")
        # list_objects' own order is --sort score's: SQLite then sorts and cuts, so that
        # the first objects of a big index come fast
        in_sql = sort in (None, "score")
        selection: dict[str, Any] = dict(
            status=status,
            segment=segment,
            kind=kind,
            bbox=bbox,
            since=since,
            min_confidence=min_score,
            transients=transients or status is not None,
            limit=limit if in_sql else None,
        )
        if fmt == "json" and in_sql:  # the entries the index keeps, no dict made
            return json_pieces({"crs": crs}, "objects", object_entries(index, **selection))
        # the table shows the counts alone
        objects = list_objects(index, **selection, with_views=fmt != "table")
        if sort is not None and not in_sql:
            from streetcd.report.export import sort_objects

            objects = sort_objects(objects, sort)
            objects = objects[:limit] if limit is not None else objects
        if fmt in ("csv", "gpkg"):
            from streetcd.report.export import export_objects

            return [export_objects(objects, crs, fmt, index, output)]
        if fmt == "table":
            return [objects_table(objects)]
        if fmt == "json":
            return [json_document({"crs": crs}, "objects", objects)]
        from streetcd.store.geojson import objects_to_geojson

        return [_geojson_text(objects_to_geojson(objects, crs, wgs84=not native_crs))]
    light = fmt != "geojson"  # the GeoJSON writer uses the records' own properties
    with ChangeIndex(index, readonly=True) as idx:
        rows = idx.query(
            segment=segment,
            bbox=bbox,
            since=since,
            min_score=min_score,
            detected_since=detected_since,
            sort=sort,  # score: best first; time: latest capture (else detection) first
            limit=limit,
            records=(ViewRow, RegionRow) if light else None,
        )
        segments = idx.segments(
            ids=sorted({r.segment_id for r in rows if r.segment_id}),
            record=SegmentTuple if light else None,
        )
        if fmt == "table":
            return [segments_table(rows, segments), "\n\n", rows_as_table(rows)]
        if fmt == "json":
            return [json_document({"crs": crs}, "views", rows_as_json(rows))]
        from streetcd.store.geojson import to_geojson

        return [_geojson_text(to_geojson(rows, segments, crs, wgs84=not native_crs))]


USAGE = "Usage: streetcd query [OPTIONS]"
STATUSES = ("awaiting", "transient", "confirmed", "false_alarm", "false-alarm", "fixed")
FORMATS = ("table", "json", "geojson", "csv", "gpkg")


class UsageError(Exception):
    """A command line argparse cannot read: printed click's way (usage, then ``Error:``)."""


def _formatter(prog: str) -> argparse.HelpFormatter:
    """argparse's help formatter, told the terminal's width: left to itself it imports shutil
    (5 ms) to ask, on every ``add_argument``."""
    try:
        width = os.get_terminal_size().columns
    except OSError:  # not a terminal
        width = 80
    return argparse.HelpFormatter(prog, width=max(width - 2, 40))


class _Parser(argparse.ArgumentParser):
    def error(self, message: str) -> Any:  # argparse's own prints and exits: we raise
        raise UsageError(message)


def parser() -> argparse.ArgumentParser:
    """``streetcd query``'s options (``streetcd query --help`` prints them)."""
    p = _Parser(
        prog="streetcd query",
        formatter_class=_formatter,
        description="List the change objects of a change index (or its flagged views, "
        "--views), filtered by segment, box, date, score and review status. Opens the index "
        "read-only.",
    )
    p.add_argument("--index", required=True, metavar="PATH", help=INDEX_HELP)
    p.add_argument(
        "--views",
        action="store_true",
        help="List flagged views (one entry per view) instead of change objects.",
    )
    p.add_argument("--segment", help="Only this segment id.")
    p.add_argument(
        "--bbox",
        metavar="MINX,MINY,MAXX,MAXY",
        help="A box in the index's CRS: objects (views: a change region) meeting it.",
    )
    p.add_argument(
        "--awaiting-review",
        dest="awaiting",
        action="store_true",
        help="Only change objects no one has reviewed yet (transients left out).",
    )
    p.add_argument(
        "--status",
        choices=STATUSES,
        help="Only change objects with this review status (or awaiting review, or transients).",
    )
    p.add_argument("--kind", choices=("added", "removed", "unknown"), help="Only this kind.")
    p.add_argument(
        "--transients", action="store_true", help="Also list transients (cars, pedestrians)."
    )
    p.add_argument("--limit", type=int, help="At most this many entries.")
    p.add_argument(
        "--sort",
        choices=("score", "time"),
        help="score: most confident first; time: last seen (views: captured) latest first.",
    )
    p.add_argument(
        "--bbox-crs",
        help="The CRS of --bbox (EPSG:4326 for longitude/latitude); default the index's.",
    )
    p.add_argument(
        "--since",
        help="ISO date or date-time (UTC if no zone): objects last seen since then; with "
        "--views, views whose image was taken since then (EXIF date; the detection date "
        "where it has none).",
    )
    p.add_argument(
        "--detected-since", help="ISO date or date-time: views detected (published) since then."
    )
    p.add_argument(
        "--min-score",
        type=float,
        help="Only objects with at least this confidence, or views scoring at least this (0-1).",
    )
    p.add_argument("--format", dest="fmt", choices=FORMATS, default="table", help="Default: table.")
    p.add_argument(
        "--native-crs",
        action="store_true",
        help="GeoJSON in the index's CRS (legacy 'crs' member) instead of WGS84 "
        "longitude/latitude.",
    )
    p.add_argument("-o", "--output", metavar="FILE", help="Write to this file.")
    return p


def _values_attached(p: argparse.ArgumentParser, argv: Sequence[str]) -> list[str]:
    """``argv`` with each option that takes a value joined to it (``--bbox=-73.9,40.7,…``):
    argparse reads a value that starts with ``-`` as the next option unless it looks like
    one plain negative number, and a box west of Greenwich or in a local frame is four.
    click took the next word whatever it was; so does this."""
    # argparse lists its actions only in this attribute; nargs None: takes one value
    takes_value = {s for act in p._actions if act.nargs is None for s in act.option_strings}
    out: list[str] = []
    words = iter(argv)
    for word in words:
        value = next(words, None) if word in takes_value else None
        out.append(word if value is None else f"{word}={value}")
    return out


def main(argv: Sequence[str]) -> int:
    """``streetcd query ARGV``: prints the answer, returns the exit status (0; 1 for an
    error in the input or the index, one ``Error:`` line; 2 for a command line it cannot
    read, click's way)."""
    p = parser()
    try:
        a = p.parse_args(_values_attached(p, argv))
    except UsageError as exc:
        print(f"{USAGE}\nTry 'streetcd query --help' for help.\n\nError: {exc}", file=sys.stderr)
        return 2
    except SystemExit as exc:  # --help
        return int(exc.code or 0)
    status = a.status
    if a.awaiting:
        if status not in (None, "awaiting"):
            print("Error: --awaiting-review and --status are exclusive", file=sys.stderr)
            return 1
        status = "awaiting"
    try:
        pieces = answer(
            a.index,
            views=a.views,
            status=status,
            kind=a.kind,
            transients=a.transients,
            limit=a.limit,
            sort=a.sort,
            bbox_crs=a.bbox_crs,
            output=a.output,
            segment=a.segment,
            bbox=_bbox(a.bbox),
            since=a.since,
            min_score=a.min_score,
            fmt=a.fmt,
            native_crs=a.native_crs,
            detected_since=a.detected_since,
        )
    except StreetcdError as exc:
        print(f"Error: {exc}", file=sys.stderr)
        return 1
    if a.fmt == "gpkg":
        print("".join(pieces), file=sys.stderr)
    elif a.output:
        with open(a.output, "w", encoding="utf-8") as f:
            f.writelines(pieces)
            f.write("\n")
        print(f"wrote {a.output}", file=sys.stderr)
    else:
        sys.stdout.writelines(pieces)
        sys.stdout.write("\n")
    return 0
