"""``streetcd query``: list the change objects of a change index (or, with ``--views``, its
flagged views), as a table, JSON or GeoJSON.

GeoJSON is written in WGS84 longitude/latitude (RFC 7946; reprojected with pyproj from the
index's CRS), which QGIS and web maps read directly; ``--native-crs`` keeps the index's CRS
and names it in the legacy ``crs`` member instead (QGIS honours it too).

The index is opened read-only (SQLite ``mode=ro``): a query never creates or changes a file,
and works on a read-only one. Numbers are checked before anything is read (a NaN, an
infinity, a score outside [0, 1] is a one-line error).

JSON is written compact, one entry (object or view) a line, by orjson: the standard
library's encoder with an indent took 3.7 of the 4.6 s that all 2,570 objects of a
10,000-view index took. Only the command's own modules and SQLite load for a table or JSON
(no numpy: it was half of a small query's time as a command); pyproj loads for GeoJSON in
WGS 84 or a box in another CRS, pyogrio and numpy for a GeoPackage (docs/BENCHMARKS.md).
"""

from __future__ import annotations

import math
import sys
from collections.abc import Sequence
from dataclasses import fields
from pathlib import Path
from typing import Any

import click

from streetcd.cli import index_option
from streetcd.errors import InputError, StreetcdError
from streetcd.store.records import FlaggedRow, RegionRecord

ROW_FIELDS = tuple(f.name for f in fields(FlaggedRow))
REGION_FIELDS = tuple(f.name for f in fields(RegionRecord))


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


def rows_as_json(rows: Sequence[FlaggedRow]) -> list[dict]:
    """Query rows (flagged views) as plain dicts (coordinates in the index's CRS): ``id`` the
    view's lasting key, ``image`` its file name, ``segment``, ``score``, and every field of
    :class:`~streetcd.store.records.FlaggedRow`, its regions as dicts of every field of
    :class:`~streetcd.store.records.RegionRecord` (what ``dataclasses.asdict`` gives, which
    copied every value and took most of the 8,280 views' 9 s)."""
    out = []
    for r in rows:
        d: dict[str, Any] = {
            "id": r.view,
            "image": r.image,
            "segment": r.segment_id,
            "score": r.score,
        }
        d.update((name, getattr(r, name)) for name in ROW_FIELDS)
        d["regions"] = [{name: getattr(g, name) for name in REGION_FIELDS} for g in r.regions]
        out.append(d)
    return out


def json_document(head: dict, key: str, entries: Sequence[dict]) -> str:
    """``{**head, key: entries}`` as compact JSON, each entry on a line of its own (so that
    ``head`` and ``grep`` work on it, and a line is one entry). ``key`` must not be in ``head``."""
    import orjson

    opening = orjson.dumps(head)[:-1] + (b"," if head else b"") + orjson.dumps(key) + b":["
    if not entries:
        return (opening + b"]}").decode()
    body = b",\n".join(orjson.dumps(e) for e in entries)
    return (opening + b"\n" + body + b"\n]}").decode()


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


def run_query(
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
) -> str:
    """The text ``streetcd query`` prints: change objects, or flagged views with ``views``.

    For objects, ``min_score`` is the least confidence, ``since`` the last night seen;
    ``status`` a :func:`~streetcd.store.objects.list_objects` status (``awaiting`` …);
    transients are left out unless ``transients`` or ``status="transient"``.
    """
    from streetcd.store.geojson import objects_to_geojson, to_geojson
    from streetcd.store.index import ChangeIndex
    from streetcd.store.object_list import list_objects

    _fraction("--min-score", min_score)
    # issue 18: --sort, --bbox-crs, csv / gpkg, GeoJSON only with a CRS (streetcd.report.export)
    from streetcd.report import export

    with ChangeIndex(index, readonly=True) as idx:
        crs = idx.crs
    if bbox is not None:
        bbox = export.bbox_in_index_crs(bbox, bbox_crs, crs)
    if fmt == "geojson":
        export.check_geojson_crs(crs, native_crs)
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
        objects = list_objects(
            index,
            status=status,
            segment=segment,
            kind=kind,
            bbox=bbox,
            since=since,
            min_confidence=min_score,
            transients=transients or status is not None,
            limit=limit if in_sql else None,
        )
        if sort is not None and not in_sql:
            objects = export.sort_objects(objects, sort)
            objects = objects[:limit] if limit is not None else objects
        if fmt in ("csv", "gpkg"):
            return export.export_objects(objects, crs, fmt, index, output)
        if fmt == "table":
            return objects_table(objects)
        if fmt == "json":
            return json_document({"crs": crs}, "objects", objects)
        return _geojson_text(objects_to_geojson(objects, crs, wgs84=not native_crs))
    with ChangeIndex(index, readonly=True) as idx:
        rows = idx.query(
            segment=segment,
            bbox=bbox,
            since=since,
            min_score=min_score,
            detected_since=detected_since,
            sort=sort,  # score: best first; time: latest capture (else detection) first
            limit=limit,
        )
        segments = idx.segments(ids=sorted({r.segment_id for r in rows if r.segment_id}))
        if fmt == "table":
            return segments_table(rows, segments) + "\n\n" + rows_as_table(rows)
        if fmt == "json":
            return json_document({"crs": crs}, "views", rows_as_json(rows))
        return _geojson_text(to_geojson(rows, segments, crs, wgs84=not native_crs))


@click.command("query")
@index_option()
@click.option(
    "--views",
    "views",
    is_flag=True,
    help="List flagged views (one entry per view) instead of change objects.",
)
@click.option("--segment", help="Only this segment id.")
@click.option(
    "--bbox",
    help="minx,miny,maxx,maxy in the index's CRS: objects (views: a change region) meeting it.",
)
@click.option(
    "--awaiting-review",
    "awaiting",
    is_flag=True,
    help="Only change objects no one has reviewed yet (transients left out).",
)
@click.option(
    "--status",
    type=click.Choice(
        ["awaiting", "transient", "confirmed", "false_alarm", "false-alarm", "fixed"]
    ),
    help="Only change objects with this review status (or awaiting review, or transients).",
)
@click.option("--kind", type=click.Choice(["added", "removed", "unknown"]), help="Only this kind.")
@click.option("--transients", is_flag=True, help="Also list transients (cars, pedestrians).")
@click.option("--limit", type=int, help="At most this many entries.")
@click.option(
    "--sort",
    type=click.Choice(["score", "time"]),
    help="score: most confident first; time: last seen (views: captured) latest first.",
)
@click.option(
    "--bbox-crs",
    help="The CRS of --bbox (EPSG:4326 for longitude/latitude); default the index's.",
)
@click.option(
    "--since",
    help="ISO date or date-time (UTC if no zone): objects last seen since then; with --views, "
    "views whose image was taken since then (EXIF date; the detection date where it has none).",
)
@click.option(
    "--detected-since", help="ISO date or date-time: views detected (published) since then."
)
@click.option(
    "--min-score",
    type=float,
    help="Only objects with at least this confidence, or views scoring at least this (0–1).",
)
@click.option(
    "--format",
    "fmt",
    type=click.Choice(["table", "json", "geojson", "csv", "gpkg"]),
    default="table",
    show_default=True,
)
@click.option(
    "--native-crs",
    is_flag=True,
    help="GeoJSON in the index's CRS (legacy 'crs' member) instead of WGS84 longitude/latitude.",
)
@click.option("-o", "--output", type=click.Path(dir_okay=False), help="Write to this file.")
def query(
    index: str,
    views: bool,
    segment: str | None,
    bbox: str | None,
    since: str | None,
    min_score: float | None,
    detected_since: str | None,
    fmt: str,
    native_crs: bool,
    output: str | None,
    awaiting: bool,
    status: str | None,
    kind: str | None,
    transients: bool,
    limit: int | None,
    sort: str | None,
    bbox_crs: str | None,
) -> None:
    """List the change objects of a change index (or its flagged views, --views), filtered by
    segment, box, date, score and review status. Opens the index read-only."""
    if awaiting:
        if status not in (None, "awaiting"):
            raise click.ClickException("--awaiting-review and --status are exclusive")
        status = "awaiting"
    try:
        text = run_query(
            index,
            views=views,
            status=status,
            kind=kind,
            transients=transients,
            limit=limit,
            sort=sort,
            bbox_crs=bbox_crs,
            output=output,
            segment=segment,
            bbox=_bbox(bbox),
            since=since,
            min_score=min_score,
            fmt=fmt,
            native_crs=native_crs,
            detected_since=detected_since,
        )
    except StreetcdError as exc:
        raise click.ClickException(str(exc)) from None
    if fmt == "gpkg":
        click.echo(text, err=True)
    elif output:
        Path(output).write_text(text + "\n", encoding="utf-8")
        click.echo(f"wrote {output}", err=True)
    else:
        sys.stdout.write(text + "\n")
