"""Tile store ingest and reading (streetcd.store.tiles, streetcd ingest / tiles commands)."""

from __future__ import annotations

import json
import os
import re
import shutil
import struct
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from streetcd.cli.ingest import ingest as ingest_cmd
from streetcd.cli.ingest import tiles as tiles_cmd
from streetcd.errors import (
    CorruptFileError,
    InputError,
    MissingInputError,
    OptionalDependencyError,
    StoreLockedError,
)
from streetcd.io.las import read_las, write_las
from streetcd.io.readers import find_archive_files, get_reader
from streetcd.store import ingest as store_ingest
from streetcd.store import tiles as store_tiles
from streetcd.store.ingest import ingest
from streetcd.store.tiles import (
    TileCache,
    TileStore,
    _plain_codecs,
    chunk_count,
    chunk_file,
    read_chunk,
    tile_cache,
)
from streetcd.types import PointCloud

ORIGIN = np.array([634_000.0, 5_712_000.0, 40.0])  # CRS metres, 10⁵–10⁶ m
TILE = 15.0


def make_archive(
    root: Path, rng: np.random.Generator, n_files: int = 4, n: int = 3000, crs: str = "EPSG:32632"
) -> dict[str, np.ndarray]:
    """Files whose footprints overlap (so tiles get fragments from several files); returns
    all points as CRS integers in mm (N, 3) int64 with their gps_time ids."""
    xyz_all, ids = [], []
    for k in range(n_files):
        xyz = rng.uniform([k * 6.0, 0.0, 0.0], [k * 6.0 + 25.0, 27.0, 12.0], (n, 3))
        gps = np.arange(k * n, (k + 1) * n, dtype=np.float64)
        write_las(
            root / f"strip_{k}.laz",
            xyz,
            rng.integers(1, 12, n),
            origin=ORIGIN,
            intensity=rng.integers(0, 4000, n),
            rgb=rng.integers(0, 65535, (n, 3)),
            gps_time=gps,
            crs=crs,
        )
        xyz_all.append(read_las(root / f"strip_{k}.laz", origin=np.zeros(3)).xyz)
        ids.append(gps)
    return {
        "mm": np.rint(np.concatenate(xyz_all) * 1000).astype(np.int64),
        "ids": np.concatenate(ids),
    }


def all_points(store: TileStore) -> tuple[dict[str, PointCloud], np.ndarray, np.ndarray]:
    """Every tile's cloud, plus all points as CRS mm integers and their gps_time ids."""
    clouds = {tid: store.read_tile(tid, cache=False) for tid in store.tiles}
    xyz = np.concatenate([c.xyz for c in clouds.values()]) + store.origin
    ids = np.concatenate([c.gps_time for c in clouds.values()])
    return clouds, np.rint(xyz * 1000).astype(np.int64), ids


def assert_same_store(a: Path, b: Path) -> None:
    """Same tiles with the same points in the same order, and the same index contents."""
    sa, sb = TileStore.open(a), TileStore.open(b)
    assert sorted(sa.tiles) == sorted(sb.tiles)
    for tid in sa.tiles:
        ca, cb = sa.read_tile(tid, cache=False), sb.read_tile(tid, cache=False)
        for name in ("xyz", "classification", "intensity", "rgb", "gps_time"):
            np.testing.assert_array_equal(getattr(ca, name), getattr(cb, name))
        assert sa.tiles[tid] == sb.tiles[tid]
    assert _without_chunking(sa.files) == _without_chunking(sb.files)
    # Nothing uncommitted left on disk: one index generation, the listed sources' points.
    for s in (a, b):
        store = TileStore.open(s)
        points = {d.name for d in (s / "points").iterdir() if d.is_dir()}
        assert points == {key for _, key in store.sources}
        listed = {f.key for t in store.tiles.values() for f in t.fragments}
        assert points == listed
        generations = [d.name for d in (s / "index").iterdir() if d.is_dir()]
        assert generations == [f"g{store.index['generation']}"]
        assert not (s / "_staging").exists()


def _without_chunking(files: dict) -> dict:
    """File records less the chunk rows of their arrays (a resumed run may chunk otherwise)."""
    out = json.loads(json.dumps(files))
    for rec in out.values():
        for field in rec.get("arrays", {}).values():
            field.pop("chunk_rows")
    return out


def snapshot(root: Path) -> dict[str, tuple[bytes, int]]:
    return {
        str(p.relative_to(root)): (p.read_bytes(), p.stat().st_mtime_ns)
        for p in sorted(root.rglob("*"))
        if p.is_file()
    }


@pytest.fixture
def archive(tmp_path):
    rng = np.random.default_rng(7)
    d = tmp_path / "archive"
    truth = make_archive(d, rng)
    return d, truth


def test_every_point_lands_in_exactly_one_tile_whatever_the_file_order(archive, tmp_path):
    d, truth = archive
    at_once = ingest(
        d, tmp_path / "a.zarr", tile_size_m=TILE, chunk_points=1000, buffer_points=1500
    )
    assert at_once.ok and at_once.points == len(truth["ids"])
    for f in sorted(d.glob("*.laz"), reverse=True):  # one file per run, reverse order
        ingest(f, tmp_path / "b.zarr", tile_size_m=TILE, chunk_points=1000)
    for name in ("a.zarr", "b.zarr"):
        store = TileStore.open(tmp_path / name)
        clouds, mm, ids = all_points(store)
        assert len(ids) == len(truth["ids"]) == store.point_count
        np.testing.assert_array_equal(np.sort(ids), np.sort(truth["ids"]))  # none lost/duped
        order, t_order = np.argsort(ids), np.argsort(truth["ids"])
        np.testing.assert_array_equal(mm[order], truth["mm"][t_order])  # exact to the mm
        for tid, cloud in clouds.items():  # each point inside its own tile's square
            box = store.tiles[tid].box
            xy = cloud.xyz[:, :2] + store.origin[:2]
            assert np.all(xy >= np.array(box[:2]) - 1e-9) and np.all(xy < np.array(box[2:]))
            assert len(cloud) == store.tiles[tid].count
    a, b = TileStore.open(tmp_path / "a.zarr"), TileStore.open(tmp_path / "b.zarr")
    assert a.tiles.keys() == b.tiles.keys()
    for tid in a.tiles:
        assert sorted(a.read_tile(tid).gps_time) == sorted(b.read_tile(tid).gps_time)


def test_tiles_read_together_equal_tiles_read_one_by_one(archive, tmp_path, monkeypatch):
    # guards read_tiles, which decompresses each chunk once for all the tiles it serves and
    # cuts their runs out of it; 500-row chunks, so that runs straddle chunk borders
    d, truth = archive
    monkeypatch.setattr(store_ingest, "CHUNK_POINTS", 500)
    ingest(d, tmp_path / "s.zarr", tile_size_m=TILE, chunk_points=1000, workers=1)
    store = TileStore.open(tmp_path / "s.zarr")
    rows = store._source_arrays(0)["xyz"].chunks[0]
    runs = store._segments[:, 3:5].tolist()
    assert rows == 500 and any(s // rows != (s + n - 1) // rows for s, n in runs if n)
    tids = sorted(store.tiles)
    together = store.read_tiles(tids[::-1], cache=False)
    assert list(together) == tids[::-1]
    for tid in tids:
        one = store.read_tile(tid, cache=False)
        for name in ("xyz", "classification", "intensity", "rgb", "gps_time"):
            np.testing.assert_array_equal(getattr(together[tid], name), getattr(one, name))
    ids = np.concatenate([together[t].gps_time for t in tids])
    np.testing.assert_array_equal(np.sort(ids), np.sort(truth["ids"]))  # none lost or twice
    tile_cache().clear()
    cached = store.read_tiles(tids[:3])
    again = store.read_tiles(tids[:5])
    assert all(again[t] is cached[t] for t in tids[:3])  # served from the cache
    assert not again[tids[4]].xyz.flags.writeable  # shared: read-only
    with pytest.raises(MissingInputError, match="no tile"):
        store.read_tiles([tids[0], "999_999"])


def test_a_store_keeps_few_sources_open_and_reads_the_same(archive, tmp_path, monkeypatch):
    """The open sources are an LRU (a city's thousands are not all kept): with room for one,
    every tile reads the same points as with room for all, and one source stays open."""
    d, _ = archive
    ingest(d, tmp_path / "s.zarr", tile_size_m=TILE, chunk_points=1000)
    roomy = TileStore.open(tmp_path / "s.zarr")
    assert len(roomy.sources) > 1
    tids = sorted(roomy.tiles)
    want = roomy.read_tiles(tids, cache=False)
    monkeypatch.setattr(store_tiles, "SOURCES_OPEN", 1)
    tight = TileStore.open(tmp_path / "s.zarr")
    for tid in tids:  # one tile at a time, so sources are opened again and again
        got = tight.read_tiles([tid], cache=False)[tid]
        assert len(tight._arrays) == 1
        for name in ("xyz", "classification", "intensity", "rgb", "gps_time"):
            np.testing.assert_array_equal(getattr(got, name), getattr(want[tid], name))
    assert len(roomy._arrays) == len(roomy.sources)


def test_stored_xy_are_the_tile_readers_x_y_and_classes_to_the_bit(archive, tmp_path, monkeypatch):
    """read_stored_xy (the road test's read) gives each tile's stored integers, from which
    x · scale + offset is read_tile's local x and y exactly (the same float operations),
    with the same classes in the same order; runs straddle 500-row chunks; it opens only
    the two fields it reads."""
    d, _ = archive
    monkeypatch.setattr(store_ingest, "CHUNK_POINTS", 500)
    ingest(d, tmp_path / "s.zarr", tile_size_m=TILE, chunk_points=1000, workers=1)
    store = TileStore.open(tmp_path / "s.zarr")
    chunks: dict = {}
    for tid in sorted(store.tiles):
        got = store.read_stored_xy(tid, chunks)
        want = store.read_tile(tid, cache=False)
        assert got.x.dtype == got.y.dtype == np.int32
        np.testing.assert_array_equal(got.x * got.scale_m + got.offset[0], want.xyz[:, 0])
        np.testing.assert_array_equal(got.y * got.scale_m + got.offset[1], want.xyz[:, 1])
        np.testing.assert_array_equal(got.classification, want.classification)
    fresh = TileStore.open(tmp_path / "s.zarr")
    fresh.read_stored_xy(sorted(fresh.tiles)[0], {})
    assert {frozenset(a) for a in fresh._arrays.values()} == {frozenset({"xyz", "classification"})}


def test_a_corrupt_chunk_in_the_store_names_the_file_and_field(archive, tmp_path):
    d, _ = archive
    ingest(d, tmp_path / "s.zarr", tile_size_m=TILE, chunk_points=1000)
    store = TileStore.open(tmp_path / "s.zarr")
    path, key = store.sources[0]
    chunk = next(p for p in (tmp_path / "s.zarr" / "points" / key / "rgb").rglob("c/*/*"))
    # an overwritten chunk (truncated and bit-flipped ones: tests/test_bad_inputs.py; the
    # CRC-32C after Blosc catches them, which Blosc alone did not, numcodecs#228)
    chunk.write_bytes(b"not a blosc frame" * 8)
    with pytest.raises(CorruptFileError, match=rf"{Path(path).name}.*field 'rgb', chunk \d+"):
        store.read_tiles(sorted(store.tiles), cache=False)


def test_chunks_decoded_without_zarr_equal_zarrs_and_a_lying_header_is_damage(tmp_path):
    """read_chunk decodes the store's own codecs itself (zarr's pipeline cost ~2 ms a
    chunk): every chunk of arrays of the store's dtypes, the short last one included, as
    zarr reads it; a chunk whose checksum holds but whose Blosc header promises other sizes
    is damage."""
    import google_crc32c
    import zarr

    from streetcd.store.tiles import ARRAY_CONFIG, COMPRESSORS

    rng = np.random.default_rng(3)
    group = zarr.open_group(str(tmp_path / "g"), mode="w")
    arrays = {
        "xyz": rng.integers(-(2**31), 2**31 - 1, (2500, 3), dtype=np.int32),
        "classification": rng.integers(0, 256, 2500).astype(np.uint8),
        "rgb": rng.integers(0, 65536, (2500, 3)).astype(np.uint16),
        "gps_time": rng.uniform(0, 6e5, 2500),
    }
    for name, data in arrays.items():
        a = group.create_array(
            name, data=data, compressors=COMPRESSORS, chunks=(1000, *data.shape[1:]),
            config=ARRAY_CONFIG,
        )  # fmt: skip
        assert _plain_codecs(a)
        folder = tmp_path / "g" / name
        parts = [read_chunk(a, folder, c) for c in range(chunk_count(a))]
        assert [len(p) for p in parts] == [1000, 1000, 500]
        assert all(p.dtype == data.dtype for p in parts)
        np.testing.assert_array_equal(np.concatenate(parts), data)
    file = chunk_file(a, folder, 0)
    body = bytearray(file.read_bytes()[:-4])
    body[4:8] = (int.from_bytes(body[4:8], "little") + 8).to_bytes(4, "little")  # its nbytes
    file.write_bytes(bytes(body) + google_crc32c.value(bytes(body)).to_bytes(4, "little"))
    with pytest.raises(CorruptFileError, match=r"chunk 0 is damaged \(ValueError: Blosc header"):
        read_chunk(a, folder, 0)


def test_tile_index_holds_bounds_counts_classes_and_sources(archive, tmp_path):
    d, _ = archive
    ingest(d, tmp_path / "s.zarr", tile_size_m=TILE)
    store = TileStore.open(tmp_path / "s.zarr")
    for tile in store.tiles.values():
        cloud = store.read_tile(tile.id)
        xyz = cloud.xyz + store.origin
        np.testing.assert_allclose(tile.bounds, [*xyz.min(axis=0), *xyz.max(axis=0)], atol=1e-6)
        codes, counts = np.unique(cloud.classification, return_counts=True)
        assert tile.classes == dict(zip(codes.tolist(), counts.tolist(), strict=True))
        assert len(set(tile.sources)) == len(tile.sources) >= 1
    assert store.crs == "EPSG:32632"
    np.testing.assert_array_equal(store.origin, [634_000.0, 5_712_000.0, 0.0])


def test_bbox_lookup_equals_brute_force(archive, tmp_path):
    d, _ = archive
    ingest(d, tmp_path / "s.zarr", tile_size_m=TILE)
    store = TileStore.open(tmp_path / "s.zarr")
    rng = np.random.default_rng(3)
    for _ in range(50):
        lo = ORIGIN[:2] + rng.uniform(-20, 60, 2)
        hi = lo + rng.uniform(0, 40, 2)
        got = {t.id for t in store.tiles_in_bbox(lo[0], lo[1], hi[0], hi[1])}
        want = {
            t.id
            for t in store.tiles.values()
            if t.box[0] <= hi[0] and t.box[2] > lo[0] and t.box[1] <= hi[1] and t.box[3] > lo[1]
        }
        assert got == want


def test_parallel_ingest_equals_serial_ingest(archive, tmp_path):
    d, _ = archive
    seen = []
    r = ingest(
        d,
        tmp_path / "par.zarr",
        tile_size_m=TILE,
        workers=2,
        chunk_points=1000,
        progress=lambda done, total, name: seen.append((done, total)),
    )
    ingest(d, tmp_path / "ser.zarr", tile_size_m=TILE, workers=1)
    assert r.ok and len(r.ingested) == 4
    assert seen[-1][0] == seen[-1][1] == 12000  # chunk progress came back from the workers
    assert_same_store(tmp_path / "par.zarr", tmp_path / "ser.zarr")


def test_ingest_on_a_dask_cluster_equals_serial_ingest_and_records_bad_files(archive, tmp_path):
    from distributed import Client, LocalCluster

    d, _ = archive
    bad = tmp_path / "arch"
    shutil.copytree(d, bad)
    (bad / "broken.laz").write_bytes((d / sorted(os.listdir(d))[0]).read_bytes()[:2000])
    seen = []
    with (
        LocalCluster(n_workers=2, threads_per_worker=1, dashboard_address=None) as cluster,
        Client(cluster, set_as_default=False) as client,  # as the flow's client is
    ):
        r = ingest(
            bad,
            tmp_path / "dask.zarr",
            tile_size_m=TILE,
            client=client,
            progress=lambda done, total, name: seen.append((done, total)),
        )
    serial = ingest(bad, tmp_path / "ser.zarr", tile_size_m=TILE, workers=1)
    assert len(r.ingested) == 4 and list(r.failed) == [str(bad / "broken.laz")]
    assert r.failed == serial.failed
    assert "broken.laz" in r.failed[str(bad / "broken.laz")]
    assert seen[-1][0] == 12000  # every good file's points reported once it finished
    assert_same_store(tmp_path / "dask.zarr", tmp_path / "ser.zarr")


def test_reingest_changes_nothing(archive, tmp_path):
    d, _ = archive
    ingest(d, tmp_path / "s.zarr", tile_size_m=TILE)
    before = snapshot(tmp_path / "s.zarr")
    again = ingest(d, tmp_path / "s.zarr", tile_size_m=TILE)
    assert again.ingested == () and len(again.skipped) == 4 and again.points == 0
    assert snapshot(tmp_path / "s.zarr") == before


class Crash(Exception):
    pass


def test_crash_mid_file_then_resume_equals_clean_ingest(archive, tmp_path, monkeypatch):
    d, truth = archive
    monkeypatch.setattr(store_ingest, "CHUNK_POINTS", 500)  # small chunks: half a file gets written
    calls = []

    def crash_in_third_file(done, total, name):
        calls.append(name)
        if calls.count("strip_2.laz") == 2:  # second chunk of the third file
            assert any((tmp_path / "s.zarr" / "_staging").rglob("c/*"))  # chunks on disk
            raise Crash(name)

    with pytest.raises(Crash):
        ingest(
            d,
            tmp_path / "s.zarr",
            tile_size_m=TILE,
            chunk_points=1000,
            buffer_points=1500,
            progress=crash_in_third_file,
        )
    # Only the two committed files are visible, though strip_2 had fragments on disk.
    half = TileStore.open(tmp_path / "s.zarr")
    assert half.point_count == 6000
    assert sorted(Path(p).name for p in half.files) == ["strip_0.laz", "strip_1.laz"]
    resumed = ingest(d, tmp_path / "s.zarr", tile_size_m=TILE, chunk_points=1000)
    assert [Path(p).name for p in resumed.ingested] == ["strip_2.laz", "strip_3.laz"]
    ingest(d, tmp_path / "clean.zarr", tile_size_m=TILE)
    assert_same_store(tmp_path / "s.zarr", tmp_path / "clean.zarr")


def test_killed_process_mid_file_then_resume_equals_clean_ingest(archive, tmp_path):
    """A real SIGKILL (no cleanup, no finally) in the middle of the second file."""
    d, _ = archive
    script = textwrap.dedent(f"""
        import os, signal
        from streetcd.store import ingest as store_ingest
        from streetcd.store.ingest import ingest
        store_ingest.CHUNK_POINTS = 500  # small chunks: the file is half on disk when it dies
        n = 0
        def kill(done, total, name):
            global n
            n += 1
            if name == "strip_1.laz" and n > 4:
                os.kill(os.getpid(), signal.SIGKILL)
        ingest({str(d)!r}, {str(tmp_path / "s.zarr")!r}, tile_size_m={TILE}, chunk_points=1000,
               buffer_points=1500, progress=kill)
    """)
    proc = subprocess.run([sys.executable, "-c", script], capture_output=True, timeout=120)
    assert proc.returncode == -9, proc.stderr.decode()
    assert any((tmp_path / "s.zarr" / "_staging").iterdir())  # it really died mid-file
    assert TileStore.open(tmp_path / "s.zarr").point_count == 3000
    ingest(d, tmp_path / "s.zarr", tile_size_m=TILE)
    ingest(d, tmp_path / "clean.zarr", tile_size_m=TILE)
    assert_same_store(tmp_path / "s.zarr", tmp_path / "clean.zarr")


def test_changed_file_replaces_its_points(archive, tmp_path):
    d, _ = archive
    ingest(d, tmp_path / "s.zarr", tile_size_m=TILE)
    rng = np.random.default_rng(11)
    xyz = rng.uniform([30, 30, 0], [45, 40, 5], (500, 3))  # moved to other tiles
    write_las(
        d / "strip_1.laz",
        xyz,
        np.full(500, 6),
        origin=ORIGIN,
        gps_time=np.arange(500.0),
        crs="EPSG:32632",
    )
    os.utime(d / "strip_1.laz", ns=(1, 1_700_000_000_000_000_000))
    r = ingest(d, tmp_path / "s.zarr", tile_size_m=TILE)
    assert [Path(p).name for p in r.ingested] == ["strip_1.laz"]
    ingest(d, tmp_path / "clean.zarr", tile_size_m=TILE)
    assert_same_store(tmp_path / "s.zarr", tmp_path / "clean.zarr")
    assert TileStore.open(tmp_path / "s.zarr").point_count == 9500


def test_second_ingest_into_a_locked_store_fails_at_once(archive, tmp_path):
    d, _ = archive
    store = tmp_path / "s.zarr"
    ingest(d / "strip_0.laz", store, tile_size_m=TILE)
    with store_ingest._store_lock(store):  # what a running ingest holds
        with pytest.raises(StoreLockedError, match="another ingest is writing"):
            ingest(d, store, tile_size_m=TILE)
    assert TileStore.open(store).point_count == 3000  # the refused run wrote nothing
    r = ingest(d, store, tile_size_m=TILE)  # the lock went with its holder
    assert len(r.ingested) == 3


def test_removed_file_keeps_its_points_unless_pruned(archive, tmp_path):
    d, _ = archive
    store = tmp_path / "s.zarr"
    ingest(d, store, tile_size_m=TILE)
    gone = d / "strip_1.laz"
    gone.unlink()
    kept = ingest(d, store, tile_size_m=TILE)
    assert kept.pruned == () and TileStore.open(store).point_count == 12000
    r = ingest(d, store, tile_size_m=TILE, prune=True)
    assert r.pruned == (str(gone),) and r.ingested == ()
    assert (
        TileStore.open(store).point_count == 9000 and str(gone) not in TileStore.open(store).files
    )
    ingest(d, tmp_path / "clean.zarr", tile_size_m=TILE)
    assert_same_store(store, tmp_path / "clean.zarr")


def test_store_objects_do_not_grow_with_the_tile_count(tmp_path):
    """Regression: a zarr group of arrays per tile and file made 10,000 tiles take minutes.
    A file's points are now one array per field, whatever the number of tiles it covers."""
    rng = np.random.default_rng(2)
    n_objects = []
    for n_tiles in (4, 400):
        side = int(np.sqrt(n_tiles))
        cell = np.arange(2000) % n_tiles  # every tile gets points
        xy = np.column_stack([cell // side, cell % side]) + rng.uniform(0.1, 0.9, (2000, 2))
        xyz = np.column_stack([xy, rng.uniform(0, 5, 2000)])
        f = write_las(
            tmp_path / f"a{n_tiles}" / "f.laz",
            xyz,
            np.full(2000, 2),
            origin=ORIGIN,
            crs="EPSG:32632",
        )
        store = tmp_path / f"s{n_tiles}.zarr"
        ingest(f, store, tile_size_m=1.0)
        assert len(TileStore.open(store)) == n_tiles
        n_objects.append(sum(1 for p in store.rglob("*") if p.is_file()))
    assert n_objects[0] == n_objects[1]


def test_tile_lookup_by_id_and_unknown_ids(archive, tmp_path):
    d, _ = archive
    ingest(d, tmp_path / "s.zarr", tile_size_m=TILE)
    store = TileStore.open(tmp_path / "s.zarr")
    ids = list(store.tiles)
    assert ids == sorted(ids, key=lambda t: tuple(int(v) for v in t.split("_")))
    for tid in ids:
        assert store.tiles[tid].id == tid and tid in store.tiles
    for bad in ("nope", "1_2_3", "99999_99999", f"{2**40}_0"):
        assert bad not in store.tiles and store.tiles.get(bad) is None


def _nan_offset(path: Path) -> None:
    data = bytearray(path.read_bytes())
    data[163:171] = struct.pack("<d", float("nan"))  # LAS header: Y offset
    path.write_bytes(bytes(data))


def test_bad_files_fail_by_name_and_good_files_still_complete(archive, tmp_path):
    d, truth = archive
    rng = np.random.default_rng(5)
    cut = write_las(
        d / "cut.laz",
        rng.uniform(0, 20, (20000, 3)),
        np.full(20000, 2),
        origin=ORIGIN,
        crs="EPSG:32632",
    )
    cut.write_bytes(cut.read_bytes()[: cut.stat().st_size // 2])
    write_las(d / "empty.laz", np.zeros((0, 3)), np.zeros(0), crs="EPSG:32632")
    (d / "zero.laz").write_bytes(b"")
    _nan_offset(
        write_las(
            d / "nan.las",
            rng.uniform(0, 20, (50, 3)),
            np.full(50, 2),
            origin=ORIGIN,
            crs="EPSG:32632",
        )
    )
    write_las(
        d / "other_crs.laz",
        rng.uniform(0, 20, (50, 3)),
        np.full(50, 2),
        origin=ORIGIN,
        crs="EPSG:25832",
    )
    seen = []
    r = ingest(
        d,
        tmp_path / "s.zarr",
        tile_size_m=TILE,
        chunk_points=4000,
        progress=lambda done, total, name: seen.append((done, total)),
    )
    assert seen[-1][0] == seen[-1][1]  # the bar ends at 100 %, the half-read cut.laz included
    expected = {
        "cut.laz": "CorruptFileError",
        "empty.laz": "InputError",
        "zero.laz": "CorruptFileError",
        "nan.las": "InputError",
        "other_crs.laz": "CRSMismatchError",
    }
    assert {Path(p).name for p in r.failed} == set(expected)
    for path, message in r.failed.items():
        assert Path(path).name in message
    assert "EPSG:25832" in r.failed[str(d / "other_crs.laz")]
    store = TileStore.open(tmp_path / "s.zarr")
    assert store.point_count == len(truth["ids"])  # the good files all went in
    for path, rec in store.files.items():
        name = Path(path).name
        assert rec["status"] == ("failed" if name in expected else "done")
        if name in expected:
            assert rec["error_type"] == expected[name] and name in rec["error"]
    assert not (tmp_path / "s.zarr" / "_staging").exists()  # cut.laz's partial output gone


def test_existing_directory_that_is_not_a_store_is_refused(archive, tmp_path):
    d, _ = archive
    (tmp_path / "precious").mkdir()
    (tmp_path / "precious" / "notes.txt").write_text("keep me")
    with pytest.raises(InputError, match="not a streetcd tile store"):
        ingest(d, tmp_path / "precious")
    assert (tmp_path / "precious" / "notes.txt").read_text() == "keep me"


def test_store_settings_cannot_change(archive, tmp_path):
    d, _ = archive
    ingest(d, tmp_path / "s.zarr", tile_size_m=TILE)
    with pytest.raises(InputError, match="tile_size_m=15.0"):
        ingest(d, tmp_path / "s.zarr", tile_size_m=50.0)


def test_archive_as_glob_and_directory(archive):
    d, _ = archive
    assert find_archive_files(d) == find_archive_files(str(d / "strip_*.laz"))
    assert len(find_archive_files(d)) == 4


def test_tile_cache_is_bounded_by_bytes():
    def cloud(n):
        return PointCloud(np.zeros((n, 3)), np.zeros(3), np.zeros(n, np.uint8))

    cache = TileCache(max_bytes=3 * 25 * 100)  # three clouds of 100 points (25 B each)
    for k in range(4):
        cache.put(("s", k), cloud(100))
    assert cache.get(("s", 0)) is None and cache.get(("s", 3)) is not None
    assert cache.bytes <= cache.max_bytes
    cache.get(("s", 1))  # touch 1: 2 is now the least recently used
    cache.put(("s", 4), cloud(100))
    assert cache.get(("s", 2)) is None and cache.get(("s", 1)) is not None


@pytest.mark.parametrize("value", ["1GB", "-5", "nan", "inf", ""])
def test_bad_tile_cache_size_is_one_input_error_at_first_use(monkeypatch, value):
    # guards the lazy process-wide cache: a bad STREETCD_TILE_CACHE_MB was a bare ValueError
    # at import of the store modules
    monkeypatch.setenv("STREETCD_TILE_CACHE_MB", value)
    monkeypatch.setattr(store_tiles, "_TILE_CACHE", None)  # this process's cache: not made yet
    with pytest.raises(InputError) as err:
        tile_cache()
    message = str(err.value)
    assert "\n" not in message
    assert "STREETCD_TILE_CACHE_MB" in message and repr(value) in message


def test_bad_tile_cache_size_does_not_break_import():
    env = {**os.environ, "STREETCD_TILE_CACHE_MB": "1GB"}
    script = "import streetcd.store.crop, streetcd.store.ingest, streetcd.store.tiles"
    proc = subprocess.run([sys.executable, "-c", script], env=env, capture_output=True, timeout=120)
    assert proc.returncode == 0, proc.stderr.decode()


def test_tile_cache_is_made_once_with_the_size_asked_for(monkeypatch):
    monkeypatch.setenv("STREETCD_TILE_CACHE_MB", "0.5")
    monkeypatch.setattr(store_tiles, "_TILE_CACHE", None)
    cache = tile_cache()
    assert cache.max_bytes == 2**19 and tile_cache() is cache


def test_pdal_missing_gives_one_clear_line(monkeypatch):
    monkeypatch.setitem(sys.modules, "pdal", None)  # what an environment without pdal sees
    with pytest.raises(OptionalDependencyError) as err:
        get_reader("pdal")
    message = str(err.value)
    assert "\n" not in message and "pip install streetcd[pdal]" in message
    assert "PDAL C++ library" in message


def test_pdal_reader_equals_laspy_reader(archive, tmp_path):
    pytest.importorskip("pdal", reason="PDAL (C++ library + python bindings) not installed")
    d, _ = archive
    ingest(d, tmp_path / "pdal.zarr", tile_size_m=TILE, reader=get_reader("pdal"))
    ingest(d, tmp_path / "laspy.zarr", tile_size_m=TILE)
    a, b = TileStore.open(tmp_path / "pdal.zarr"), TileStore.open(tmp_path / "laspy.zarr")
    assert a.tiles.keys() == b.tiles.keys()
    for tid in a.tiles:
        np.testing.assert_array_equal(a.read_tile(tid).xyz, b.read_tile(tid).xyz)


def test_cli_ingest_and_tiles_json(archive, tmp_path):
    d, truth = archive
    (d / "zero.laz").write_bytes(b"")
    runner = CliRunner()
    store = tmp_path / "s.zarr"
    r = runner.invoke(
        ingest_cmd,
        ["--archive", str(d), "--store", str(store), "--tile-size", "15", "--workers", "1"],
    )
    assert r.exit_code == 1, r.output  # a file failed: reported, the rest ingested
    assert "zero.laz" in r.output and "4 files ingested" in r.output
    r = runner.invoke(tiles_cmd, [str(store), "--json"])
    assert r.exit_code == 0, r.output
    doc = json.loads(r.output)
    assert sum(t["count"] for t in doc["tiles"]) == len(truth["ids"])
    for t in doc["tiles"]:
        assert {"id", "bounds", "count", "classes", "sources"} <= set(t)
        assert len(t["bounds"]) == 6 and t["sources"]
    r = runner.invoke(tiles_cmd, [str(store)])
    assert r.exit_code == 0 and "failed file" in r.output


def test_cli_pipeline_needs_pdal_reader(archive, tmp_path):
    d, _ = archive
    r = CliRunner().invoke(
        ingest_cmd,
        [
            "--archive",
            str(d),
            "--store",
            str(tmp_path / "s"),
            "--pipeline",
            str(tmp_path / "p.json"),
        ],
    )
    assert r.exit_code != 0 and "needs --reader pdal" in r.output


@pytest.mark.slow
def test_views_that_failed_on_a_damaged_store_are_redone_once_it_is_repaired(small_city, tmp_path):
    """The issue's deleted chunk, end to end: the views that need it fail with one line
    naming the tile (not zeros read as a street), the failure is in the index, a rerun on the
    still-damaged store does not take it for done, and after ``ingest --recheck`` a rerun
    redoes them and the index holds what a run on the sound store holds."""
    from streetcd.run.cluster import dask_client
    from streetcd.run.night import NightInputs, run_night
    from streetcd.run.plan import plan_run
    from streetcd.store.index import ChangeIndex, canonical_dump

    def night(client, store, index, out):
        inputs = NightInputs(
            str(small_city.images), str(small_city.poses), str(store), str(index), str(out)
        )
        return run_night(inputs, client=client)

    def results(index):  # the dump less the input hashes (a repaired source has a new key)
        return [
            " ".join(
                t for k, t in enumerate(line.split(" ")) if not (line[:5] == "view " and k == 2)
            )
            for line in canonical_dump(index)
        ]

    store = tmp_path / "store.zarr"
    shutil.copytree(small_city.store, store)
    sound = TileStore.open(store)
    for _, key in sound.sources:  # the first xyz chunk of every source
        (store / "points" / key / "xyz" / "c" / "0" / "0").unlink()
    index = tmp_path / "change_index.sqlite"
    with dask_client(workers=2) as client:
        night(client, small_city.store, tmp_path / "clean.sqlite", tmp_path / "clean")
        night(client, store, index, tmp_path / "out")
        with ChangeIndex(index, create=False) as idx:
            failed = dict(idx.failures())
        assert failed, "no view needed the damaged chunks"
        for message in failed.values():
            assert "\n" not in message
            assert re.search(
                r"tile -?\d+_-?\d+: points of .*field 'xyz', chunk 0 is missing", message
            )
        again = plan_run(small_city.images, small_city.poses, store, index, tmp_path / "out")
        assert again.n_todo == 0  # failed with the same inputs: recorded, not retried blindly
        repaired = ingest(small_city.manifest.parent / "cloud", store, recheck=True)
        assert repaired.ok and len(repaired.ingested) == len(sound.sources)
        plan = plan_run(small_city.images, small_city.poses, store, index, tmp_path / "out")
        names = {v.split("#", 1)[0] for v in failed}  # the index may suffix a view's name
        assert names <= {t.view.name for b in plan.batches for t in b.tasks}
        night(client, store, index, tmp_path / "out")
    with ChangeIndex(index, create=False) as idx:
        assert not idx.failures()
    assert results(index) == results(tmp_path / "clean.sqlite")
