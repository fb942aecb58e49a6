"""Street segments: fixed pieces of the street, the views in each in trajectory order.

A segment is the unit the nightly workflow schedules and the change index is queried by
(DESIGN.md, data flow step 3). It is a square cell of a fixed grid in the CRS, ``length_m``
on a side, aligned on multiples of ``length_m``: its id names the cell
(``g100-E372000-N143000``: 100 m cells, the cell's south-west corner), so the same stretch of
street has the same id every night, whatever images arrive or are missing, and a view
belongs to the cell its camera centre lies in. Planning uses poses alone, so it is cheap and
deterministic.

Coordinates are those of the poses (the CRS, georeferenced metres); planning only takes
differences and norms of camera centres, which float64 keeps exact to well under a millimetre.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np

from streetcd.config import SegmentParams
from streetcd.errors import InputError
from streetcd.geometry.chainage import project_on_polyline
from streetcd.geometry.neighbours import MIN_PARALLAX_PX, select_neighbours_many
from streetcd.io.roads import RoadLine, read_roads
from streetcd.types import View

Order = Literal["auto", "time", "path"]


@dataclass(frozen=True)
class Segment:
    """A run of consecutive views along the trajectory.

    id : the grid cell's id (:func:`cell_id`), the same every night for the same street.
    views : view names in trajectory order.
    neighbours : for each view (same order), the names of its overlapping views; they may
        belong to the next or previous segment.
    polyline : (K, 2) float64, metres, CRS x/y of the camera centres in order (K ≥ 1).
    bbox : (min_x, min_y, max_x, max_y), metres in the CRS, grown by ``bbox_margin_m``.
    length_m : trajectory length inside the segment.
    """

    id: str
    views: tuple[str, ...]
    neighbours: tuple[tuple[str, ...], ...]
    polyline: np.ndarray
    bbox: tuple[float, float, float, float]
    length_m: float


def path_order(centers: np.ndarray) -> np.ndarray:
    """A path through camera centres: greedy nearest neighbour from one end of the cloud.

    centers : (N, 3) float64, metres. Returns (N,) int, a permutation of ``range(N)``.
    The start is the centre farthest from the centre farthest from view 0 (the two sweeps
    find an end of the trajectory for a street-like, elongated layout). Ties go to the
    lower index, so the order is deterministic.
    """
    n = len(centers)
    if n == 0:
        return np.zeros(0, dtype=np.int64)
    xy = np.asarray(centers, dtype=np.float64)[:, :2]
    far = int(np.argmax(np.linalg.norm(xy - xy[0], axis=1)))
    start = int(np.argmax(np.linalg.norm(xy - xy[far], axis=1)))
    order = [start]
    left = np.ones(n, dtype=bool)
    left[start] = False
    for _ in range(n - 1):
        d = np.linalg.norm(xy - xy[order[-1]], axis=1)
        d[~left] = np.inf
        nxt = int(np.argmin(d))
        order.append(nxt)
        left[nxt] = False
    return np.asarray(order, dtype=np.int64)


def order_views(views: Sequence[View], order: Order = "auto") -> list[View]:
    """Views in acquisition order: by ``time`` (ties by name) where every view has one and
    ``order`` is ``"auto"`` or ``"time"``, else by :func:`path_order` through the centres."""
    views = sorted(views, key=lambda v: v.name)  # input order must not matter
    if order not in ("auto", "time", "path"):
        raise InputError(f"order = {order!r} must be 'auto', 'time' or 'path'")
    has_time = all(v.time is not None for v in views)
    if order == "time" and not has_time:
        missing = next(v.name for v in views if v.time is None)
        raise InputError(f"order='time' but view {missing!r} has no time")
    if order != "path" and has_time:
        return sorted(views, key=lambda v: (v.time, v.name))
    centers = np.array([v.center for v in views]).reshape(-1, 3)
    return [views[i] for i in path_order(centers)]


def cut_points(centers: np.ndarray, length_m: float, max_gap_m: float) -> list[slice]:
    """Cut an ordered trajectory into pieces of at most ``length_m`` metres.

    centers : (N, 3) float64, metres, in trajectory order. A new piece starts where the
    length since the piece's first view would exceed ``length_m`` or where one step is
    longer than ``max_gap_m``. Returns slices into the N views, in order, covering all.
    (No longer how segments are cut, which is :func:`cell_id`; kept for callers that cut a
    trajectory into runs.)
    """
    n = len(centers)
    if n == 0:
        return []
    steps = np.linalg.norm(np.diff(centers[:, :2], axis=0), axis=1)
    pieces, start, run = [], 0, 0.0
    for i, step in enumerate(steps, start=1):
        if step > max_gap_m or run + step > length_m:
            pieces.append(slice(start, i))
            start, run = i, 0.0
        else:
            run += step
    pieces.append(slice(start, n))
    return pieces


def _metres(value: float) -> str:
    """A coordinate in an id: whole metres without a decimal point, else to the millimetre."""
    return str(int(value)) if float(value).is_integer() else f"{value:.3f}"


def cell_id(x: float, y: float, size_m: float) -> str:
    """The id of the grid cell (side ``size_m`` metres, aligned on its multiples) holding the
    point (x, y) of the CRS: ``g<size>-E<west edge>-N<south edge>``. A point on an edge
    belongs to the cell east / north of it."""
    i, j = math.floor(x / size_m), math.floor(y / size_m)
    return f"g{_metres(size_m)}-E{_metres(i * size_m)}-N{_metres(j * size_m)}"


def road_piece_id(road: str, chainage_m: float, size_m: float) -> str:
    """The id of the piece of road ``road`` (its id in the network) ``size_m`` long holding
    chainage ``chainage_m``: ``r<size>-<road>-C<start chainage>``, characters other than
    letters, digits, ``.`` and ``_`` in the road's id written as ``_``."""
    safe = "".join(ch if ch.isascii() and (ch.isalnum() or ch in "._") else "_" for ch in road)
    start = math.floor(chainage_m / size_m) * size_m
    return f"r{_metres(size_m)}-{safe}-C{_metres(start)}"


def segment_keys(centers: np.ndarray, params: SegmentParams) -> list[str]:
    """The segment id of each camera centre ((N, 3) or (N, 2) metres): the piece of the
    nearest road within ``params.roads_max_distance_m`` when ``params.roads`` names a network
    (ties to the line first in the file), else the grid cell (:func:`cell_id`)."""
    xy = np.asarray(centers, np.float64)
    xy = xy.reshape(len(xy), -1)[:, :2] if len(xy) else np.zeros((0, 2))
    grid = [cell_id(float(x), float(y), params.length_m) for x, y in xy]
    if not params.roads or len(xy) == 0:
        return grid
    best = np.full(len(xy), np.inf)
    keys = list(grid)
    for line in _roads(params.roads, params.roads_id_field):
        chainage, dist = project_on_polyline(xy, line.xy)
        for i in np.flatnonzero((dist < best) & (dist <= params.roads_max_distance_m)):
            best[i] = dist[i]
            keys[i] = road_piece_id(line.id, float(chainage[i]), params.length_m)
    return keys


_ROADS: dict[tuple[str, str, float], tuple[RoadLine, ...]] = {}


def _roads(path: str, id_field: str) -> tuple[RoadLine, ...]:
    """The network's lines, read once per file version (a flow plans many nights)."""
    p = Path(path)
    key = (str(p.resolve()), id_field, p.stat().st_mtime if p.exists() else 0.0)
    if key not in _ROADS:
        _ROADS[key] = read_roads(p, id_field)
    return _ROADS[key]


def segment_id(names: Sequence[str], centers: np.ndarray, size_m: float = 100.0) -> str:
    """The id of the segment of views at ``centers`` ((N, 3) metres, N ≥ 1): the grid cell of
    the first centre (every view of a segment lies in one cell). ``names`` is not used: an
    id never depends on which images arrived."""
    c = np.asarray(centers, dtype=np.float64).reshape(-1, 3)[0]
    return cell_id(float(c[0]), float(c[1]), size_m)


def neighbours_of(
    views: Sequence[View],
    n: int,
    radius_m: float,
    max_candidates: int = 12,
    min_parallax_px: float = MIN_PARALLAX_PX,
) -> dict[str, tuple[str, ...]]:
    """For each view, its ``n`` best overlapping views among the ``max_candidates`` nearest
    centres within ``radius_m``.

    The choice by frustum overlap is :func:`streetcd.geometry.neighbours.select_neighbours`, the
    detector's own definition; here we only narrow the candidates with a k-d tree, so that
    dense acquisitions (a camera every metre) and a city's worth of views stay cheap.
    """
    if len(views) < 2:
        return {v.name: () for v in views}
    centers = np.array([v.center for v in views])
    from scipy.spatial import cKDTree  # here: Dask workers import this module, not use it

    tree = cKDTree(centers[:, :2])
    k = min(max_candidates + 1, len(views))  # +1: the view itself comes back too
    dist, idx = tree.query(centers[:, :2], k=k, distance_upper_bound=radius_m)
    found = np.isfinite(dist) & (idx != np.arange(len(views))[:, None])
    cands = [[views[j] for j in sorted(idx[i][found[i]].tolist())] for i in range(len(views))]
    picked = select_neighbours_many(views, cands, n=n, min_parallax_px=min_parallax_px)
    return {v.name: tuple(p.name for p in chosen) for v, chosen in zip(views, picked, strict=True)}


def plan_segments(
    views: Sequence[View],
    params: SegmentParams = SegmentParams(),
    n_neighbours: int = 3,
    order: Order = "auto",
    min_parallax_px: float = MIN_PARALLAX_PX,
) -> list[Segment]:
    """Order ``views`` along the trajectory, group them by grid cell (``params.length_m``
    on a side, :func:`cell_id`), or by piece of road where ``params.roads`` names a road
    network (:func:`segment_keys`), into segments, pair each view with its
    ``n_neighbours`` best overlapping views (``detect.correlate.n_neighbours`` of the config).

    Views must have unique names; poses in the CRS (any frame works, ids and boxes are in
    the frame of the poses). Returns segments in trajectory order.
    """
    names = [v.name for v in views]
    if len(set(names)) != len(names):
        dup = sorted({x for x in names if names.count(x) > 1})
        raise InputError(f"view names must be unique; repeated: {', '.join(dup[:5])}")
    ordered = order_views(views, order)
    neighbours = neighbours_of(
        ordered, n_neighbours, params.neighbour_radius_m, params.max_candidates, min_parallax_px
    )
    # Views by grid cell, each cell's views in trajectory order; cells in the order the
    # trajectory first enters them.
    cells: dict[str, list[View]] = {}
    keys = segment_keys(np.array([v.center for v in ordered]).reshape(-1, 3), params)
    for v, cell in zip(ordered, keys, strict=True):
        cells.setdefault(cell, []).append(v)
    segments = []
    for cid, seg_views in cells.items():
        c = np.array([v.center for v in seg_views]).reshape(-1, 3)
        lo = c[:, :2].min(axis=0) - params.bbox_margin_m
        hi = c[:, :2].max(axis=0) + params.bbox_margin_m
        seg_names = tuple(v.name for v in seg_views)
        segments.append(
            Segment(
                id=cid,
                views=seg_names,
                neighbours=tuple(neighbours[name] for name in seg_names),
                polyline=c[:, :2].copy(),
                bbox=(float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1])),
                length_m=float(np.linalg.norm(np.diff(c[:, :2], axis=0), axis=1).sum()),
            )
        )
    return segments
