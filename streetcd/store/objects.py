"""Change objects: one record per physical change, merged in 3D from the flagged views'
regions of every night, with the operator's review of it.

The change index lists per-view regions (:mod:`streetcd.store.index`); a change seen by
twelve views is twelve regions. :func:`rebuild_objects` merges a segment's located regions
(all nights) into objects (:func:`streetcd.geometry.merge.link_regions`), finds where each
stands (the least-squares meeting point of the views' lines of sight through their regions,
:func:`streetcd.geometry.merge.nearest_to_rays`), the views that see the spot without a
change, a confidence from how well the views agree, and whether it is a transient (a car,
a pedestrian) rather than a change of the street. It rewrites the segment's objects in one
transaction from what the index holds, so it is deterministic and can be run again at any
time (a run does it for every segment it planned, at its end).

An object's id is ``o-`` and 12 hex digits of a SHA-1 over its segment and the first
region that saw it (earliest night, then view key and label): the same change keeps its id
as later nights add views to it.

Reviews (:func:`record_review`) live in their own table, keyed by object id, with the box
the operator looked at. A reviewed object keeps its id and review: regions of later nights
whose centroid lies in that box (grown by :data:`REVIEW_TOLERANCE_M`) join it and raise no
new object. An object reviewed ``fixed`` that is seen again after the review is a new
change (the street changed again), as is a change outside the box.

:func:`list_objects` is the read side (the contract of ``docs/DECISIONS.md``): it opens the
index read-only. It lives in :mod:`streetcd.store.object_list`, which imports no numpy, so
that ``streetcd query`` starts fast; it and the status and kind names are re-exported here.
"""

from __future__ import annotations

import hashlib
import json
import logging
import math
import sqlite3
from collections import OrderedDict
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from streetcd import classes as C
from streetcd.config import ClassMap, RunParams
from streetcd.errors import InputError, MissingInputError, StreetcdError
from streetcd.geometry.merge import covers, link_regions, nearest_to_rays
from streetcd.store.index import ChangeIndex, utc_now
from streetcd.store.object_list import KINDS as KINDS
from streetcd.store.object_list import LIST_STATUSES as LIST_STATUSES
from streetcd.store.object_list import REVIEW_STATUSES as REVIEW_STATUSES
from streetcd.store.object_list import check_fraction as check_fraction
from streetcd.store.object_list import list_objects as list_objects
from streetcd.store.object_list import normalise_status, write_entries
from streetcd.store.records import camera_from_json

if TYPE_CHECKING:
    from streetcd.store.tiles import StoredXY

log = logging.getLogger(__name__)

MERGE_MARGIN_M = 0.5  # regions whose boxes come this close are one change...
MAX_LINK_M = 4.0  # ...when their centroids are this close too
MAX_RAY_GAP_M = 1.0  # or when two views' lines of sight through them pass this close
REVIEW_TOLERANCE_M = 0.5  # a later region inside a reviewed box (grown by this) joins it
SEE_RANGE_M = 30.0  # a view "sees the spot" when the spot is in its image and this close
IN_FRONT_M = 1.0  # lines of sight meeting this far before the old surface: an added object
MIN_REGION_FRACTION = RunParams().min_region_fraction  # without a config: its default
MAX_RAY_MISS_M = 1.0  # lines of sight that miss each other by more do not locate a change
# Lines of sight that miss each other by more than this (RMS) are not one thing standing in
# one place: regions of several things chained by their links (a car parked in front of a new
# bench, a passer-by beside it), which _agreeing splits. Twice MAX_RAY_MISS_M: a car seen in
# parts by two views, or a region cut by the image border, still meets within it.
MAX_AGREE_MISS_M = 2.0
# Where its regions stand (streetcd.detect.locate) puts an object on the road only where the
# road is this far around it as well: the depth locates a region to about a metre, and
# railings, poles and bins stand at the kerb (a hedge where a railing stood, on a sparse
# street, was placed 0.4 m from it, over the road); a parked car's middle is a metre into it.
KERB_MARGIN_M = 1.0
# A change near a segment's edge is seen by the views of two segments (seed 0's new pole:
# one view in one grid cell, two in the next). Each segment's regions are linked with the
# other segments' regions whose boxes lie this close to its own: ray links between one
# object's regions span ~6 m on the quick tour's façades, so 20 m leaves room.
HALO_M = 20.0

# Where the old cloud says the change is on the road, or was a parked car, a vehicle or a
# pedestrian came or went (issue 17): not a change of the street.
ROAD_CLASSES = (C.ROAD,)
VEHICLE_CLASSES = (C.CAR, C.PEDESTRIAN)
OBJECT_CLASSES = (C.POLE, C.SIGN, C.RAILING, C.FURNITURE, C.VEGETATION)


@dataclass
class _Region:
    view: str
    label: int
    pixels: int
    score: float
    centroid: np.ndarray  # (3,) metres
    lo: np.ndarray
    hi: np.ndarray
    cls: int
    night: str  # YYYY-MM-DD: capture date, else detection date
    seen_at: str  # full timestamp, for reviews
    camera: np.ndarray | None  # (3,) camera centre
    image_px: int | None  # pixels in the view's image (None: camera unknown)
    foot: int = 0  # old cloud's class behind the region's lowest pixels
    segment: str = ""  # the segment of its view
    depth_fraction: float = math.nan  # where it stands: C + f (centroid − C); NaN: unknown


# --- building ---------------------------------------------------------------------------


GroundClass = Callable[[float, float], "int | None"]


def rebuild_objects(
    idx: ChangeIndex,
    segment_ids: Iterable[str],
    ground_class: GroundClass | None = None,
    min_region_fraction: float = MIN_REGION_FRACTION,
) -> int:
    """Rewrite the change objects of ``segment_ids`` from the index's regions, one
    transaction per segment. Returns how many objects they now hold.

    ground_class : (x, y) in the CRS → the old cloud's class on the ground there (None:
    no points), e.g. :func:`ground_classes`; with it, an added object standing on the road
    is a transient. Without it that test is skipped. min_region_fraction : the config's
    ``run.min_region_fraction``: an object none of whose regions covers that share of its
    image is a transient ("small"), as a view with no such region is not flagged.
    """
    asked = set(segment_ids)
    # A segment whose regions are linked with the asked ones' may own an object that takes
    # their new regions: it is rebuilt too.
    near = {
        g.segment for seg in asked for g in _load_near(idx.conn, seg, _load_regions(idx.conn, seg))
    }
    total = 0
    for seg in sorted(asked | near):
        with idx.transaction():
            total += _rebuild_segment(idx.conn, seg, ground_class, min_region_fraction)
    return total


def influence_m(max_range_m: float) -> float:
    """How far (x/y metres) from a segment's box a view's camera centre can be and its
    results still change the segment's objects: a view within SEE_RANGE_M sees its spots;
    a view's regions lie within ``max_range_m`` (the detector's) of its camera, and a
    segment links the other segments' regions within HALO_M of its own, which lie within
    ``max_range_m`` of its cameras."""
    return max(SEE_RANGE_M, 2 * max_range_m + HALO_M)


GROUND_CACHE_BYTES = 192 * 2**20  # the road test's tiles (9 bytes a point)...
GROUND_CHUNK_BYTES = 128 * 2**20  # ...and the store's chunks it decompressed (13 bytes a point)


def ground_classes(
    store: str | Path, radius_m: float = 0.75, class_map: ClassMap | None = None
) -> GroundClass:
    """``(x, y) → class``: the most frequent class of the tile store's points within
    ``radius_m`` (x/y) of the point, in streetcd's codes (the store's own codes read
    through ``class_map``, the config's ``detect.classes``; its default without one), None
    where there are none. The store is opened on the first call; a store that cannot be
    opened is logged once and answers None (the road test is then skipped, nothing fails).

    Reading and scanning whole tiles on every call was most of a 10,000-view night's last
    two minutes. Here a tile is read once, its stored integer x, y and classes only (not
    through the process's tile cache, no float coordinates of the whole tile), its
    decompressed chunks kept for the next tiles that share them
    (:data:`GROUND_CHUNK_BYTES`), and kept (:class:`_GroundTile`, an LRU of
    :data:`GROUND_CACHE_BYTES`): a call compares the tile's integers with a small square
    and tests the few points inside exactly (docs/BENCHMARKS.md, 2026-11-28)."""
    roles = np.asarray((class_map or ClassMap()).table(), np.uint8)
    from streetcd.store.tiles import TileStore

    opened: list[Any] = []
    cache: OrderedDict[str, _GroundTile] = OrderedDict()
    chunks: dict[tuple[int, str, int], np.ndarray] = {}

    def tile(tiles: Any, tid: str) -> _GroundTile:
        hit = cache.get(tid)
        if hit is not None:
            cache.move_to_end(tid)
            return hit
        cache[tid] = new = _GroundTile.of(tiles.read_stored_xy(tid, chunks), roles, tiles.origin)
        _trim(chunks, GROUND_CHUNK_BYTES, lambda a: a.nbytes)
        _trim(cache, GROUND_CACHE_BYTES, lambda t: t.nbytes)
        return new

    def at(x: float, y: float) -> int | None:
        if not opened:
            try:
                opened.append(TileStore.open(store))
            except (StreetcdError, OSError) as exc:
                log.warning("change objects: no road test, tile store unreadable: %s", exc)
                opened.append(None)
        tiles = opened[0]
        if tiles is None:
            return None
        found = tiles.tiles_in_bbox(x - radius_m, y - radius_m, x + radius_m, y + radius_m)
        codes = [tile(tiles, t.id).near(x, y, radius_m) for t in found]
        allc = np.concatenate(codes) if codes else np.zeros(0, np.uint8)
        return int(np.bincount(allc).argmax()) if allc.size else None

    return at


def _trim(cache: dict, max_bytes: int, size: Callable[[Any], int]) -> None:
    """Drop the oldest entries of ``cache`` (insertion order) until it holds ``max_bytes``
    or one entry."""
    held = sum(size(v) for v in cache.values())
    while held > max_bytes and len(cache) > 1:
        held -= size(cache.pop(next(iter(cache))))


@dataclass(frozen=True)
class _GroundTile:
    """One tile's points for the road test: ``points`` as the store holds them
    (:class:`StoredXY`: int32 x, y, the scale and corner offset that make them local),
    ``role`` (M,) uint8 their streetcd codes, ``origin`` (2,) the store's (local → CRS)."""

    points: StoredXY
    role: np.ndarray
    origin: np.ndarray

    @staticmethod
    def of(points: StoredXY, roles: np.ndarray, origin: np.ndarray) -> _GroundTile:
        return _GroundTile(points, roles[points.classification], np.asarray(origin[:2], np.float64))

    @property
    def nbytes(self) -> int:
        return int(self.points.x.nbytes + self.points.y.nbytes + self.role.nbytes)

    def near(self, x: float, y: float, radius_m: float) -> np.ndarray:
        """The roles of the points within ``radius_m`` of CRS (x, y): the points of the
        square around it in stored integers (a unit wider each way, for rounding: a
        comparison of the tile's integers, no float coordinates of the whole tile), then
        the exact test of the whole-tile scan it replaces, on coordinates made by the same
        float operations as the tile reader's (stored · scale + corner offset, + origin)."""
        p, scale, off = self.points, self.points.scale_m, self.points.offset
        reach = radius_m / scale + 1.0
        ux = (x - self.origin[0] - off[0]) / scale
        uy = (y - self.origin[1] - off[1]) / scale
        box = (
            (p.x >= math.floor(ux - reach))
            & (p.x <= math.ceil(ux + reach))
            & (p.y >= math.floor(uy - reach))
            & (p.y <= math.ceil(uy + reach))
        )
        at = np.flatnonzero(box)
        gx = (p.x[at] * scale + off[0]) + self.origin[0]
        gy = (p.y[at] * scale + off[1]) + self.origin[1]
        near = (gx - x) ** 2 + (gy - y) ** 2 <= radius_m**2
        return self.role[at][near]


def _rebuild_segment(
    conn: sqlite3.Connection,
    segment: str,
    ground_class: GroundClass | None = None,
    min_region_fraction: float = MIN_REGION_FRACTION,
) -> int:
    own = _load_regions(conn, segment)
    near = _load_near(conn, segment, own)
    regions = sorted(own + near, key=lambda g: (g.night, g.view, g.label))
    _drop_objects(conn, segment)
    segments = sorted({segment} | {g.segment for g in near})
    reviews = conn.execute(
        f"SELECT * FROM reviews WHERE segment_id IN ({','.join('?' * len(segments))})"
        " ORDER BY object_id",
        segments,
    ).fetchall()
    groups: list[tuple[str | None, list[_Region]]] = []
    free = list(regions)
    for rv in reviews:
        mine, free = _claim(rv, free)
        if rv["segment_id"] == segment:  # another segment's review is written there
            groups.append((rv["object_id"], mine))
    if free:
        view_of = {v: k for k, v in enumerate(sorted({g.view for g in free}))}
        labels = link_regions(
            np.array([g.centroid for g in free]),
            np.array([g.lo for g in free]),
            np.array([g.hi for g in free]),
            MERGE_MARGIN_M,
            MAX_LINK_M,
            cameras=np.array([np.full(3, np.nan) if g.camera is None else g.camera for g in free]),
            view_ids=np.array([view_of[g.view] for g in free]),
            max_ray_gap_m=MAX_RAY_GAP_M,
            object_ids=np.array([g.cls if g.cls in OBJECT_CLASSES else -1 for g in free]),
            pixels=np.array([g.pixels for g in free]),
        )
        for k in range(int(labels.max()) + 1):
            linked = [g for g, lab in zip(free, labels, strict=True) if lab == k]
            # An object belongs to the segment of its first region (earliest night, view
            # key): the neighbour's rebuild, linking the same regions, writes the others.
            groups.extend((None, p) for p in _agreeing(linked) if p and p[0].segment == segment)
    views = _views_near(conn, segment)
    n = 0
    for object_id, members in groups:
        if not members and object_id is None:
            continue
        n += _write_object(
            conn, segment, object_id, members, views, ground_class, min_region_fraction
        )
    write_entries(conn, segment)
    return n


def _agreeing(members: list[_Region]) -> list[list[_Region]]:
    """``members`` split where their views do not agree on one place: when the lines of
    sight of a group's views miss each other by more than MAX_AGREE_MISS_M (RMS) and the
    regions are not on one spot of the old surface, links have chained several things (a car
    parked since the scan whose region of one view touches a new pole's). The view whose
    regions' leaving brings the others' lines of sight closest together leaves, one at a
    time, until they meet within MAX_RAY_MISS_M or two views are left; each view that left is
    a group of its own (it is then judged alone: often seen by one view only)."""
    meet = _meeting(members)
    if meet is None or not meet.miss > MAX_AGREE_MISS_M or _on_one_spot(members):
        return [members]
    keep, parts = list(members), []
    while True:
        views = sorted({g.view for g in keep if g.camera is not None})
        meet = _meeting(keep)
        if meet is None or len(views) <= 2 or meet.miss <= MAX_RAY_MISS_M:
            break
        gone = min(views, key=lambda v: (_miss_without(keep, v), v))
        parts.append([g for g in keep if g.view == gone])
        keep = [g for g in keep if g.view != gone]
    return [keep, *parts]


def _miss_without(members: Sequence[_Region], view: str) -> float:
    """How far the lines of sight of ``members`` other than ``view``'s miss each other."""
    meet = _meeting([g for g in members if g.view != view])
    return math.inf if meet is None or not math.isfinite(meet.miss) else meet.miss


def _claim(review: sqlite3.Row, regions: list[_Region]) -> tuple[list[_Region], list[_Region]]:
    """The regions a reviewed object keeps (centroid in its reviewed box, grown by the
    tolerance; for ``fixed``, only those seen up to the review) and the others."""
    lo = np.array([review["min_x"], review["min_y"], review["min_z"]]) - REVIEW_TOLERANCE_M
    hi = np.array([review["max_x"], review["max_y"], review["max_z"]]) + REVIEW_TOLERANCE_M
    mine, rest = [], []
    for g in regions:
        inside = bool(np.all(g.centroid >= lo) and np.all(g.centroid <= hi))
        if inside and (review["status"] != "fixed" or g.seen_at <= review["at"]):
            mine.append(g)
        else:
            rest.append(g)
    return mine, rest


_REGION_SQL = (
    "SELECT f.view, g.label, g.pixels, g.score, g.x, g.y, g.z, g.min_x, g.min_y, g.min_z,"
    " g.max_x, g.max_y, g.max_z, g.dominant_class, g.foot_class, g.depth_fraction, f.segment_id,"
    " coalesce(f.captured_at, f.detected_at) AS seen, v.center_x, v.center_y, v.center_z,"
    " v.camera"
    " FROM regions g JOIN flagged f ON f.id = g.flagged_id JOIN views v ON v.view = f.view"
)


def _load_regions(conn: sqlite3.Connection, segment: str) -> list[_Region]:
    """The located regions of the segment's flagged views, all nights."""
    rows = conn.execute(
        _REGION_SQL + " WHERE f.segment_id = ? AND g.x IS NOT NULL", (segment,)
    ).fetchall()
    return _as_regions(rows)


def _load_near(conn: sqlite3.Connection, segment: str, own: Sequence[_Region]) -> list[_Region]:
    """The located regions of other segments' views whose x/y boxes come within HALO_M of
    the x/y box of ``own`` (the segment's regions): what a change near its edge may link."""
    if not own:
        return []
    lo = np.min([g.lo for g in own], axis=0) - HALO_M
    hi = np.max([g.hi for g in own], axis=0) + HALO_M
    rows = conn.execute(
        _REGION_SQL + " WHERE f.segment_id != ? AND g.x IS NOT NULL AND g.id IN"
        " (SELECT id FROM regions_rtree WHERE max_x >= ? AND min_x <= ? AND max_y >= ?"
        " AND min_y <= ?)",
        (segment, float(lo[0]), float(hi[0]), float(lo[1]), float(hi[1])),
    ).fetchall()
    return _as_regions(rows)


def _as_regions(rows: Sequence[sqlite3.Row]) -> list[_Region]:
    out = []
    for r in rows:
        cam = (
            None
            if r["center_x"] is None
            else np.array([r[k] for k in ("center_x", "center_y", "center_z")])
        )
        out.append(
            _Region(
                r["view"],
                int(r["label"]),
                int(r["pixels"]),
                float(r["score"]),
                np.array([r["x"], r["y"], r["z"]], dtype=np.float64),
                np.array([r["min_x"], r["min_y"], r["min_z"]], dtype=np.float64),
                np.array([r["max_x"], r["max_y"], r["max_z"]], dtype=np.float64),
                int(r["dominant_class"]),
                r["seen"][:10],
                r["seen"],
                cam,
                _image_px(r["camera"]),
                int(r["foot_class"]),
                r["segment_id"],
                math.nan if r["depth_fraction"] is None else float(r["depth_fraction"]),
            )
        )
    # Night first, so that an object's first region is its first night's.
    out.sort(key=lambda g: (g.night, g.view, g.label))
    return out


def _image_px(camera: str | None) -> int | None:
    if camera is None:
        return None
    d = json.loads(camera)
    return int(d["w"]) * int(d["h"])


def _drop_objects(conn: sqlite3.Connection, segment: str) -> None:
    conn.execute(
        "DELETE FROM object_json WHERE id IN (SELECT id FROM objects WHERE segment_id = ?)",
        (segment,),
    )
    conn.execute(
        "DELETE FROM object_views WHERE object_id IN"
        " (SELECT object_id FROM objects WHERE segment_id = ?)",
        (segment,),
    )
    conn.execute(
        "DELETE FROM objects_rtree WHERE id IN (SELECT id FROM objects WHERE segment_id = ?)",
        (segment,),
    )
    conn.execute("DELETE FROM objects WHERE segment_id = ?", (segment,))


@dataclass
class _ViewGeom:
    key: str
    night: str
    status: str
    view: Any  # streetcd.types.View, or None without a camera


def _views_near(conn: sqlite3.Connection, segment: str) -> list[_ViewGeom]:
    """The done views with a camera whose centre is within SEE_RANGE_M of the segment's box."""
    box = conn.execute(
        "SELECT min_x, min_y, max_x, max_y FROM segments WHERE segment_id = ?", (segment,)
    ).fetchone()
    if box is None:
        rows = conn.execute(
            "SELECT view, camera, coalesce(captured_at, processed_at) AS seen FROM views"
            " WHERE segment_id = ? AND status = 'done' AND camera IS NOT NULL",
            (segment,),
        ).fetchall()
    else:
        r = SEE_RANGE_M
        rows = conn.execute(
            "SELECT view, camera, coalesce(captured_at, processed_at) AS seen FROM views"
            " WHERE status = 'done' AND camera IS NOT NULL AND center_x BETWEEN ? AND ?"
            " AND center_y BETWEEN ? AND ?",
            (box[0] - r, box[2] + r, box[1] - r, box[3] + r),
        ).fetchall()
    return [
        _ViewGeom(
            row["view"],
            (row["seen"] or "")[:10],
            "done",
            camera_from_json(row["view"], row["camera"]),
        )
        for row in sorted(rows, key=lambda x: x["view"])
    ]


def sees(view: Any, point: np.ndarray, max_range_m: float = SEE_RANGE_M) -> bool:
    """Whether ``point`` ((3,) metres, CRS) is in the image of ``view`` (a
    :class:`streetcd.types.View`), in front of it and within ``max_range_m``. Occlusion is
    not known here (the index keeps no depth), so a spot behind a wall counts as seen."""
    x = view.pose.R @ point + view.pose.t
    if x[2] <= 0.1 or float(np.linalg.norm(x)) > max_range_m:
        return False
    i = view.intrinsics
    u, v = i.fx * x[0] / x[2] + i.cx, i.fy * x[1] / x[2] + i.cy
    return bool(0 <= u < i.width and 0 <= v < i.height)


def _write_object(
    conn: sqlite3.Connection,
    segment: str,
    object_id: str | None,
    members: Sequence[_Region],
    views: Sequence[_ViewGeom],
    ground_class: GroundClass | None,
    min_region_fraction: float = MIN_REGION_FRACTION,
) -> int:
    """Insert one object (and its views); 0 when a reviewed object has no region left."""
    if not members:
        return 0
    first = members[0]
    if object_id is None:
        key = f"{segment}|{first.night}|{first.view}|{first.label}"
        object_id = "o-" + hashlib.sha1(key.encode()).hexdigest()[:12]
    w = np.array([g.pixels for g in members], dtype=np.float64)
    cents = np.array([g.centroid for g in members])
    centroid = (cents * w[:, None]).sum(axis=0) / w.sum()
    lo = np.min([g.lo for g in members], axis=0)
    hi = np.max([g.hi for g in members], axis=0)
    cls = _majority([g.cls for g in members], w)
    meet = _meeting(members)
    kind, where = _kind(members, cls, meet)
    if kind == "added" and where is not None:
        centroid = where
        lo, hi = np.minimum(lo, where), np.maximum(hi, where)
    seeing = {g.view for g in members}
    without = [v for v in views if v.key not in seeing and sees(v.view, centroid)]
    nights = sorted({g.night for g in members})
    n_see, n_without = len(seeing), len(without)
    # Views of a night before the change was first seen do not disagree: it was not there.
    against = [v for v in without if v.night in set(nights)]
    confidence = (n_see / (n_see + len(against))) * (1.0 - 0.5**n_see)
    foot = _majority([g.foot for g in members], w)
    transient = _transient(cls, members, without)
    if transient is None and kind != "removed" and foot in ROAD_CLASSES:
        transient = (
            "stands on the road (the old cloud's class at its foot): a vehicle or a passer-by"
        )
    if transient is None and not _large_enough(members, min_region_fraction):
        transient = (
            f"small: no view's region of it covers {min_region_fraction:.1%} of its image"
            " (run.min_region_fraction)"
        )
    if transient is None and kind == "added" and ground_class is not None:
        under = ground_class(float(centroid[0]), float(centroid[1]))
        if under in ROAD_CLASSES:
            transient = "stands on the road (the old cloud's class there): a vehicle or a passer-by"
    if transient is None and kind == "unknown":
        transient = _not_one_place(members, meet, ground_class)
    if transient is None and kind == "unknown" and ground_class is not None:
        transient = _stands_on_road(members, ground_class)
    cur = conn.execute(
        "INSERT INTO objects (object_id, segment_id, kind, class, confidence, x, y, z, min_x,"
        " min_y, min_z, max_x, max_y, max_z, pixels, n_views, n_without, first_seen, last_seen,"
        " transient) VALUES (?,?,?,?,?,?,?,?,?,?,?,?,?,?,?,?,?,?,?,?)",
        (
            object_id,
            segment,
            kind,
            cls,
            round(float(confidence), 6),
            *(float(c) for c in centroid),
            *(float(c) for c in lo),
            *(float(c) for c in hi),
            int(w.sum()),
            n_see,
            n_without,
            nights[0],
            nights[-1],
            transient,
        ),
    )
    conn.execute(
        "INSERT INTO objects_rtree VALUES (?, ?, ?, ?, ?)",
        (cur.lastrowid, float(lo[0]), float(hi[0]), float(lo[1]), float(hi[1])),
    )
    labels: dict[str, list[int]] = {}
    for g in members:
        labels.setdefault(g.view, []).append(g.label)
    for view, labs in sorted(labels.items()):
        conn.execute(
            "INSERT INTO object_views VALUES (?, ?, 1, ?)", (object_id, view, json.dumps(labs))
        )
    for v in without:
        conn.execute("INSERT INTO object_views VALUES (?, ?, 0, '[]')", (object_id, v.key))
    return 1


def _large_enough(members: Sequence[_Region], fraction: float) -> bool:
    """Whether one region covers ``fraction`` of its view's image: the rule by which a view
    is flagged at all (:func:`streetcd.run.worker.is_flagged`), held by each object."""
    return any(g.image_px is None or g.pixels >= fraction * g.image_px for g in members)


def _majority(values: Sequence[int], weights: np.ndarray) -> int:
    """The value with the largest total weight (ties: the smallest value)."""
    totals: dict[int, float] = {}
    for v, wt in zip(values, weights, strict=True):
        totals[v] = totals.get(v, 0.0) + float(wt)
    return min(totals, key=lambda v: (-totals[v], v))


@dataclass(frozen=True)
class _Meeting:
    """Where the lines of sight of an object's views (camera → region centroid) meet:
    ``where`` (3,) metres, ``miss`` their RMS distance to it (metres; inf: parallel),
    ``in_front`` the median distance from it to the old surface along them (metres)."""

    where: np.ndarray
    miss: float
    in_front: float


def _meeting(members: Sequence[_Region]) -> _Meeting | None:
    """The meeting of the members' lines of sight; None with fewer than two views with a
    camera (no depth from one view)."""
    with_cam = [g for g in members if g.camera is not None]
    if len({g.view for g in with_cam}) < 2:
        return None
    origins = np.array([g.camera for g in with_cam])
    targets = np.array([g.centroid for g in with_cam])
    where, miss = nearest_to_rays(origins, targets)
    depth_surface = np.linalg.norm(targets - origins, axis=1)
    depth_change = np.linalg.norm(where[None] - origins, axis=1)
    return _Meeting(where, miss, float(np.median(depth_surface - depth_change)))


def _kind(
    members: Sequence[_Region], cls: int, meet: _Meeting | None
) -> tuple[str, np.ndarray | None]:
    """``removed`` where every view puts the change on the same spot of the old surface and
    the old cloud has an object there (what was seen there is gone); ``added`` where the
    views' lines of sight through their regions meet well in front of the old surface, at a
    point every region covers (something new stands there; that place is returned); else
    ``unknown``. ``meet`` is :func:`_meeting` of the members."""
    if meet is None:
        return "unknown", None
    if _on_one_spot(members):
        # Every view located it on the same spot of the old surface: what changed is that
        # surface itself (an object of the old cloud gone), not something before it.
        if cls in (*OBJECT_CLASSES, *VEHICLE_CLASSES):
            return "removed", None
        return "unknown", None
    if not math.isfinite(meet.miss) or meet.miss > MAX_RAY_MISS_M:
        return "unknown", None
    if meet.in_front > IN_FRONT_M and all(
        covers(meet.where, g.camera, g.centroid, g.lo, g.hi, MERGE_MARGIN_M)
        for g in members
        if g.camera is not None
    ):
        return "added", meet.where
    return "unknown", None


def _not_one_place(
    members: Sequence[_Region], meet: _Meeting | None, ground_class: GroundClass | None
) -> str | None:
    """Why an object of kind ``unknown`` seen by two views or more is not a change of the
    street, or None. Two tests of where its views' lines of sight meet (``meet``):

    * they meet (within MAX_RAY_MISS_M) well before the old surface (IN_FRONT_M), over the
      road: something stood on the road: a vehicle (a car parked since the scan, whose
      region also holds a new board behind it is one such object: ``added`` needs every
      region to cover the meeting point, and the board's does not);
    * they miss each other by more than MAX_AGREE_MISS_M and the regions are not on one spot
      of the old surface: the views do not agree on one thing in one place. :func:`_agreeing`
      has split such chains down to two views; two views whose lines of sight still pass
      that far apart do not locate one thing."""
    if meet is None or _on_one_spot(members):
        return None
    if (
        ground_class is not None
        and meet.miss <= MAX_RAY_MISS_M
        and meet.in_front > IN_FRONT_M
        and ground_class(float(meet.where[0]), float(meet.where[1])) in ROAD_CLASSES
    ):
        return (
            f"stands on the road (its views' lines of sight meet {meet.in_front:.1f} m before"
            " the old surface, over the old cloud's road): a vehicle or a passer-by"
        )
    if math.isfinite(meet.miss) and meet.miss > MAX_AGREE_MISS_M:
        return (
            f"views disagree on where it is: their lines of sight miss each other by"
            f" {meet.miss:.1f} m (RMS); not one thing standing in one place"
        )
    return None


def _stands_on_road(members: Sequence[_Region], ground_class: GroundClass) -> str | None:
    """Why an object of kind ``unknown`` stands on the road by where its regions stand, or
    None (an ``added`` object is placed by where its lines of sight meet, a ``removed`` one
    on the old surface).

    A region with a depth fraction ``f`` (:mod:`streetcd.detect.locate`: the depth at which
    its view and the neighbours agree) stands at ``C + f (X − C)`` for its centroid ``X`` on
    the old surface and its camera ``C``. Where those points agree (every one within
    MAX_AGREE_MISS_M of their mean weighted by pixels), the old cloud's class is read under
    the mean and KERB_MARGIN_M from it along x and y: road at all five means a vehicle or a
    passer-by. A car parked since the scan, its cabin seen against a façade by two views
    whose regions cut it differently, is placed on the façade by the old surface and by the
    meeting of the lines of sight, on the road by this. Points that disagree (a thin pole's
    few pixels, measured at depths metres apart) tell nothing; the margin because the depth
    places a region to about a metre and railings, poles and bins stand at the kerb.
    """
    located = [g for g in members if g.camera is not None and math.isfinite(g.depth_fraction)]
    if not located:
        return None
    at = np.array([g.camera + g.depth_fraction * (g.centroid - g.camera) for g in located])
    w = np.array([g.pixels for g in located], dtype=np.float64)
    where = (at * w[:, None]).sum(axis=0) / w.sum()
    if np.max(np.linalg.norm(at[:, :2] - where[:2], axis=1)) > MAX_AGREE_MISS_M:
        return None
    x, y = float(where[0]), float(where[1])
    m = KERB_MARGIN_M
    probes = ((x, y), (x - m, y), (x + m, y), (x, y - m), (x, y + m))
    if any(ground_class(px, py) not in ROAD_CLASSES for px, py in probes):
        return None  # not well inside the road: at the kerb, a railing or a pole stands too
    before = [
        (1.0 - g.depth_fraction) * float(np.linalg.norm(g.centroid - g.camera)) for g in located
    ]
    metres = float(np.median(before))
    return (
        f"stands on the road (where its views and their neighbours agree, {metres:.1f} m before"
        " the old surface): a vehicle or a passer-by"
    )


def _on_one_spot(members: Sequence[_Region]) -> bool:
    """Whether the regions of every two views overlap on the old surface (boxes grown by
    the merge margin): no parallax between the views, so the change is on that surface."""
    for a in members:
        for b in members:
            if a.view < b.view and not (
                np.all(a.lo - MERGE_MARGIN_M <= b.hi + MERGE_MARGIN_M)
                and np.all(b.lo - MERGE_MARGIN_M <= a.hi + MERGE_MARGIN_M)
            ):
                return False
    return True


def _transient(cls: int, members: Sequence[_Region], without: Sequence[_ViewGeom]) -> str | None:
    """Why the object is a transient and not a change of the street, or None.

    The views are counted night by night for "one view only": the same camera position on
    two nights is not a second line of sight."""
    if cls in VEHICLE_CLASSES:
        return f"the old cloud has a {C.NAMES[cls]} there: a vehicle came or went"
    if cls in ROAD_CLASSES:
        return "on the road surface: a vehicle or a pedestrian passing"
    last = max(g.night for g in members)
    later = sorted({v.night for v in without if v.night > last})
    if later:
        return f"gone on a later night ({later[0]}): came and went"
    per_night: dict[str, set[str]] = {}
    for g in members:
        per_night.setdefault(g.night, set()).add(g.view)
    without = [v for v in without if v.night in per_night]  # the nights it was seen on
    n_see = len({g.view for g in members})
    if max(len(v) for v in per_night.values()) == 1 and without:
        return f"seen by one view only; {len(without)} view(s) see the spot without a change"
    if len(without) > n_see:
        return (
            f"views disagree: {len(without)} of {n_see + len(without)} views that see the spot"
            " see no change there"
        )
    return None


# --- reading: streetcd.store.object_list (list_objects, check_fraction) -----------------


# --- reviewing ----------------------------------------------------------------------------


def record_review(
    index_path: str | Path,
    object_id: str,
    status: str,
    *,
    who: str,
    note: str | None = None,
) -> dict:
    """Store an operator's decision on a change object: ``confirmed``, ``false_alarm``
    (``false-alarm`` too) or ``fixed``, who made it, when (now, UTC) and a note. A second
    review replaces the first. The object's box at the review is kept with it: later
    nights' regions inside it join the object instead of raising a new one (see the module
    docstring). Returns the review as stored. InputError for a bad status,
    MissingInputError for an unknown object id or index."""
    status = normalise_status(status)
    if not str(who).strip():
        raise InputError("who must name the reviewer")
    with ChangeIndex(index_path, create=False) as idx:
        row = idx.conn.execute("SELECT * FROM objects WHERE object_id = ?", (object_id,)).fetchone()
        if row is None:
            raise MissingInputError(f"{index_path}: no change object {object_id!r}")
        review = {"status": status, "who": str(who), "at": utc_now(), "note": note}
        with idx.transaction():
            idx.conn.execute(
                "INSERT OR REPLACE INTO reviews VALUES (?,?,?,?,?,?,?,?,?,?,?,?)",
                (
                    object_id,
                    row["segment_id"],
                    status,
                    review["who"],
                    review["at"],
                    note,
                    *(row[k] for k in ("min_x", "min_y", "min_z", "max_x", "max_y", "max_z")),
                ),
            )
    return review
