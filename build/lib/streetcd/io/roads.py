"""A city's road network: street centre lines from a GeoPackage or GeoJSON (ours; issue 17).

Read with pyogrio (GDAL in its wheel). Each feature is a LineString or MultiLineString; its
id is the value of ``id_field`` when given (a city's own street id: lasting across edits of
the file), else the feature's FID. A MultiLineString's parts are ``<id>.<n>``. Geometries
are read in 2D and must be in the CRS of the poses.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from streetcd.errors import InputError, MissingInputError

LINESTRING, MULTILINESTRING = 2, 5


@dataclass(frozen=True)
class RoadLine:
    """One centre line: ``id`` (str) and ``xy`` (K, 2) float64 metres, K ≥ 2."""

    id: str
    xy: np.ndarray


def read_roads(path: str | Path, id_field: str = "") -> tuple[RoadLine, ...]:
    """The centre lines of ``path`` (GeoPackage, GeoJSON or any vector file GDAL reads).

    A missing file, an unreadable one, a geometry other than lines, a missing or repeated id
    fail with one line naming the file (and the feature)."""
    path = Path(path)
    if not path.is_file():
        raise MissingInputError(f"{path}: road network not found")
    import pyogrio.raw

    try:
        meta, fids, geoms, fields = pyogrio.raw.read(str(path), force_2d=True, return_fids=True)
    except Exception as exc:  # pyogrio's errors are GDAL's: one line with the file
        raise InputError(f"{path}: cannot read the road network: {exc}") from None
    names = list(meta["fields"])
    if id_field and id_field not in names:
        raise InputError(f"{path}: no field {id_field!r} (fields: {', '.join(names) or 'none'})")
    ids = fields[names.index(id_field)] if id_field else fids
    lines: list[RoadLine] = []
    for fid, rid, wkb in zip(fids, ids, geoms, strict=True):
        where = f"{path}: feature {fid}"
        if wkb is None:
            raise InputError(f"{where}: no geometry")
        parts = _lines_of(bytes(wkb), where)
        key = str(rid)
        for n, xy in enumerate(parts):
            lines.append(RoadLine(key if len(parts) == 1 else f"{key}.{n}", xy))
    seen: set[str] = set()
    for line in lines:
        if line.id in seen:
            raise InputError(f"{path}: road id {line.id!r} repeated ({id_field or 'FID'})")
        seen.add(line.id)
    if not lines:
        raise InputError(f"{path}: the road network holds no line")
    return tuple(lines)


def _lines_of(wkb: bytes, where: str) -> list[np.ndarray]:
    """The polylines of a 2D WKB LineString or MultiLineString."""
    kind, body, _ = _header(wkb, 0, where)
    if kind == LINESTRING:
        return [_linestring(wkb, body, where)[0]]
    if kind == MULTILINESTRING:
        order = "<" if wkb[0] == 1 else ">"
        (n,) = struct.unpack_from(order + "I", wkb, body)
        out, at = [], body + 4
        for _ in range(n):
            k, at, _ = _header(wkb, at, where)
            if k != LINESTRING:
                raise InputError(f"{where}: a MultiLineString part of type {k}")
            xy, at = _linestring(wkb, at, where)
            out.append(xy)
        return out
    raise InputError(f"{where}: geometry type {kind} is not a (Multi)LineString")


def _header(wkb: bytes, at: int, where: str) -> tuple[int, int, str]:
    if len(wkb) < at + 5 or wkb[at] not in (0, 1):
        raise InputError(f"{where}: malformed geometry")
    order = "<" if wkb[at] == 1 else ">"
    (kind,) = struct.unpack_from(order + "I", wkb, at + 1)
    return kind, at + 5, order


def _linestring(wkb: bytes, at: int, where: str) -> tuple[np.ndarray, int]:
    """A LineString body at ``at`` (after its header): (K, 2) vertices and the next offset."""
    order = "<" if wkb[at - 5] == 1 else ">"
    (n,) = struct.unpack_from(order + "I", wkb, at)
    end = at + 4 + 16 * n
    if len(wkb) < end:
        raise InputError(f"{where}: malformed geometry")
    xy = np.frombuffer(wkb, dtype=order + "f8", count=2 * n, offset=at + 4).reshape(n, 2)
    if n < 2 or not np.isfinite(xy).all():
        raise InputError(f"{where}: a line needs two or more finite vertices")
    return xy.astype(np.float64), end
