"""Ingest: an archive of LAS/LAZ files into the tile store (:mod:`streetcd.store.tiles`, whose
docstring describes the layout), streamed, resumable and parallel.

Each source file is one unit of work: read in chunks by a :class:`~streetcd.io.readers.PointReader`,
binned into tiles and written under ``_staging/<key>``, in this process, in a local process
pool (``workers``) or as a task on a Dask cluster (``client``). Every commit happens in the
process that called :func:`ingest`, one file at a time.

**Visibility and resumability.** Readers trust only the root attribute: a generation and the
points of a source exist for them once it names them. A worker writes a file under
``_staging/<key>``; the single committing process renames it to ``points/<key>``, writes
``index/g<N+1>`` and then the root attribute with generation N + 1 (zarr writes zarr.json to
a temporary file and renames it: atomic). That write is the commit point: a crash leaves the
old index (the file is ingested again next time) or the new one; what no committed index
names (staging, old generations, replaced sources) is removed after the commit or at the
start of the next ingest. The key hashes the file's absolute path, size and mtime, so a
changed file gets a new key and replaces the old version in one commit. Files already in the
index with the same size and mtime are skipped; re-ingesting an unchanged archive writes
nothing. A file gone from the archive keeps its points unless ingest runs with ``prune``.

**One ingest at a time.** Ingest holds an exclusive ``flock`` on ``STORE/.lock``; a second
ingest into the same store fails at once with :class:`~streetcd.errors.StoreLockedError`
(failing beats waiting: a nightly flow retries, a person sees why). The kernel drops the lock
when its holder exits, even on SIGKILL, so there is never a stale lock to clear.
"""

from __future__ import annotations

import filecmp
import functools
import hashlib
import math
import multiprocessing
import os
import queue as queue_mod
import shutil
import time
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import zarr

from streetcd.errors import CRSMismatchError, InputError, StoreLockedError, StreetcdError
from streetcd.io.las import LasInfo
from streetcd.io.readers import LaspyReader, PointReader, find_archive_files
from streetcd.store.locks import exclusive
from streetcd.store.tiles import (
    _SEGMENT_COLUMNS,
    ARRAY_CONFIG,
    COMPRESSORS,
    FORMAT,
    INDEX_ATTR,
    LOCK_NAME,
    _cell_codes,
    _read_generation,
    read_index,
)
from streetcd.types import PointCloud

CHUNK_POINTS = 262_144  # points per zarr chunk of a source's arrays
SEGMENT_POINTS = 262_144  # a tile's buffer is written out as one segment at this size
_INT32_MAX = 2**31 - 1

# progress(points_done, points_total, message): called from the process that runs ingest().
Progress = Callable[[int, int, str], None]


# --- the index, as the committing process writes it ----------------------------------------


def _empty_index(
    tile_size_m: float, scale_m: float, origin: np.ndarray, crs: str | None
) -> dict[str, Any]:
    return {
        "format": FORMAT,
        "tile_size_m": tile_size_m,
        "scale_m": scale_m,
        "origin": [float(v) for v in origin],
        "crs": crs,
        "generation": None,
        "files": {},
    }


# One source's part of the index: its key, segments (s, 10) int64 (i, j, start, count,
# min xyz, max xyz) and classes (k, 3) int64 (row in its segments, class code, count).
_Source = tuple[str, np.ndarray, np.ndarray]


def _split_sources(
    sources: list[tuple[str, str]], segments: np.ndarray, classes: np.ndarray
) -> dict[str, _Source]:
    """The inverse of :func:`_write_generation`: the index as one block per source."""
    seg_order = np.argsort(segments[:, 2], kind="stable")
    seg_cuts = np.searchsorted(segments[seg_order, 2], np.arange(len(sources) + 1))
    local = np.empty(len(segments), np.int64)  # segment row → row within its source
    cls_source = segments[classes[:, 0], 2]
    cls_order = np.argsort(cls_source, kind="stable")
    cls_cuts = np.searchsorted(cls_source[cls_order], np.arange(len(sources) + 1))
    out: dict[str, _Source] = {}
    for row, (src, key) in enumerate(sources):
        rows = seg_order[seg_cuts[row] : seg_cuts[row + 1]]
        local[rows] = np.arange(len(rows))
        cls = classes[cls_order[cls_cuts[row] : cls_cuts[row + 1]]].copy()
        cls[:, 0] = local[cls[:, 0]]
        out[src] = (key, np.delete(segments[rows], 2, axis=1), cls)
    return out


def _write_generation(path: Path, generation: int, sources: dict[str, _Source]) -> None:
    """Write ``index/g<generation>``: the sources by path, segments sorted by (i, j, source
    row, start) so that a tile is a block of rows, classes sorted by segment row."""
    names = sorted(sources)
    segs = [np.empty((0, _SEGMENT_COLUMNS), np.int64)]
    clss = [np.empty((0, 3), np.int64)]
    offset = 0
    for row, src in enumerate(names):
        _, seg, cls = sources[src]
        segs.append(np.column_stack([seg[:, :2], np.full(len(seg), row), seg[:, 2:]]))
        clss.append(cls + np.array([offset, 0, 0]))
        offset += len(seg)
    seg, cls = np.concatenate(segs), np.concatenate(clss)
    order = np.lexsort((seg[:, 3], seg[:, 2], seg[:, 1], seg[:, 0]))
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    seg = seg[order]
    cls[:, 0] = rank[cls[:, 0]]
    cls = cls[np.argsort(cls[:, 0], kind="stable")]
    group = zarr.open_group(
        str(path / "index" / f"g{generation}"),
        mode="w",
        attributes={"sources": [[src, sources[src][0]] for src in names]},
    )
    for name, a in (("segments", seg), ("classes", cls)):
        rows = min(max(len(a), 1), 1_048_576)
        group.create_array(
            name, data=a, chunks=(rows, a.shape[1]), compressors=COMPRESSORS, config=ARRAY_CONFIG
        )


# --- ingest: one file on a worker --------------------------------------------------------


@dataclass
class _TileBuffer:
    """Points of one tile from one file, buffered until written out as a segment."""

    parts: list[dict[str, np.ndarray]] = field(default_factory=list)
    count: int = 0

    def take(self) -> dict[str, np.ndarray]:
        data = {k: np.concatenate([p[k] for p in self.parts]) for k in self.parts[0]}
        self.parts, self.count = [], 0
        return data


class _SourceWriter:
    """One source file's points as one zarr array per field, written segment after segment
    in whole chunks (a chunk is compressed and written once; the last one may be partial).

    Memory: the segments not yet written, less than one chunk after each :meth:`add`.
    """

    def __init__(self, path: Path, chunk_points: int) -> None:
        self.path = path
        self.chunk_points = chunk_points
        self.arrays: dict[str, Any] = {}
        self.written = 0  # rows in the arrays
        self.pending: list[dict[str, np.ndarray]] = []
        self.pending_points = 0
        self.segments: list[list[int]] = []  # i, j, start, count, min xyz, max xyz
        self.classes: list[np.ndarray] = []  # (k, 3) segment row, class code, count

    def add(self, i: int, j: int, data: dict[str, np.ndarray]) -> None:
        """Append the points ``data`` (fields, xyz tile-local int32) of tile (i, j)."""
        xyz, n = data["xyz"], len(data["xyz"])
        lo, hi = xyz.min(axis=0).tolist(), xyz.max(axis=0).tolist()
        hist = np.bincount(data["classification"], minlength=256)
        codes = np.flatnonzero(hist)
        row = np.full(len(codes), len(self.segments))
        self.classes.append(np.column_stack([row, codes, hist[codes]]))
        self.segments.append([i, j, self.written + self.pending_points, n, *lo, *hi])
        self.pending.append(data)
        self.pending_points += n
        if self.pending_points >= self.chunk_points:
            self._write(final=False)

    def finish(self) -> tuple[np.ndarray, np.ndarray, dict[str, dict[str, Any]]]:
        """Write what is pending; the segments (s, 10) and classes (k, 3), int64, and the
        manifest of the arrays (field → dtype, shape, chunk rows) the reader checks."""
        if self.pending_points:
            self._write(final=True)
        segments = np.array(self.segments, dtype=np.int64).reshape(-1, _SEGMENT_COLUMNS - 1)
        classes = np.concatenate([np.empty((0, 3), np.int64), *self.classes]).astype(np.int64)
        manifest = {
            k: {"dtype": str(a.dtype), "shape": list(a.shape), "chunk_rows": a.chunks[0]}
            for k, a in self.arrays.items()
        }
        return segments, classes, manifest

    def _write(self, final: bool) -> None:
        data = {k: np.concatenate([p[k] for p in self.pending]) for k in self.pending[0]}
        n = self.pending_points
        if not final:
            n -= n % self.chunk_points
        end = self.written + n
        if not self.arrays:  # the first write creates the arrays with their data
            # A source written in one go gets one chunk of its own size: zarr pads a partial
            # chunk to full size before compressing, which made small sources cost like big.
            rows = n if final and n < self.chunk_points else self.chunk_points
            group = zarr.open_group(str(self.path), mode="w")
            for k, a in data.items():
                self.arrays[k] = group.create_array(
                    k,
                    data=a[:n],
                    compressors=COMPRESSORS,
                    chunks=(rows, *a.shape[1:]),
                    config=ARRAY_CONFIG,
                )
        else:
            for k, a in data.items():
                self.arrays[k].resize((end, *a.shape[1:]))
                self.arrays[k][self.written : end] = a[:n]
        self.written = end
        self.pending = [{k: a[n:] for k, a in data.items()}] if n < self.pending_points else []
        self.pending_points -= n


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
    segments: np.ndarray  # (s, 10) int64: i, j, start, count, min xyz, max xyz
    classes: np.ndarray  # (k, 3) int64: segment row, class code, count
    arrays: dict[str, dict[str, Any]]  # field → dtype, shape, chunk rows (the manifest)


def _split_by_tile(
    cloud: PointCloud, ts: float, scale: float, path: str
) -> Iterator[tuple[tuple[int, int], dict[str, np.ndarray]]]:
    """Bin one chunk (CRS coordinates) into tiles: ((i, j), fields) with xyz quantised to
    int32 relative to the tile corner."""
    xyz = cloud.xyz
    cells = np.floor(xyz[:, :2] / ts)
    if np.abs(cells).max() >= _INT32_MAX:  # tile numbers must fit the grid's int32 codes
        raise InputError(
            f"{path}: field 'X/Y' out of range for {ts} m tiles (|x|, |y| up to "
            f"{np.abs(xyz[:, :2]).max():.1f} m)"
        )
    ij = cells.astype(np.int64)
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


_WORKER_QUEUE: Any = None


def _init_worker(q: Any) -> None:
    global _WORKER_QUEUE
    _WORKER_QUEUE = q


def _ingest_file(task: _FileTask, report: Callable[[str, int], None] | None = None) -> _FileDone:
    """Stream one file into ``task.staging``, tile by tile; memory is one read chunk, at most
    ``buffer_points`` buffered points and one zarr chunk."""
    staging = Path(task.staging)
    shutil.rmtree(staging, ignore_errors=True)
    report = report or _queue_report
    writer = _SourceWriter(staging, CHUNK_POINTS)
    tiles: dict[tuple[int, int], _TileBuffer] = {}
    total = buffered = 0
    for cloud in task.reader.chunks(Path(task.path), task.chunk_points):
        for ij, part in _split_by_tile(cloud, task.tile_size_m, task.scale_m, task.path):
            buf = tiles.setdefault(ij, _TileBuffer())
            buf.parts.append(part)
            buf.count += len(part["xyz"])
            buffered += len(part["xyz"])
            if buf.count >= SEGMENT_POINTS:  # a big tile goes out in big segments
                buffered -= buf.count
                writer.add(*ij, buf.take())
        if buffered > task.buffer_points:  # bounded memory: write out every tile
            for ij, buf in tiles.items():
                if buf.count:
                    writer.add(*ij, buf.take())
            buffered = 0
        total += len(cloud)
        report(task.path, len(cloud))
    if total == 0:
        raise InputError(f"{task.path}: contains no points")
    for ij, buf in tiles.items():
        if buf.count:
            writer.add(*ij, buf.take())
    segments, classes, arrays = writer.finish()
    return _FileDone(task.path, task.key, total, segments, classes, arrays)


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
    pruned: tuple[str, ...] = ()  # sources dropped because they left the archive (prune)

    @property
    def ok(self) -> bool:
        return not self.failed


def _file_key(path: Path, size: int, mtime_ns: int, replaces: str = "") -> str:
    """The key of one version of a source; ``replaces``: the key of the damaged copy of the
    same version that it repairs."""
    salt = f"|repairs {replaces}" if replaces else ""
    return hashlib.sha1(f"{path}|{size}|{mtime_ns}{salt}".encode()).hexdigest()[:16]


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


@contextmanager
def _store_lock(path: Path) -> Iterator[None]:
    """Hold the ingest lock of the store at ``path`` (created as a directory if missing), or
    raise :class:`StoreLockedError` at once."""
    if path.exists() and not (path / "zarr.json").exists():
        if not path.is_dir() or any(p.name != LOCK_NAME for p in path.iterdir()):
            raise InputError(
                f"{path}: exists and is not a streetcd tile store; choose a new path for --store"
            )
    path.mkdir(parents=True, exist_ok=True)

    def busy(_: str) -> StoreLockedError:
        return StoreLockedError(
            f"{path}: another ingest is writing to this store; run again when it is done"
        )

    # the lock file is never written: re-ingesting an unchanged archive touches nothing
    with exclusive(path / LOCK_NAME, busy):
        yield


class _Store:
    """The committing side of a tile store (single writer, holding the lock)."""

    def __init__(self, path: Path, index: dict[str, Any]) -> None:
        self.path = path
        self.index = index
        self.root = zarr.open_group(str(path), mode="a")
        self.sources = _split_sources(*_read_generation(path, index["generation"]))

    @classmethod
    def create(cls, path: Path, index: dict[str, Any]) -> _Store:
        # Not mode="w": that would delete the lock file this process holds.
        root = zarr.create_group(str(path), attributes={INDEX_ATTR: index})
        root.require_group("index")
        root.require_group("points")
        return cls(path, index)

    @property
    def tile_count(self) -> int:
        segs = [s[:, :2] for _, s, _ in self.sources.values()]
        ij = np.concatenate([np.empty((0, 2), np.int64), *segs])
        return len(np.unique(_cell_codes(ij[:, 0], ij[:, 1])))

    def write_index(self) -> None:
        self.root.attrs.put({INDEX_ATTR: self.index})  # zarr writes zarr.json atomically

    def publish(self) -> None:
        """Write the next index generation, then point the root at it: the commit point."""
        old = self.index["generation"]
        new = (old or 0) + 1
        _write_generation(self.path, new, self.sources)
        self.index["generation"] = new
        self.write_index()
        shutil.rmtree(self.path / "index" / f"g{old}", ignore_errors=True)

    def sweep(self) -> None:
        """Remove what the committed index does not name: staging, other generations and
        sources of crashed runs or replaced files."""
        shutil.rmtree(self.path / "_staging", ignore_errors=True)
        keep = {f"g{self.index['generation']}"}
        live = {key for key, _, _ in self.sources.values()}
        for folder, names in (("index", keep), ("points", live)):
            d = self.path / folder
            for sub in d.iterdir() if d.is_dir() else ():
                if sub.is_dir() and sub.name not in names:
                    shutil.rmtree(sub)

    def commit(self, done: _FileDone, size: int, mtime_ns: int) -> None:
        """Move a finished file into points/ and publish an index that lists it."""
        old = self.sources.get(done.path)
        if old is not None and old[0] == done.key:
            # The same version is in the store already (kept by a failed record): the index
            # must stop naming it before its folder is replaced.
            del self.sources[done.path]
            self.publish()
        dst = self.path / "points" / done.key
        shutil.rmtree(dst, ignore_errors=True)  # not named by the committed index
        os.rename(self.path / "_staging" / done.key, dst)
        self.sources[done.path] = (done.key, done.segments, done.classes)
        self.index["files"][done.path] = {
            "status": "done",
            "key": done.key,
            "size": size,
            "mtime_ns": mtime_ns,
            "points": done.points,
            "tiles": len(np.unique(_cell_codes(done.segments[:, 0], done.segments[:, 1]))),
            "arrays": done.arrays,
        }
        self.publish()
        if old is not None and old[0] != done.key:
            shutil.rmtree(self.path / "points" / old[0], ignore_errors=True)

    def fail(self, path: str, size: int, mtime_ns: int, exc: StreetcdError) -> None:
        """Record a failed file. An earlier good version of it stays in the store (its
        ``key``, ``points`` and ``tiles`` are kept; a later good version replaces it)."""
        old = self.index["files"].get(path, {})
        rec = {k: old[k] for k in ("key", "points", "tiles", "arrays") if k in old}
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

    def prune(self, present: set[str]) -> list[str]:
        """Forget the files not in ``present`` and drop their points (one commit)."""
        gone = sorted(p for p in self.index["files"] if p not in present)
        keys = [self.sources.pop(p)[0] for p in gone if p in self.sources]
        for p in gone:
            del self.index["files"][p]
        if gone:
            self.publish()
        for key in keys:
            shutil.rmtree(self.path / "points" / key, ignore_errors=True)
        return gone


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
    prune: bool = False,
    progress: Progress | None = None,
    client: Any | None = None,
    recheck: bool = False,
) -> IngestResult:
    """Ingest an archive of LAS/LAZ files into the tile store ``store`` (created if needed).

    Files already ingested (same size and mtime) are skipped. A file that cannot be read
    (truncated, empty, non-finite coordinates, a CRS other than the store's) is recorded as
    failed in the index and in the result, and the run goes on. ``workers`` > 1 reads files
    in that many local processes; with ``client`` (a ``distributed.Client``) each file is a
    task on that Dask cluster instead (``workers`` is then ignored; the store and the archive
    must be on storage its workers share, and progress comes per finished file). Commits
    happen here, one file at a time. Memory per process is about
    ``chunk_points + buffer_points`` points (≈ 60 B each), whatever the archive size.
    ``prune`` drops the points of files the store has but the archive no longer lists.
    ``recheck`` reads every chunk of the files it would skip (:func:`~streetcd.store.verify.
    verify_store`) and ingests again those whose points are damaged, under a new key (so the
    views that read them are redone). Raises StoreLockedError when another ingest is writing
    to ``store``.
    """
    t0 = time.perf_counter()
    if not (tile_size_m > 0 and math.isfinite(tile_size_m)):
        raise InputError(f"tile_size_m must be a positive number, got {tile_size_m}")
    if workers < 1:
        raise InputError(f"workers must be >= 1, got {workers}")
    reader = reader or LaspyReader()
    path = Path(store).resolve()
    files = find_archive_files(archive)
    job = _Job(
        path,
        tuple(files),
        tile_size_m,
        scale_m,
        workers,
        reader,
        chunk_points,
        buffer_points,
        recheck,
    )
    with _store_lock(path):
        return _ingest_locked(job, prune, progress, t0, client)


@dataclass(frozen=True)
class _Job:
    """What one ingest call was asked to do."""

    path: Path
    files: tuple[Path, ...]
    tile_size_m: float
    scale_m: float
    workers: int
    reader: PointReader
    chunk_points: int
    buffer_points: int
    recheck: bool = False


def _damaged(path: Path, skipped: list[str], index: dict[str, Any]) -> dict[str, str]:
    """{source: its key} for the ``skipped`` sources whose points in the store are damaged
    (every chunk read and checked)."""
    from streetcd.store.verify import verify_store

    report = verify_store(path, only=skipped)
    return {s: index["files"][s]["key"] for s in sorted(report.damaged) if s in skipped}


def _plan(
    files: Sequence[Path], index: dict[str, Any] | None, reader: PointReader, path: Path
) -> tuple[
    list[tuple[str, LasInfo]],
    list[str],
    dict[str, StreetcdError],
    dict[str, tuple[int, int]],
    str | None,
]:
    """Files to ingest (with headers), to skip, that failed already; their (size, mtime_ns);
    the store CRS."""
    failed: dict[str, StreetcdError] = {}
    stats: dict[str, tuple[int, int]] = {}
    skipped: list[str] = []
    todo: list[tuple[str, LasInfo]] = []
    for f in files:
        st = f.stat()
        name = str(f)
        try:
            name.encode("utf-8")
        except UnicodeEncodeError:  # the index is JSON (UTF-8): record it under a readable name
            name = os.fsencode(f).decode("utf-8", "backslashreplace")
            stats[name] = (st.st_size, st.st_mtime_ns)
            failed[name] = InputError(f"{name}: the file name is not valid UTF-8; rename it")
            continue
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
    for fp, original in _duplicates([fp for fp, _ in todo], skipped, stats).items():
        failed[fp] = InputError(
            f"{fp}: has the same bytes as {original}; its points would be in the store twice "
            "(remove one copy from the archive)"
        )
    todo = [(fp, info) for fp, info in todo if fp not in failed]
    crs = index["crs"] if index is not None else _reference_crs([i for _, i in todo])
    for fp, info in todo:
        if info.crs != crs:
            failed[fp] = CRSMismatchError(
                f"{fp}: field 'CRS' is {info.crs}, but the store {path.name} is in {crs}"
            )
    todo = [(fp, info) for fp, info in todo if fp not in failed]
    return todo, skipped, failed, stats, crs


def _duplicates(
    todo: Sequence[str], kept: Sequence[str], stats: dict[str, tuple[int, int]]
) -> dict[str, str]:
    """{file to ingest: the file it is a byte-for-byte copy of}: a copy of a file already in
    the store (``kept``), or of an earlier one (path order) of ``todo``. Only files of the
    same size are compared, their first 64 KiB (header, VLRs, first points) before the rest."""
    by_size: dict[int, list[str]] = {}
    for f in [*kept, *todo]:
        by_size.setdefault(stats[f][0], []).append(f)
    out: dict[str, str] = {}
    new = set(todo)
    for group in by_size.values():
        originals: list[str] = []
        for f in group:
            same = next((o for o in originals if _same_bytes(o, f)), None)
            if same is not None and f in new:
                out[f] = same
            elif same is None:
                originals.append(f)
    return out


def _same_bytes(a: str, b: str) -> bool:
    try:
        with open(a, "rb") as fa, open(b, "rb") as fb:
            if fa.read(1 << 16) != fb.read(1 << 16):
                return False
        return filecmp.cmp(a, b, shallow=False)
    except OSError:  # unreadable: its own read fails it, by name
        return False


def _ingest_locked(
    job: _Job, prune: bool, progress: Progress | None, t0: float, client: Any | None = None
) -> IngestResult:
    path, tile_size_m, scale_m = job.path, job.tile_size_m, job.scale_m
    index = read_index(path)
    if index is not None and (index["tile_size_m"] != tile_size_m or index["scale_m"] != scale_m):
        raise InputError(
            f"{path}: store has tile_size_m={index['tile_size_m']}, "
            f"scale_m={index['scale_m']}; asked for {tile_size_m}, {scale_m}"
        )
    todo, skipped, failed, stats, crs = _plan(job.files, index, job.reader, path)
    repair = _damaged(path, skipped, index) if job.recheck and index is not None else {}
    for f in repair:  # ingested again, as if changed
        skipped.remove(f)
        try:
            todo.append((f, job.reader.info(Path(f))))
        except StreetcdError as exc:
            failed[f] = exc
    if index is None:
        index = _empty_index(tile_size_m, scale_m, _store_origin([i for _, i in todo]), crs)
        writer = _Store.create(path, index)
    else:
        writer = _Store(path, index)
        writer.sweep()
    for fp in sorted(failed):
        writer.fail(fp, *stats[fp], failed[fp])

    expected = {f: info.point_count for f, info in todo}
    total = sum(expected.values())
    done_points = 0
    reported: dict[str, int] = {}
    ingested: list[str] = []

    def report(p: str, n: int) -> None:
        nonlocal done_points
        done_points += n
        reported[p] = reported.get(p, 0) + n
        if progress is not None:
            progress(min(done_points, total), total, Path(p).name)

    # a repaired source gets a new key: the fingerprint of its tiles, and so the input hash
    # of every view that reads them, changes, and views that failed on the damage are redone
    keys = {f: _file_key(Path(f), *stats[f], repair.get(f, "")) for f, _ in todo}
    tasks = [
        _FileTask(
            f,
            keys[f],
            str(path / "_staging" / keys[f]),
            tile_size_m,
            scale_m,
            job.chunk_points,
            job.buffer_points,
            job.reader,
        )
        for f, _ in todo
    ]
    if todo:
        (path / "_staging").mkdir(exist_ok=True)

    def finish(task: _FileTask, fut_result: Callable[[], _FileDone]) -> None:
        try:
            done = fut_result()
        except StreetcdError as exc:
            failed[task.path] = exc
            writer.fail(task.path, *stats[task.path], exc)
            shutil.rmtree(Path(task.staging), ignore_errors=True)
            # the points it will never deliver are done with too: the bar still reaches 100 %
            left = expected[task.path] - reported.get(task.path, 0)
            if left > 0:
                report(task.path, left)
            return
        writer.commit(done, *stats[task.path])
        ingested.append(task.path)

    if client is not None and tasks:
        _run_dask(tasks, client, report, finish)
    elif job.workers == 1 or len(tasks) <= 1:
        for task in tasks:
            finish(task, functools.partial(_ingest_file, task, report))
    else:
        _run_pool(tasks, job.workers, report, finish)
    shutil.rmtree(path / "_staging", ignore_errors=True)
    pruned = writer.prune({str(f) for f in job.files}) if prune else []
    points = sum(index["files"][f]["points"] for f in ingested)
    messages = {f: str(failed[f]) for f in sorted(failed)}
    return IngestResult(
        path,
        tuple(ingested),
        tuple(skipped),
        messages,
        points,
        writer.tile_count,
        time.perf_counter() - t0,
        tuple(pruned),
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


def _run_dask(
    tasks: list[_FileTask],
    client: Any,
    report: Callable[[str, int], None],
    finish: Callable[[_FileTask, Callable[[], _FileDone]], None],
) -> None:
    """Files as tasks on a Dask cluster, committed here as they finish (any order: a
    commit is per file); progress is reported per finished file."""
    from distributed import as_completed

    futures = {
        client.submit(_ingest_file, t, _no_report, key=f"streetcd-ingest-{t.key}", pure=False): t
        for t in tasks
    }
    try:
        for fut in as_completed(list(futures), loop=client.loop):
            task = futures[fut]
            finish(task, fut.result)
            if fut.status == "finished":
                report(task.path, fut.result().points)
    except BaseException:
        client.cancel(list(futures))
        raise


def _no_report(path: str, n: int) -> None:
    """Chunk progress inside a Dask task goes nowhere; the caller reports whole files."""


def _drain(q: Any, report: Callable[[str, int], None]) -> None:
    while True:
        try:
            p, n = q.get_nowait()
        except queue_mod.Empty:
            return
        report(p, n)
