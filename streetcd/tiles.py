"""The MLS archive as a zarr v3 tile store: ingest (streamed, resumable, parallel) and reading.

Layout of ``STORE.zarr`` (one zarr v3 hierarchy)::

    zarr.json                    root group; attribute ``streetcd_tiles`` = the tile index
    tiles/<i>_<j>/               one group per ground tile: i = ⌊X / tile_size⌋, j = ⌊Y / tile_size⌋
    tiles/<i>_<j>/<key>/         one fragment per (tile, source file version), arrays:
        xyz             (N, 3) int32   round((X_crs − corner) / scale), corner = (i·ts, j·ts, 0)
        classification  (N,) uint8
        intensity       (N,) uint16    when the source has it (LAS always does)
        rgb             (N, 3) uint16  when present
        gps_time        (N,) float64   when present
    _staging/<key>/<i>_<j>/      fragments of a file being ingested; moved under tiles/ on commit

**Coordinates** are int32 at the store scale (1 mm by default) relative to the tile corner: a
50 m tile spans 0…50 000 units, z (CRS heights) fits ±2 147 km, and the tile grid is anchored
at CRS (0, 0), so a tile's content does not depend on which file came first. Measured on
scan-like MLS points (see benchmarks/ingest.py, ``--compare-coords``): int32 + Blosc-zstd stores
xyz in about a third of the bytes of local float64 and decodes faster; the quantisation error
(≤ 0.5 mm) is below the 1 mm scale every MLS archive is delivered at.

**Visibility and resumability.** The index (root attribute, rewritten atomically by zarr for
each committed file) is the only thing readers trust: a fragment exists for a reader only
once the index lists it. A worker writes a file's fragments under ``_staging/<key>``; the
single committing process then renames them into ``tiles/`` and writes the index. A crash at
any point leaves either the old index (the file is re-ingested next time; stray directories
are swept at the start of the next ingest) or the new one. The fragment key hashes the file's
absolute path, size and mtime, so a changed file gets new fragments and the old ones go only
after the new index is written. Files already in the index with the same size and mtime are
skipped; re-ingesting an unchanged archive writes nothing. One ingest at a time per store.
"""

from __future__ import annotations

import functools
import glob
import hashlib
import math
import multiprocessing
import os
import queue as queue_mod
import shutil
import threading
import time
from collections import OrderedDict
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

import numpy as np
import zarr
from zarr.codecs import BloscCodec

from streetcd.errors import CRSMismatchError, InputError, MissingInputError, StreetcdError
from streetcd.io.las import LasInfo, PointCloud, iter_las_chunks, las_info

FORMAT = "streetcd-tiles/1"
INDEX_ATTR = "streetcd_tiles"
LAS_SUFFIXES = (".las", ".laz")
FRAGMENT_CHUNK_POINTS = 262_144  # points per zarr chunk along the point axis
_COMPRESSOR = BloscCodec(cname="zstd", clevel=1, shuffle="shuffle")  # = clevel 3's size, faster
_INT32_MAX = 2**31 - 1

# progress(points_done, points_total, message): called from the process that runs ingest().
Progress = Callable[[int, int, str], None]


# --- readers -----------------------------------------------------------------------------


class PointReader(Protocol):
    """How ingest reads one source file: its header, then its points in chunks.

    ``chunks`` yields :class:`PointCloud` with CRS coordinates (origin zeros) in float64.
    Implementations must be picklable (they travel to worker processes).
    """

    name: str

    def info(self, path: Path) -> LasInfo: ...

    def chunks(self, path: Path, chunk_points: int) -> Iterator[PointCloud]: ...


class LaspyReader:
    """LAS/LAZ through laspy's chunked reader (lazrs backend for LAZ)."""

    name = "laspy"

    def info(self, path: Path) -> LasInfo:
        return las_info(path)

    def chunks(self, path: Path, chunk_points: int) -> Iterator[PointCloud]:
        return iter_las_chunks(path, chunk_points, origin=np.zeros(3))


def get_reader(name: str = "laspy", pipeline: str | Path | None = None) -> PointReader:
    """The reader called ``name`` ("laspy" or "pdal"); ``pipeline`` is a PDAL pipeline JSON."""
    if name == "laspy":
        if pipeline is not None:
            raise InputError(f"--pipeline {pipeline} needs --reader pdal (reader is {name!r})")
        return LaspyReader()
    if name == "pdal":
        from streetcd.io.pdal_reader import PdalReader

        return PdalReader.from_file(pipeline) if pipeline is not None else PdalReader()
    raise InputError(f"unknown reader {name!r}; choose 'laspy' or 'pdal'")


def find_archive_files(archive: str | Path | Sequence[str | Path]) -> list[Path]:
    """LAS/LAZ files of an archive: a directory (searched recursively), a glob pattern, a
    single file, or a list of files. Sorted absolute paths; MissingInputError if none."""
    if isinstance(archive, (list, tuple)):
        paths = [Path(p) for p in archive]
        for p in paths:
            if not p.is_file():
                raise MissingInputError(f"point cloud file not found: {p}")
    else:
        a = Path(str(archive))
        if a.is_dir():
            paths = [p for p in a.rglob("*") if p.is_file() and p.suffix.lower() in LAS_SUFFIXES]
        elif a.is_file():
            paths = [a]
        else:
            paths = [Path(p) for p in glob.glob(str(archive), recursive=True)]
            paths = [p for p in paths if p.is_file()]
    paths = sorted({p.resolve() for p in paths if not p.name.startswith(".")})
    if not paths:
        raise MissingInputError(f"no LAS/LAZ files in archive {archive}")
    return paths


# --- the index ---------------------------------------------------------------------------


@dataclass(frozen=True)
class Fragment:
    """One source file's points in one tile."""

    key: str
    source: str
    count: int


@dataclass(frozen=True)
class TileInfo:
    """One ground tile as the index describes it.

    bounds : (minx, miny, minz, maxx, maxy, maxz) float, metres in the CRS, of its points.
    box : (minx, miny, maxx, maxy), the tile square in the CRS.
    classes : class code → point count.
    """

    id: str
    i: int
    j: int
    count: int
    bounds: tuple[float, float, float, float, float, float]
    box: tuple[float, float, float, float]
    classes: dict[int, int]
    fragments: tuple[Fragment, ...]

    @property
    def sources(self) -> list[str]:
        return [f.source for f in self.fragments]

    def to_json(self) -> dict[str, Any]:
        return {
            "id": self.id,
            "i": self.i,
            "j": self.j,
            "bounds": list(self.bounds),
            "box": list(self.box),
            "count": self.count,
            "classes": {str(k): v for k, v in sorted(self.classes.items())},
            "sources": self.sources,
        }


def tile_id(i: int, j: int) -> str:
    return f"{i}_{j}"


def _empty_index(
    tile_size_m: float, scale_m: float, origin: np.ndarray, crs: str | None
) -> dict[str, Any]:
    return {
        "format": FORMAT,
        "tile_size_m": tile_size_m,
        "scale_m": scale_m,
        "origin": [float(v) for v in origin],
        "crs": crs,
        "files": {},
        "tiles": {},
    }


def _aggregate(fragments: dict[str, dict[str, Any]]) -> dict[str, Any]:
    """Tile totals from its fragments' records (count, bounds, classes)."""
    count = sum(f["count"] for f in fragments.values())
    lo = np.min([f["bounds"][:3] for f in fragments.values()], axis=0)
    hi = np.max([f["bounds"][3:] for f in fragments.values()], axis=0)
    classes: dict[str, int] = {}
    for f in fragments.values():
        for k, n in f["classes"].items():
            classes[k] = classes.get(k, 0) + n
    return {
        "count": count,
        "bounds": [*map(float, lo), *map(float, hi)],
        "classes": dict(sorted(classes.items(), key=lambda kv: int(kv[0]))),
    }


# --- the process-wide tile cache ---------------------------------------------------------


class TileCache:
    """LRU cache of decoded tiles (PointCloud) bounded by their bytes, shared by all stores
    of a process so that neighbouring views reuse tiles. The process-wide one,
    :data:`TILE_CACHE`, holds ``STREETCD_TILE_CACHE_MB`` MiB (default 1024)."""

    def __init__(self, max_bytes: int) -> None:
        self.max_bytes = int(max_bytes)
        self.bytes = 0
        self.hits = 0
        self.misses = 0
        self._items: OrderedDict[tuple, tuple[PointCloud, int]] = OrderedDict()
        self._lock = threading.Lock()

    @staticmethod
    def nbytes(cloud: PointCloud) -> int:
        arrays = (cloud.xyz, cloud.classification, cloud.intensity, cloud.rgb, cloud.gps_time)
        return sum(a.nbytes for a in arrays if a is not None)

    def get(self, key: tuple) -> PointCloud | None:
        with self._lock:
            item = self._items.get(key)
            if item is None:
                self.misses += 1
                return None
            self._items.move_to_end(key)
            self.hits += 1
            return item[0]

    def put(self, key: tuple, cloud: PointCloud) -> None:
        size = self.nbytes(cloud)
        if size > self.max_bytes:
            return
        with self._lock:
            if key in self._items:
                return
            self._items[key] = (cloud, size)
            self.bytes += size
            while self.bytes > self.max_bytes:
                _, (_, old) = self._items.popitem(last=False)
                self.bytes -= old

    def clear(self) -> None:
        with self._lock:
            self._items.clear()
            self.bytes = 0


TILE_CACHE = TileCache(int(float(os.environ.get("STREETCD_TILE_CACHE_MB", "1024")) * 2**20))


# --- reading -----------------------------------------------------------------------------


class TileStore:
    """A tile store opened for reading. ``TileStore.open(path)``.

    origin : (3,) float64, CRS metres; every PointCloud it returns is local to it.
    """

    def __init__(self, path: Path, index: dict[str, Any]) -> None:
        self.path = path
        self.index = index
        self.tile_size_m = float(index["tile_size_m"])
        self.scale_m = float(index["scale_m"])
        self.origin = np.asarray(index["origin"], dtype=np.float64)
        self.crs: str | None = index["crs"]
        self.tiles: dict[str, TileInfo] = {
            tid: self._info(tid, t) for tid, t in index["tiles"].items()
        }
        # (i, j) → tile: the tiles are a regular grid, so a bbox lookup touches only its cells.
        self._grid = {(t.i, t.j): t for t in self.tiles.values()}

    @classmethod
    def open(cls, path: str | Path) -> TileStore:
        path = Path(path)
        index = read_index(path)
        if index is None:
            raise MissingInputError(f"not a streetcd tile store (no '{INDEX_ATTR}' index): {path}")
        return cls(path.resolve(), index)

    def _info(self, tid: str, t: dict[str, Any]) -> TileInfo:
        ts = self.tile_size_m
        frags = tuple(
            sorted(
                (Fragment(k, f["source"], f["count"]) for k, f in t["fragments"].items()),
                key=lambda f: f.source,
            )
        )
        return TileInfo(
            tid,
            t["i"],
            t["j"],
            t["count"],
            tuple(t["bounds"]),
            (t["i"] * ts, t["j"] * ts, (t["i"] + 1) * ts, (t["j"] + 1) * ts),
            {int(k): v for k, v in t["classes"].items()},
            frags,
        )

    def __len__(self) -> int:
        return len(self.tiles)

    @property
    def point_count(self) -> int:
        return sum(t.count for t in self.tiles.values())

    @property
    def files(self) -> dict[str, dict[str, Any]]:
        """Source path → record (status "done" or "failed", size, mtime_ns, points, error)."""
        return self.index["files"]

    def tiles_in_bbox(self, minx: float, miny: float, maxx: float, maxy: float) -> list[TileInfo]:
        """Tiles whose square meets the box (CRS metres): a grid lookup over the box's cells
        (or over the tiles when the box has more cells than the store has tiles)."""
        ts = self.tile_size_m
        i0, i1 = math.floor(minx / ts), math.floor(maxx / ts)
        j0, j1 = math.floor(miny / ts), math.floor(maxy / ts)
        if (i1 - i0 + 1) * (j1 - j0 + 1) > len(self._grid):
            return [
                t for (i, j), t in sorted(self._grid.items()) if i0 <= i <= i1 and j0 <= j <= j1
            ]
        cells = ((i, j) for i in range(i0, i1 + 1) for j in range(j0, j1 + 1))
        return [self._grid[c] for c in cells if c in self._grid]

    def read_tile(self, tid: str, *, cache: bool = True) -> PointCloud:
        """All points of tile ``tid`` as a PointCloud local to :attr:`origin` (fragments in
        source-path order). Cached in the process-wide :data:`TILE_CACHE`; its arrays are
        then read-only (shared by every caller of this process)."""
        info = self.tiles.get(tid)
        if info is None:
            raise MissingInputError(f"{self.path}: no tile {tid!r}")
        key = (str(self.path), tid, tuple((f.key, f.count) for f in info.fragments))
        if cache and (hit := TILE_CACHE.get(key)) is not None:
            return hit
        cloud = self._read_fragments(info)
        if cache:
            for a in (cloud.xyz, cloud.classification, cloud.intensity, cloud.rgb, cloud.gps_time):
                if a is not None:
                    a.flags.writeable = False
            TILE_CACHE.put(key, cloud)
        return cloud

    def _read_fragments(self, info: TileInfo) -> PointCloud:
        parts = []
        for frag in info.fragments:
            group = zarr.open_group(str(self.path / "tiles" / info.id / frag.key), mode="r")
            parts.append({name: arr[:] for name, arr in group.arrays()})
        names = set.intersection(*(set(p) for p in parts))  # fields every fragment has
        cat = {n: np.concatenate([p[n] for p in parts]) for n in names}
        corner = np.array([info.i * self.tile_size_m, info.j * self.tile_size_m, 0.0])
        xyz = cat["xyz"] * self.scale_m + (corner - self.origin)  # float64, local
        return PointCloud(
            xyz=xyz,
            origin=self.origin,
            classification=cat["classification"],
            intensity=cat.get("intensity"),
            rgb=cat.get("rgb"),
            gps_time=cat.get("gps_time"),
            crs=self.crs,
        )

    def to_json(self) -> dict[str, Any]:
        """The index as plain JSON: store settings, ``tiles`` (id, bounds, count, classes,
        sources) and ``files``."""
        return {
            "store": str(self.path),
            "format": FORMAT,
            "crs": self.crs,
            "origin": self.origin.tolist(),
            "tile_size_m": self.tile_size_m,
            "scale_m": self.scale_m,
            "point_count": self.point_count,
            "tiles": [self.tiles[k].to_json() for k in sorted(self.tiles, key=_tile_order)],
            "files": self.files,
        }


def _tile_order(tid: str) -> tuple[int, int]:
    i, j = tid.split("_")
    return int(i), int(j)


def read_index(path: Path) -> dict[str, Any] | None:
    """The committed index of the store at ``path``, or None where there is no store."""
    if not (path / "zarr.json").exists():
        return None
    attrs = zarr.open_group(str(path), mode="r").attrs.asdict()
    index: dict[str, Any] | None = attrs.get(INDEX_ATTR)  # type: ignore[assignment]
    if index is not None and index.get("format") != FORMAT:
        raise InputError(f"{path}: tile store format {index.get('format')!r}, expected {FORMAT!r}")
    return index


# --- ingest: one file on a worker --------------------------------------------------------


@dataclass
class _TileAccumulator:
    """Points of one tile from one file, buffered until flushed to its fragment arrays."""

    parts: list[dict[str, np.ndarray]] = field(default_factory=list)
    buffered: int = 0
    count: int = 0
    lo: np.ndarray = field(default_factory=lambda: np.full(3, _INT32_MAX, dtype=np.int64))
    hi: np.ndarray = field(default_factory=lambda: np.full(3, -_INT32_MAX, dtype=np.int64))
    classes: np.ndarray = field(default_factory=lambda: np.zeros(256, dtype=np.int64))
    arrays: dict[str, Any] = field(default_factory=dict)  # zarr arrays, made at first flush


@dataclass(frozen=True)
class _FileTask:
    path: str
    key: str
    staging: str
    tile_size_m: float
    scale_m: float
    chunk_points: int
    buffer_points: int
    reader: PointReader


@dataclass(frozen=True)
class _FileDone:
    path: str
    key: str
    points: int
    tiles: dict[str, dict[str, Any]]  # tile id → {i, j, count, bounds (CRS), classes}


def _split_by_tile(
    cloud: PointCloud, ts: float, scale: float, path: str
) -> Iterator[tuple[tuple[int, int], dict[str, np.ndarray]]]:
    """Bin one chunk (CRS coordinates) into tiles: ((i, j), fields) with xyz quantised to
    int32 relative to the tile corner."""
    xyz = cloud.xyz
    ij = np.floor(xyz[:, :2] / ts).astype(np.int64)
    zmax = np.abs(xyz[:, 2]).max()
    if zmax / scale >= _INT32_MAX:
        raise InputError(
            f"{path}: field 'Z' out of range for the store scale {scale} m (|z| up to {zmax:.1f} m)"
        )
    q = np.empty(xyz.shape, dtype=np.int32)
    q[:, :2] = np.rint((xyz[:, :2] - ij * ts) / scale)  # 0 … tile/scale: fits int32
    q[:, 2] = np.rint(xyz[:, 2] / scale)
    lo = ij.min(axis=0)
    width = int(ij[:, 1].max() - lo[1]) + 1
    code = (ij[:, 0] - lo[0]) * width + (ij[:, 1] - lo[1])
    order = np.argsort(code, kind="stable")  # stable: file order kept within a tile
    code = code[order]
    starts = np.flatnonzero(np.r_[True, code[1:] != code[:-1]])
    ends = np.r_[starts[1:], len(code)]
    # One gather per field into tile order; each tile is then a contiguous slice.
    fields = {"xyz": q[order], "classification": cloud.classification[order]}
    for name in ("intensity", "rgb", "gps_time"):
        if getattr(cloud, name) is not None:
            fields[name] = getattr(cloud, name)[order]
    ij = ij[order[starts]]
    for (i, j), s, e in zip(ij, starts, ends, strict=True):
        yield (int(i), int(j)), {n: a[s:e] for n, a in fields.items()}


def _flush(acc: _TileAccumulator, path: Path, n: int, final: bool = False) -> None:
    """Append the first ``n`` buffered points of ``acc`` to its fragment arrays."""
    data = {k: np.concatenate([p[k] for p in acc.parts]) for k in acc.parts[0]}
    if not acc.arrays:  # first flush creates the arrays with their data (fewer zarr calls)
        # A fragment written in one go gets one chunk of its own size: zarr pads a partial
        # chunk to full size before compressing, which made small tiles cost like big ones.
        rows = n if final and n < FRAGMENT_CHUNK_POINTS else FRAGMENT_CHUNK_POINTS
        group = zarr.open_group(str(path), mode="w")
        for k, a in data.items():
            acc.arrays[k] = group.create_array(
                k, data=a[:n], compressors=_COMPRESSOR, chunks=(rows, *a.shape[1:])
            )
    else:
        for k, a in data.items():
            acc.arrays[k].append(a[:n])
    rest = {k: a[n:] for k, a in data.items()}
    acc.parts = [rest] if n < len(data["xyz"]) else []
    acc.buffered -= n


_WORKER_QUEUE: Any = None


def _init_worker(q: Any) -> None:
    global _WORKER_QUEUE
    _WORKER_QUEUE = q


def _ingest_file(task: _FileTask, report: Callable[[str, int], None] | None = None) -> _FileDone:
    """Stream one file into per-tile fragments under ``task.staging``; memory is one chunk
    plus at most ``buffer_points`` buffered points."""
    staging = Path(task.staging)
    shutil.rmtree(staging, ignore_errors=True)
    zarr.open_group(str(staging), mode="w")
    report = report or _queue_report
    tiles: dict[tuple[int, int], _TileAccumulator] = {}
    total = buffered = 0
    for cloud in task.reader.chunks(Path(task.path), task.chunk_points):
        for ij, part in _split_by_tile(cloud, task.tile_size_m, task.scale_m, task.path):
            acc = tiles.setdefault(ij, _TileAccumulator())
            n = len(part["xyz"])
            acc.parts.append(part)
            acc.buffered += n
            acc.count += n
            acc.lo = np.minimum(acc.lo, part["xyz"].min(axis=0))
            acc.hi = np.maximum(acc.hi, part["xyz"].max(axis=0))
            acc.classes += np.bincount(part["classification"], minlength=256)
            buffered += n
            if acc.buffered >= FRAGMENT_CHUNK_POINTS:  # whole chunks: appends stay aligned
                full = acc.buffered - acc.buffered % FRAGMENT_CHUNK_POINTS
                _flush(acc, staging / tile_id(*ij), full)
                buffered -= full
        if buffered > task.buffer_points:  # bounded memory: flush everything, even partial
            for ij, acc in tiles.items():
                if acc.buffered:
                    _flush(acc, staging / tile_id(*ij), acc.buffered)
            buffered = 0
        total += len(cloud)
        report(task.path, len(cloud))
    if total == 0:
        raise InputError(f"{task.path}: contains no points")
    out: dict[str, dict[str, Any]] = {}
    for (i, j), acc in tiles.items():
        if acc.buffered:
            _flush(acc, staging / tile_id(i, j), acc.buffered, final=True)
        corner = np.array([i * task.tile_size_m, j * task.tile_size_m, 0.0])
        lo, hi = corner + acc.lo * task.scale_m, corner + acc.hi * task.scale_m
        out[tile_id(i, j)] = {
            "i": i,
            "j": j,
            "count": acc.count,
            "source": task.path,
            "bounds": [*map(float, lo), *map(float, hi)],
            "classes": {str(c): int(acc.classes[c]) for c in np.flatnonzero(acc.classes)},
        }
    return _FileDone(task.path, task.key, total, out)


def _queue_report(path: str, n: int) -> None:
    if _WORKER_QUEUE is not None:
        _WORKER_QUEUE.put((path, n))


# --- ingest: planning and committing (one process) ---------------------------------------


@dataclass(frozen=True)
class IngestResult:
    """What one ingest run did. ``failed`` maps a source path to the error message."""

    store: Path
    ingested: tuple[str, ...]
    skipped: tuple[str, ...]
    failed: dict[str, str]
    points: int  # points written by this run
    tiles: int  # tiles in the store after the run
    seconds: float

    @property
    def ok(self) -> bool:
        return not self.failed


def _file_key(path: Path, size: int, mtime_ns: int) -> str:
    return hashlib.sha1(f"{path}|{size}|{mtime_ns}".encode()).hexdigest()[:16]


def _store_origin(infos: Sequence[LasInfo]) -> np.ndarray:
    """The store origin: the archive's minimum corner floored to the kilometre (order-free)."""
    if not infos:
        return np.zeros(3)
    lo = np.min([i.mins for i in infos], axis=0)
    return np.floor(lo / 1000.0) * 1000.0


def _reference_crs(infos: Sequence[LasInfo]) -> str | None:
    """The CRS most files state (ties: the first file's in path order)."""
    counts: dict[str | None, int] = {}
    for info in infos:
        counts[info.crs] = counts.get(info.crs, 0) + 1
    best = max(counts.values(), default=0)
    return next((i.crs for i in infos if counts[i.crs] == best), None)


class _Store:
    """The committing side of a tile store (single writer)."""

    def __init__(self, path: Path, index: dict[str, Any]) -> None:
        self.path = path
        self.index = index
        self.root = zarr.open_group(str(path), mode="a")

    @classmethod
    def create(cls, path: Path, index: dict[str, Any]) -> _Store:
        root = zarr.open_group(str(path), mode="w", attributes={INDEX_ATTR: index})
        root.require_group("tiles")
        return cls(path, index)

    def write_index(self) -> None:
        self.root.attrs.put({INDEX_ATTR: self.index})  # zarr writes zarr.json atomically

    def sweep(self) -> None:
        """Remove what no committed index lists: staging and fragments of crashed runs."""
        shutil.rmtree(self.path / "_staging", ignore_errors=True)
        tiles_dir = self.path / "tiles"
        committed = self.index["tiles"]
        for tdir in tiles_dir.iterdir() if tiles_dir.is_dir() else ():
            if not tdir.is_dir():
                continue
            keep = committed.get(tdir.name, {}).get("fragments", {})
            if not keep:
                shutil.rmtree(tdir)
                continue
            for fdir in tdir.iterdir():
                if fdir.is_dir() and fdir.name not in keep:
                    shutil.rmtree(fdir)

    def commit(self, done: _FileDone, size: int, mtime_ns: int) -> None:
        """Move a finished file's fragments into tiles/ and record it in the index."""
        files, tiles = self.index["files"], self.index["tiles"]
        old = files.get(done.path, {})
        tiles_group = self.root.require_group("tiles")
        for tid in done.tiles:
            if tid not in tiles:
                tiles_group.require_group(tid)
            dst = self.path / "tiles" / tid / done.key
            shutil.rmtree(dst, ignore_errors=True)
            os.rename(self.path / "_staging" / done.key / tid, dst)
        stale = old.get("key") if old.get("key") != done.key else None
        for tid in old.get("tiles", []) if stale else []:
            tiles[tid]["fragments"].pop(stale, None)
        for tid, stats in done.tiles.items():
            t = tiles.setdefault(tid, {"i": stats["i"], "j": stats["j"], "fragments": {}})
            t["fragments"][done.key] = {
                k: stats[k] for k in ("count", "bounds", "classes", "source")
            }
        for tid in set(done.tiles) | set(old.get("tiles", [])):
            if tiles.get(tid, {}).get("fragments"):
                tiles[tid].update(_aggregate(tiles[tid]["fragments"]))
            else:
                tiles.pop(tid, None)
        files[done.path] = {
            "status": "done",
            "key": done.key,
            "size": size,
            "mtime_ns": mtime_ns,
            "points": done.points,
            "tiles": sorted(done.tiles, key=_tile_order),
        }
        self.write_index()  # the commit point
        shutil.rmtree(self.path / "_staging" / done.key, ignore_errors=True)
        for tid in old.get("tiles", []) if stale else []:
            shutil.rmtree(self.path / "tiles" / tid / stale, ignore_errors=True)
            if tid not in tiles:
                shutil.rmtree(self.path / "tiles" / tid, ignore_errors=True)

    def fail(self, path: str, size: int, mtime_ns: int, exc: StreetcdError) -> None:
        """Record a failed file. An earlier good version of it stays in the store (its
        ``key`` and ``tiles`` are kept so that a later good version replaces it)."""
        old = self.index["files"].get(path, {})
        rec = {k: old[k] for k in ("key", "points", "tiles") if k in old}
        rec.update(
            status="failed",
            error=str(exc),
            error_type=type(exc).__name__,
            size=size,
            mtime_ns=mtime_ns,
        )
        if old != rec:
            self.index["files"][path] = rec
            self.write_index()


def ingest(
    archive: str | Path | Sequence[str | Path],
    store: str | Path,
    *,
    tile_size_m: float = 50.0,
    scale_m: float = 0.001,
    workers: int = 1,
    reader: PointReader | None = None,
    chunk_points: int = 1_000_000,
    buffer_points: int = 4_000_000,
    progress: Progress | None = None,
) -> IngestResult:
    """Ingest an archive of LAS/LAZ files into the tile store ``store`` (created if needed).

    Files already ingested (same size and mtime) are skipped. A file that cannot be read
    (truncated, empty, non-finite coordinates, a CRS other than the store's) is recorded as
    failed in the index and in the result, and the run goes on. ``workers`` > 1 reads files
    in that many processes; commits happen here, one file at a time. Memory per process is
    about ``chunk_points + buffer_points`` points (≈ 60 B each), whatever the archive size.
    """
    t0 = time.perf_counter()
    if not (tile_size_m > 0 and math.isfinite(tile_size_m)):
        raise InputError(f"tile_size_m must be a positive number, got {tile_size_m}")
    if workers < 1:
        raise InputError(f"workers must be >= 1, got {workers}")
    reader = reader or LaspyReader()
    path = Path(store).resolve()
    files = find_archive_files(archive)
    index = read_index(path)
    if index is not None and (index["tile_size_m"] != tile_size_m or index["scale_m"] != scale_m):
        raise InputError(
            f"{path}: store has tile_size_m={index['tile_size_m']}, "
            f"scale_m={index['scale_m']}; asked for {tile_size_m}, {scale_m}"
        )

    failed: dict[str, StreetcdError] = {}
    stats: dict[str, tuple[int, int]] = {}
    skipped: list[str] = []
    todo: list[tuple[str, LasInfo]] = []
    for f in files:
        st = f.stat()
        stats[str(f)] = (st.st_size, st.st_mtime_ns)
        rec = (index or {}).get("files", {}).get(str(f))
        if rec and rec["status"] == "done" and (rec["size"], rec["mtime_ns"]) == stats[str(f)]:
            skipped.append(str(f))
            continue
        try:
            info = reader.info(f)
            if info.point_count == 0:
                raise InputError(f"{f}: contains no points")
            todo.append((str(f), info))
        except StreetcdError as exc:
            failed[str(f)] = exc

    crs = index["crs"] if index is not None else _reference_crs([i for _, i in todo])
    for fp, info in todo:
        if info.crs != crs:
            failed[fp] = CRSMismatchError(
                f"{fp}: field 'CRS' is {info.crs}, but the store {path.name} is in {crs}"
            )
    todo = [(fp, info) for fp, info in todo if fp not in failed]

    if index is None:
        if path.exists() and any(path.iterdir()):
            raise InputError(
                f"{path}: exists and is not a streetcd tile store; choose a new path for --store"
            )
        index = _empty_index(tile_size_m, scale_m, _store_origin([i for _, i in todo]), crs)
        writer = _Store.create(path, index)
    else:
        writer = _Store(path, index)
        writer.sweep()
    for fp in sorted(failed):
        writer.fail(fp, *stats[fp], failed[fp])

    total = sum(info.point_count for _, info in todo)
    done_points = 0
    ingested: list[str] = []

    def report(p: str, n: int) -> None:
        nonlocal done_points
        done_points += n
        if progress is not None:
            progress(done_points, total, Path(p).name)

    tasks = [
        _FileTask(
            f,
            _file_key(Path(f), *stats[f]),
            str(path / "_staging" / _file_key(Path(f), *stats[f])),
            tile_size_m,
            scale_m,
            chunk_points,
            buffer_points,
            reader,
        )
        for f, _ in todo
    ]
    if todo:
        zarr.open_group(str(path / "_staging"), mode="w")

    def finish(task: _FileTask, fut_result: Callable[[], _FileDone]) -> None:
        try:
            done = fut_result()
        except StreetcdError as exc:
            failed[task.path] = exc
            writer.fail(task.path, *stats[task.path], exc)
            shutil.rmtree(Path(task.staging), ignore_errors=True)
            return
        writer.commit(done, *stats[task.path])
        ingested.append(task.path)

    if workers == 1 or len(tasks) <= 1:
        for task in tasks:
            finish(task, functools.partial(_ingest_file, task, report))
    else:
        _run_pool(tasks, workers, report, finish)
    shutil.rmtree(path / "_staging", ignore_errors=True)
    points = sum(index["files"][f]["points"] for f in ingested)
    messages = {f: str(failed[f]) for f in sorted(failed)}
    return IngestResult(
        path,
        tuple(ingested),
        tuple(skipped),
        messages,
        points,
        len(index["tiles"]),
        time.perf_counter() - t0,
    )


def _run_pool(
    tasks: list[_FileTask],
    workers: int,
    report: Callable[[str, int], None],
    finish: Callable[[_FileTask, Callable[[], _FileDone]], None],
) -> None:
    """Files on a process pool (spawned: zarr keeps an event-loop thread that fork would
    copy mid-flight); chunk progress comes back through a queue."""
    ctx = multiprocessing.get_context("spawn")
    q = ctx.Queue()
    with ProcessPoolExecutor(
        min(workers, len(tasks)), mp_context=ctx, initializer=_init_worker, initargs=(q,)
    ) as pool:
        futures: dict[Future, _FileTask] = {pool.submit(_ingest_file, t): t for t in tasks}
        pending = set(futures)
        try:
            while pending:
                finished, pending = wait(pending, timeout=0.2, return_when=FIRST_COMPLETED)
                _drain(q, report)
                for fut in finished:
                    finish(futures[fut], fut.result)
        except BaseException:
            pool.shutdown(wait=False, cancel_futures=True)
            raise
        _drain(q, report)


def _drain(q: Any, report: Callable[[str, int], None]) -> None:
    while True:
        try:
            p, n = q.get_nowait()
        except queue_mod.Empty:
            return
        report(p, n)
