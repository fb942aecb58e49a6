"""Queries: every filter against a brute-force filter over all rows; the CLI's formats."""

import json
import subprocess
import sys
from dataclasses import replace

import numpy as np
import pyproj
import pytest
from click.testing import CliRunner
from test_segments import E0, N0, street

from streetcd.cli.main import query as query_cmd
from streetcd.errors import InputError
from streetcd.run.segments import SegmentParams, plan_segments
from streetcd.store.index import ChangeIndex
from streetcd.store.records import RegionRecord, ViewRecord

CRS = "EPSG:32648"
DATES = ["2026-11-01T02:00:00Z", "2026-11-10T03:30:00Z", "2026-11-20T01:15:00Z"]
# Capture times: each one a little before a detection date, so that a view taken before a
# date but detected after it tells the two filters apart.
TAKEN = ["2026-10-30T09:00:00Z", "2026-11-09T10:00:00Z", "2026-11-19T08:00:00Z"]


@pytest.fixture(scope="module")
def index_path(tmp_path_factory):
    """60 views on two streets, a third flagged, with random regions, detection dates and
    capture dates (unknown for some)."""
    rng = np.random.default_rng(11)
    taken = np.random.default_rng(12)
    views = street(30, step_m=5.0) + street(
        30, step_m=5.0, start=(E0 + 400, N0), along=(0, 1), prefix="b", t0=100
    )
    segments = plan_segments(views, SegmentParams(length_m=40.0))
    seg_of = {n: s.id for s in segments for n in s.views}
    path = tmp_path_factory.mktemp("q") / "change_index.sqlite"
    with ChangeIndex(path) as idx:
        idx.set_crs(CRS)
        idx.add_segments(segments)
        for k, v in enumerate(views):
            c = tuple(float(x) for x in v.center)
            if rng.random() > 0.35:
                rec = ViewRecord(v.name, f"h{k}", "p", seg_of[v.name], "done", center=c)
            else:
                regions = []
                for label in range(1, int(rng.integers(0, 4)) + 1):
                    if rng.random() < 0.15:
                        regions.append(RegionRecord(label, 30, 0.5, None, None, None, 0))
                        continue
                    lo = np.array(c) + rng.uniform([-10, -15, -2], [10, 15, 0])
                    hi = lo + rng.uniform(0.2, 4.0, 3)
                    regions.append(
                        RegionRecord(
                            label,
                            int(rng.integers(50, 5000)),
                            float(rng.uniform(0.5, 1)),
                            tuple((lo + hi) / 2),
                            tuple(lo),
                            tuple(hi),
                            64,
                        )
                    )
                rec = ViewRecord(
                    v.name,
                    f"h{k}",
                    "p",
                    seg_of[v.name],
                    "done",
                    flagged=True,
                    score=max((g.score for g in regions), default=0.0),
                    changed_fraction=float(rng.uniform(0.001, 0.2)),
                    regions=tuple(regions),
                    mask_path=f"/m/{v.stem}.png",
                    center=c,
                    captured_at=TAKEN[int(taken.integers(0, 3))] if taken.random() < 0.6 else None,
                )
            idx.publish("r", [rec])
        for view in [r.view for r in idx.query()]:
            idx.conn.execute(
                "UPDATE flagged SET detected_at = ? WHERE view = ?",
                (DATES[int(rng.integers(0, 3))], view),
            )
    return path


def brute(rows, segment=None, bbox=None, since=None, min_score=None, detected_since=None):
    def meets(g):
        return (
            g.bbox_max[0] >= bbox[0]
            and g.bbox_min[0] <= bbox[2]
            and g.bbox_max[1] >= bbox[1]
            and g.bbox_min[1] <= bbox[3]
        )

    out = []
    for r in rows:
        if segment is not None and r.segment_id != segment:
            continue
        if since is not None and (r.captured_at or r.detected_at) < since:
            continue
        if detected_since is not None and r.detected_at < detected_since:
            continue
        if min_score is not None and r.score < min_score:
            continue
        if bbox is not None:
            located = [g for g in r.regions if g.located]
            if located:
                if not any(meets(g) for g in located):
                    continue
            elif not (bbox[0] <= r.center[0] <= bbox[2] and bbox[1] <= r.center[1] <= bbox[3]):
                continue
        out.append(r)
    return out


def test_the_fixture_has_every_case(index_path):
    with ChangeIndex(index_path, create=False) as idx:
        rows = idx.query()
    assert 10 < len(rows) < 40
    assert any(not r.regions for r in rows) and any(len(r.regions) > 1 for r in rows)
    assert any(not g.located for r in rows for g in r.regions)
    assert any(r.captured_at is None for r in rows)
    assert any(r.captured_at is not None and r.captured_at < r.detected_at for r in rows)


@pytest.mark.parametrize("case", range(40))
def test_filters_match_brute_force(index_path, case):
    rng = np.random.default_rng(100 + case)
    with ChangeIndex(index_path, create=False) as idx:
        rows = idx.query()
        segment_ids = sorted({r.segment_id for r in rows})
        kw = {}
        if rng.random() < 0.4:
            kw["segment"] = segment_ids[int(rng.integers(0, len(segment_ids)))]
        if rng.random() < 0.6:
            x0, y0 = E0 + rng.uniform(-20, 420), N0 + rng.uniform(-20, 150)
            kw["bbox"] = (x0, y0, x0 + rng.uniform(1, 60), y0 + rng.uniform(1, 60))
        if rng.random() < 0.5:
            kw["since"] = DATES[int(rng.integers(0, 3))]
        if rng.random() < 0.5:
            kw["min_score"] = float(rng.uniform(0.4, 1.0))
        if rng.random() < 0.3:
            kw["detected_since"] = DATES[int(rng.integers(0, 3))]
        got = idx.query(**kw)
    assert [r.view for r in got] == [r.view for r in brute(rows, **kw)]


@pytest.mark.parametrize("sort", [None, "score", "time"])
@pytest.mark.parametrize("limit", [None, 0, 1, 7])
def test_sort_and_limit_in_sqlite_match_sorting_in_python(index_path, sort, limit):
    with ChangeIndex(index_path, create=False) as idx:
        rows = idx.query(min_score=0.3)
        got = idx.query(min_score=0.3, sort=sort, limit=limit)
    if sort:  # the order `streetcd query --sort` promises (ties by score, then view)
        rows.sort(key=lambda r: (-r.score, r.view))
        if sort == "time":
            rows.sort(key=lambda r: r.captured_at or r.detected_at, reverse=True)
    assert got == rows[:limit]


def test_since_is_the_capture_date_where_known_else_the_detection_date(index_path):
    with ChangeIndex(index_path, create=False) as idx:
        rows = idx.query()
        since = idx.query(since=DATES[1])
        detected = idx.query(detected_since=DATES[1])
    # Taken on 11-09, detected on 11-10 or later: a change since 11-10 it is not.
    taken_before = {r.view for r in rows if r.captured_at == TAKEN[1] and r.detected_at >= DATES[1]}
    assert taken_before and not taken_before & {r.view for r in since}
    assert taken_before <= {r.view for r in detected}
    unknown = {r.view for r in rows if r.captured_at is None and r.detected_at >= DATES[1]}
    assert unknown and unknown <= {r.view for r in since}  # never left out


def test_since_takes_plain_dates_and_rejects_junk(index_path):
    with ChangeIndex(index_path, create=False) as idx:
        rows = idx.query()
        assert idx.query(since="2026-11-10") == brute(rows, since="2026-11-10T00:00:00Z")
        assert idx.query(since="2026-11-10T04:30+01:00") == brute(rows, since=DATES[1])
        with pytest.raises(InputError, match="yesterday"):
            idx.query(since="yesterday")
        with pytest.raises(InputError, match="bbox"):
            idx.query(bbox=(1, 2, 0, 3))


def test_cli_json_lists_the_same_rows(index_path):
    out = CliRunner().invoke(
        query_cmd,
        ["--index", str(index_path), "--views", "--min-score", "0.7", "--format", "json"],
    )
    assert out.exit_code == 0, out.output
    data = json.loads(out.output)
    with ChangeIndex(index_path, create=False) as idx:
        expected = [r.view for r in brute(idx.query(), min_score=0.7)]
    assert data["crs"] == CRS and [r["id"] for r in data["views"]] == expected
    assert all(r["image"] == r["id"] and r["segment"] == r["segment_id"] for r in data["views"])


def test_cli_table_has_one_line_per_view(index_path):
    out = CliRunner().invoke(query_cmd, ["--index", str(index_path), "--views"])
    assert out.exit_code == 0, out.output
    with ChangeIndex(index_path, create=False) as idx:
        n = len(idx.query())
        n_segments = len({r.segment_id for r in idx.query()})
    lines = out.output.splitlines()
    assert lines[0] == f"flagged segments: {n_segments}"
    assert lines[n_segments + 4] == f"flagged views: {n}"
    assert len(lines) == n_segments + 3 + 1 + n + 3


def test_geojson_is_wgs84_and_lines_up_with_the_crs(index_path, tmp_path):
    target = tmp_path / "changes.geojson"
    out = CliRunner().invoke(
        query_cmd,
        ["--index", str(index_path), "--views", "--format", "geojson", "-o", str(target)],
    )
    assert out.exit_code == 0, out.output
    gj = json.loads(target.read_text())
    assert gj["type"] == "FeatureCollection" and "crs" not in gj
    assert gj["streetcd"]["source_crs"] == CRS
    kinds = {f["properties"]["kind"] for f in gj["features"]}
    assert kinds == {"segment", "region", "view"}
    back = pyproj.Transformer.from_crs("EPSG:4326", CRS, always_xy=True)
    with ChangeIndex(index_path, create=False) as idx:
        rows = {r.view: r for r in idx.query()}
        segs = {s.segment_id: s for s in idx.segments()}
    for f in gj["features"]:
        p, geom = f["properties"], f["geometry"]
        if p["kind"] == "segment":
            assert geom["type"] == "LineString"
            xy = np.array([back.transform(*c) for c in geom["coordinates"]])
            np.testing.assert_allclose(xy, segs[p["segment_id"]].polyline, atol=0.02)
        elif p["kind"] == "region":
            ring = geom["coordinates"][0]
            assert geom["type"] == "Polygon" and ring[0] == ring[-1] and len(ring) == 5
            g = next(g for g in rows[p["view"]].regions if g.label == p["label"])
            x, y = back.transform(*ring[0])
            assert (x, y) == pytest.approx(g.bbox_min[:2], abs=0.02)
        else:
            assert not [g for g in rows[p["view"]].regions if g.located]
        if geom["type"] == "Point":
            lon, lat = geom["coordinates"]
        else:
            lon, lat = np.asarray(geom["coordinates"]).reshape(-1, 2)[0]
        assert 100 < lon < 110 and 0 < lat < 2  # EPSG:32648 near (372 km E, 143 km N)


def test_geojson_native_crs_names_it(index_path):
    out = CliRunner().invoke(
        query_cmd, ["--index", str(index_path), "--views", "--format", "geojson", "--native-crs"]
    )
    gj = json.loads(out.output)
    assert gj["crs"]["properties"]["name"] == "urn:ogc:def:crs:EPSG::32648"
    seg = next(f for f in gj["features"] if f["properties"]["kind"] == "segment")
    assert seg["geometry"]["coordinates"][0][0] > 300_000


def test_query_on_a_missing_index_names_it(tmp_path):
    out = CliRunner().invoke(query_cmd, ["--index", str(tmp_path / "none.sqlite")])
    assert out.exit_code != 0 and "none.sqlite" in out.output


def test_records_round_trip(index_path):
    with ChangeIndex(index_path, create=False) as idx:
        row = next(r for r in idx.query() if r.regions)
        assert replace(row, regions=()).view == row.view
        assert row.n_regions == len(row.regions)


@pytest.mark.parametrize("views", [False, True])
def test_query_never_creates_or_changes_a_file(tmp_path, index_path, views):
    flag = ["--views"] if views else []
    missing = tmp_path / "none.sqlite"
    out = CliRunner().invoke(query_cmd, ["--index", str(missing), *flag])
    assert out.exit_code == 1 and "none.sqlite" in out.output and not missing.exists()
    empty = tmp_path / "empty.sqlite"
    empty.touch()
    out = CliRunner().invoke(query_cmd, ["--index", str(empty), *flag])
    assert out.exit_code == 1 and "not a streetcd change index" in out.output
    assert empty.stat().st_size == 0 and sorted(p.name for p in tmp_path.iterdir()) == [
        "empty.sqlite"
    ]
    copy = tmp_path / "ro.sqlite"
    copy.write_bytes(index_path.read_bytes())
    before = copy.read_bytes()
    copy.chmod(0o444)
    try:
        out = CliRunner().invoke(query_cmd, ["--index", str(copy), "--format", "json", *flag])
        assert out.exit_code == 0, out.output
    finally:
        copy.chmod(0o644)
    assert copy.read_bytes() == before


@pytest.mark.parametrize(
    "args, message",
    [
        (["--min-score", "nan"], "--min-score nan must be a finite number in [0, 1]"),
        (["--min-score", "inf"], "--min-score inf must be a finite number in [0, 1]"),
        (["--min-score", "1.5"], "--min-score 1.5 must be a finite number in [0, 1]"),
        (["--bbox", "0,0,nan,1"], "four finite numbers"),
        (["--bbox", "0,0,inf,1"], "four finite numbers"),
        (["--bbox", "1,0,0,1"], "minx must be <= maxx"),
        (["--limit", "-1"], "--limit -1 must be >= 0"),
        (["--since", "yesterday"], "--since 'yesterday' is not an ISO date"),
    ],
)
@pytest.mark.parametrize("views", [False, True])
def test_bad_numbers_are_one_line_errors(index_path, args, message, views):
    flag = ["--views"] if views else []
    out = CliRunner().invoke(query_cmd, ["--index", str(index_path), *flag, *args])
    assert out.exit_code == 1
    assert out.output.strip() == f"Error: {out.output.strip()[7:]}" and message in out.output
    assert len(out.output.strip().splitlines()) == 1


def test_query_imports_neither_the_detector_nor_the_generator():
    # `streetcd query` on a large index is mostly Python start and imports: the lazy command
    # group (streetcd/cli/main.py) must not import numba or the generator for it
    probe = (
        "import sys; from click.testing import CliRunner; from streetcd.cli.main import cli; "
        "r = CliRunner().invoke(cli, ['query', '--help']); assert r.exit_code == 0, r.output; "
        "print(sorted(m for m in ('numba', 'streetcd.synth', 'streetcd.detect', 'cv2') "
        "if m in sys.modules))"
    )
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"
