"""The change index: schema, idempotent batch writes, rollback, R*Trees, canonical dumps."""

import dataclasses
import os
import sqlite3

import numpy as np
import pytest

from streetcd.errors import CRSMismatchError, InputError, MissingInputError
from streetcd.run.segments import Segment
from streetcd.store.index import SCHEMA_VERSION, ChangeIndex, canonical_dump
from streetcd.store.records import RegionRecord, ViewRecord

E0, N0 = 372_000.0, 143_000.0


def segment(name, x0, n=3):
    poly = np.array([[E0 + x0 + 4 * i, N0] for i in range(n)])
    return Segment(
        f"{name}-0123456789",
        tuple(f"{name}_{i}.jpg" for i in range(n)),
        tuple(() for _ in range(n)),
        poly,
        (poly[:, 0].min() - 15, N0 - 15, poly[:, 0].max() + 15, N0 + 15),
        float(4 * (n - 1)),
    )


def region(label, x, score=0.8):
    return RegionRecord(
        label, 500, score, (x, N0 + 10, 101.0), (x - 1, N0 + 9, 100.0), (x + 1, N0 + 11, 102.5), 64
    )


def flagged(view, seg, x, score=0.8, regions=1):
    return ViewRecord(
        view,
        "in1",
        "p1",
        seg,
        "done",
        flagged=True,
        score=score,
        changed_fraction=0.05,
        regions=tuple(region(k + 1, x + 3 * k, score) for k in range(regions)),
        mask_path=f"/out/masks/{seg}/{view}.mask.png",
        center=(x, N0, 101.8),
        detect_s=1.0,
        total_s=1.2,
    )


def quiet(view, seg, x):
    return ViewRecord(view, "in1", "p1", seg, "done", center=(x, N0, 101.8), detect_s=1.0)


@pytest.fixture
def idx(tmp_path):
    with ChangeIndex(tmp_path / "change_index.sqlite") as index:
        index.set_crs("EPSG:32648")
        index.add_segments([segment("a", 0), segment("b", 100)], run_id="r1")
        index.begin_run("r1", "p1")
        yield index


def test_schema_is_wal_with_rtrees(idx):
    assert idx.conn.execute("PRAGMA journal_mode").fetchone()[0] == "wal"
    names = {r[0] for r in idx.conn.execute("SELECT name FROM sqlite_master")}
    assert {
        "runs",
        "segments",
        "views",
        "flagged",
        "regions",
        "segments_rtree",
        "regions_rtree",
    } <= names
    assert idx.counts()["segments"] == 2
    assert idx.conn.execute("SELECT count(*) FROM segments_rtree").fetchone()[0] == 2


def test_only_flagged_views_are_listed(idx):
    idx.publish(
        "r1",
        [
            flagged("a_0.jpg", "a-0123456789", E0),
            quiet("a_1.jpg", "a-0123456789", E0 + 4),
            ViewRecord(
                "a_2.jpg",
                "in1",
                "p1",
                "a-0123456789",
                "failed",
                error="CorruptFileError: a_2.jpg: cannot be decoded",
            ),
        ],
    )
    assert idx.counts() == {
        "views": 3,
        "done": 2,
        "failed": 1,
        "flagged": 1,
        "regions": 1,
        "segments": 2,
    }
    assert [r.view for r in idx.query()] == ["a_0.jpg"]
    assert idx.failures() == [("a_2.jpg", "CorruptFileError: a_2.jpg: cannot be decoded")]


def test_publishing_twice_changes_nothing(idx, tmp_path):
    batch = [
        flagged("a_0.jpg", "a-0123456789", E0, regions=2),
        quiet("a_1.jpg", "a-0123456789", E0 + 4),
    ]
    idx.publish("r1", batch)
    before = canonical_dump(idx.path)
    idx.publish("r2", batch)
    assert canonical_dump(idx.path) == before
    assert idx.conn.execute("SELECT count(*) FROM regions_rtree").fetchone()[0] == 2


def test_a_new_result_replaces_the_old_one(idx):
    idx.publish("r1", [flagged("a_0.jpg", "a-0123456789", E0, regions=3)])
    idx.publish("r2", [quiet("a_0.jpg", "a-0123456789", E0)])
    assert idx.counts()["flagged"] == 0 and idx.counts()["regions"] == 0
    assert idx.conn.execute("SELECT count(*) FROM regions_rtree").fetchone()[0] == 0


def test_a_failing_batch_leaves_nothing(idx):
    good = flagged("a_0.jpg", "a-0123456789", E0)
    bad = ViewRecord(
        "a_1.jpg", "in1", "p1", "a-0123456789", "done", flagged=True, score=float("nan"), regions=()
    )  # NaN score violates NOT NULL
    with pytest.raises(sqlite3.IntegrityError):
        idx.publish("r1", [good, bad])
    assert idx.counts()["views"] == 0 and idx.counts()["flagged"] == 0


def test_unlocated_regions_are_kept_but_not_in_the_rtree(idx):
    r = ViewRecord(
        "a_0.jpg",
        "in1",
        "p1",
        "a-0123456789",
        "done",
        flagged=True,
        score=0.7,
        changed_fraction=0.01,
        regions=(RegionRecord(1, 40, 0.7, None, None, None, 0), region(2, E0)),
        center=(E0, N0, 101.8),
    )
    idx.publish("r1", [r])
    (row,) = idx.query()
    assert [g.located for g in row.regions] == [False, True]
    assert idx.conn.execute("SELECT count(*) FROM regions_rtree").fetchone()[0] == 1


def test_canonical_dump_ignores_run_ids_times_and_mask_folders(tmp_path):
    dumps = []
    for k, order in enumerate(([0, 1, 2], [2, 0, 1])):
        with ChangeIndex(tmp_path / f"i{k}.sqlite") as idx:
            idx.add_segments([segment("a", 0)], run_id=f"run{k}")
            recs = [flagged(f"a_{i}.jpg", "a-0123456789", E0 + 4 * i, regions=i) for i in range(3)]
            for i in order:  # another publishing order gives other row ids
                r = recs[i]
                idx.publish(
                    f"run{k}-{i}",
                    [r.__class__(**{**r.__dict__, "mask_path": f"/tmp/out{k}/{r.view}.png"})],
                )
        dumps.append(canonical_dump(tmp_path / f"i{k}.sqlite"))
    assert dumps[0] == dumps[1]
    with ChangeIndex(tmp_path / "i1.sqlite") as idx:
        idx.publish("x", [flagged("a_0.jpg", "a-0123456789", E0, score=0.81)])
    assert canonical_dump(tmp_path / "i1.sqlite") != dumps[0]


def test_crs_is_checked(idx):
    idx.set_crs("EPSG:32648")
    with pytest.raises(CRSMismatchError, match="EPSG:2056"):
        idx.set_crs("EPSG:2056")


def test_runs_are_recorded(idx):
    idx.finish_run("r1", n_planned=3, n_done=2, n_failed=1, n_flagged=1, n_skipped=0)
    row = idx.conn.execute("SELECT status, n_done, finished_at FROM runs").fetchone()
    assert row[0] == "finished" and row[1] == 2 and row[2].endswith("Z")


def test_opening_what_is_not_an_index_says_so(tmp_path):
    with pytest.raises(MissingInputError, match="nope.sqlite"):
        ChangeIndex(tmp_path / "nope.sqlite", create=False)
    (tmp_path / "junk.sqlite").write_bytes(b"not a database at all" * 100)
    with pytest.raises(InputError, match="junk.sqlite"):
        ChangeIndex(tmp_path / "junk.sqlite")


# --- the run lock ---------------------------------------------------------------------------

HOLD_LOCK = """
import sys, time
from streetcd.store.locks import run_lock
with run_lock(sys.argv[1], "the holder of this test"):
    print("locked", flush=True)
    time.sleep(120)
"""


def test_a_second_run_fails_fast_naming_the_holder_and_a_killed_holder_leaves_no_lock(tmp_path):
    import os
    import signal
    import socket
    import subprocess
    import sys

    from streetcd.errors import IndexBusyError
    from streetcd.store.locks import lock_path, run_lock

    index = tmp_path / "change_index.sqlite"
    holder = subprocess.Popen(
        [sys.executable, "-c", HOLD_LOCK, str(index)], stdout=subprocess.PIPE, text=True
    )
    try:
        assert holder.stdout is not None and holder.stdout.readline().strip() == "locked"
        with pytest.raises(IndexBusyError) as caught, run_lock(index):
            pass
        message = str(caught.value)
        assert str(index) in message and "the holder of this test" in message
        assert f"process {holder.pid} on {socket.gethostname()}" in message
        assert isinstance(caught.value, RuntimeError)
    finally:
        os.kill(holder.pid, signal.SIGKILL)  # no clean-up in the holder: the kernel frees it
        holder.wait(timeout=30)
        holder.stdout.close()
    with run_lock(index, "the next run") as path:
        assert path == lock_path(index)
        assert "the next run" in path.read_text()
    assert path.read_text() == ""  # released: nothing claims to hold it


def test_the_lock_also_keeps_out_a_second_run_of_the_same_process(tmp_path):
    from streetcd.errors import IndexBusyError
    from streetcd.store.locks import run_lock

    index = tmp_path / "change_index.sqlite"
    with run_lock(index, "first"):
        with pytest.raises(IndexBusyError, match=f"first, process {os.getpid()}"), run_lock(index):
            pass
    with run_lock(index):
        pass


def test_a_schema_4_index_is_read_as_it_is_and_migrated_when_written(tmp_path):
    """Schema 5 adds regions.depth_fraction: a reader never asks for it, so a schema-4 file
    is read untouched; opened for writing it gains the column (NULL: not measured)."""
    path = tmp_path / "change_index.sqlite"
    region = RegionRecord(1, 10, 0.5, (1.0, 2.0, 3.0), (0.0, 1.0, 2.0), (2.0, 3.0, 4.0), 6)
    flagged = ViewRecord("a.jpg", "h", "p", None, "done", flagged=True, score=0.5)
    with ChangeIndex(path) as idx:
        idx.publish("r", [dataclasses.replace(flagged, regions=(region,))])
    con = sqlite3.connect(path)
    con.executescript(
        "ALTER TABLE regions DROP COLUMN depth_fraction;"
        " UPDATE meta SET value = '4' WHERE key = 'schema_version';"
    )
    con.close()
    before = path.read_bytes()
    with ChangeIndex(path, readonly=True) as idx:
        (row,) = idx.query()
        assert row.regions == (region,)
    assert path.read_bytes() == before
    with ChangeIndex(path) as idx:
        assert idx.conn.execute("SELECT depth_fraction FROM regions").fetchall()[0][0] is None
        idx.publish(
            "r2",
            [
                dataclasses.replace(
                    flagged,
                    view="b.jpg",
                    regions=(dataclasses.replace(region, depth_fraction=0.5),),
                )
            ],
        )
        got = idx.conn.execute("SELECT depth_fraction FROM regions ORDER BY id").fetchall()
        assert [g[0] for g in got] == [None, 0.5]
        assert [r.regions[0].depth_fraction for r in idx.query()] == [None, 0.5]
    with ChangeIndex(path, readonly=True) as idx:
        assert idx._meta("schema_version") == SCHEMA_VERSION == "6"


def test_an_index_of_an_older_schema_is_refused_and_left_untouched(tmp_path):
    path = tmp_path / "change_index.sqlite"
    with ChangeIndex(path) as idx:
        idx.publish("r", [ViewRecord("a.jpg", "h", "p", None, "done", flagged=True, score=0.5)])
    # What a schema-3 index looked like: views keyed by bare name, no change objects.
    con = sqlite3.connect(path)
    con.executescript(
        "DROP TABLE objects; DROP TABLE object_views; DROP TABLE reviews;"
        " UPDATE meta SET value = '3' WHERE key = 'schema_version';"
    )
    con.close()
    before = path.read_bytes()
    for kwargs in ({}, {"create": False}, {"readonly": True}):
        with pytest.raises(InputError, match="schema_version 3 keys views by bare file name"):
            ChangeIndex(path, **kwargs)
    assert path.read_bytes() == before
    con = sqlite3.connect(path)
    assert con.execute("SELECT count(*) FROM sqlite_master WHERE name = 'objects'").fetchone() == (
        0,
    )
    con.close()


def test_a_migration_finds_a_column_already_there(tmp_path):
    """A file whose version says 4 but which has schema 5's column (its version set back by
    hand) is brought to this schema, not refused with "duplicate column name"."""
    path = tmp_path / "change_index.sqlite"
    with ChangeIndex(path) as idx:
        idx.publish("r", [ViewRecord("a.jpg", "h", "p", None, "done", flagged=True, score=0.5)])
    con = sqlite3.connect(path)
    con.executescript("UPDATE meta SET value = '4' WHERE key = 'schema_version';")
    con.close()
    with ChangeIndex(path) as idx:
        assert idx._meta("schema_version") == SCHEMA_VERSION
        assert [r.view for r in idx.query()] == ["a.jpg"]
