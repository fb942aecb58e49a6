"""The cloud one view can see: the points inside its frustum (range-limited, plus a buffer,
:mod:`streetcd.geometry.frustum`), read from the tile store (only tiles the frustum's ground
footprint meets) or from a handful of LAS/LAZ files.

The frustum of a view, in its camera frame (OpenCV axes, z forward), is the pyramid bounded by
the rays through the image border: normalised coordinates ``x0 ≤ x/z ≤ x1``, ``y0 ≤ y/z ≤ y1``
(the undistorted border's bounding box, so distortion never cuts points off). A point is kept
when its signed distance to each of the four side planes is ≤ ``buffer_m`` and its range
``|X − C|`` is ≤ ``max_range_m + buffer_m``.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from streetcd.errors import CRSMismatchError, InputError
from streetcd.geometry.frustum import boxes_seen, lookup_box, union_mask
from streetcd.io.las import iter_las_chunks, las_info
from streetcd.store.tiles import TileInfo, TileStore
from streetcd.types import PointCloud, View

# A point's arrays besides xyz and classification, which every crop has.
OPTIONAL_FIELDS = ("intensity", "rgb", "gps_time")


def _check_args(max_range_m: float, buffer_m: float) -> None:
    if not (np.isfinite(max_range_m) and max_range_m > 0):
        raise InputError(f"max_range_m must be a positive number, got {max_range_m}")
    if not (np.isfinite(buffer_m) and buffer_m >= 0):
        raise InputError(f"buffer_m must be >= 0, got {buffer_m}")


def _concat(parts: list[PointCloud], origin: np.ndarray, crs: str | None) -> PointCloud:
    """Concatenate crops; optional fields survive only where every part has them."""
    if not parts:
        return PointCloud(np.empty((0, 3)), origin, np.empty(0, np.uint8), crs=crs)

    def cat(name: str) -> np.ndarray | None:
        arrays = [getattr(p, name) for p in parts]
        return None if any(a is None for a in arrays) else np.concatenate(arrays)

    return PointCloud(
        np.concatenate([p.xyz for p in parts]),
        origin,
        np.concatenate([p.classification for p in parts]),
        cat("intensity"),
        cat("rgb"),
        cat("gps_time"),
        crs,
    )


def crop_for_view(
    source: TileStore | str | Path | Sequence[str | Path],
    view: View,
    *,
    max_range_m: float = 60.0,
    buffer_m: float = 1.0,
    fields: Sequence[str] | None = None,
) -> PointCloud:
    """The points ``view`` can see, local to the store origin.

    source : a :class:`TileStore` (or its path), or a list of a few LAS/LAZ files (read
        directly; origin = their minimum corner floored to the kilometre, as ingest picks).
    view : pose in the CRS.
    fields : the optional point arrays to keep (of ``intensity``, ``rgb``, ``gps_time``), or
        None for all; a store then reads and decompresses only those.
    Returns a PointCloud (xyz (N, 3) float64 metres, local; classes; RGB when every source
    has it), possibly empty. Tiles come through the process-wide LRU cache.
    """
    return crop_for_views(source, [view], max_range_m=max_range_m, buffer_m=buffer_m, fields=fields)


def crop_for_views(
    source: TileStore | str | Path | Sequence[str | Path],
    views: Sequence[View],
    *,
    max_range_m: float = 60.0,
    buffer_m: float = 1.0,
    fields: Sequence[str] | None = None,
) -> PointCloud:
    """The points any of ``views`` can see, as one cloud (see :func:`crop_for_view`,
    ``fields`` as there).

    A worker that checks several neighbouring views crops once for all of them: each tile is
    read and each point kept once, and the views share one cloud object, so the detector's
    surface cache (keyed on the cloud) builds each view's surface only once.
    """
    _check_args(max_range_m, buffer_m)
    if not views:
        raise InputError("crop_for_views: no views given")
    unknown = set(fields or ()) - set(OPTIONAL_FIELDS)
    if unknown:
        raise InputError(f"crop fields {sorted(unknown)}: not among {OPTIONAL_FIELDS}")
    if isinstance(source, (str, Path)) and not str(source).lower().endswith((".las", ".laz")):
        source = TileStore.open(source)
    if isinstance(source, TileStore):
        return _crop_store(source, views, max_range_m, buffer_m, fields)
    paths = [Path(source)] if isinstance(source, (str, Path)) else [Path(p) for p in source]
    cloud = _crop_files(paths, views, max_range_m, buffer_m)
    if fields is None:
        return cloud
    # LAS files are read whole: the fields left out are dropped after, for the same answer
    dropped: dict[str, Any] = {f: None for f in OPTIONAL_FIELDS if f not in fields}
    return dataclasses.replace(cloud, **dropped)


def _hits(
    views: Sequence[View],
    origin: np.ndarray,
    boxes: np.ndarray,
    max_range_m: float,
    buffer_m: float,
) -> np.ndarray:
    """(V, M) bool: which of the boxes each view may see (see :func:`~streetcd.geometry.frustum.boxes_seen`)."""
    return np.array([boxes_seen(v, origin, boxes, max_range_m, buffer_m) for v in views])


def _crop_store(
    store: TileStore,
    views: Sequence[View],
    max_range_m: float,
    buffer_m: float,
    fields: Sequence[str] | None = None,
) -> PointCloud:
    candidates: dict[str, TileInfo] = {}  # tile id -> tile, in order of first appearance
    for view in views:
        for tile in store.tiles_in_bbox(*lookup_box(view, store.origin, max_range_m, buffer_m)):
            candidates.setdefault(tile.id, tile)
    if not candidates:
        return _concat([], store.origin, store.crs)
    tiles = list(candidates.values())
    boxes = np.array([t.bounds[0:2] + t.bounds[3:5] for t in tiles])
    hits = _hits(views, store.origin, boxes, max_range_m, buffer_m)
    seen = [k for k in range(len(tiles)) if hits[:, k].any()]
    # read together: tiles that share a compressed chunk decompress it once
    clouds = store.read_tiles([tiles[k].id for k in seen], fields=fields)
    parts = []
    for k in seen:
        seeing = [v for v, hit in zip(views, hits[:, k], strict=True) if hit]
        cloud = clouds[tiles[k].id]
        parts.append(
            cloud.subset(union_mask(cloud.xyz, seeing, store.origin, max_range_m, buffer_m))
        )
    return _concat(parts, store.origin, store.crs)


def _crop_files(
    paths: list[Path], views: Sequence[View], max_range_m: float, buffer_m: float
) -> PointCloud:
    infos = [las_info(p) for p in sorted(paths)]
    if not infos:
        raise InputError("crop_for_view: no LAS/LAZ files given")
    for info in infos[1:]:
        if info.crs != infos[0].crs:
            raise CRSMismatchError(
                f"{info.path}: field 'CRS' is {info.crs}, but "
                f"{infos[0].path.name} is in {infos[0].crs}"
            )
    origin = np.floor(np.min([i.mins for i in infos], axis=0) / 1000.0) * 1000.0
    boxes = np.array([[*i.mins[:2], *i.maxs[:2]] for i in infos])
    hits = _hits(views, origin, boxes, max_range_m, buffer_m)
    parts = []
    for k, info in enumerate(infos):
        seeing = [v for v, hit in zip(views, hits[:, k], strict=True) if hit]
        if seeing:
            for chunk in iter_las_chunks(info.path, origin=origin):
                parts.append(
                    chunk.subset(union_mask(chunk.xyz, seeing, origin, max_range_m, buffer_m))
                )
    return _concat(parts, origin, infos[0].crs)
