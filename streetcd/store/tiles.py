"""The MLS archive as a zarr v3 tile store: its format, and reading it (:class:`TileStore`).

Writing it (streamed, resumable, parallel) is :mod:`streetcd.store.ingest`; the readers of
the source files are :mod:`streetcd.io.readers`.

Layout of ``STORE.zarr`` (format ``streetcd-tiles/3``, one zarr v3 hierarchy)::

    zarr.json            root group; attribute ``streetcd_tiles``: the store settings
                         (tile_size_m, scale_m, origin, crs), ``files`` (a record per source
                         path, with the ``arrays`` manifest of its points: dtype, shape and
                         chunk rows per field) and ``generation`` N, the index generation
                         readers use
    index/g<N>/          the tile index; group attribute ``sources``: [path, key] per row
        segments    (S, 11) int64  i, j, source row, start, count, min xyz, max xyz
        classes     (K, 3)  int64  segment row, class code, point count
    points/<key>/        every point of one source file version, one array per field
        xyz             (N, 3) int32   round((X_crs − corner) / scale), corner = (i·ts, j·ts, 0)
        classification  (N,) uint8
        intensity       (N,) uint16    when the source has it (LAS always does)
        rgb             (N, 3) uint16  when present
        gps_time        (N,) float64   when present
    _staging/<key>/      a source being ingested; renamed to points/<key> when committed
    .lock                held (flock) by the one ingest that writes the store

A **segment** is rows ``start … start + count`` of ``points/<key>`` that all lie in tile
(i, j) = (⌊X / tile_size⌋, ⌊Y / tile_size⌋); its min/max xyz are in the integer units of
``xyz``. Ingest buffers each tile's points and writes them out as one run, so a tile is one
segment per source, or a few when a source is larger than the ingest buffer. Segment rows are
sorted by (i, j, source row, start): a tile is a block of consecutive rows, and its points
come in source-path order, then file order.

**Why this layout.** The cost of building the store is one zarr array per field per source
file, one chunk per 262,144 points and one index row per segment: linear in points, a few
bytes per tile. (The first layout, a group of arrays per tile and file plus a rename each,
paid that per tile, which dominated the build: see docs/BENCHMARKS.md.) Opening reads two small
arrays, not a JSON object per tile; a bounding-box lookup is a binary search of the box's grid
cells in the sorted (i, j) codes, so its cost does not grow with the store.

**Coordinates** are int32 at the store scale (1 mm by default) relative to the tile corner: a
50 m tile spans 0…50 000 units, z (CRS heights) fits ±2 147 km, and the tile grid is anchored
at CRS (0, 0), so a tile's content does not depend on which file came first. Measured on
scan-like MLS points (see benchmarks/ingest.py, ``coords`` table, and docs/BENCHMARKS.md):
int32 + Blosc-zstd stores xyz in fewer bytes than local float64 and decodes faster; the
quantisation error (≤ 0.5 mm) is below the 1 mm scale every MLS archive is delivered at.

**Integrity** (format 3). Every chunk of every array ends in a CRC-32C of its compressed
bytes (zarr's ``crc32c`` codec after Blosc), so a truncated or bit-flipped chunk fails its
read instead of decoding to garbage (Blosc trusts the sizes in its own header,
zarr-developers/numcodecs#228). zarr reads a chunk that is not there as fill values, so the
reader checks that each chunk it needs exists (every chunk is written, empty or not), that
each array's metadata matches the manifest the root record holds for it, and that a tile
reads back the point count its segments promise. Any of these fails the read with
:class:`~streetcd.errors.CorruptFileError`, one line naming the tile, the source file, the
field and the chunk, and the command that rewrites it (``streetcd ingest … --recheck``,
which gives the source a new key, so the tile's fingerprint and the input hashes of the
views that read it change). :mod:`streetcd.store.verify` checks a whole store. Stores of
format 2 (no checksums) are refused with the command to re-ingest them.

**Readers** trust only the root attribute: a generation and the points of a source exist for
them once it names them (how ingest commits: :mod:`streetcd.store.ingest`). Readers take no
lock. A TileStore opened before a commit that replaced a source cannot read that source's
points any more: open the store again. Decoded tiles are kept in one LRU cache per process,
:func:`tile_cache`, created on first use and sized by ``STREETCD_TILE_CACHE_MB`` (MiB,
default 256).
"""

from __future__ import annotations

import functools
import math
import os
import struct
import sys
import threading
import time
from collections import OrderedDict
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import google_crc32c
import numpy as np
import zarr
from numcodecs import blosc
from zarr.codecs import BloscCodec, BytesCodec, Crc32cCodec
from zarr.codecs.bytes import Endian

from streetcd.errors import CorruptFileError, InputError, MissingInputError
from streetcd.types import PointCloud

FORMAT = "streetcd-tiles/3"
# Every array's bytes codecs: Blosc-zstd, then a CRC-32C of the compressed chunk. zstd level 1
# gives level 3's size, faster; the checksum must come last so that it covers what is stored.
COMPRESSORS = (BloscCodec(cname="zstd", clevel=1, shuffle="shuffle"), Crc32cCodec())
# zarr leaves out a chunk that is all fill value; the reader takes a missing chunk as damage,
# so every chunk is written.
ARRAY_CONFIG: Any = {"write_empty_chunks": True}
BLOSC_HEADER = 16  # bytes: version, flags, type size, then uncompressed, block, compressed sizes
INDEX_ATTR = "streetcd_tiles"
LOCK_NAME = ".lock"
_SEGMENT_COLUMNS = 11  # i, j, source row, start, count, min xyz, max xyz
CACHE_ENV = "STREETCD_TILE_CACHE_MB"  # MiB of the process-wide tile cache
DEFAULT_CACHE_MB = "256"
SOURCES_OPEN = 64  # sources whose zarr arrays a TileStore keeps open (least recently used out)


# --- the index ---------------------------------------------------------------------------


@dataclass(frozen=True)
class StoredXY:
    """A tile's points as the store holds them, x, y and classes only
    (:meth:`TileStore.read_stored_xy`).

    x, y : (N,) int32, units of ``scale_m`` from the tile's corner. classification : (N,)
    uint8, the store's codes. offset : (2,) float64 metres, the corner less the store's
    origin: a point's local x is ``x · scale_m + offset[0]``, the float operations by which
    :meth:`TileStore.read_tile` makes it, so the two agree to the bit.
    """

    x: np.ndarray
    y: np.ndarray
    classification: np.ndarray
    scale_m: float
    offset: np.ndarray


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


def _cell_codes(i: np.ndarray, j: np.ndarray) -> np.ndarray:
    """(N,) uint64 codes of grid cells (i, j) int64, |i|, |j| < 2³¹, ordered as (i, j) are."""
    bias = np.int64(2**31)
    hi = (np.asarray(i, dtype=np.int64) + bias).astype(np.uint64)
    lo = (np.asarray(j, dtype=np.int64) + bias).astype(np.uint64)
    return (hi << np.uint64(32)) | lo


def _read_generation(
    path: Path, generation: int | None
) -> tuple[list[tuple[str, str]], np.ndarray, np.ndarray]:
    """The [(path, key)] sources, segments (S, 11) and classes (K, 3) of one index generation.

    FileNotFoundError when the generation's folder is gone (a commit replaced it);
    CorruptFileError, naming the file, when its metadata or a chunk is damaged or missing.
    """
    if generation is None:  # a store that has no committed file yet
        return [], np.empty((0, _SEGMENT_COLUMNS), np.int64), np.empty((0, 3), np.int64)
    folder = path / "index" / f"g{generation}"
    if not (folder / "zarr.json").exists():
        raise FileNotFoundError(folder)
    group = _open_node(folder, zarr.open_group)
    try:
        listed: Any = group.attrs.asdict()["sources"]
        sources = [(str(p), str(k)) for p, k in listed]
    except (KeyError, TypeError, ValueError) as exc:
        raise _corrupt(folder / "zarr.json", f"attribute 'sources' is malformed ({exc})") from None
    tables = {}
    for name, columns in (("segments", _SEGMENT_COLUMNS), ("classes", 3)):
        a = _open_node(folder / name, zarr.open_array)
        if a.ndim != 2 or a.shape[1] != columns:
            raise _corrupt(folder / name / "zarr.json", f"shape {a.shape}, expected (n, {columns})")
        parts = [read_chunk(a, folder / name, c) for c in range(chunk_count(a))]
        tables[name] = np.concatenate([np.empty((0, columns), np.int64), *parts]).astype(np.int64)
    return sources, tables["segments"], tables["classes"]


def _problem(exc: CorruptFileError) -> str:
    """A store error as the part of a line that follows the source file's name."""
    if isinstance(exc, ChunkError):
        return f"field {exc.field!r}, chunk {exc.chunk} {exc.problem} ({exc.file})"
    return str(exc)


def _corrupt(file: Path, what: str) -> CorruptFileError:
    return CorruptFileError(f"{file}: {what}")


def _open_node(folder: Path, opener: Any) -> Any:
    """``opener(folder)`` (a zarr group or array, read-only); garbage in its ``zarr.json`` is
    a CorruptFileError naming that file."""
    try:
        return opener(str(folder), mode="r")
    except FileNotFoundError:
        raise _corrupt(folder / "zarr.json", "is missing") from None
    except Exception as exc:  # zarr raises JSON, key, type and value errors for bad metadata
        raise _corrupt(
            folder / "zarr.json", f"is not valid zarr metadata ({type(exc).__name__}: {exc})"
        ) from None


def open_field(folder: Path, want: dict[str, Any], source: str) -> Any:
    """The zarr array of one field of a source's points, in ``folder``, checked against its
    manifest entry ``want`` ({dtype, shape, chunk_rows}); CorruptFileError names its file."""
    a = _open_node(folder, zarr.open_array)
    have = {"dtype": str(a.dtype), "shape": list(a.shape), "chunk_rows": a.chunks[0]}
    expected = {k: want.get(k) for k in have}
    if have != expected:
        raise _corrupt(
            folder / "zarr.json",
            f"array of {source}, field {folder.name!r}, is {have}; the store's manifest says "
            f"{expected}",
        )
    return a


def chunk_count(a: Any) -> int:
    """Chunks of zarr array ``a`` along its first axis (the only chunked one here)."""
    return -(-a.shape[0] // a.chunks[0]) if a.shape[0] else 0


def chunk_file(a: Any, folder: Path, c: int) -> Path:
    """The file of chunk ``c`` (first axis) of array ``a`` stored in ``folder``."""
    return folder / a.metadata.encode_chunk_key((c,) + (0,) * (a.ndim - 1))


class ChunkError(CorruptFileError):
    """Chunk ``chunk`` (file ``file``) of array ``field`` is missing or damaged."""

    def __init__(self, file: Path, field: str, chunk: int, problem: str) -> None:
        super().__init__(f"{file}: chunk {chunk} {problem}")
        self.file, self.field, self.chunk, self.problem = file, field, chunk, problem


def read_chunk(a: Any, folder: Path, c: int) -> np.ndarray:
    """Rows of chunk ``c`` of array ``a`` (in ``folder``), decoded and checksum-checked.
    :class:`ChunkError` when it is missing (zarr would return fill values) or cannot be
    decoded (checksum, truncation).

    A chunk written with :data:`COMPRESSORS` is decoded here (:func:`_decode_chunk`), the
    same steps in the same order as zarr's pipeline; any other through zarr."""
    rows = a.chunks[0]
    file = chunk_file(a, folder, c)
    if not file.is_file():
        raise ChunkError(file, folder.name, c, "is missing")
    try:
        if _plain_codecs(a):
            return _decode_chunk(file.read_bytes(), a, c)
        return np.asarray(a[c * rows : (c + 1) * rows])
    except Exception as exc:
        text = "checksum mismatch" if "checksum" in str(exc) else f"{type(exc).__name__}: {exc}"
        raise ChunkError(file, folder.name, c, f"is damaged ({text})") from None


def _plain_codecs(a: Any) -> bool:
    """Whether array ``a`` is stored as :data:`COMPRESSORS` writes it: little-endian bytes,
    Blosc, a CRC-32C of the compressed bytes, on a little-endian machine."""
    codecs: tuple[Any, ...] = tuple(getattr(a.metadata, "codecs", ()))
    return (
        sys.byteorder == "little"
        and a.dtype.byteorder in "=<|"
        and len(codecs) == 3
        and isinstance(codecs[0], BytesCodec)
        and codecs[0].endian in (None, Endian.little)
        and isinstance(codecs[1], BloscCodec)
        and isinstance(codecs[2], Crc32cCodec)
    )


def _decode_chunk(stored: bytes, a: Any, c: int) -> np.ndarray:
    """Rows of chunk ``c`` of ``a`` from its ``stored`` bytes (:func:`_plain_codecs`): the
    CRC-32C of all but the last 4 bytes must be those 4 (little-endian), Blosc's header must
    promise exactly the compressed and the chunk's bytes, then Blosc decompresses into the
    chunk's array. zarr does the same through its asynchronous pipeline, a thread hop per
    codec: ~2 ms a chunk whatever its size, twice the time of decoding a 3 MB one
    (docs/BENCHMARKS.md)."""
    body, crc = stored[:-4], stored[-4:]
    if len(stored) < 4 + BLOSC_HEADER or google_crc32c.value(body) != int.from_bytes(crc, "little"):
        raise ValueError("checksum mismatch")
    out = np.empty(a.chunks, dtype=a.dtype)
    nbytes, _, cbytes = struct.unpack_from("<III", body, 4)
    if (nbytes, cbytes) != (out.nbytes, len(body)):
        raise ValueError(
            f"Blosc header says {nbytes} bytes from {cbytes}; the chunk has "
            f"{out.nbytes} from {len(body)}"
        )
    blosc.decompress(body, out)
    return out[: max(min(a.chunks[0], a.shape[0] - c * a.chunks[0]), 0)]


# --- the process-wide tile cache ---------------------------------------------------------


class TileCache:
    """LRU cache of decoded tiles (PointCloud) bounded by their bytes, shared by all stores
    of a process so that neighbouring views reuse tiles. The process-wide one,
    :func:`tile_cache`, holds ``STREETCD_TILE_CACHE_MB`` MiB (default 256)."""

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


_TILE_CACHE: TileCache | None = None
_TILE_CACHE_LOCK = threading.Lock()


def tile_cache() -> TileCache:
    """The process-wide :class:`TileCache`, created on the first call with
    ``STREETCD_TILE_CACHE_MB`` MiB (default 256). InputError, naming the variable and its
    value, when that is not a number ≥ 0."""
    global _TILE_CACHE
    if _TILE_CACHE is None:
        with _TILE_CACHE_LOCK:
            if _TILE_CACHE is None:
                _TILE_CACHE = TileCache(_cache_bytes())
    return _TILE_CACHE


def _cache_bytes() -> int:
    """The tile cache's size in bytes, from ``STREETCD_TILE_CACHE_MB`` (MiB, default 256:
    a segment's tiles and its neighbours', filled within the first few hundred views so
    that a worker's memory is flat from then on; docs/DECISIONS.md, 2026-11-25)."""
    raw = os.environ.get(CACHE_ENV, DEFAULT_CACHE_MB)
    try:
        mib = float(raw)
    except ValueError:
        mib = math.nan
    if not (math.isfinite(mib) and mib >= 0):
        raise InputError(
            f"{CACHE_ENV}={raw!r}: the tile cache size must be a number of MiB >= 0 "
            f"(e.g. {DEFAULT_CACHE_MB}, the default)"
        )
    return int(mib * 2**20)


# --- reading -----------------------------------------------------------------------------


class _TileTable(Mapping[str, TileInfo]):
    """Tile id → :class:`TileInfo` of a store, in (i, j) order; an entry is built on first
    access, so opening a store of 10,000 tiles does not make 10,000 objects."""

    def __init__(self, store: TileStore) -> None:
        self._store = store
        self._built: dict[int, TileInfo] = {}

    def __len__(self) -> int:
        return len(self._store._ij)

    def __iter__(self) -> Iterator[str]:
        return (tile_id(i, j) for i, j in self._store._ij.tolist())

    def __getitem__(self, tid: str) -> TileInfo:
        row = self._store._row(tid)
        if row is None:
            raise KeyError(tid)
        return self.at(row)

    def at(self, row: int) -> TileInfo:
        info = self._built.get(row)
        if info is None:
            info = self._built[row] = self._store._info(row)
        return info


class TileStore:
    """A tile store opened for reading. ``TileStore.open(path)``.

    origin : (3,) float64, CRS metres; every PointCloud it returns is local to it.
    tiles : mapping tile id → :class:`TileInfo`, in (i, j) order.
    """

    def __init__(
        self,
        path: Path,
        index: dict[str, Any],
        sources: list[tuple[str, str]],
        segments: np.ndarray,
        classes: np.ndarray,
    ) -> None:
        self.path = path
        self.index = index
        self.tile_size_m = float(index["tile_size_m"])
        self.scale_m = float(index["scale_m"])
        self.origin = np.asarray(index["origin"], dtype=np.float64)
        self.crs: str | None = index["crs"]
        self.sources = sources
        self._segments = segments
        self._classes = classes
        ij = segments[:, :2]
        self._first = np.flatnonzero(np.r_[True, np.any(ij[1:] != ij[:-1], axis=1)])[
            : len(segments)
        ]
        self._last = np.r_[self._first[1:], len(segments)].astype(np.int64)
        self._ij = ij[self._first]
        self._codes = _cell_codes(self._ij[:, 0], self._ij[:, 1])  # sorted: segments are
        self._counts = (
            np.add.reduceat(segments[:, 4], self._first) if len(segments) else np.zeros(0, int)
        )
        # source row → its zarr arrays, the last SOURCES_OPEN used (an LRU)
        self._arrays: OrderedDict[int, dict[str, Any]] = OrderedDict()
        self._arrays_lock = threading.Lock()
        self.tiles = _TileTable(self)

    @classmethod
    def open(cls, path: str | Path, *, check: bool = True) -> TileStore:
        """Open the store at ``path``. MissingInputError where there is none; InputError for
        another format; CorruptFileError, naming the file, for damaged metadata or index
        (``check``: the index against the file records, :meth:`check_index`)."""
        path = Path(path).resolve()
        generation = None
        for _ in range(5):
            index = read_index(path)
            if index is None:
                raise MissingInputError(
                    f"not a streetcd tile store (no '{INDEX_ATTR}' index): {path}"
                )
            generation = index["generation"]
            try:
                store = cls(path, index, *_read_generation(path, generation))
                if check:
                    store.check_index()
                return store
            except (FileNotFoundError, CorruptFileError) as exc:
                # an ingest committed meanwhile (its old generation is gone): read the new index
                again = read_index(path)
                if again is not None and again["generation"] != generation:
                    time.sleep(0.05)
                    continue
                if isinstance(exc, CorruptFileError):  # the index itself is damaged
                    raise CorruptFileError(
                        f"{exc}; the tile index is damaged, rebuild the store: "
                        f"{reingest_command(index, path)}"
                    ) from None
                raise
        raise MissingInputError(f"{path}: index generation {generation} is missing")

    def check_index(self) -> None:
        """The index against the file records: each source's segments add up to the points
        its record counts and lie inside its arrays; tile numbers fit the grid.
        CorruptFileError naming the index otherwise (e.g. a chunk of it read as zeros)."""
        seg = self._segments
        where = self.path / "index" / f"g{self.index['generation']}"
        if len(seg) and (
            seg[:, 2].min() < 0 or seg[:, 2].max() >= len(self.sources) or seg[:, 3:5].min() < 0
        ):
            raise _corrupt(where, "segments name sources or rows that do not exist")
        counts = np.bincount(seg[:, 2], weights=seg[:, 4], minlength=len(self.sources))
        ends = np.zeros(len(self.sources), np.int64)
        np.maximum.at(ends, seg[:, 2], seg[:, 3] + seg[:, 4])
        for row, (path, _) in enumerate(self.sources):
            shape = self._manifest(path)["xyz"]["shape"]
            points = self.files[path].get("points")
            if int(counts[row]) != points or ends[row] > shape[0]:
                raise _corrupt(
                    where,
                    f"the segments of {path} hold {int(counts[row])} points up to row "
                    f"{ends[row]}, its record {points} points in {shape[0]} rows",
                )
        if len(seg) and np.abs(seg[:, :2]).max() >= 2**31 - 1:
            raise _corrupt(where, "a tile number is beyond the grid (|i|, |j| >= 2^31)")

    def _row(self, tid: str) -> int | None:
        """The row of tile ``tid`` ("i_j"), or None where the store has no such tile."""
        try:
            i, j = (int(v) for v in tid.split("_"))
        except ValueError:
            return None
        if not (-(2**31) <= i < 2**31 and -(2**31) <= j < 2**31):
            return None
        return self._grid.get((i + 2**31) << 32 | (j + 2**31))

    def _info(self, row: int) -> TileInfo:
        seg = self._segments[self._first[row] : self._last[row]]
        i, j = (int(v) for v in self._ij[row])
        ts = self.tile_size_m
        corner = np.array([i * ts, j * ts, 0.0])
        lo = corner + seg[:, 5:8].min(axis=0) * self.scale_m
        hi = corner + seg[:, 8:11].max(axis=0) * self.scale_m
        a, b = np.searchsorted(self._classes[:, 0], [self._first[row], self._last[row]])
        hist = np.bincount(self._classes[a:b, 1], weights=self._classes[a:b, 2], minlength=256)
        sources, starts = np.unique(seg[:, 2], return_index=True)  # rows are sorted by source
        counts = np.add.reduceat(seg[:, 4], starts)
        frags = tuple(
            Fragment(self.sources[s][1], self.sources[s][0], int(n))
            for s, n in zip(sources.tolist(), counts.tolist(), strict=True)
        )
        return TileInfo(
            tile_id(i, j),
            i,
            j,
            int(self._counts[row]),
            (float(lo[0]), float(lo[1]), float(lo[2]), float(hi[0]), float(hi[1]), float(hi[2])),
            (i * ts, j * ts, (i + 1) * ts, (j + 1) * ts),
            {int(c): int(hist[c]) for c in np.flatnonzero(hist)},
            frags,
        )

    def __len__(self) -> int:
        return len(self._ij)

    @property
    def point_count(self) -> int:
        return int(self._counts.sum())

    @property
    def files(self) -> dict[str, dict[str, Any]]:
        """Source path → record (status "done" or "failed", key, size, mtime_ns, points,
        tiles, error)."""
        return self.index["files"]

    def tiles_in_bbox(self, minx: float, miny: float, maxx: float, maxy: float) -> list[TileInfo]:
        """Tiles whose square meets the box (CRS metres), in (i, j) order: a hash lookup
        for each grid cell of the box (a vectorised test of every tile where the box has
        more cells than the store has tiles)."""
        ts = self.tile_size_m
        i0, i1 = math.floor(minx / ts), math.floor(maxx / ts)
        j0, j1 = math.floor(miny / ts), math.floor(maxy / ts)
        if i1 < i0 or j1 < j0:
            return []
        if (i1 - i0 + 1) * (j1 - j0 + 1) > len(self._ij):
            i, j = self._ij[:, 0], self._ij[:, 1]
            rows = np.flatnonzero((i >= i0) & (i <= i1) & (j >= j0) & (j <= j1)).tolist()
        else:  # a view's box has a handful of cells: plain dict lookups beat numpy calls
            grid, bias = self._grid, 2**31
            codes = (
                ((i + bias) << 32) | (j + bias)
                for i in range(i0, i1 + 1)
                for j in range(j0, j1 + 1)
            )
            rows = [r for c in codes if (r := grid.get(c)) is not None]
        return [self.tiles.at(r) for r in rows]

    @functools.cached_property
    def _grid(self) -> dict[int, int]:
        """Cell code (as :func:`_cell_codes`) → tile row; built on the first lookup."""
        return dict(zip(self._codes.tolist(), range(len(self._codes)), strict=True))

    def read_tile(self, tid: str, *, cache: bool = True) -> PointCloud:
        """All points of tile ``tid`` as a PointCloud local to :attr:`origin` (sources in
        path order, then file order). Cached in the process-wide :func:`tile_cache`; its
        arrays are then read-only (shared by every caller of this process)."""
        return self.read_tiles([tid], cache=cache)[tid]

    def read_tiles(
        self,
        tids: Sequence[str],
        *,
        cache: bool = True,
        fields: Sequence[str] | None = None,
        chunks: dict[tuple[int, str, int], np.ndarray] | None = None,
    ) -> dict[str, PointCloud]:
        """:meth:`read_tile` for several tiles at once: {tile id: cloud}. ``fields``: read
        only these of the points' arrays (``xyz`` and ``classification`` always; the
        change objects' road test needs only those two: 13 of the 41 bytes a point holds,
        the detector no ``gps_time``); the tile cache keeps a tile read with other fields
        apart. ``chunks``: the decompressed chunks, {(source, field,
        chunk number): rows}, kept by the caller from call to call (this adds to it; the
        caller bounds it) so that tiles read one at a time decompress a chunk once.

        A source file's points are stored in chunks of ``chunk_points`` rows, each
        compressed as a whole, and a tile's run is usually a few thousand rows of one chunk:
        read tile by tile, a chunk was decompressed again for every tile in it. Here each
        chunk the missing tiles need is decompressed once (the gain, per tile and per segment
        crop: docs/BENCHMARKS.md).
        """
        tc = tile_cache() if cache else None
        want = None if fields is None else {"xyz", "classification", *fields}
        which = None if want is None else tuple(sorted(want))
        out: dict[str, PointCloud] = {}
        todo: list[tuple[str, int, TileInfo, tuple]] = []
        for tid in dict.fromkeys(tids):
            row = self._known_row(tid)
            info = self.tiles.at(row)
            key = (str(self.path), tid, tuple((f.key, f.count) for f in info.fragments), which)
            if tc is not None and (hit := tc.get(key)) is not None:
                out[tid] = hit
            else:
                todo.append((tid, row, info, key))
        runs = {t[0]: self._runs(t[1]) for t in todo}
        chunks = {} if chunks is None else chunks
        for tid, *_ in todo:
            self._chunks_for(tid, runs[tid].tolist(), chunks, want)
        for tid, _, info, key in todo:
            cloud = self._assemble(info, runs[tid], chunks, want)
            self._check_count(tid, info, len(cloud))
            if tc is not None:
                for a in (
                    cloud.xyz,
                    cloud.classification,
                    cloud.intensity,
                    cloud.rgb,
                    cloud.gps_time,
                ):
                    if a is not None:
                        a.flags.writeable = False
                tc.put(key, cloud)
            out[tid] = cloud
        return {tid: out[tid] for tid in tids}

    def read_stored_xy(self, tid: str, chunks: dict[tuple[int, str, int], np.ndarray]) -> StoredXY:
        """Tile ``tid``'s x, y and classes as the store holds them (:class:`StoredXY`), for
        a lookup that needs no z and no float coordinates of the whole tile (the change
        objects' road test): read_tiles' float conversion of every point was most of that
        test's time. ``chunks`` as :meth:`read_tiles`'; the same checks (a short tile is a
        CorruptFileError)."""
        row = self._known_row(tid)
        info = self.tiles.at(row)
        runs = self._runs(row).tolist()
        self._chunks_for(tid, runs, chunks, {"xyz", "classification"})
        xs, ys, cls = [np.empty(0, np.int32)], [np.empty(0, np.int32)], [np.empty(0, np.uint8)]
        for source, start, count in runs:
            arrays = self._source_arrays(source, {"xyz", "classification"})
            xyz = _rows_of(chunks, source, "xyz", arrays["xyz"], start, count)
            xs.append(xyz[:, 0])
            ys.append(xyz[:, 1])
            cls.append(
                _rows_of(chunks, source, "classification", arrays["classification"], start, count)
            )
        x = np.concatenate(xs)  # copies: the chunks are not kept with the tile
        self._check_count(tid, info, len(x))
        return StoredXY(
            x=x,
            y=np.concatenate(ys),
            classification=np.concatenate(cls),
            scale_m=self.scale_m,
            offset=self._corner_offset(info)[:2],
        )

    def _known_row(self, tid: str) -> int:
        """Tile ``tid``'s row in the index; MissingInputError where the store has none."""
        row = self._row(tid)
        if row is None:
            raise MissingInputError(f"{self.path}: no tile {tid!r}")
        return row

    def _runs(self, row: int) -> np.ndarray:
        """(K, 3) int64: (source, start, count) of the tile at index ``row``."""
        return self._segments[self._first[row] : self._last[row], 2:5]

    def _check_count(self, tid: str, info: TileInfo, n: int) -> None:
        """A manifest or index that lies: never a short tile."""
        if n != info.count:
            raise CorruptFileError(
                f"{self.path}: tile {tid}: read {n} points, its index says "
                f"{info.count}; check the store: streetcd verify {self.path}"
            )

    def _corner_offset(self, info: TileInfo) -> np.ndarray:
        """(3,) float64 metres: tile ``info``'s corner less the store origin, what a stored
        coordinate × ``scale_m`` is added to for the local one."""
        corner = np.array([info.i * self.tile_size_m, info.j * self.tile_size_m, 0.0])
        return corner - self.origin

    def _source_arrays(self, source: int, fields: set[str] | None = None) -> dict[str, Any]:
        """{field: zarr array} of a source, the ``fields`` of its manifest (all when None),
        each checked against the manifest its file record holds (dtype, shape, chunk rows);
        CorruptFileError names the array's file. A field is opened when first asked for:
        opening one is a hop through zarr's event loop (~0.5 ms), and the road test wants
        two of a source's five."""
        path, key = self.sources[source]
        manifest = self._manifest(path)
        names = [n for n in manifest if fields is None or n in fields]
        with self._arrays_lock:
            arrays = self._arrays.get(source)
            if arrays is None:
                arrays = self._arrays[source] = {}
                # A city's store has thousands of sources; kept all night, their zarr
                # objects (tens each) were most of what the flow process's cycle collector
                # walked (docs/BENCHMARKS.md). A crop or a road test touches a handful.
                while len(self._arrays) > SOURCES_OPEN:
                    self._arrays.popitem(last=False)
            else:
                self._arrays.move_to_end(source)
            missing = [n for n in names if n not in arrays]
        folder = self.path / "points" / key
        for name in missing:  # outside the lock; two threads may both open one: harmless
            arrays[name] = open_field(folder / name, manifest[name], path)
        return {n: arrays[n] for n in names}

    def _manifest(self, path: str) -> dict[str, dict[str, Any]]:
        """The ``arrays`` manifest of source ``path``: field → {dtype, shape, chunk_rows}."""
        try:
            manifest: dict[str, dict[str, Any]] = self.files[path]["arrays"]
            if not {"xyz", "classification"} <= set(manifest):
                raise KeyError("xyz/classification")
        except (KeyError, TypeError) as exc:
            raise _corrupt(
                self.path / "zarr.json", f"the record of {path} has no array manifest ({exc})"
            ) from None
        return manifest

    def _chunks_for(
        self,
        tid: str,
        runs: list[list[int]],
        out: dict[tuple[int, str, int], np.ndarray],
        fields: set[str] | None = None,
    ) -> None:
        """Put into ``out`` {(source, field, chunk number): its rows} every chunk the
        (source, start, count) ``runs`` of tile ``tid`` touch that is not there yet, each
        read (decompressed) once. A field whose metadata or chunk is missing, truncated or
        corrupt raises CorruptFileError naming the tile, the source file, the file at fault
        and the command that rewrites that source's points."""
        for source, start, count in runs:
            try:
                for name, a in self._source_arrays(source, fields).items():
                    folder = self.path / "points" / self.sources[source][1] / name
                    for c in _chunk_numbers(start, count, a.chunks[0]):
                        if (source, name, c) not in out:
                            out[source, name, c] = read_chunk(a, folder, c)
            except CorruptFileError as exc:
                path = self.sources[source][0]
                raise CorruptFileError(
                    f"{self.path}: tile {tid}: points of {path}, {_problem(exc)}; "
                    f"{repair_hint(path, self.path)}"
                ) from None

    def _assemble(
        self,
        info: TileInfo,
        runs: np.ndarray,
        chunks: dict[tuple[int, str, int], np.ndarray],
        want: set[str] | None = None,
    ) -> PointCloud:
        """Tile ``info``'s cloud from its (source, start, count) ``runs``, cut out of the
        decompressed ``chunks`` of :meth:`_chunks_for`."""
        parts = []
        for source, start, count in runs.tolist():
            fields = {}
            for name, a in self._source_arrays(source, want).items():
                fields[name] = _rows_of(chunks, source, name, a, start, count)
            parts.append(fields)
        names = set.intersection(*(set(p) for p in parts))  # fields every source has
        cat = {n: np.concatenate([p[n] for p in parts]) for n in names}
        xyz = cat["xyz"] * self.scale_m + self._corner_offset(info)  # float64, local
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
            "tiles": [t.to_json() for t in self.tiles.values()],
            "files": self.files,
        }


def _rows_of(
    chunks: dict[tuple[int, str, int], np.ndarray],
    source: int,
    name: str,
    array: Any,
    start: int,
    count: int,
) -> np.ndarray:
    """Rows ``start … start + count − 1`` of field ``name`` of ``source``, cut out of its
    decompressed ``chunks`` (a view when they lie in one chunk)."""
    rows = array.chunks[0]
    pieces = [
        chunks[source, name, c][max(start - c * rows, 0) : start + count - c * rows]
        for c in _chunk_numbers(start, count, rows)
    ]
    if len(pieces) == 1:
        return pieces[0]
    return np.concatenate(pieces) if pieces else np.empty((0, *array.shape[1:]), array.dtype)


def _chunk_numbers(start: int, count: int, rows: int) -> range:
    """The chunks of ``rows`` rows that rows ``start … start + count − 1`` lie in."""
    return range(start // rows, (start + count - 1) // rows + 1) if count > 0 else range(0)


def read_index(path: Path) -> dict[str, Any] | None:
    """The committed root record of the store at ``path``, or None where there is no store.
    CorruptFileError naming ``zarr.json`` when it is garbage; InputError, with the command
    that re-ingests it, for a store of another format."""
    root = path / "zarr.json"
    if not root.exists():
        return None
    attrs = _open_node(path, zarr.open_group).attrs.asdict()
    index: Any = attrs.get(INDEX_ATTR)
    if index is None:
        return None
    if not isinstance(index, dict):
        raise _corrupt(root, f"attribute {INDEX_ATTR!r} is not a record")
    if index.get("format") != FORMAT:
        raise InputError(
            f"{path}: tile store format {index.get('format')!r}, this streetcd reads {FORMAT!r} "
            f"(chunk checksums); re-ingest into a new store: {reingest_command(index, path)}"
        )
    missing = [k for k in _INDEX_KEYS if k not in index]
    if missing or not isinstance(index["files"], dict):
        raise _corrupt(
            root, f"attribute {INDEX_ATTR!r} lacks field(s) {', '.join(missing) or 'files'}"
        )
    return dict(index)


_INDEX_KEYS = ("tile_size_m", "scale_m", "origin", "crs", "generation", "files")


def reingest_command(index: dict[str, Any], path: Path) -> str:
    """The ``streetcd ingest`` command that rebuilds the store at ``path`` (from the folder
    all its sources share) into a new store next to it, with the same tile size."""
    files = [f for f in (index.get("files") or {}) if isinstance(f, str)]
    archive = os.path.commonpath(files) if files else "ARCHIVE"  # one file: the file itself
    new = path.with_name(path.stem + "-v3" + path.suffix)
    return f"streetcd ingest --archive {archive} --store {new} --tile-size {index.get('tile_size_m', 50)}"


def repair_hint(source: str, store: Path) -> str:
    """The command that rewrites the points of ``source`` in ``store`` (a new key, so the
    views that read them are redone)."""
    return f"rewrite them: streetcd ingest --archive {source} --store {store} --recheck"
