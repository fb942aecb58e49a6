"""Street segments: views ordered along the acquisition trajectory and cut into pieces.

A segment is the unit the nightly workflow schedules and the change index is queried by
(DESIGN.md, data flow step 3). It is planned from poses alone, so planning is cheap and
deterministic: the same views give the same segments, with the same ids, on every rerun.

Coordinates are those of the poses (the CRS, georeferenced metres); planning only takes
differences and norms of camera centres, which float64 keeps exact to well under a millimetre.
"""

from __future__ import annotations

import hashlib
import re
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np

from streetcd.config import SegmentParams
from streetcd.errors import InputError
from streetcd.geometry.neighbours import select_neighbours
from streetcd.types import View

Order = Literal["auto", "time", "path"]


@dataclass(frozen=True)
class Segment:
    """A run of consecutive views along the trajectory.

    id : stable, derived from the content (first view's stem + a hash of the views' names and
        centres), so reruns on the same poses agree.
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


def segment_id(names: Sequence[str], centers: np.ndarray) -> str:
    """Stable id: the first view's stem (made filename-safe) and 10 hex digits of a SHA-1
    over the names and the centres rounded to the millimetre."""
    h = hashlib.sha1()
    for name, c in zip(names, np.round(np.asarray(centers, dtype=np.float64), 3), strict=True):
        h.update(f"{name}:{c[0]:.3f},{c[1]:.3f},{c[2]:.3f}\n".encode())
    stem = re.sub(r"[^A-Za-z0-9_.-]+", "_", names[0].rsplit("/", 1)[-1].rsplit(".", 1)[0])
    return f"{stem}-{h.hexdigest()[:10]}"


def neighbours_of(
    views: Sequence[View], n: int, radius_m: float, max_candidates: int = 12
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
    out = {}
    for i, view in enumerate(views):
        near = sorted(
            int(j) for d, j in zip(dist[i], idx[i], strict=True) if np.isfinite(d) and j != i
        )
        picked = select_neighbours(view, [views[j] for j in near], n=n) if near else []
        out[view.name] = tuple(v.name for v in picked)
    return out


def plan_segments(
    views: Sequence[View],
    params: SegmentParams = SegmentParams(),
    n_neighbours: int = 3,
    order: Order = "auto",
) -> list[Segment]:
    """Order ``views`` along the trajectory, cut them into segments, pair each view with its
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
        ordered, n_neighbours, params.neighbour_radius_m, params.max_candidates
    )
    centers = np.array([v.center for v in ordered]).reshape(-1, 3)
    segments = []
    for piece in cut_points(centers, params.length_m, params.max_gap_m):
        seg_views = ordered[piece]
        c = centers[piece]
        lo = c[:, :2].min(axis=0) - params.bbox_margin_m
        hi = c[:, :2].max(axis=0) + params.bbox_margin_m
        seg_names = tuple(v.name for v in seg_views)
        segments.append(
            Segment(
                id=segment_id(seg_names, c),
                views=seg_names,
                neighbours=tuple(neighbours[name] for name in seg_names),
                polyline=c[:, :2].copy(),
                bbox=(float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1])),
                length_m=float(np.linalg.norm(np.diff(c[:, :2], axis=0), axis=1).sum()),
            )
        )
    return segments
