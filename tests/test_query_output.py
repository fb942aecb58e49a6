"""``streetcd query``'s fast paths give what the slow ones gave: JSON written by orjson one
entry a line parses to the same objects and views as the standard library's encoding of
the same records; the read side loads no numpy (docs/BENCHMARKS.md, query speed)."""

import json
import shutil
import sqlite3
import subprocess
import sys
from dataclasses import asdict
from pathlib import Path

import pytest
from click.testing import CliRunner
from test_objects import BIN, BOX, POLE, night

from streetcd.cli.main import query as query_cmd
from streetcd.cli.query import run_query
from streetcd.store import object_list, objects
from streetcd.store.index import ChangeIndex
from streetcd.store.records import ViewRecord

HEAVY = ("numpy", "zarr", "numba", "yaml", "streetcd.config", "streetcd.types")
HEAVY += ("streetcd.geometry", "streetcd.detect", "streetcd.store.objects")


@pytest.fixture(scope="module")
def two_nights(tmp_path_factory):
    """Two nights of test_objects' street (a pole gone, a box added, then a bin): change
    objects, transients among them, and flagged views with located regions."""
    index = tmp_path_factory.mktemp("q") / "change_index.sqlite"
    night(index, "aaa", [("removed", POLE), ("added", BOX)], "2026-11-01")
    night(index, "bbb", [("removed", POLE), ("added", BOX), ("added", BIN)], "2026-11-08")
    return index


def cli(index, *args):
    out = CliRunner().invoke(query_cmd, ["--index", str(index), *args])
    assert out.exit_code == 0, out.output
    return out.output


def test_objects_json_is_the_listing_one_object_a_line(two_nights):
    text = cli(two_nights, "--format", "json", "--transients")
    listing = object_list.list_objects(two_nights)
    assert len(listing) >= 2
    # what the standard library wrote before, parsed: the same document
    assert json.loads(text) == json.loads(json.dumps({"crs": None, "objects": listing}))
    lines = text.rstrip("\n").split("\n")
    assert lines[0] == '{"crs":null,"objects":[' and lines[-1] == "]}"
    entries = [json.loads(line.removesuffix(",")) for line in lines[1:-1]]
    assert [e["id"] for e in entries] == [o["id"] for o in listing]
    for key in ("id", "kind", "confidence", "centroid", "bbox", "views", "first_seen"):
        assert all(key in e for e in entries)
    assert all("last_seen" in e and "review" in e for e in entries)


def test_views_json_equals_the_dataclass_form(two_nights):
    text = cli(two_nights, "--views", "--format", "json")
    with ChangeIndex(two_nights, readonly=True) as idx:
        rows = idx.query()
    before = [
        {"id": r.view, "image": r.image, "segment": r.segment_id, "score": r.score, **asdict(r)}
        for r in rows
    ]
    assert any(g.located for r in rows for g in r.regions)
    assert json.loads(text) == json.loads(json.dumps({"crs": None, "views": before}))
    assert len(text.rstrip("\n").split("\n")) == len(rows) + 2


@pytest.mark.parametrize("views", [False, True])
def test_an_empty_answer_is_still_a_document(two_nights, views):
    text = run_query(two_nights, fmt="json", views=views, limit=0)
    assert json.loads(text) == {"crs": None, ("views" if views else "objects"): []}


def test_geojson_lists_the_same_objects(two_nights):
    text = cli(two_nights, "--format", "geojson", "--native-crs", "--transients")
    gj = json.loads(text)
    ids = [f["properties"]["id"] for f in gj["features"]]
    assert ids == [o["id"] for o in object_list.list_objects(two_nights)]


def test_the_cli_leaves_transients_out_the_library_keeps_them(two_nights):
    every = object_list.list_objects(two_nights)
    street = [o["id"] for o in every if o["transient"] is None]
    assert len(street) < len(every)  # the fixture has transients
    data = json.loads(cli(two_nights, "--format", "json"))
    assert [o["id"] for o in data["objects"]] == street


def test_view_labels_are_not_shared_between_views(two_nights):
    views = [v for o in object_list.list_objects(two_nights) for v in o["views"]]
    same = [v for v in views if v["labels"] == views[0]["labels"]]
    assert len(same) >= 2  # label lists recur (that is why they are decoded once)
    same[0]["labels"].append(99)
    assert 99 not in same[1]["labels"]


@pytest.mark.parametrize(
    "args",
    [
        ["--format", "json"],
        ["--limit", "5"],
        ["--bbox", "-1e9,-1e9,1e9,1e9"],
        ["--views"],
        ["--views", "--format", "json", "--limit", "5"],
    ],
)
def test_the_program_lists_objects_without_click_typing_or_dataclasses(two_nights, args):
    # as a process a query was mostly imports: click (for every other command), typing and
    # dataclasses (under the records and orjson) were ~80 of its ~190 ms (streetcd/cli/entry.py)
    loaded, answer = loaded_by_a_query(
        two_nights, args, ("click", "typing", "dataclasses", "orjson")
    )
    assert loaded == []
    if "json" in args:
        assert json.loads(answer)["views" if "--views" in args else "objects"]
    else:
        assert answer.startswith("flagged segments:" if "--views" in args else "change objects:")


def test_the_listings_named_tuples_have_the_records_fields():
    """`streetcd query --views` makes its rows as named tuples (no dataclasses to import):
    the same fields in the same order as the index's records, which the index fills by
    position."""
    from dataclasses import fields

    from streetcd.cli.query import RegionRow, SegmentTuple, ViewRow
    from streetcd.store.records import FlaggedRow, RegionRecord, SegmentRow

    for light, record in ((ViewRow, FlaggedRow), (RegionRow, RegionRecord)):
        assert light._fields == tuple(f.name for f in fields(record))
    assert SegmentTuple._fields == tuple(f.name for f in fields(SegmentRow))


def test_long_and_short_answers_are_the_same_json(two_nights, monkeypatch):
    from streetcd.cli import query

    short = run_query(two_nights, fmt="json", transients=True)
    monkeypatch.setattr(query, "ORJSON_FROM", 0)  # orjson for any length
    assert run_query(two_nights, fmt="json", transients=True) == short
    nan = query.json_document({"crs": None}, "objects", [{"id": "a", "confidence": float("nan")}])
    assert json.loads(nan)["objects"][0]["confidence"] is None  # null, never the invalid NaN


def test_the_write_side_reexports_the_read_side():
    assert objects.list_objects is object_list.list_objects
    assert objects.REVIEW_STATUSES == object_list.REVIEW_STATUSES
    assert objects.check_fraction is object_list.check_fraction


@pytest.mark.parametrize(
    "args",
    [["--format", "json"], ["--limit", "5"], ["--views"], ["--views", "--format", "json"]],
)
def test_a_real_query_loads_no_numpy_nor_the_detector(two_nights, args):
    # half of a small query's time as a command was numpy and the rebuild's modules; the
    # click group (`python -m streetcd.cli.main query`) hands over to the same parser
    for start in ("program", "click"):
        loaded, answer = loaded_by_a_query(two_nights, args, HEAVY, start)
        assert loaded == [] and answer.strip(), start


def loaded_by_a_query(
    index: Path, args: list[str], modules: tuple[str, ...], start: str = "program"
) -> tuple[list[str], str]:
    """Which of ``modules`` ``streetcd query --index INDEX ARGS`` loads in a fresh
    interpreter, started as the installed program does (``program``: streetcd.cli.entry) or
    through the click group (``click``); and its answer."""
    run = {
        "program": "sys.argv = ['streetcd', *sys.argv[1:]]\nfrom streetcd.cli.entry import main\n",
        "click": "from streetcd.cli.main import cli\nmain = lambda: cli(sys.argv[1:], prog_name='streetcd')\n",
    }[start]
    probe = (
        f"import sys\n{run}try:\n    main()\nexcept SystemExit as e:\n    assert not e.code, e.code\n"
        f"print(sorted(m for m in {modules!r} if m in sys.modules), file=sys.stderr)\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", probe, "query", "--index", str(index), *args],
        capture_output=True,
        text=True,
        check=True,
    )
    return json.loads(out.stderr.strip().splitlines()[-1].replace("'", '"')), out.stdout


SELECTIONS = [
    {},
    {"transients": False},
    {"kind": "added"},
    {"status": "awaiting"},
    {"status": "transient"},
    {"sort": "id", "limit": 2},
    {"since": "2026-11-08", "min_confidence": 0.1},
]


def kept_rows(index):
    with ChangeIndex(index, readonly=True) as idx:
        return dict(idx.conn.execute("SELECT id, entry FROM object_json").fetchall())


def same_as_the_listing(index):
    """The kept entries (object_entries, and list_objects parsing them) give what the tables
    give: the same index without its entries, where every object is made from the tables."""
    tables = index.with_name("without-entries.sqlite")
    shutil.copy(index, tables)
    con = sqlite3.connect(tables)
    if con.execute("SELECT 1 FROM sqlite_master WHERE name = 'object_json'").fetchone():
        con.execute("DELETE FROM object_json")  # (a schema-5 file has none to delete)
        con.commit()
    con.close()
    for selection in SELECTIONS:
        entries = object_list.object_entries(index, **selection)
        assert entries == object_list.object_entries(tables, **selection)
        listing = object_list.list_objects(tables, **selection)
        assert [json.loads(e) for e in entries] == listing
        assert object_list.list_objects(index, **selection) == listing
    tables.unlink()


def test_the_kept_entries_list_what_the_tables_hold_reviews_and_republished_views_too(tmp_path):
    """The JSON listing reads each object's entry as the rebuild kept it (object_json): it
    must parse to what list_objects makes from the tables, after a review (written apart)
    and after a view of an object is published again without a rebuild (its entry dropped,
    the object made from the tables)."""
    index = tmp_path / "change_index.sqlite"
    night(index, "aaa", [("removed", POLE), ("added", BOX)], "2026-11-01")
    night(index, "bbb", [("removed", POLE), ("added", BOX), ("added", BIN)], "2026-11-08")
    every = object_list.list_objects(index)
    street = [o for o in every if o["transient"] is None]
    assert len(kept_rows(index)) == len(street) >= 2 and len(every) > len(street)
    same_as_the_listing(index)

    objects.record_review(index, street[0]["id"], "false-alarm", who="ana", note="ünïcode")
    same_as_the_listing(index)
    assert object_list.list_objects(index, status="false_alarm")[0]["review"]["who"] == "ana"

    kept = kept_rows(index)
    others = {v["view"] for o in street[:1] + street[2:] for v in o["views"]}
    view = next(v["view"] for v in street[1]["views"] if v["view"] not in others)
    with ChangeIndex(index) as idx:  # the view done again: unflagged now
        idx.publish("r2", [ViewRecord(view, "h2", "p", street[1]["segment"], "done")])
    left = kept_rows(index)
    assert len(left) == len(kept) - 1  # street[1]'s entry went...
    assert all(kept[k] == v for k, v in left.items())  # ...the others stay as they were
    again = next(o for o in object_list.list_objects(index) if o["id"] == street[1]["id"])
    assert next(v for v in again["views"] if v["view"] == view)["overlay"] is None
    same_as_the_listing(index)


def test_an_index_of_schema_5_is_listed_from_its_tables_and_gains_the_entries_when_written(
    tmp_path,
):
    index = tmp_path / "change_index.sqlite"
    segments = night(index, "aaa", [("removed", POLE), ("added", BOX)], "2026-11-01")
    listing = run_query(index, fmt="json", transients=True)
    con = sqlite3.connect(index)
    con.executescript(
        "DROP TABLE object_json; DROP INDEX object_views_view;"
        " UPDATE meta SET value = '5' WHERE key = 'schema_version';"
    )
    con.close()
    before = index.read_bytes()
    assert run_query(index, fmt="json", transients=True) == listing
    same_as_the_listing(index)
    assert index.read_bytes() == before  # read as it is
    with ChangeIndex(index) as idx:
        assert idx.file_version == "6"
        assert idx.conn.execute("SELECT count(*) FROM object_json").fetchone()[0] == 0
        objects.rebuild_objects(idx, segments)
    assert len(kept_rows(index)) == 2
    assert run_query(index, fmt="json", transients=True) == listing
