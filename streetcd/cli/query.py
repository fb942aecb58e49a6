"""``streetcd query``: list flagged views from a change index, as a table, JSON or GeoJSON.

GeoJSON is written in WGS84 longitude/latitude (RFC 7946; reprojected with pyproj from the
index's CRS), which QGIS and web maps read directly; ``--native-crs`` keeps the index's CRS
and names it in the legacy ``crs`` member instead (QGIS honours it too).
"""

from __future__ import annotations

import json
import sys
from collections.abc import Sequence
from pathlib import Path

import click

from streetcd.errors import StreetcdError


def _bbox(text: str | None) -> tuple[float, float, float, float] | None:
    if text is None:
        return None
    parts = text.split(",")
    try:
        values: tuple[float, ...] = tuple(float(p) for p in parts)
    except ValueError:
        values = ()
    if len(values) != 4:
        raise click.BadParameter(f"{text!r}: expected minx,miny,maxx,maxy (four numbers)")
    return values[0], values[1], values[2], values[3]


def rows_as_json(rows: Sequence) -> list[dict]:
    """Query rows as plain dicts (coordinates in the index's CRS)."""
    from dataclasses import asdict

    return [asdict(r) for r in rows]


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
    for s in segments:
        mine = [r for r in rows if r.segment_id == s.segment_id]
        lines.append(
            f"{s.segment_id:<28} {len(mine):>4} / {s.n_views:<2} "
            f"{max(r.score for r in mine):>9.3f} {s.length_m:>9.1f}"
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
) -> str:
    """The text ``streetcd query`` prints."""
    from streetcd.store.geojson import to_geojson
    from streetcd.store.index import ChangeIndex

    with ChangeIndex(index, create=False) as idx:
        rows = idx.query(
            segment=segment,
            bbox=bbox,
            since=since,
            min_score=min_score,
            detected_since=detected_since,
        )
        segments = idx.segments(ids=sorted({r.segment_id for r in rows if r.segment_id}))
        if fmt == "table":
            return segments_table(rows, segments) + "\n\n" + rows_as_table(rows)
        if fmt == "json":
            return json.dumps({"crs": idx.crs, "flagged": rows_as_json(rows)}, indent=1)
        return json.dumps(to_geojson(rows, segments, idx.crs, wgs84=not native_crs))


@click.command("query")
@click.option(
    "--index",
    "index",
    required=True,
    type=click.Path(dir_okay=False),
    help="The change index (SQLite) a run wrote.",
)
@click.option("--segment", help="Only this segment id.")
@click.option(
    "--bbox",
    help="minx,miny,maxx,maxy in the index's CRS: views with a change region meeting the box.",
)
@click.option(
    "--since",
    help="ISO date or date-time (UTC if no zone): views whose image was taken since then (EXIF "
    "date; the detection date where the image has none).",
)
@click.option(
    "--detected-since", help="ISO date or date-time: views detected (published) since then."
)
@click.option("--min-score", type=float, help="Only views scoring at least this (0–1).")
@click.option(
    "--format",
    "fmt",
    type=click.Choice(["table", "json", "geojson"]),
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
    segment: str | None,
    bbox: str | None,
    since: str | None,
    min_score: float | None,
    detected_since: str | None,
    fmt: str,
    native_crs: bool,
    output: str | None,
) -> None:
    """List the flagged views of a change index, filtered by segment, box, date and score."""
    try:
        text = run_query(
            index,
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
    if output:
        Path(output).write_text(text + "\n", encoding="utf-8")
        click.echo(f"wrote {output}", err=True)
    else:
        sys.stdout.write(text + "\n")
